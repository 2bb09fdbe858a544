"""SIGTERM (systemd, ``timeout``, a supervisor) or SIGINT to a command that started processes
leaves none of them behind (issue 32).

Each command runs as a real ``ovamos`` process in a session of its own; once its children are up,
every descendant is recorded (from /proc), the signal goes to the command alone (its children
are in sessions of their own, and get nothing from a terminal or from us), and then none of the
recorded processes may be left. The command's own word tells the clean-up ran in it (after
unwinding, SIGTERM ends it with "SIGTERM: what this process started is stopped"; ``ovamos up``
stops cleanly with 0): a child's own guard against its parent dying (PR_SET_PDEATHSIG) would
otherwise hide a command that merely died.

The guard pieces (:func:`ovamos.shared.procs.signals_unwind`, :class:`ovamos.shared.procs.deferred_signals`,
``die_with_parent``) are checked on their own in small child scripts at the end.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from ovamos.shared.procs import free_port, loopback
from tests.polling import port_open, wait_for

REPO = Path(__file__).resolve().parents[1]
OVAMOS = Path(sys.executable).with_name("ovamos")
STARTUP_S = 150.0   # generous: other suites load this 2-core machine
STOP_S = 90.0       # the supervisor gives each child up to 10 s after SIGTERM

pytestmark = [pytest.mark.system, pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc (Linux)")]


# -- processes from /proc ---------------------------------------------------------------------
def _stat(pid: int) -> tuple[str, int, int] | None:
    """(state, parent pid, start time) of ``pid``; None once it is gone."""
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = raw[raw.rindex(")") + 2:].split()
    return fields[0], int(fields[1]), int(fields[19])


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def descendants(root: int) -> dict[int, int]:
    """Every live descendant of ``root``: pid -> start time (to tell a reused pid)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (stat := _stat(int(entry.name))) is not None and stat[0] not in "ZX":
            children.setdefault(stat[1], []).append(int(entry.name))
    found: dict[int, int] = {}
    todo = [root]
    while todo:
        for pid in children.get(todo.pop(), []):
            if (stat := _stat(pid)) is not None:
                found[pid] = stat[2]
                todo.append(pid)
    return found


def alive(pid: int, started: int) -> bool:
    """Whether that process (not a later one with its pid) still runs; a zombie has ended."""
    stat = _stat(pid)
    return stat is not None and stat[2] == started and stat[0] not in "ZX"


ENDED = "SIGTERM: what this process started is stopped; ending"


def survivors(recorded: dict[int, int], seen: dict[int, str]) -> dict[int, str]:
    """The recorded processes still alive, each with its command line; one that reads empty (an
    exiting process has released its memory, and with it its command line) with the one ``seen``
    last, so the resource tracker ending as we look is still known for what it is."""
    return {pid: _cmdline(pid) or seen.get(pid, "") for pid, started in recorded.items() if alive(pid, started)}


def _resource_tracker(cmdline: str) -> bool:
    """multiprocessing's semaphore tracker: it ends by itself once its last user has (after its parent)."""
    return "resource_tracker" in cmdline


