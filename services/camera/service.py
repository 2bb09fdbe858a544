"""The camera service (on the robot): SDK frames in, posed ``sensors/rgbd`` frames and ``camera/state`` out.

A thin adapter over :class:`services.camera.core.CameraCore`. The SDK's blocking
reads run on a reader thread of their own, which, like Zenoh's callbacks, only
enqueues: captured frames and camera errors go to the service's inbox and are
handled on the service's one thread with odometry and driver states, so the
core needs no lock. A frame channel keeps the newest two captures while the
service is busy (counted as dropped).

Recovery without restarting the process: a camera error (unplugged, stream
stopped) is reported as the camera's fault, the reader stops the backend and
starts it again every ``RESTART_S`` until frames return; the core clears the
fault on the first good frame. The end of a recording (``file`` backend) is
reported once and not restarted: the run it held is over.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from services.camera.capture import CameraBackend, CameraError, CapturedFrame
from services.camera.config import CameraConfig
from services.camera.core import CameraCore
from shared.bus import BusCore
from shared.log import fields, sampled
from shared.messages import DriverState, Odometry
from shared.service import Service

__all__ = ["CameraService", "make_backend"]

TICK_HZ = 50.0    # the core's timers (lock-step gate, odometry waits, faults) are polled this often
READ_TIMEOUT_S = 0.2
RESTART_S = 1.0   # between attempts to start a failed camera again
CAPTURE_KEEP = 2  # captures waiting for the service's thread at most


def make_backend(config: CameraConfig) -> CameraBackend:
    """The configured backend; the SDK is imported only for the backend that is used."""
    if config.backend == "realsense":
        from services.camera.realsense import RealSenseBackend
        return RealSenseBackend(config.realsense)
    if config.backend == "file":
        from services.camera.file import FileBackend
        assert config.file is not None  # the config's validator requires it
        return FileBackend(config.file)
    from services.camera.oakd import OakdBackend
    return OakdBackend(config.oakd)


class CameraService(Service):
    name = "camera"
    Config = CameraConfig
    config: CameraConfig

    def __init__(self, bus: BusCore, config: CameraConfig, backend: CameraBackend | None = None) -> None:
        super().__init__(bus, config)
        self.tick_hz = TICK_HZ
        self.backend = backend or make_backend(config)
        self.core = CameraCore(config, time.monotonic())
        self._capture_key = f"{self.name}/capture"
        self._stopping = threading.Event()
        self._reader = threading.Thread(target=self._read_loop, name="camera-reader", daemon=True)
        self.restarts = 0
        self.errors = 0

    def start(self) -> None:
        self.wire({"odom": self._on_odom, "driver_state": self._on_driver})
        self._reader.start()

    # -- the service's thread --------------------------------------------------------------------
    def _on_odom(self, msg: Odometry) -> None:
        self.core.on_odom(msg)
        self._flush()

    def _on_driver(self, msg: DriverState) -> None:
        self.core.on_driver(msg, time.monotonic())
        self._flush()

    def _on_capture(self, frame: CapturedFrame) -> None:
        self.core.on_frame(frame)
        self._flush()

    def _on_error(self, error: CameraError) -> None:
        self.errors += 1
        if sampled(self.errors):  # a camera that is not there fails every RESTART_S: no log flood
            self.log.warning("camera: %s", error, extra=fields(count=self.errors))
        self.core.on_error(error)
        self._flush()

    def tick(self) -> None:
        self._flush()

    def _flush(self) -> None:
        frames, state = self.core.poll(time.monotonic())
        for frame in frames:
            self.out["rgbd"].put(frame)
        if state is not None:
            self.out["camera_state"].put(state)

    # -- the reader thread: blocking SDK calls, enqueue only ----------------------------------------
    def _read_loop(self) -> None:
        running = False
        while not self._stopping.is_set():
            try:
                if not running:
                    self.backend.start()
                    running = True
                frame = self.backend.read(READ_TIMEOUT_S)
                if frame is not None:
                    self.bus.inbox.put(self._on_capture, frame, channel=self._capture_key, keep=CAPTURE_KEEP,
                                       on_drop=self._count_drop)
            except CameraError as exc:
                self.bus.inbox.put(self._on_error, exc)
                running = False
                self._stop_backend()
                if getattr(self.backend, "ended", False):
                    return  # a recording played to its end: nothing to restart
                self.restarts += 1
                self._stopping.wait(RESTART_S)
            except Exception:  # a bug, not the camera: count it, keep trying
                self.bus.record_failure(self._capture_key)
                running = False
                self._stop_backend()
                self._stopping.wait(RESTART_S)

    def _count_drop(self) -> None:
        self.bus.counters.bump(self._capture_key, "dropped")

    def _stop_backend(self) -> None:
        try:
            self.backend.stop()
        except Exception:
            self.bus.record_failure(self._capture_key)

    def info(self) -> dict[str, Any]:
        return {"backend": self.backend.name, "fault": self.core.fault(time.monotonic()),
                "restarts": self.restarts, **self.core.info()}

    def stop(self) -> None:
        self._stopping.set()
        if self._reader.is_alive():
            self._reader.join(timeout=5)
        self._stop_backend()
