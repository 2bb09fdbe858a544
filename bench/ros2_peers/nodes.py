"""The mock ROS 2 peers (fake_base.py, fake_camera.py, fake_viewer.py) as processes: started in
this namespace, waited for, their JSON lines collected, told things on stdin."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent


class MockNode:
    """One mock node's process (``script`` in this folder, with ``args``)."""

    def __init__(self, script: str, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, str(HERE / script), *args], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, cwd=HERE.parent.parent)  # the repo: bench/ros2_peers/..
        self._lock = threading.Lock()
        self._lines: list[dict[str, Any]] = []
        self._ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()
        if not self._ready.wait(30):
            self.close()
            raise AssertionError(f"the mock node {script} did not start")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            got = json.loads(line)
            if got.get("ready"):
                self._ready.set()
                continue
            with self._lock:
                self._lines.append(got)

    def lines(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._lines)

    def say(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def serve(node: Any) -> None:
    """In a mock node's own process: say it is ready (the line :class:`MockNode` waits for), then
    spin until terminated."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    print(json.dumps({"ready": True}), flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
