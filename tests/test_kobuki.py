"""The Kobuki (TurtleBot 2) hardware interface: known bytes, the decoder under garbage, and the
real pyserial client against a simulated Kobuki on a pseudo-terminal (no mocks).

Sources for the expected values (see services/base_driver/kobuki/protocol.py):
[SPEC] Kobuki protocol specification, kobuki_driver "Appendix: Protocol Specification"
(yujinrobot/kobuki_core kobuki_driver/doxygen/english/en_appendix_protocol.dox): packet
``AA 55 | length | payload | XOR(length + payload)``, LSB first; Base Control = id 1, length 4,
speed mm/s, radius mm; its conversion table (pure rotation: radius 1, speed = w * b / 2, b = 230 mm).
[DIFF] kobuki_driver DiffDrive::velocityCommands / bound() (kobuki-base/kobuki_core
src/driver/diff_drive.cpp). The specification gives the layout and the conversion table but
prints no byte dump of a whole packet, so each expected packet below is worked by hand from
those tables (shown in the comments), not produced by this code.
"""

from __future__ import annotations

import os
import time
import tty
from collections.abc import Callable, Iterator

import pytest

from ovamos.services.base_driver.hardware import HardwareError
from ovamos.services.base_driver.kobuki.client import KobukiHardware
from ovamos.services.base_driver.kobuki.config import KobukiConfig
from ovamos.services.base_driver.kobuki.protocol import (
    TICK_TO_RAD,
    TICKS_PER_REV,
    WHEEL_BASE_M,
    WHEEL_RADIUS_M,
    BasicSensorData,
    PacketDecoder,
    ProtocolError,
    TickUnwrapper,
    body_to_speed_radius,
    checksum,
    encode_base_control,
    encode_packet,
    encode_sub_payload,
    speed_radius_to_wheels,
    split_sub_payloads,
)
from ovamos.services.base_driver.kobuki.sim import SimKobuki
from tests.polling import wait_for

pytestmark = pytest.mark.serial  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

R = WHEEL_RADIUS_M


def poll(predicate: Callable[[], object], timeout: float = 2.0, what: str = "condition") -> object:
    """Poll fast (the base streams at 50 Hz); fail with ``what`` after ``timeout``."""
    return wait_for(predicate, timeout, what, interval=0.005)


# -- known bytes ---------------------------------------------------------------------------


@pytest.mark.parametrize("v, w, speed, radius, packet", [
    # [SPEC] pure translation: radius 0, speed = 100 mm/s = 0x0064.
    # checksum = 06 ^ 01 ^ 04 ^ 64 ^ 00 ^ 00 ^ 00 = 0x67
    (0.1, 0.0, 100, 0, "aa 55 06 01 04 64 00 00 00 67"),
    # [SPEC] pure rotation at 1 rad/s: radius 1, speed = w * b / 2 = 1 * 230 / 2 = 115 = 0x0073.
    # checksum = 06 ^ 01 ^ 04 ^ 73 ^ 00 ^ 01 ^ 00 = 0x71
    (0.0, 1.0, 115, 1, "aa 55 06 01 04 73 00 01 00 71"),
    # [SPEC] pure rotation clockwise: speed = -1 * 230 / 2 = -115 = 0xff8d, radius 1 (not -1) as [DIFF] sends it.
    # checksum = 06 ^ 01 ^ 04 ^ 8d ^ ff ^ 01 ^ 00 = 0x70
    (0.0, -1.0, -115, 1, "aa 55 06 01 04 8d ff 01 00 70"),
    # [SPEC] translation + rotation, R = v / w = 0.2 / 0.5 = 400 mm = 0x0190 > 1:
    # speed = v * (R + b/2) / R = 200 * 515 / 400 = 257.5 -> 257 = 0x0101 ([DIFF] bound() truncates).
    # checksum = 06 ^ 01 ^ 04 ^ 01 ^ 01 ^ 90 ^ 01 = 0x92
    (0.2, 0.5, 257, 400, "aa 55 06 01 04 01 01 90 01 92"),
    # [SPEC] R = 100 / -0.5 = -200 mm = 0xff38 < -1: speed = v * (R - b/2) / R = 100 * -315 / -200 = 157.5
    # -> 157 = 0x009d. checksum = 06 ^ 01 ^ 04 ^ 9d ^ 00 ^ 38 ^ ff = 0x59
    (0.1, -0.5, 157, -200, "aa 55 06 01 04 9d 00 38 ff 59"),
])
def test_base_control_packet_matches_the_specification(v: float, w: float, speed: int, radius: int,
                                                       packet: str) -> None:
    assert body_to_speed_radius(v, w) == (speed, radius)
    assert encode_base_control(speed, radius) == bytes.fromhex(packet)


