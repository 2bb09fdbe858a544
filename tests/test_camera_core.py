"""The camera core without a camera: clock mapping, odometry interpolation, lock-step, faults.

Time is injected everywhere (host monotonic times are plain numbers, the wall clock is the
monotonic one plus ``WALL``), so every case is exact and instant.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from ovamos.services.camera.capture import CapturedFrame
from ovamos.services.camera.clock import DeviceClock, HostClock, make_clock
from ovamos.services.camera.config import CameraConfig, ClockConfig
from ovamos.services.camera.core import CLOCK_JUMP, DEPTH_ALL_ZERO, CameraCore
from ovamos.services.camera.pose import BasePose, Miss, OdometryBuffer, wrap_angle
from ovamos.shared.camera import camera_pose as sim_camera_pose
from ovamos.shared.config import ServiceConfigError, read_config
from ovamos.shared.messages import CameraState, DriverMode, DriverState, Intrinsics, Odometry, RgbdFrame
from ovamos.shared.sessions import SessionSwitch

WALL = 1.7e9            # host wall clock = host monotonic + WALL
K = Intrinsics(fx=20.0, fy=20.0, cx=7.5, cy=5.5)
H, W = 12, 16


def shot(device: float, host: float, *, depth: int = 1500, mm: bool = True) -> CapturedFrame:
    """A small frame: device time ``device``, received at host monotonic ``host``."""
    return CapturedFrame(rgb=np.full((H, W, 3), 90, np.uint8), depth=np.full((H, W), depth, np.uint16),
                         depth_scale=0.001 if mm else 0.0001, intrinsics=K, device_time_s=device,
                         host_time_s=host)


def odom(seq: int, t: float, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, *,
         linear: float = 0.0, angular: float = 0.0, session: str = "") -> Odometry:
    """Odometry measured at host monotonic ``t`` (stamped with the wall clock, as the driver does)."""
    return Odometry(seq=seq, stamp=t + WALL, x=x, y=y, yaw=yaw, linear=linear, angular=angular,
                    odom_session=session)


def driver(completed: int, mode: DriverMode = DriverMode.READY, active: int | None = None) -> DriverState:
    return DriverState(stamp=0.0, mode=mode, last_completed=completed, active_action=active)


def make_core(now: float = 0.0, **overrides: object) -> CameraCore:
    """A core started at host monotonic ``now``. Unless a test configures ``clock``, frames are
    stamped on the host clock (``shot(c, r)``: captured at c, received at r), so that tests of
    other things need not reason about the clock estimate; unless it configures ``odometry``, all
    the odometry a test gives stays in the window (it is given ahead of the frames)."""
    overrides.setdefault("clock", {"source": "host"})
    overrides.setdefault("odometry", {"window_s": 100.0})
    return CameraCore(CameraConfig.model_validate(overrides), now, wall_offset=lambda: WALL)


def still_odometry(core: CameraCore, t0: float, t1: float, hz: float = 50.0) -> None:
    """A base standing at the origin, odometry from t0 to t1 (host monotonic), seq by time."""
    for k in range(int(round((t1 - t0) * hz)) + 1):
        t = t0 + k / hz
        core.on_odom(odom(int(round(t * 1000)), t))


def pose_of(frame: RgbdFrame) -> tuple[float, float, float]:
    """(x, y, yaw) of the base under a frame taken by the default (level, centred) mount."""
    m = frame.pose_matrix
    return float(m[0, 3]), float(m[1, 3]), math.atan2(m[1, 2], m[0, 2])


# -- config --------------------------------------------------------------------------------------


def test_config_rejects_unknown_and_out_of_range_keys(tmp_path) -> None:
    path = tmp_path / "camera.toml"
    path.write_text("backend = 'realsense'\n[mount]\nz = 0.5\npitch = 12.0\n")
    config = read_config(CameraConfig, path)
    assert config.mount.z == 0.5 and config.mount.pitch == 12.0 and config.lock_step
    path.write_text("[mount]\nheight = 0.5\n")
    with pytest.raises(ServiceConfigError, match="mount.height"):
        read_config(CameraConfig, path)
    with pytest.raises(ServiceConfigError, match="max_hz"):
        read_config(CameraConfig, None, {"max_hz": 0})
    with pytest.raises(ServiceConfigError, match="backend"):
        read_config(CameraConfig, None, {"backend": "kinect"})


# -- device clock -> host monotonic clock ---------------------------------------------------------


def test_clock_offset_is_the_least_delay_despite_jitter() -> None:
    """Delays of 30 ms plus jitter up to 40 ms and a 0.3 s stall: the capture times come out
    within 2 ms of the truth once a fast frame was seen, and never after the receipt."""
    rng = np.random.default_rng(1)
    clock = DeviceClock(window_s=5.0, reset_s=0.5, min_latency_s=0.030)
    errors = []
    for j in range(300):
        capture = 50.0 + j / 30
        delay = 0.030 + rng.exponential(0.010) + (0.3 if j == 150 else 0.0)
        host = capture + delay
        got = clock.to_host(capture * (1 + 2e-5) - 1234.5, host)  # own epoch, 20 ppm fast
        assert got is not None and got <= host
        errors.append(got - capture)
    assert max(abs(e) for e in errors[10:]) < 0.002, max(errors[10:])
    assert clock.resets == 0, "one slow frame is not a clock jump"


def test_clock_without_min_latency_is_late_by_the_least_delay() -> None:
    clock = DeviceClock()
    for j in range(10):
        got = clock.to_host(j / 30, 7.0 + j / 30 + 0.025)
    assert got == pytest.approx(7.0 + 9 / 30 + 0.025)


def test_clock_device_reset_restarts_the_estimate_at_once() -> None:
    """The camera was re-plugged: its counter starts at 0 again. The next frame's time is right
    (it cannot be wrong by the old offset, thousands of seconds)."""
    clock = DeviceClock(min_latency_s=0.02)
    for j in range(60):
        clock.to_host(5000.0 + j / 30, 10.0 + j / 30 + 0.02)
    for j in range(30):
        got = clock.to_host(0.1 + j / 30, 13.0 + j / 30 + 0.02 + 0.003 * (j % 2))
        assert got == pytest.approx(13.0 + j / 30, abs=0.004)
    assert clock.resets == 1


def test_clock_that_jumps_later_is_confirmed_before_use() -> None:
    """A device clock that paused for 2 s: the first frames after it look 2 s late; they are not
    timed (None) until ``reset_confirm`` frames agree, then the estimate follows the new clock.
    A clock that jumps ahead (a negative delay) restarts at once."""
    clock = DeviceClock(reset_confirm=3)
    for j in range(30):
        clock.to_host(100.0 + j / 30, 20.0 + j / 30)
    assert clock.to_host(101.0, 23.0) is None
    assert clock.to_host(101.0 + 1 / 30, 23.0 + 1 / 30) is None
    assert clock.to_host(101.0 + 2 / 30, 23.0 + 2 / 30) == pytest.approx(23.0 + 2 / 30)
    assert clock.to_host(101.1, 23.1) == pytest.approx(23.1)
    assert clock.resets == 1
    assert clock.to_host(160.0, 23.2) == pytest.approx(23.2)  # jumped ahead 59 s
    assert clock.resets == 2


def test_clock_window_forgets_old_fast_frames() -> None:
    """The estimate is the least delay of the last ``window_s`` only: a drifting device clock
    (here a 1 ms/s drift, exaggerated) is followed instead of piling up error."""
    clock = DeviceClock(window_s=1.0)
    for j in range(300):
        t = j / 30
        got = clock.to_host(t * (1 - 1e-3), t)
    assert got == pytest.approx(t, abs=0.0012)


def test_host_clock_passes_device_times_through() -> None:
    assert isinstance(make_clock(ClockConfig(source="host")), HostClock)
    assert make_clock(ClockConfig(source="host")).to_host(12.5, 12.6) == 12.5
    assert isinstance(make_clock(ClockConfig()), DeviceClock)


# -- odometry buffer ------------------------------------------------------------------------------


def test_buffer_interpolates_translation_and_shortest_arc_yaw() -> None:
    buf = OdometryBuffer(window_s=2.0, tolerance_s=0.05)
    buf.add(odom(0, 1.00, 0.0, 0.0, 3.0))
    buf.add(odom(1, 1.02, 0.2, -0.1, -3.0))   # through +-pi: 0.283 rad, not 6 rad the long way
    pose = buf.pose_at(1.005 + WALL)
    assert isinstance(pose, BasePose)
    # (stamps near 1.7e9 s hold times to 0.24 us: the fraction is right to 1e-5)
    assert (pose.x, pose.y) == pytest.approx((0.05, -0.025), abs=1e-5)
    step = wrap_angle(-3.0 - 3.0)
    assert pose.yaw == pytest.approx(wrap_angle(3.0 + 0.25 * step), abs=1e-5)
    middle = buf.pose_at(1.01 + WALL)
    assert isinstance(middle, BasePose) and abs(middle.yaw) == pytest.approx(math.pi, abs=1e-5)
    exact = buf.pose_at(1.02 + WALL)
    assert isinstance(exact, BasePose) and exact.x == 0.2


def test_buffer_says_why_it_has_no_pose() -> None:
    buf = OdometryBuffer(window_s=1.0, tolerance_s=0.05)
    assert buf.pose_at(WALL) is Miss.NO_ODOMETRY
    for k in range(101):
        buf.add(odom(k, k / 50, x=k / 50))
    assert buf.oldest == pytest.approx(1.0 + WALL)      # the window: 1 s back from the newest
    assert buf.pose_at(0.99 + WALL) is Miss.TOO_OLD
    assert buf.pose_at(2.001 + WALL) is Miss.TOO_NEW
    assert not buf.add(odom(200, 0.5))                  # older than the window: dropped
    assert not buf.add(odom(201, 1.5))                  # a stamp it has: dropped
    assert buf.add(odom(202, 1.505, x=9.0))             # late but in the window: put in place
    pose = buf.pose_at(1.5025 + WALL)
    assert isinstance(pose, BasePose) and pose.x == pytest.approx((1.5 + 9.0) / 2, abs=1e-4)
    assert buf.dropped == 2


def test_buffer_extrapolates_an_arc_within_tolerance_only() -> None:
    buf = OdometryBuffer(window_s=1.0, tolerance_s=0.05)
    buf.add(odom(0, 0.98, 1.0, 0.0, 0.0, linear=0.5, angular=1.0))
    buf.add(odom(1, 1.0, 1.0, 0.0, math.pi / 2, linear=0.5, angular=1.0))
    pose = buf.extrapolate(1.04 + WALL)
    assert isinstance(pose, BasePose)
    # an arc of radius 0.5 m heading +y: 0.04 rad of it
    assert (pose.x, pose.y, pose.yaw) == pytest.approx(
        (1.0 - 0.5 * (1 - math.cos(0.04)), 0.5 * math.sin(0.04), math.pi / 2 + 0.04), abs=1e-6)
    assert buf.extrapolate(1.06 + WALL) is Miss.TOO_NEW


def test_buffer_does_not_interpolate_across_a_gap() -> None:
    """Odometry that stalled for 1 s says nothing of where the base went meanwhile."""
    buf = OdometryBuffer(window_s=5.0, tolerance_s=0.0, max_gap_s=0.25)
    for t in (0.0, 0.2, 1.2, 1.4):
        buf.add(odom(int(t * 10), t, x=t))
    assert isinstance(buf.pose_at(0.1 + WALL), BasePose)
    assert buf.pose_at(0.7 + WALL) is Miss.GAP
    assert isinstance(buf.pose_at(1.3 + WALL), BasePose)


def test_buffer_starts_again_when_the_driver_restarts() -> None:
    buf = OdometryBuffer(window_s=2.0, tolerance_s=0.0)
    for k in range(10):
        buf.add(odom(100 + k, k / 50, x=5.0))
    buf.add(odom(0, 0.3, x=0.0))   # seq starts again: a new odometry frame
    assert len(buf) == 1 and buf.restarts == 1
    assert buf.pose_at(0.1 + WALL) is Miss.TOO_OLD


AT_ONCE = {"messages": 1, "min_span_s": 0.0, "quiet_s": 0.0}
"""A session switch on one message: for tests of what a switch does, not of when it happens."""


def test_buffer_starts_again_with_a_new_odometry_session_and_frames_carry_theirs() -> None:
    """A restarted driver says so with a new session even when its seq and stamps look like a
    continuation; a late message of the old session is dropped; each frame names its session."""
    core = make_core(0.0, lock_step=False, odometry={"window_s": 100.0, "session_switch": AT_ONCE})
    for k in range(10):
        core.on_odom(odom(k, k / 50, x=5.0, session="A"))
    core.on_frame(shot(0.1, 0.1))
    core.on_odom(odom(10, 0.2, x=0.0, session="B"))   # restarted: odometry back at zero
    core.on_odom(odom(11, 0.22, x=0.0, session="B"))
    core.on_odom(odom(9, 0.19, x=5.0, session="A"))   # late, of the old session
    core.on_frame(shot(0.21, 0.21))
    published = core.poll(0.3)[0]
    assert [(f.odom_session, pose_of(f)[0]) for f in published] == [("A", 5.0), ("B", 0.0)]
    buf = OdometryBuffer(window_s=2.0, tolerance_s=0.0, switch=SessionSwitch(**AT_ONCE))
    for k in range(3):
        buf.add(odom(k, k / 50, session="A"))
    assert buf.add(odom(3, 0.1, session="B")) and len(buf) == 1 and buf.restarts == 1
    assert not buf.add(odom(3, 0.05, session="A")) and buf.stray == 1 and buf.session == "B"


class FakeClock:
    """Receipt times for the session evidence, advanced by the test."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_a_forged_session_does_not_restart_the_buffer_and_a_real_restart_does() -> None:
    """Issue 33, finding 1: one odometry message of a made-up session emptied the buffer (every
    frame after it posed in the forger's frame, or not at all)."""
    clock = FakeClock()
    buf = OdometryBuffer(window_s=2.0, tolerance_s=0.0, clock=clock)
    for k in range(10):
        clock.now = k / 50
        assert buf.add(odom(k, k / 50, x=5.0, session="A"))
    for forged in ("20991231T235959Z-ffffff", ""):
        assert not buf.add(odom(10**6, 0.19, session=forged))
    # a forged stream while the real driver still talks: no restart either
    for k in range(10, 30):
        clock.now = k / 50
        assert not buf.add(odom(10**6 + k, k / 50, session="X"))
        assert buf.add(odom(k, k / 50, x=5.0, session="A"))
    assert buf.session == "A" and buf.restarts == 0 and buf.stray == 22 and len(buf) == 30
    assert buf.pose_at(0.5 + WALL) == BasePose(5.0, 0.0, 0.0)
    # the driver restarts: A goes quiet, B streams at 50 Hz; B is followed once the rule holds
    took = []
    for k in range(40):
        clock.now = 1.5 + k / 50
        took.append(buf.add(odom(k, 1.5 + k / 50, session="B")))
    assert SessionSwitch() == SessionSwitch(messages=5, min_span_s=0.1, quiet_s=0.5)
    assert took.index(True) == 5  # the 6th: 5 messages and more, spanning 0.1 s at 50 Hz
    assert all(took[5:]) and buf.session == "B" and buf.restarts == 1 and len(buf) == 35
    assert buf.sessions.switched_on is not None and buf.sessions.switched_on.quiet_for >= 0.5


