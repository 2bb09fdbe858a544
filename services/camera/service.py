"""The camera service (on the robot): SDK frames in, posed ``sensors/rgbd`` frames and ``camera/state`` out.

A thin adapter over :class:`ovamos.services.camera.core.CameraCore`. The SDK's blocking
reads run on a reader thread of their own, which, like Zenoh's callbacks, only
enqueues: captured frames and camera errors go to the service's inbox and are
handled on the service's one thread with odometry and driver states, so the
core needs no lock. A live camera's frame channel keeps the newest two captures
while the service is busy (counted as dropped): a late frame is worth less than
the next one. A backend that promises every frame (``lossless``: a recording
played at ``rate = "max"``, whose playback waits for its reader) is paced
instead: the reader waits, before reading the next frame, until the service has
room for it, so nothing is dropped and memory stays bounded. It starts reading
only once odometry has come (a frame captured before the first odometry the
service hears could only be skipped as older than it). Room is counted
over the captures queued for the service's thread and the frames the core holds
waiting for odometry together, up to the core's own ``odometry.max_pending``
(more, and the core would skip its oldest). Stopping wakes a waiting reader.

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

from ovamos.services.camera.capture import CameraBackend, CameraError, CapturedFrame
from ovamos.services.camera.config import CameraConfig
from ovamos.services.camera.core import CameraCore
from ovamos.shared.bus import BusCore
from ovamos.shared.log import fields, sampled
from ovamos.shared.messages import DriverState, Odometry
from ovamos.shared.service import Service

__all__ = ["CameraService", "make_backend"]

TICK_HZ = 50.0    # the core's timers (lock-step gate, odometry waits, faults) are polled this often
READ_TIMEOUT_S = 0.2
RESTART_S = 1.0   # between attempts to start a failed camera again
CAPTURE_KEEP = 2  # captures waiting for the service's thread at most (a live camera)


def make_backend(config: CameraConfig) -> CameraBackend:
    """The configured backend; the SDK is imported only for the backend that is used."""
    if config.backend == "realsense":
        from ovamos.services.camera.realsense import RealSenseBackend
        return RealSenseBackend(config.realsense)
    if config.backend == "file":
        from ovamos.services.camera.file import FileBackend
        assert config.file is not None  # the config's validator requires it
        return FileBackend(config.file)
    if config.backend == "ros2":
        from ovamos.services.camera.ros2 import Ros2Backend
        return Ros2Backend(config.ros2)
    from ovamos.services.camera.oakd import OakdBackend
    return OakdBackend(config.oakd)


class _Pacer:
    """A lossless backend's hand-over: the reader takes a place before it reads a frame and
    waits until odometry has come, then while ``capacity`` frames are in flight (queued for the
    service's thread, or held by the core for odometry); the service's thread gives places back
    as the core decides frames.
    """

    def __init__(self, capacity: int, stopping: threading.Event) -> None:
        self._room = threading.Condition()
        self._capacity = capacity
        self._stopping = stopping
        self.posing = False  # odometry has come: frames read from now on can be posed
        self._queued = 0  # places taken by the reader and not yet handed to the core
        self._held = 0    # frames the core holds (as the service's thread last saw)
        self.waits = 0    # times the reader waited for room (``ovamos status``)

    def take(self) -> bool:
        """Reader: wait for a place for the next frame; False once the service stops."""
        with self._room:
            waited = False
            while ((not self.posing or self._queued + self._held >= self._capacity)
                   and not self._stopping.is_set()):
                waited = True
                self._room.wait(READ_TIMEOUT_S)  # stop() notifies; the timeout is a safety net
            self.waits += waited
            if self._stopping.is_set():
                return False
            self._queued += 1
            return True

    def cancel(self) -> None:
        """Reader: the place taken was not used (no frame came, or the read failed)."""
        self.update(1, None)

    def update(self, taken: int, held: int | None) -> None:
        """``taken`` places handed to the core, which now holds ``held`` frames (None: unchanged)."""
        with self._room:
            self._queued -= taken
            if held is not None:
                self._held = held
            if self._queued + self._held < self._capacity:
                self._room.notify()

    def start_posing(self) -> None:
        """Service's thread: odometry has come, the reader may read."""
        with self._room:
            if not self.posing:
                self.posing = True
                self._room.notify()

    def wake(self) -> None:
        with self._room:
            self._room.notify_all()

    def in_flight(self) -> int:
        with self._room:
            return self._queued + self._held


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
        self._pacer: _Pacer | None = None
        if getattr(self.backend, "lossless", False):  # every frame: wait for the service, never drop
            self._pacer = _Pacer(config.odometry.max_pending, self._stopping)
        self._reader = threading.Thread(target=self._read_loop, name="camera-reader", daemon=True)
        self.restarts = 0
        self.errors = 0

    def start(self) -> None:
        self.wire({"odom": self._on_odom, "driver_state": self._on_driver})
        self._reader.start()

    # -- the service's thread --------------------------------------------------------------------
    def _on_odom(self, msg: Odometry) -> None:
        self.core.on_odom(msg)
        if self._pacer is not None:
            self._pacer.start_posing()
        self._flush()

    def _on_driver(self, msg: DriverState) -> None:
        self.core.on_driver(msg, time.monotonic())
        self._flush()

    def _on_capture(self, frame: CapturedFrame) -> None:
        self.core.on_frame(frame)
        self._flush()

    def _on_paced_capture(self, frame: CapturedFrame) -> None:
        assert self._pacer is not None
        try:
            self._on_capture(frame)
        finally:  # even if the core failed on it: a place lost would stall the reader for good
            self._pacer.update(1, self.core.pending)

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
        if self._pacer is not None:  # frames decided (posed or skipped) leave room for the reader
            self._pacer.update(0, self.core.pending)

    # -- the reader thread: blocking SDK calls, enqueue only ----------------------------------------
    def _read_loop(self) -> None:
        """The only thread that touches the backend: an SDK stopped from another thread while this
        one is inside it can hang both."""
        try:
            self._read_until_stopped()
        finally:
            self._stop_backend()

    def _read_until_stopped(self) -> None:
        running = False
        while not self._stopping.is_set():
            try:
                if not running:
                    self.backend.start()
                    running = True
                if self._pacer is not None:
                    self._read_paced(self._pacer)
                    continue
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

    def _read_paced(self, pacer: _Pacer) -> None:
        """One frame of a lossless backend: a place first (the playback waits meanwhile), then
        the read, then an ordinary event, which the inbox never drops below its limit."""
        if not pacer.take():
            return  # stopping
        try:
            frame = self.backend.read(READ_TIMEOUT_S)
        except BaseException:
            pacer.cancel()
            raise
        if frame is None:
            pacer.cancel()
        else:
            self.bus.inbox.put(self._on_paced_capture, frame)

    def _count_drop(self) -> None:
        self.bus.counters.bump(self._capture_key, "dropped")

    def _stop_backend(self) -> None:
        try:
            self.backend.stop()
        except Exception:
            self.bus.record_failure(self._capture_key)

    def info(self) -> dict[str, Any]:
        pacing = {} if self._pacer is None else {"paced_in_flight": self._pacer.in_flight(),
                                                  "paced_waits": self._pacer.waits,
                                                  "paced_posing": self._pacer.posing}
        return {"backend": self.backend.name, "fault": self.core.fault(time.monotonic()),
                "restarts": self.restarts, **pacing, **self.core.info()}

    def stop(self) -> None:
        self._stopping.set()
        if self._pacer is not None:
            self._pacer.wake()  # a reader waiting for room sees the stop now
        if self._reader.is_alive():
            self._reader.join(timeout=5)
        if self._reader.is_alive():  # inside the SDK: it stops the backend when it comes out
            self.log.warning("camera: the reader is still in the camera SDK 5 s after the stop")