def test_checksum_is_the_xor_of_length_and_payload() -> None:
    # [SPEC]: "XOR'ed value of every bytes of bytestream except headers"; a whole packet then XORs to 0
    packet = encode_base_control(-300, 250)
    assert packet[:2] == b"\xaa\x55" and packet[2] == 6
    assert checksum(packet[2:-1]) == packet[-1]
    assert checksum(packet[2:]) == 0
    assert checksum(bytes([0x06, 0x01, 0x04, 0x64, 0x00, 0x00, 0x00])) == 0x67
    with pytest.raises(ProtocolError):
        encode_packet(b"\x01\x00")  # [SPEC] minimum payload length is 3


def test_the_published_wheel_figures() -> None:
    # [DIFF] tick_to_rad(0.002436916871363930187454): 2578.33 ticks per wheel revolution
    assert TICKS_PER_REV == pytest.approx(2578.33, abs=0.01)
    assert (WHEEL_BASE_M, WHEEL_RADIUS_M) == (0.230, 0.035)
    # one tick is 0.085 mm of wheel travel
    assert TICK_TO_RAD * R == pytest.approx(8.53e-5, rel=1e-3)


@pytest.mark.parametrize("v", [-0.3, -0.07, 0.0, 0.05, 0.25])
@pytest.mark.parametrize("w", [-1.5, -0.4, 0.0, 0.3, 1.8])
def test_speed_radius_gives_the_wheel_speeds_of_the_body_velocity(v: float, w: float) -> None:
    """Host rule and firmware rule are inverses: each wheel runs at v -+ w b / 2 (to the truncation)."""
    speed, radius = body_to_speed_radius(v, w)
    left, right = speed_radius_to_wheels(speed, radius)
    half_b = WHEEL_BASE_M / 2
    # truncation to whole mm of speed and radius: at most ~2 mm/s at these speeds
    assert left == pytest.approx(v - w * half_b, abs=0.003)
    assert right == pytest.approx(v + w * half_b, abs=0.003)


def test_basic_sensor_data_round_trip_and_length_check() -> None:
    bsd = BasicSensorData(timestamp_ms=65535, bumper=0x05, wheel_drop=0x02, cliff=0x01, left_encoder=1,
                          right_encoder=65535, left_pwm=-20, right_pwm=30, battery_dv=167, overcurrent=0x02)
    sub = bsd.encode()
    assert sub[:2] == b"\x01\x0f"  # [SPEC] id 1, length 15
    # [SPEC] field order: timestamp (LE) ff ff, bumper 05, wheel drop 02, cliff 01, left 01 00, right ff ff,
    # PWM ec 1e, buttons 00, charger 00, battery a7 (16.7 V), over-current 02
    assert sub[2:] == bytes.fromhex("ffff 05 02 01 0100 ffff ec 1e 00 00 a7 02")
    assert BasicSensorData.parse(sub[2:]) == bsd
    with pytest.raises(ProtocolError):
        BasicSensorData.parse(sub[2:] + b"\x00")  # [CORE]: exactly 15


# -- the decoder under garbage ----------------------------------------------------------------


def _feedback(i: int) -> bytes:
    bsd = BasicSensorData(timestamp_ms=20 * i, left_encoder=100 * i, right_encoder=200 * i)
    return encode_packet(bsd.encode() + encode_sub_payload(3, b"\x00\x00\x00"))


def _garbage_stream() -> tuple[bytes, list[bytes]]:
    """Good packets with every kind of garbage between them; returns (stream, the good packets)."""
    good = [_feedback(i) for i in range(14)]
    bad_checksum = bytearray(_feedback(99))
    bad_checksum[-1] ^= 0x5A
    noise = bytes(range(0x10, 0x40))                   # no 0xAA in it
    short_length = b"\xaa\x55\x02\x01\x00\x03"          # a header with length 2 < 3 ([SPEC] minimum)
    stream = (noise + good[0]
              + good[1][:9] + good[2]                  # good[1] cut short: its length swallows good[2]'s head
              + bytes(bad_checksum) + good[3]
              + b"\xaa" + short_length + good[4]       # a lone 0xAA, then a bogus header
              + noise + b"\xaa\x55" + b"".join(good[5:]))  # a bare header: its "length" is 0xAA,
    # so the packets behind it wait (never lost) until 170 bytes prove it false
    return stream, [good[0], good[2], good[3], good[4], *good[5:]]


@pytest.mark.parametrize("chunk", [1, 3, 7, 64, 10_000])
def test_decoder_skips_noise_partial_packets_and_bad_checksums(chunk: int) -> None:
    stream, good = _garbage_stream()
    decoder = PacketDecoder()
    got: list[bytes] = []
    for i in range(0, len(stream), chunk):
        got += decoder.feed(stream[i:i + chunk])
    assert got == [p[3:-1] for p in good]               # every good packet, in order, and nothing else
    c = decoder.counters()
    assert c["packets"] == len(good)
    assert c["bytes_skipped"] == len(stream) - sum(len(p) for p in good)  # every other byte accounted for
    assert c["malformed"] >= 4                          # the cut packet, bad checksum, short length, bare header
    assert c["resyncs"] >= 3