# -- interpolation through the core ---------------------------------------------------------------


def moving(t: float) -> tuple[float, float, float, float, float]:
    """A base on an arc, 0.5 m/s and 1.5 rad/s, its yaw crossing +-pi every 4.2 s."""
    v, w, yaw0 = 0.5, 1.5, 2.5
    yaw = yaw0 + w * t
    return (v / w * (math.sin(yaw) - math.sin(yaw0)), -v / w * (math.cos(yaw) - math.cos(yaw0)),
            wrap_angle(yaw), v, w)


def run_events(core: CameraCore, events: list[tuple[float, object]],
               on_frame: Callable[[RgbdFrame], None]) -> None:
    """Dispatch (receipt time, message) in receipt order, polling after each, as the service does."""
    now = 0.0
    for now, msg in sorted(events, key=lambda e: e[0]):
        if isinstance(msg, Odometry):
            core.on_odom(msg)
        else:
            assert isinstance(msg, CapturedFrame)
            core.on_frame(msg)
        for frame in core.poll(now)[0]:
            on_frame(frame)
    for frame in core.poll(now + 1.0)[0]:
        on_frame(frame)


def test_frames_get_the_pose_interpolated_at_their_capture_time() -> None:
    """Odometry at 50 Hz with jitter, frames at 30 Hz received 30 ms late (+ up to 3 ms), both
    clocks different: every frame is published, its pose is the interpolation of the two odometry
    messages around its capture time (exactly), and that is where the base really was (to a
    millimetre and two milliradians, the clock estimate's error) -- across the yaw wrap."""
    rng = np.random.default_rng(7)
    core = make_core(0.0, lock_step=False, clock={"min_latency_s": 0.030})
    odoms: list[Odometry] = []
    events: list[tuple[float, object]] = []
    for k in range(int(6.0 * 50)):
        t = k / 50 + rng.uniform(-0.004, 0.004)
        x, y, yaw, v, w = moving(t)
        odoms.append(odom(k, t, x, y, yaw, linear=v, angular=w))
        events.append((t + rng.uniform(0.001, 0.015), odoms[-1]))  # late, sometimes after a frame
    captures = [0.5 + j / 30 for j in range(150)]
    for c in captures:
        events.append((c + 0.030 + rng.uniform(0.0, 0.003), shot(c * 1.00002 + 321.0, 0.0)))
    # the frame's receipt time goes into host_time_s
    events = [(at, shot(m.device_time_s, at) if isinstance(m, CapturedFrame) else m) for at, m in events]
    published: list[RgbdFrame] = []
    run_events(core, events, published.append)

    assert len(published) == len(captures) and not core.skipped
    assert [f.seq for f in published] == list(range(len(captures)))
    stamps = [o.stamp for o in odoms]
    wrapped = 0
    for frame, capture in zip(published, captures):
        i = int(np.searchsorted(stamps, frame.stamp))
        a, b = odoms[i - 1], odoms[i]
        f = (frame.stamp - a.stamp) / (b.stamp - a.stamp)
        want_yaw = wrap_angle(a.yaw + f * wrap_angle(b.yaw - a.yaw))
        want = sim_camera_pose(a.x + f * (b.x - a.x), a.y + f * (b.y - a.y), want_yaw)
        np.testing.assert_allclose(frame.camera_pose, want, atol=1e-9)
        wrapped += (a.yaw > 0) != (b.yaw > 0) and abs(a.yaw) > 3
        assert abs(frame.stamp - (capture + WALL)) < 0.0035  # the first frames' jitter at most
        if frame.seq >= 15:  # once a frame with little jitter was seen
            x, y, yaw = pose_of(frame)
            tx, ty, tyaw, _, _ = moving(capture)
            assert math.hypot(x - tx, y - ty) < 0.001 and abs(wrap_angle(yaw - tyaw)) < 0.002
    assert wrapped >= 1, "a frame fell between two messages on either side of +-pi"


