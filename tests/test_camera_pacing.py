"""The camera service's hand-over from its reader thread, on the fake bus without an SDK: a
``lossless`` backend (a recording at ``rate = "max"``) is paced, never dropped, with at most
``odometry.max_pending`` frames in flight, and a stop while the reader waits does not hang; a live
camera keeps only the newest captures while the service is busy, as before."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from ovamos.services.camera.capture import CameraError, CapturedFrame
from ovamos.services.camera.config import CameraConfig, OdometryConfig
from ovamos.services.camera.service import CAPTURE_KEEP, CameraService
from ovamos.shared import keys
from ovamos.shared.fake_bus import FakeNetwork
from ovamos.shared.messages import Intrinsics, Odometry, RgbdFrame
from tests.polling import wait_for

pytestmark = pytest.mark.serial  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

ROBOT = "r1"
CAPACITY = 4  # odometry.max_pending here: frames in flight at most
INTRINSICS = Intrinsics(fx=4.0, fy=4.0, cx=2.0, cy=2.0)


class Frames:
    """A backend of ``count`` 4x4 frames (frame n's colour is n), as fast as they are read once
    ``go`` is set, then the end of the recording (``count`` None: no end)."""

    name = "frames"

    def __init__(self, count: int | None, *, lossless: bool) -> None:
        self.count, self.lossless = count, lossless
        self.go = threading.Event()
        self.delivered = 0
        self.ended = False
        self.stopped_by: list[str] = []  # the thread of each stop()

    def start(self) -> None:
        self.delivered, self.ended = 0, False

    def read(self, timeout_s: float) -> CapturedFrame | None:
        if not self.go.wait(timeout_s):
            return None
        n = self.delivered
        if self.count is not None and n >= self.count:
            self.ended = True
            raise CameraError("end of recording: frames")
        self.delivered += 1
        return CapturedFrame(rgb=np.full((4, 4, 3), n % 256, np.uint8),
                             depth=np.full((4, 4), 1000, np.uint16), depth_scale=0.001,
                             intrinsics=INTRINSICS, device_time_s=n / 30.0, host_time_s=time.monotonic())

    def stop(self) -> None:
        self.stopped_by.append(threading.current_thread().name)


class Rig:
    """The camera service on a fake bus, the service's thread being the test's (``step``), and
    the base's odometry at 50 Hz from a thread of its own (standing still)."""

    def __init__(self, backend: Frames) -> None:
        config = CameraConfig(lock_step=False, odometry=OdometryConfig(max_pending=CAPACITY, wait_s=5.0))
        self.net = FakeNetwork()
        self.backend = backend
        self.service = CameraService(self.net.bus(ROBOT, "camera"), config, backend=backend)
        tester = self.net.bus(ROBOT, "tester")
        self.frames: list[RgbdFrame] = []
        tester.subscribe(keys.rgbd(ROBOT), RgbdFrame, self.frames.append)
        self._odom = tester.publisher(keys.odom(ROBOT), Odometry)
        self._done = threading.Event()
        self._base = threading.Thread(target=self._odometry, daemon=True)

    def _odometry(self) -> None:
        seq = 0
        while not self._done.is_set():
            seq += 1
            self._odom.put(Odometry(seq=seq, stamp=time.time(), x=1.0, y=2.0, yaw=0.5))
            self._done.wait(0.02)

    def __enter__(self) -> Rig:
        self.service.start()
        self._base.start()
        wait_for(lambda: self.step() >= 0 and self.service.core.info()["odometry"], 10,
                 "odometry in the core")
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._base.join(5)
        self.service.stop()

    def step(self) -> int:
        """One turn of the service's loop: what is queued, then a tick."""
        ran = self.net.pump()
        self.service.tick()
        return ran + self.net.pump()

    def dropped(self) -> int:
        entry = self.service.bus.counters.snapshot().get("camera/capture")
        return entry.dropped if entry else 0


def test_a_lossless_backend_waits_for_the_service_and_every_frame_is_published() -> None:
    count = 5 * CAPACITY
    with Rig(Frames(count, lossless=True)) as rig:
        rig.backend.go.set()
        # The service's thread is busy (not pumped): the reader stops at CAPACITY in flight.
        wait_for(lambda: rig.service.info()["paced_in_flight"] == CAPACITY, 10,
                 "the reader to fill its places")
        assert rig.backend.delivered == CAPACITY and rig.dropped() == 0
        most = 0

        def played() -> bool:
            nonlocal most
            rig.step()
            info = rig.service.info()
            most = max(most, info["paced_in_flight"], info["pending"])
            return rig.backend.ended and len(rig.frames) == count and info["pending"] == 0

        wait_for(played, 20, "every frame published", interval=0.01)
        info = rig.service.info()
    assert [int(f.rgb[0, 0, 0]) for f in rig.frames] == list(range(count))  # all, in order, once
    assert rig.dropped() == 0 and info["skipped"] == {} and info["rejected"] == {}
    assert most <= CAPACITY and info["paced_waits"] >= 1 and info["paced_in_flight"] == 0


def test_stopping_while_the_reader_waits_for_room_does_not_hang() -> None:
    rig = Rig(Frames(None, lossless=True))
    with rig:
        rig.backend.go.set()
        wait_for(lambda: rig.service.info()["paced_in_flight"] == CAPACITY, 10, "the reader to wait")
        started = time.monotonic()
    assert time.monotonic() - started < 2.0  # the waiting reader saw the stop (join gives up at 5 s)
    assert not rig.service._reader.is_alive()
    assert rig.backend.delivered == CAPACITY
    # only the reader touches the backend: an SDK stopped from another thread mid-call can hang
    assert rig.backend.stopped_by == ["camera-reader"]


def test_a_live_camera_keeps_the_newest_captures_while_the_service_is_busy() -> None:
    count = 10
    with Rig(Frames(count, lossless=False)) as rig:
        rig.backend.go.set()
        wait_for(lambda: not rig.service._reader.is_alive(), 10, "the reader to reach the end")
        assert rig.backend.delivered == count  # never waited for the service
        assert rig.dropped() == count - CAPTURE_KEEP
        assert "paced_in_flight" not in rig.service.info()
        wait_for(lambda: rig.step() >= 0 and len(rig.frames) == CAPTURE_KEEP
                 and rig.service.core.pending == 0, 10, "the kept captures published")
    assert [int(f.rgb[0, 0, 0]) for f in rig.frames] == list(range(count - CAPTURE_KEEP, count))