def test_split_sub_payloads_refuses_a_bad_tiling() -> None:
    assert split_sub_payloads(b"\x01\x01\x07\x03\x00") == [(1, b"\x07"), (3, b"")]
    with pytest.raises(ProtocolError):
        split_sub_payloads(b"\x01\x05\x00\x00")


def test_ticks_unwrap_across_the_16_bit_wrap() -> None:
    u = TickUnwrapper()
    seq = [65530, 65535, 4, 100, 65500 % 65536, 65000, 64000]
    totals = [u.update(x) for x in seq]
    # +5, +5 (65535 -> 4 wraps), +96, then 100 -> 65500 is -136 (backwards through 0), -500, -1000
    assert totals == [0, 5, 10, 106, -30, -530, -1530]


# -- through the pseudo-terminal ---------------------------------------------------------------


@pytest.fixture
def sim() -> Iterator[SimKobuki]:
    s = SimKobuki(start_ticks=(65000, 300))  # the left encoder wraps within the first 0.2 m
    s.start()
    yield s
    s.close()


@pytest.fixture
def hw(sim: SimKobuki) -> Iterator[KobukiHardware]:
    h = KobukiHardware(KobukiConfig(port=sim.port))
    h.open()
    yield h
    h.close()


def test_forward_moves_both_wheels_and_feedback_agrees(sim: SimKobuki, hw: KobukiHardware) -> None:
    first = hw.feedback()
    assert first is not None and first.left_pos_rad == 0.0 == first.right_pos_rad
    hw.set_velocity(0.2, 0.0)
    t0 = time.monotonic()
    poll(lambda: sim.last_command == (200, 0), what="the Base Control packet at the simulated Kobuki")
    time.sleep(max(0.0, 1.0 - (time.monotonic() - t0)))
    moving = hw.feedback()
    hw.halt()
    poll(lambda: sim.last_command == (0, 0), what="the stop")
    time.sleep(0.1)                                      # let the last travel reach the host
    assert sim.left_travel_m == pytest.approx(0.2, abs=0.015)
    assert sim.right_travel_m == pytest.approx(sim.left_travel_m, abs=1e-9)
    fb = hw.feedback()
    assert fb is not None
    # feedback agrees with the truth to a tick (0.085 mm), the left wheel across the 16-bit wrap
    assert fb.left_pos_rad * R == pytest.approx(sim.left_travel_m, abs=1e-4)
    assert fb.right_pos_rad * R == pytest.approx(sim.right_travel_m, abs=1e-4)
    assert fb.extra["left_ticks"] < 65000                # it did wrap
    assert moving is not None and moving.left_vel_rad_s == pytest.approx(0.2 / R, rel=0.1)
    assert hw.counters()["malformed"] == 0


def test_pure_rotation_turns_the_wheels_opposite(sim: SimKobuki, hw: KobukiHardware) -> None:
    hw.set_velocity(0.0, 1.0)                            # [SPEC] radius 1, speed 115 mm/s
    poll(lambda: sim.last_command == (115, 1), what="the pure rotation command")
    time.sleep(0.5)
    hw.halt()
    poll(lambda: sim.last_command == (0, 0), what="the stop")
    time.sleep(0.1)
    left, right = sim.left_travel_m, sim.right_travel_m
    assert right == pytest.approx(0.115 * 0.5, abs=0.01)
    assert left == pytest.approx(-right, abs=1e-9)
    fb = hw.feedback()
    assert fb is not None
    assert fb.left_pos_rad * R == pytest.approx(left, abs=1e-4)
    assert fb.right_pos_rad * R == pytest.approx(right, abs=1e-4)
    # body rotation from the wheels: (right - left) / b ~ 1 rad/s * 0.5 s
    assert (fb.right_pos_rad - fb.left_pos_rad) * R / WHEEL_BASE_M == pytest.approx(0.5, abs=0.09)


def test_safety_sensors_appear_in_feedback(sim: SimKobuki, hw: KobukiHardware) -> None:
    sim.press_bumper("left")
    poll(lambda: hw.feedback().bumpers == ("left",), what="the left bumper")
    sim.press_bumper("centre", "right")
    poll(lambda: hw.feedback().bumpers == ("right", "centre"), what="two bumpers")
    sim.lift_wheel("right")
    sim.set_cliff("centre")
    sim.set_overcurrent("left")
    fb = poll(lambda: (f := hw.feedback()).wheel_drops and f.cliffs and f.faults and f, what="drop, cliff, overcurrent")
    assert (fb.wheel_drops, fb.cliffs, fb.faults) == (("right",), ("centre",), ("overcurrent left wheel",))
    assert fb.extra["battery_v"] == pytest.approx(16.5)
    sim.press_bumper()
    sim.lift_wheel()
    sim.set_cliff()
    sim.set_overcurrent()
    poll(lambda: not (f := hw.feedback()).bumpers and not f.wheel_drops and not f.cliffs and not f.faults,
         what="all clear")