def test_a_frame_outside_the_odometry_is_skipped_and_counted() -> None:
    core = make_core(0.0, lock_step=False, odometry={"window_s": 1.0, "tolerance_s": 0.03,
                                                     "wait_s": 0.1})
    core.on_frame(shot(0.5, 0.5))                # no odometry at all: waits, then gives up
    assert core.poll(0.55)[0] == []
    assert core.poll(0.61)[0] == [] and core.skipped == {Miss.NO_ODOMETRY.value: 1}
    still_odometry(core, 1.0, 3.0)               # kept: 2.0 .. 3.0
    core.on_frame(shot(1.9, 3.01))               # older than the window
    assert core.skipped[Miss.TOO_OLD.value] == 1
    core.on_frame(shot(3.02, 3.03))              # newer than the newest odometry, within tolerance
    assert core.poll(3.05)[0] == []              # still waiting for the next message
    frames, _ = core.poll(3.14)
    assert len(frames) == 1                      # extrapolated after the wait
    core.on_frame(shot(3.2, 3.21))               # 0.2 s past the newest odometry
    frames, state = core.poll(3.4)
    assert frames == [] and core.skipped[Miss.TOO_NEW.value] == 1
    assert core.state(3.4).skipped == 3 and core.published == 1


def test_a_frame_waits_for_the_odometry_after_it() -> None:
    core = make_core(0.0, lock_step=False)
    core.on_odom(odom(0, 1.00, x=0.0))
    core.on_frame(shot(1.01, 1.012))
    assert core.poll(1.013)[0] == []             # no odometry after 1.01 yet
    core.on_odom(odom(1, 1.02, x=0.2))
    frames, _ = core.poll(1.021)
    assert len(frames) == 1 and pose_of(frames[0])[0] == pytest.approx(0.1)