# -- a command under test ---------------------------------------------------------------------
@dataclass
class Command:
    """An ``ovamos`` command started in a session of its own, output to files."""

    argv: list[str]
    folder: Path
    proc: subprocess.Popen = field(init=False)
    recorded: dict[int, int] = field(default_factory=dict)
    seen: dict[int, str] = field(default_factory=dict)  # pid -> its last non-empty command line

    def start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        exe = [str(OVAMOS)] if OVAMOS.exists() else [sys.executable, "-m", "ovamos.cli"]
        env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONUNBUFFERED": "1"}
        with self.out.open("wb") as out, self.err.open("wb") as err:
            self.proc = subprocess.Popen([*exe, *self.argv], stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                                         cwd=self.folder, env=env, start_new_session=True)

    @property
    def out(self) -> Path:
        return self.folder / "stdout.txt"

    @property
    def err(self) -> Path:
        return self.folder / "stderr.txt"

    def output(self) -> str:
        return self.out.read_text(errors="replace") + self.err.read_text(errors="replace")

    def children(self, needle: str = "") -> list[int]:
        """The command's live direct children whose command line contains ``needle``."""
        return [pid for pid in descendants(self.proc.pid)
                if (_stat(pid) or ("", 0, 0))[1] == self.proc.pid and needle in _cmdline(pid)]

    def wait_until(self, predicate: Callable[[], object], what: str, timeout: float = STARTUP_S) -> None:
        def ready() -> object:
            if self.proc.poll() is not None:
                pytest.fail(f"{self.argv[0]} ended ({self.proc.returncode}) before {what}:\n"
                            f"{self.output()[-3000:]}")
            self.record()
            return predicate()

        wait_for(ready, timeout=timeout, what=what, interval=0.2)

    def record(self) -> None:
        """Every live descendant, and what each runs."""
        found = descendants(self.proc.pid)
        self.recorded.update(found)
        self.seen.update({pid: cmd for pid in found if (cmd := _cmdline(pid))})

    def signal_and_wait(self, sig: int) -> int:
        """Record every descendant, send ``sig`` to the command alone, wait for it to exit (still
        recording what it starts meanwhile); its exit code."""
        self.record()
        assert self.recorded, "the command had no children to leave behind"
        os.kill(self.proc.pid, sig)
        deadline = time.monotonic() + STOP_S
        while self.proc.poll() is None:
            self.record()
            if time.monotonic() > deadline:
                pytest.fail(f"{self.argv[0]} still runs {STOP_S:.0f} s after {signal.Signals(sig).name}:\n"
                            f"{self.output()[-3000:]}")
            time.sleep(0.05)
        return self.proc.returncode

    def assert_ended_by_sigterm(self) -> None:
        """SIGTERM unwound the command (its clean-up ran), then ended it as the signal does."""
        assert self.signal_and_wait(signal.SIGTERM) == -signal.SIGTERM, self.output()[-3000:]
        assert ENDED in self.output(), self.output()[-3000:]
        self.assert_nothing_left()

    def assert_nothing_left(self) -> None:
        """At the command's exit its children are gone (it stopped them); the multiprocessing
        resource tracker, which ends after its last user, goes soon after."""
        left = survivors(self.recorded, self.seen)
        assert not {p: c for p, c in left.items() if not _resource_tracker(c)}, \
            f"left running after the command ended: {left}\n{self.output()[-3000:]}"
        wait_for(lambda: not survivors(self.recorded, self.seen), timeout=30,
                 what=f"the resource tracker to end: {survivors(self.recorded, self.seen)}")

    def cleanup(self) -> None:
        """Whatever survived a failing test: the command's group, then each recorded process's."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        for pid, started in self.recorded.items():
            if alive(pid, started):
                for kill in (lambda: os.killpg(os.getpgid(pid), signal.SIGKILL),
                             lambda: os.kill(pid, signal.SIGKILL)):
                    try:
                        kill()
                    except OSError:
                        pass


@pytest.fixture
def command(tmp_path: Path) -> Iterator[Callable[..., Command]]:
    made: list[Command] = []

    def start(*argv: str, folder: str = "cmd") -> Command:
        cmd = Command(list(argv), tmp_path / folder)
        cmd.start()
        made.append(cmd)
        return cmd

    yield start
    for cmd in made:
        cmd.cleanup()


# -- the commands ---------------------------------------------------------------------------
def test_sigterm_to_ovamos_demo_leaves_no_process(command: Callable[..., Command], tmp_path: Path) -> None:
    cmd = command("demo", "--out", str(tmp_path / "demo"), "--timeout", "120")
    entries = 7  # router, recorder, mapping, perception, planner, sim, gateway
    cmd.wait_until(lambda: len(cmd.children("ovamos.cli")) >= entries, f"the demo's {entries} processes")
    cmd.wait_until(lambda: re.search(r"gateway http://127\.0\.0\.1:(\d+)", cmd.output()), "the gateway's URL")
    port = int(re.search(r"gateway http://127\.0\.0\.1:(\d+)", cmd.output()).group(1))  # type: ignore[union-attr]
    cmd.wait_until(lambda: port_open(port), f"the gateway on port {port}")
    cmd.assert_ended_by_sigterm()


def test_sigterm_to_a_kept_running_demo_leaves_no_process(command: Callable[..., Command],
                                                          tmp_path: Path) -> None:
    """``--keep-running`` installs its own SIGINT / SIGTERM handlers: they end the wait, and the
    supervisor stops everything as the demo leaves (exit code 1: the 1 s search was cancelled)."""
    cmd = command("demo", "--out", str(tmp_path / "demo"), "--timeout", "1", "--keep-running", "--no-record")
    cmd.wait_until(lambda: "Everything keeps running" in cmd.output(), "the demo to keep running")
    assert len(cmd.children("ovamos.cli")) == 6  # router, mapping, perception, planner, sim, gateway
    assert cmd.signal_and_wait(signal.SIGTERM) == 1, cmd.output()[-3000:]
    cmd.assert_nothing_left()


def test_sigterm_to_ovamos_up_leaves_no_process(command: Callable[..., Command], tmp_path: Path) -> None:
    port = free_port()
    profile = tmp_path / "sigterm.toml"
    profile.write_text(textwrap.dedent(f"""
        robot_id = "sigterm"
        [router]
        config = "{REPO}/deploy/zenoh/router.json5"
        listen = ["{loopback(port)}"]
        [[services]]
        service = "testpattern"
        zenoh = "{REPO}/deploy/zenoh/service.json5"
        connect = ["{loopback(port)}"]
        [[services]]
        service = "testpattern"
        instance = "1"
        zenoh = "{REPO}/deploy/zenoh/service.json5"
        connect = ["{loopback(port)}"]
    """))
    cmd = command("up", str(profile), "--log-dir", str(tmp_path / "logs"))
    cmd.wait_until(lambda: port_open(port), f"the router on port {port}")
    cmd.wait_until(lambda: len(cmd.children("ovamos.cli")) >= 3, "the router and both services")
    cmd.wait_until(lambda: "testpattern-1" in cmd.output(), "the status table")
    assert cmd.signal_and_wait(signal.SIGTERM) == 0, cmd.output()[-3000:]
    cmd.assert_nothing_left()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_ovamos_bench_transport_leaves_no_process(command: Callable[..., Command],
                                                              sig: int) -> None:
    cmd = command("bench", "transport", "--frames", "10", "--runs", "100000", "--gap-ms", "1")
    cmd.wait_until(lambda: len(cmd.children("router")) == 1 and len(cmd.children("multiprocessing")) >= 5,
                   "the router and the 5 echo processes")
    cmd.wait_until(lambda: "run 1/" in cmd.output(), "the first measured run")
    if sig == signal.SIGTERM:
        cmd.assert_ended_by_sigterm()
    else:  # KeyboardInterrupt, which the command line reports with exit code 130
        assert cmd.signal_and_wait(sig) == 128 + sig, cmd.output()[-3000:]
        cmd.assert_nothing_left()


def test_sigterm_to_ovamos_bench_transport_stages_leaves_no_process(command: Callable[..., Command]) -> None:
    cmd = command("bench", "transport", "--stages", "--frames", "100000", "--gap-ms", "1")
    cmd.wait_until(lambda: len(cmd.children("router")) == 1 and len(cmd.children("multiprocessing")) >= 4,
                   "the router and the 4 echo processes")
    cmd.assert_ended_by_sigterm()


def test_sigterm_to_ovamos_bench_transport_tls_leaves_no_process(command: Callable[..., Command]) -> None:
    cmd = command("bench", "transport", "--tls", "--frames", "10", "--runs", "100000", "--gap-ms", "1")
    cmd.wait_until(lambda: "run 1/" in cmd.output(), "the first measured run over the three links")
    assert len(cmd.children("router")) == 6
    cmd.assert_ended_by_sigterm()


# -- the pieces -------------------------------------------------------------------------------
def _script(tmp_path: Path, body: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(body)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _lines_until(proc: subprocess.Popen, marker: str) -> list[str]:
    lines = []
    for line in proc.stdout or ():
        lines.append(line.rstrip("\n"))
        if line.startswith(marker):
            return lines
    pytest.fail(f"no {marker!r} line; output: {lines}")


@pytest.fixture
def scripts() -> Iterator[list[subprocess.Popen]]:
    made: list[subprocess.Popen] = []
    yield made
    for proc in made:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        if proc.stdout:
            proc.stdout.close()


def test_sigterm_unwinds_and_then_ends_the_process(tmp_path: Path, scripts: list[subprocess.Popen]) -> None:
    """Inside the scope SIGTERM unwinds (``except`` / ``finally`` run), a deferred block holds a
    signal back to its end, SIGINT stays KeyboardInterrupt; the scope's end lets SIGTERM end the
    process, as it would have at once without the scope."""
    proc = _script(tmp_path, """
        import os, signal
        from ovamos.shared.procs import Terminated, deferred_signals, signals_unwind
        kill = lambda sig: os.kill(os.getpid(), sig)
        with signals_unwind():
            try:
                kill(signal.SIGTERM)
                print("not reached", flush=True)
            except Terminated as exc:
                print("unwound", exc.code, flush=True)
            try:
                with deferred_signals():
                    kill(signal.SIGINT)
                    kill(signal.SIGTERM)
                    print("deferred", flush=True)
            except Terminated as exc:
                print("after the block", exc.code, flush=True)
            try:
                kill(signal.SIGINT)
            except KeyboardInterrupt:
                print("interrupted", flush=True)
            print("CLOSING", flush=True)
        print("not reached either", flush=True)
    """)
    scripts.append(proc)
    assert _lines_until(proc, "CLOSING") == ["unwound 143", "deferred", "after the block 143", "interrupted",
                                             "CLOSING"]
    assert proc.wait(30) == -signal.SIGTERM
    assert (proc.stdout.read() if proc.stdout else "").strip() == ENDED


def test_signals_unwind_restores_the_handlers_and_keeps_the_programs_own(
        tmp_path: Path, scripts: list[subprocess.Popen]) -> None:
    proc = _script(tmp_path, """
        import os, signal
        from ovamos.shared.procs import signals_unwind
        def own(*_): print("own handler", flush=True)
        signal.signal(signal.SIGUSR1, own)
        with signals_unwind():
            with signals_unwind():  # nested: the outer one restores
                print("taken", signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, own), flush=True)
            signal.signal(signal.SIGHUP, own)  # the program's own, set inside: left in place
            try:
                os.kill(os.getpid(), signal.SIGINT)
            except KeyboardInterrupt:
                print("interrupted", flush=True)
        print("restored", signal.getsignal(signal.SIGTERM) == signal.SIG_DFL,
              signal.getsignal(signal.SIGINT) is signal.default_int_handler,
              signal.getsignal(signal.SIGHUP) is own, signal.getsignal(signal.SIGUSR1) is own, flush=True)
        os.kill(os.getpid(), signal.SIGHUP)
        print("END", flush=True)
    """)
    scripts.append(proc)
    assert _lines_until(proc, "END") == ["taken True", "interrupted", "restored True True True True",
                                         "own handler", "END"]
    assert proc.wait(30) == 0


def test_a_child_dies_with_its_sigkilled_parent(tmp_path: Path, scripts: list[subprocess.Popen]) -> None:
    """A parent SIGKILLed runs no clean-up: its router child still gets SIGTERM (PR_SET_PDEATHSIG)."""
    port = free_port()
    proc = _script(tmp_path, f"""
        import time
        from ovamos.shared.procs import start_cli
        router = start_cli(["router", "--listen", "{loopback(port)}", "--log-level", "WARNING"])
        print("CHILD", router.pid, flush=True)
        time.sleep(600)
    """)
    scripts.append(proc)
    child = int(_lines_until(proc, "CHILD")[-1].split()[1])
    stat = _stat(child)
    assert stat is not None
    try:
        wait_for(lambda: port_open(port), timeout=60, what="the router")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        wait_for(lambda: not alive(child, stat[2]), timeout=30, what="the orphaned router to end")
    finally:
        try:
            os.killpg(child, signal.SIGKILL)
        except OSError:
            pass