def test_stale_feedback_is_visible_by_its_stamp(sim: SimKobuki, hw: KobukiHardware) -> None:
    poll(lambda: time.monotonic() - hw.feedback().stamp < 0.05, what="fresh feedback")
    sim.stop_sending()
    time.sleep(0.3)
    fb = hw.feedback()
    assert fb is not None and time.monotonic() - fb.stamp > 0.2   # the controller's 200 ms limit
    sim.resume_sending()
    poll(lambda: time.monotonic() - hw.feedback().stamp < 0.05, what="feedback again")


def test_garbage_on_the_line_is_skipped_and_counted(sim: SimKobuki, hw: KobukiHardware) -> None:
    before = hw.counters()
    commands = sim.counters()["commands"]
    sim.send_noise(bytes(range(256)) * 2)               # contains AA 55 pairs and every other byte
    sim.send_bad_checksum(2)
    sim.send_partial_packet()
    sim.send_noise(n=100)
    poll(lambda: hw.counters()["packets"] >= before["packets"] + 10, what="packets after the garbage")
    after = hw.counters()
    assert after["malformed"] >= before["malformed"] + 3
    assert after["bytes_skipped"] > before["bytes_skipped"] + 512
    assert after["resyncs"] > before["resyncs"]
    assert hw.error is None
    assert time.monotonic() - hw.feedback().stamp < 0.1
    assert sim.counters()["commands"] == commands and sim.wheel_speeds_m_s == (0.0, 0.0)  # nothing moved


def test_unplugged_port_is_reported_and_raises_on_the_next_command(sim: SimKobuki, hw: KobukiHardware) -> None:
    """Documented behaviour: the reader records the loss; set_velocity raises HardwareError;
    halt never raises; feedback() keeps the last message, ageing; open() raises while it is gone."""
    last = hw.feedback()
    sim.unplug()
    poll(lambda: hw.error is not None, what="the loss noticed by the reader")
    assert "unplugged" in hw.error
    with pytest.raises(HardwareError, match="lost"):
        hw.set_velocity(0.1, 0.0)
    hw.halt()                                            # best effort, silent
    fb = hw.feedback()
    assert fb is not None and fb.stamp >= last.stamp
    time.sleep(0.25)
    assert time.monotonic() - hw.feedback().stamp > 0.2
    assert hw.counters()["port_errors"] == 1
    with pytest.raises(HardwareError):
        hw.open()


def test_missing_port_says_what_to_check() -> None:
    hw = KobukiHardware(KobukiConfig(port="/dev/ttyUSB-ovamos-absent"))
    with pytest.raises(HardwareError, match="not found: is the Kobuki plugged in and are you in the dialout group"):
        hw.open()
    with pytest.raises(HardwareError):
        hw.set_velocity(0.1, 0.0)
    hw.halt()
    assert hw.feedback() is None
    hw.close()
    hw.close()


def test_a_silent_port_fails_open() -> None:
    """A serial device that sends no Basic Sensor Data (wrong port, base switched off) fails open()."""
    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        hw = KobukiHardware(KobukiConfig(port=os.ttyname(slave), first_feedback_timeout_s=0.2))
        with pytest.raises(HardwareError, match="no Basic Sensor Data"):
            hw.open()
        hw.close()
    finally:
        os.close(master)
        os.close(slave)


def test_reopen_keeps_positions_continuous(sim: SimKobuki, hw: KobukiHardware) -> None:
    """The base keeps counting while the host is away: a reopen continues the positions (no odometry jump)."""
    hw.set_velocity(0.1, 0.0)
    time.sleep(0.2)
    hw.close()                                           # the simulated base rolls on at 0.1 m/s meanwhile
    time.sleep(0.2)
    hw.open()
    hw.halt()
    poll(lambda: sim.last_command == (0, 0), what="the stop")
    time.sleep(0.1)
    fb = hw.feedback()
    assert fb is not None and fb.left_pos_rad * R == pytest.approx(sim.left_travel_m, abs=1e-4)
    assert sim.left_travel_m == pytest.approx(0.04, abs=0.01)   # travel while away is counted too


def test_stale_reason_names_the_lost_port(sim: SimKobuki, hw: KobukiHardware) -> None:
    assert hw.stale_reason(time.monotonic()) == ""
    sim.unplug()
    poll(lambda: hw.stale_reason(time.monotonic()), what="the reason")
    assert sim.port in hw.stale_reason(time.monotonic())