# -- lock-step gate ------------------------------------------------------------------------------


def test_lock_step_publishes_the_first_frame_after_each_completion() -> None:
    core = make_core(0.0, republish_s=1.0)
    still_odometry(core, 0.0, 10.0)
    seen: list[RgbdFrame] = []  # new frames (re-published ones are tested on their own)

    def frames_at(t0: float, t1: float) -> None:
        """Frames at 30 Hz captured in [t0, t1), each received (and polled) 30 ms later."""
        for j in range(int(round((t1 - t0) * 30))):
            c = t0 + j / 30
            core.on_frame(shot(c, c + 0.03))
            seen.extend(f for f in core.poll(c + 0.03)[0] if f.seq not in {g.seq for g in seen})

    frames_at(1.0, 2.0)        # before any driver state: the start-up frame only
    assert [(f.seq, f.after_action) for f in seen] == [(0, 0)]
    assert seen[0].stamp == pytest.approx(1.0 + WALL)
    core.on_driver(driver(0, DriverMode.MOVING, active=1), 2.0)
    frames_at(2.0, 3.0)
    core.on_driver(driver(1), 3.05)    # command 1 done: frames captured before 3.05 do not count
    frames_at(3.0, 4.0)
    assert [(f.seq, f.after_action) for f in seen] == [(0, 0), (1, 1)]
    assert seen[1].stamp == pytest.approx(3.0 + 2 / 30 + WALL)  # the first capture after 3.05
    frames_at(4.0, 4.05)               # idle: nothing more ...
    assert len(seen) == 2
    published_at = 3.0 + 2 / 30 + 0.03
    republished = core.republished
    assert core.poll(published_at + 0.99)[0] == []
    again, _ = core.poll(published_at + 1.0)  # ... but the latest again every republish_s
    assert [(f.seq, f.after_action) for f in again] == [(1, 1)]
    assert core.republished == republished + 1
    assert core.poll(published_at + 1.5)[0] == []

    core.on_driver(driver(1, DriverMode.MOVING, active=2), 5.0)
    core.on_driver(driver(2, DriverMode.MOVING, active=3), 5.5)   # done, but already moving on
    frames_at(5.0, 6.0)
    assert len(seen) == 2, "no frame while the base moves"
    core.on_driver(driver(3), 6.0)     # stopped: one frame, for the newest completion
    frames_at(6.0, 7.0)
    assert [(f.seq, f.after_action) for f in seen[2:]] == [(2, 3)]
    assert core.state(7.1).frames == 3


def test_lock_step_frame_skipped_for_odometry_leaves_the_gate_open() -> None:
    """A completion's frame that cannot be posed is not published; the next frame that can is."""
    core = make_core(0.0, republish_s=100.0, odometry={"tolerance_s": 0.0, "wait_s": 0.05})
    still_odometry(core, 0.0, 1.0)
    core.on_frame(shot(0.5, 0.52))
    assert len(core.poll(0.52)[0]) == 1
    core.on_driver(driver(1), 2.0)
    core.on_frame(shot(2.1, 2.12))     # no odometry after 1.0: skipped after its wait
    assert core.poll(2.2)[0] == [] and core.skipped[Miss.TOO_NEW.value] == 1
    still_odometry(core, 2.0, 3.0)
    core.on_frame(shot(2.5, 2.52))
    frames, _ = core.poll(2.52)
    assert [(f.seq, f.after_action) for f in frames] == [(1, 1)]


def test_lock_step_starts_again_with_a_restarted_driver() -> None:
    core = make_core(0.0)
    still_odometry(core, 0.0, 5.0)
    core.on_driver(driver(7), 0.1)
    core.on_frame(shot(0.2, 0.2))
    assert [f.after_action for f in core.poll(0.2)[0]] == [7]
    core.on_driver(driver(0), 1.0)     # a new driver process: ids start again
    core.on_driver(driver(1), 2.0)
    core.on_frame(shot(2.1, 2.1))
    assert [f.after_action for f in core.poll(2.1)[0]] == [1]


def test_settle_time_delays_the_completions_frame() -> None:
    core = make_core(0.0, settle_s=0.2)
    still_odometry(core, 0.0, 5.0)
    core.on_frame(shot(0.1, 0.1))
    core.poll(0.1)
    core.on_driver(driver(1), 1.0)
    for c in (1.1, 1.15, 1.25):
        core.on_frame(shot(c, c))
    frames, _ = core.poll(1.3)
    assert [f.stamp - WALL for f in frames] == [pytest.approx(1.25)]


def test_free_running_publishes_every_frame_with_the_completion_before_it() -> None:
    core = make_core(0.0, lock_step=False)
    still_odometry(core, 0.0, 3.0)
    core.on_driver(driver(4), 1.01)    # received after the capture at 1.0, before 1.0333
    core.on_driver(driver(5, DriverMode.MOVING, active=6), 1.51)
    out = []
    for j in range(60):
        c = j / 30
        core.on_frame(shot(c, c + 0.01))
        out += core.poll(c + 0.01)[0]
    assert [f.seq for f in out] == list(range(60))
    assert [f.after_action for f in out] == [0] * 31 + [4] * 15 + [5] * 14
    assert core.poll(5.0)[0] == [], "no re-publishing when free-running"


def test_free_running_max_hz_keeps_the_average_rate() -> None:
    rng = np.random.default_rng(3)
    core = make_core(0.0, lock_step=False, max_hz=10.0)
    still_odometry(core, 0.0, 11.0)
    n = 0
    for j in range(300):
        c = 0.5 + j / 30 + rng.uniform(-0.003, 0.003)
        core.on_frame(shot(c, c))
        n += len(core.poll(c)[0])
    assert n == pytest.approx(100, abs=1)
    assert core.rate_limited == 300 - n


# -- faults and health ----------------------------------------------------------------------------


def test_no_frames_is_a_fault_within_1_5_s_and_frames_recover_it() -> None:
    core = make_core(0.0)
    still_odometry(core, 0.0, 10.0)
    for j in range(30):
        core.on_frame(shot(j / 30, j / 30))
        core.poll(j / 30)
    last = 29 / 30
    fault_at, fault_state = None, None
    t = last
    while t < last + 3.0:
        t += 0.05
        _, state = core.poll(t)
        if state is not None and state.fault:
            fault_at, fault_state = t, state
            break
    assert fault_at is not None and last + 1.0 < fault_at <= last + 1.5
    assert fault_state is not None and fault_state.fault.startswith("no camera frames")
    assert fault_state.stamp == pytest.approx(fault_at + WALL)
    core.on_frame(shot(4.0, 4.0))
    _, state = core.poll(4.0)
    assert state is not None and state.fault == ""      # the change is published at once


def test_start_without_frames_is_a_fault() -> None:
    core = make_core(10.0)
    assert core.poll(10.5)[1] is not None            # the first state goes out at once
    assert core.fault(10.9) == ""
    assert core.fault(11.1).startswith("no camera frames")


def test_all_zero_depth_is_published_until_it_lasts_then_a_fault() -> None:
    """A wall nearer than the camera's range shows no depth: that frame must reach the planner
    (it turns the robot away); only depth that stays all zero is a broken stream."""
    core = make_core(0.0, lock_step=False, depth_zero_fault_s=2.0)
    still_odometry(core, 0.0, 5.0)
    core.on_frame(shot(1.0, 1.0, depth=0))
    frames, state = core.poll(1.0)
    assert len(frames) == 1 and not frames[0].depth.any() and state is not None and state.fault == ""
    core.on_frame(shot(2.9, 2.9, depth=0))
    assert len(core.poll(2.9)[0]) == 1 and core.fault(2.9) == ""
    core.on_frame(shot(3.0, 3.0, depth=0))  # all zero for 2 s
    frames, state = core.poll(3.0)
    assert frames == [] and state is not None and state.fault.startswith(DEPTH_ALL_ZERO + " for 2 s")
    assert core.rejected[DEPTH_ALL_ZERO] == 1 and core.zero_depth == 3 and core.published == 2
    core.on_frame(shot(3.1, 3.1))
    frames, state = core.poll(3.1)
    assert len(frames) == 1 and state is not None and state.fault == ""
    core.on_frame(shot(3.2, 3.2, depth=0))  # a new run of them: published again
    assert len(core.poll(3.2)[0]) == 1 and core.fault(3.2) == ""


def test_camera_error_is_reported_until_frames_return() -> None:
    core = make_core(0.0, lock_step=False)
    still_odometry(core, 0.0, 5.0)
    core.on_frame(shot(100.0, 1.0))                  # device clock: 99 s behind
    core.poll(1.0)
    core.on_error(RuntimeError("device 123456 disconnected"))
    _, state = core.poll(1.2)
    assert state is not None and state.fault == "camera error: device 123456 disconnected"
    assert core.fault(3.0) == state.fault, "the backend's error is the reason, not the silence"
    core.on_frame(shot(0.5, 3.5))                    # re-plugged: its clock starts again
    frames, state = core.poll(3.5)
    assert state is not None and state.fault == ""
    assert len(frames) == 1 and frames[0].stamp == pytest.approx(3.5 + WALL)


def test_bad_arrays_from_a_backend_are_a_clear_fault() -> None:
    core = make_core(0.0, lock_step=False)
    bad = CapturedFrame(rgb=np.zeros((H, W, 3), np.uint8), depth=np.ones((H, W), np.float32),
                        depth_scale=1.0, intrinsics=K, device_time_s=0.0, host_time_s=0.0)
    core.on_frame(bad)
    assert "depth must be an H x W uint16 array, got 2-d float32" in core.fault(0.0)
    small_rgb = CapturedFrame(rgb=np.zeros((H, W - 1, 3), np.uint8), depth=np.ones((H, W), np.uint16),
                              depth_scale=0.001, intrinsics=K, device_time_s=0.0, host_time_s=0.0)
    core.on_frame(small_rgb)
    assert "rgb must be 12 x 16 x 3 uint8" in core.fault(0.0)
    assert core.rejected["bad frame"] == 2


def test_frames_that_cannot_be_posed_for_long_are_a_fault() -> None:
    """Frames arrive but odometry stopped: the planner must learn why the map stopped growing."""
    core = make_core(0.0, lock_step=False)
    still_odometry(core, 0.0, 1.0)
    faults = []
    for j in range(60):
        c = 1.0 + j / 30
        core.on_frame(shot(c, c))
        faults.append(core.poll(c)[1])
    fault = core.fault(3.0)
    assert fault.startswith("frames not posed for over 1 s") and Miss.TOO_NEW.value in fault
    still_odometry(core, 3.0, 4.0)
    core.on_frame(shot(3.5, 3.5))
    assert core.poll(3.5)[1] is not None and core.fault(3.5) == ""


def test_state_goes_out_at_state_hz_and_on_change() -> None:
    core = make_core(0.0, lock_step=False, state_hz=2.0, depth_zero_fault_s=0.0)  # one frame: a fault
    still_odometry(core, 0.0, 10.0)
    states: list[tuple[float, CameraState]] = []
    for j in range(90):
        c = j / 30
        core.on_frame(shot(c, c, depth=0 if j == 45 else 1500))
        _, state = core.poll(c)
        if state is not None:
            states.append((c, state))
    faults = [s.fault for _, s in states]
    i = faults.index(DEPTH_ALL_ZERO)
    assert states[i][0] == 45 / 30 and states[i + 1] == (46 / 30, states[i + 1][1])
    assert faults[i + 1] == "" and faults.count(DEPTH_ALL_ZERO) == 1   # both changes at once
    gaps = np.diff([t for t, _ in states])
    on_time = np.delete(gaps, [i - 1, i])        # the gaps that end at a change
    assert states[0][0] == 0.0 and ((on_time > 0.5 - 1e-9) & (on_time < 0.5 + 1 / 30 + 1e-9)).all()
    final = core.state(3.0)
    assert (final.frames, final.last_seq, final.skipped) == (89, 88, 0)


def test_clock_jump_frames_are_not_published() -> None:
    core = make_core(0.0, lock_step=False, clock={"reset_confirm": 2})
    still_odometry(core, 0.0, 5.0)
    for j in range(10):
        core.on_frame(shot(j / 30, j / 30))
    core.on_frame(shot(1.0, 3.0))                   # the device clock paused 2 s
    assert core.rejected[CLOCK_JUMP] == 1
    core.on_frame(shot(1.1, 3.1))                   # confirmed: timed on the new offset
    frames, _ = core.poll(3.1)
    assert frames[-1].stamp == pytest.approx(3.1 + WALL)
