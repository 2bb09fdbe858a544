"""The TurtleBot 3 (OpenCR) base: Dynamixel 2.0 bytes, and the real dynamixel-sdk over a pty against the simulated board.

Known bytes come from the worked examples of the public Protocol 2.0 e-manual,
https://emanual.robotis.com/docs/en/dxl/protocol2/ (sections "Ping" Example 1,
"Read" Example, "Write" Example), each with its CRC bytes.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import pytest

dxl = pytest.importorskip("dynamixel_sdk")

from ovamos.services.base_driver.hardware import HardwareError  # noqa: E402
from ovamos.services.base_driver.opencr import table as T  # noqa: E402
from ovamos.services.base_driver.opencr.client import OpenCRHardware  # noqa: E402
from ovamos.services.base_driver.opencr.config import OpenCRConfig  # noqa: E402
from ovamos.services.base_driver.opencr.protocol import Decoder, Inst, crc16, instruction_packet, status_packet  # noqa: E402
from ovamos.services.base_driver.opencr.sim import SimOpenCR, body_from_wheels  # noqa: E402

pytestmark = pytest.mark.serial  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)

# e-manual Protocol 2.0 worked examples (ID 1, XM430-W210)
PING = bytes.fromhex("FF FF FD 00 01 03 00 01 19 4E")
PING_STATUS = bytes.fromhex("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")   # model 1030, fw 38
READ_132_4 = bytes.fromhex("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15")   # Present Position
READ_STATUS = bytes.fromhex("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")  # = 166
WRITE_116_512 = bytes.fromhex("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89")  # Goal Position 512
WRITE_STATUS = bytes.fromhex("FF FF FD 00 01 04 00 55 00 A1 0C")


# ---- known bytes --------------------------------------------------------------------------------
def test_our_encoder_reproduces_the_emanual_examples() -> None:
    assert instruction_packet(1, Inst.PING) == PING
    assert status_packet(1, 0, bytes([0x06, 0x04, 0x26])) == PING_STATUS
    assert instruction_packet(1, Inst.READ, bytes([0x84, 0, 4, 0])) == READ_132_4
    assert status_packet(1, 0, (166).to_bytes(4, "little")) == READ_STATUS
    assert instruction_packet(1, Inst.WRITE, bytes([0x74, 0]) + (512).to_bytes(4, "little")) == WRITE_116_512
    assert status_packet(1) == WRITE_STATUS
    for frame in (PING, PING_STATUS, READ_132_4, READ_STATUS, WRITE_116_512, WRITE_STATUS):
        assert crc16(frame[:-2]) == int.from_bytes(frame[-2:], "little")
        assert dxl.PacketHandler(2.0).updateCRC(0, list(frame), len(frame) - 2) == crc16(frame[:-2])


def _pty_port() -> tuple[int, object]:
    master, slave = os.openpty()
    import tty
    tty.setraw(slave)
    tty.setraw(master)
    port = dxl.PortHandler(os.ttyname(slave))
    assert port.openPort()
    os.close(slave)
    return master, port


def _read_all(fd: int, n: int, timeout: float = 1.0) -> bytes:
    out = b""
    end = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < end:
        out += os.read(fd, n - len(out))
    return out


def test_the_sdk_puts_the_emanual_bytes_on_the_wire() -> None:
    """What dynamixel-sdk writes to a serial port, byte for byte, is the e-manual's example."""
    master, port = _pty_port()
    try:
        ph = dxl.PacketHandler(2.0)
        assert ph.write4ByteTxOnly(port, 1, 116, 512) == dxl.COMM_SUCCESS
        assert _read_all(master, len(WRITE_116_512)) == WRITE_116_512
        assert ph.readTx(port, 1, 132, 4) == dxl.COMM_SUCCESS
        assert _read_all(master, len(READ_132_4)) == READ_132_4
        # and it accepts the e-manual's status packet, behind garbage it must skip
        os.write(master, b"\x13\x37\xff" + READ_STATUS)
        port.setPacketTimeoutMillis(500)
        data, result, error = ph.readRx(port, 1, 4)
        assert (result, error, int.from_bytes(bytes(data), "little")) == (dxl.COMM_SUCCESS, 0, 166)
    finally:
        port.closePort()
        os.close(master)


def test_decoder_resyncs_on_garbage_split_reads_bad_crc_and_stuffing() -> None:
    d = Decoder()
    bad = bytearray(WRITE_116_512)
    bad[-1] ^= 0xFF
    stream = b"\x00\x01\xff\xff" + bytes(bad) + b"\xfd\x00" + PING + WRITE_116_512
    out = []
    for i in range(0, len(stream), 3):       # worst case: packets split across reads
        out += d.feed(stream[i:i + 3])
    assert [(p.id, p.instruction) for p in out] == [(1, Inst.PING), (1, Inst.WRITE)]
    assert out[1].params == bytes([0x74, 0, 0, 2, 0, 0])
    assert d.crc_errors == 1 and d.skipped_bytes > 0 and d.resyncs >= 1
    # byte stuffing round trip: FF FF FD in the parameters
    params = bytes([0x10, 0x00, 0xFF, 0xFF, 0xFD, 0x01])
    frame = instruction_packet(200, Inst.WRITE, params)
    assert b"\xff\xff\xfd\xfd" in frame
    assert d.feed(frame)[0].params == params


# ---- through the pty, against the simulated OpenCR ---------------------------------------------
@pytest.fixture
def sim(tmp_path: Path):
    board = SimOpenCR("burger", link=tmp_path / "ttyOPENCR").start()
    yield board
    board.stop()


def _hw(sim: SimOpenCR, **kw: object) -> OpenCRHardware:
    hw = OpenCRHardware(OpenCRConfig(port=sim.path, **kw))
    hw.open()
    return hw


def _drive(hw: OpenCRHardware, lin: float, ang: float, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        hw.set_velocity(lin, ang)
        hw.feedback()
        time.sleep(0.02)
    hw.set_velocity(0.0, 0.0)
    time.sleep(0.05)


def test_forward_1s_at_0_2_moves_0_2_m_and_feedback_agrees(sim: SimOpenCR) -> None:
    hw = _hw(sim)
    try:
        assert hw.firmware_version is not None and hw.counters()["heartbeats"] >= 1
        f0 = hw.feedback()
        assert f0 is not None
        sim_l0, sim_r0 = sim.left_rad, sim.right_rad
        t0 = time.monotonic()
        _drive(hw, 0.2, 0.0, 1.0)
        elapsed = time.monotonic() - t0
        time.sleep(0.03)
        f1 = hw.feedback()
        assert f1 is not None and f1.stamp > f0.stamp
        fwd, yaw = body_from_wheels("burger", f1.left_pos_rad - f0.left_pos_rad, f1.right_pos_rad - f0.right_pos_rad)
        sim_fwd, _ = body_from_wheels("burger", sim.left_rad - sim_l0, sim.right_rad - sim_r0)
        # 0.2 m/s -> 252 motor units (firmware truncation) = 0.1994 m/s; ~1 s of driving
        assert fwd == pytest.approx(0.1994 * (elapsed - 0.05), abs=0.02)
        assert 0.18 < fwd < 0.23 and abs(yaw) < 1e-6
        assert fwd == pytest.approx(sim_fwd, abs=0.002)        # the client reads what the board did
        assert f1.left_vel_rad_s == 0.0                          # stopped
        assert hw.counters()["rx_timeouts"] == 0 and sim.counters()["crc_errors"] == 0
    finally:
        hw.close()


def test_turn_in_place(sim: SimOpenCR) -> None:
    hw = _hw(sim)
    try:
        f0 = hw.feedback()
        _drive(hw, 0.0, 1.0, 0.5)
        time.sleep(0.03)
        f1 = hw.feedback()
        fwd, yaw = body_from_wheels("burger", f1.left_pos_rad - f0.left_pos_rad, f1.right_pos_rad - f0.right_pos_rad)
        assert abs(fwd) < 1e-6
        assert yaw == pytest.approx(0.5, abs=0.08)               # 1 rad/s for ~0.5 s, counter-clockwise
        assert f1.right_pos_rad > f0.right_pos_rad and f1.left_pos_rad < f0.left_pos_rad
    finally:
        hw.close()


def test_velocity_mid_drive_is_reported_in_rad_s(sim: SimOpenCR) -> None:
    hw = _hw(sim)
    try:
        hw.set_velocity(0.1, 0.0)
        time.sleep(0.05)
        hw._last_poll = -1e9
        fb = hw.feedback()
        # 0.1 m/s -> 126 units x 0.229 rpm = 3.02 rad/s of wheel
        assert fb.left_vel_rad_s == pytest.approx(126 * T.VELOCITY_UNIT_RAD_S)
        assert fb.left_vel_rad_s * 0.033 == pytest.approx(0.1, abs=0.002)
    finally:
        hw.halt()
        hw.close()


def test_the_firmware_stops_without_heartbeat(sim: SimOpenCR) -> None:
    """A client that stops calling stops the robot within the firmware's 500 ms."""
    hw = _hw(sim)
    try:
        hw.set_velocity(0.2, 0.0)
        time.sleep(0.8)                     # no calls: no heartbeat
        assert sim.left_units == 0 and not sim.connected_to_host
    finally:
        hw.close()


def test_stale_board_gives_a_visible_stale_stamp_and_commands_raise(sim: SimOpenCR) -> None:
    hw = _hw(sim, poll_period_s=0.01)
    try:
        good = hw.feedback()
        sim.silent = True
        time.sleep(0.02)
        stale = hw.feedback()
        assert stale is good                                   # the same message, its old stamp
        time.sleep(0.25)
        assert time.monotonic() - hw.feedback().stamp > 0.2    # the controller's limit sees it
        with pytest.raises(HardwareError, match="OpenCR write"):
            hw.set_velocity(0.1, 0.0)
        assert hw.counters()["rx_timeouts"] >= 2 and sim.counters()["unanswered"] >= 2
        sim.silent = False
        time.sleep(0.02)
        assert hw.feedback().stamp > good.stamp               # recovered
        hw.set_velocity(0.0, 0.0)
    finally:
        hw.close()


def test_a_write_whose_answer_is_lost_is_tried_again_before_it_is_a_fault(sim: SimOpenCR) -> None:
    """Writes are idempotent: one lost status packet (a busy host, a USB hiccup) is asked again;
    as many lost answers as write_attempts raise."""
    for attempts, raises in ((2, False), (1, True)):
        hw = _hw(sim, write_attempts=attempts)
        try:
            timeouts = hw.counters()["rx_timeouts"]
            sim.drop_answers = 1
            if raises:
                with pytest.raises(HardwareError, match="no status packet"):
                    hw.set_velocity(0.1, 0.0)
            else:
                hw.set_velocity(0.1, 0.0)
                assert hw.counters()["writes"] >= 1
            assert hw.counters()["rx_timeouts"] == timeouts + 1 and sim.drop_answers == 0
        finally:
            hw.close()


def test_noise_and_bad_crc_towards_the_host_are_skipped_and_counted(sim: SimOpenCR) -> None:
    hw = _hw(sim, poll_period_s=0.01)
    try:
        f0 = hw.feedback()
        sim.inject_noise(b"\x00\xff\xff\x13\xfd\x42" * 5)
        time.sleep(0.02)
        f1 = hw.feedback()
        assert f1.stamp > f0.stamp                             # the SDK skipped the garbage
        sim.corrupt_replies(1)
        time.sleep(0.02)
        assert hw.feedback() is f1                             # bad CRC: not used, stale
        assert hw.counters()["rx_corrupt"] == 1
        time.sleep(0.02)
        assert hw.feedback().stamp > f1.stamp
    finally:
        hw.close()


def test_garbage_towards_the_board_is_skipped_and_counted(sim: SimOpenCR) -> None:
    hw = _hw(sim, poll_period_s=0.01)
    try:
        bad = bytearray(instruction_packet(200, Inst.WRITE, bytes([150, 0]) + (20).to_bytes(4, "little")))
        bad[-2] ^= 0x01                                        # a command with a bad CRC must not move
        hw._port.ser.write(b"\x01\x02\xff\xff\xfd" + bytes(bad) + b"\xff\xff\xfd\x00\xc8\xff\xff")
        time.sleep(0.15)                                       # > inter-byte timeout: partial dropped
        c = sim.counters()
        assert c["crc_errors"] == 1 and c["skipped_bytes"] > 0 and c["resyncs"] >= 1
        assert c["bad_lengths"] + c["partial_dropped"] >= 1
        assert sim.left_units == 0
        _drive(hw, 0.1, 0.0, 0.2)                              # the line still works
        assert sim.left_rad > 0
    finally:
        hw.close()


def test_unplug_raises_on_command_stale_feedback_and_replug_recovers(sim: SimOpenCR) -> None:
    hw = _hw(sim, poll_period_s=0.01)
    try:
        good = hw.feedback()
        sim.unplug()
        with pytest.raises(HardwareError):
            hw.set_velocity(0.1, 0.0)
            hw.set_velocity(0.1, 0.0)
        assert hw.feedback() is good                           # never raises; stale
        hw.halt()                                              # never raises
        assert hw.counters()["port_errors"] + hw.counters()["rx_timeouts"] >= 1
        with pytest.raises(HardwareError, match="not found: is the OpenCR plugged in"):
            hw.open()
        sim.replug()
        hw.open()
        time.sleep(0.02)
        assert hw.feedback().stamp > good.stamp
        hw.set_velocity(0.0, 0.0)
    finally:
        hw.close()


def test_clear_errors_missing_port_wrong_model_wrong_id_protected_address(sim: SimOpenCR, tmp_path: Path) -> None:
    with pytest.raises(HardwareError, match=r"serial port .*ttyACM9 not found: is the OpenCR plugged in and "
                                            r"are you in the dialout group\?"):
        OpenCRHardware(OpenCRConfig(port=str(tmp_path / "ttyACM9"))).open()
    with pytest.raises(HardwareError, match="TurtleBot 3 burger, but the config says model = 'waffle'"):
        _hw(sim, model="waffle")
    with pytest.raises(HardwareError, match="no answer from the OpenCR"):
        _hw(sim, device_id=1, open_attempts=1)
    with SimOpenCR("burger", model_number=1030) as xm430:    # an XM430 answering as id 200
        with pytest.raises(HardwareError, match="model 0x0406, not an OpenCR"):
            _hw(xm430)
    hw = OpenCRHardware(OpenCRConfig(port=sim.path))
    hw.open()
    try:
        with pytest.raises(HardwareError, match="refused write"):
            hw._write(T.ADDR_ID, bytes([1]))                   # read-only: the firmware's Access Error
        assert hw.counters()["device_errors"] == 1
    finally:
        hw.close()


def test_halt_stops_and_releases_torque_then_set_velocity_reenables(sim: SimOpenCR) -> None:
    hw = _hw(sim)
    try:
        hw.set_velocity(0.2, 0.0)
        time.sleep(0.05)
        hw.halt()
        time.sleep(0.03)
        assert not sim.torque and sim.left_units == 0
        hw.set_velocity(0.1, 0.0)
        time.sleep(0.03)
        assert sim.torque and sim.left_units == int(0.1 * T.GOAL_VELOCITY_PER_M_S)
    finally:
        hw.halt()
        hw.close()


def test_waffle_geometry_and_firmware_clamp(tmp_path: Path) -> None:
    with SimOpenCR("waffle") as board:
        hw = _hw(board, model="waffle")
        try:
            hw.set_velocity(5.0, 0.0)                          # clamped by the firmware to 0.266 m/s
            time.sleep(0.03)
            m = T.MODELS["waffle"]
            assert board.left_units == int(m.max_linear_m_s * T.GOAL_VELOCITY_PER_M_S)
            assert m.track_m == 0.287 and m.wheel_radius_m == 0.033
            assert m.max_angular_rad_s == pytest.approx(0.26609 / 0.1435, rel=1e-3)
            assert math.isclose(T.TICK_TO_RAD, 0.001533981, rel_tol=1e-6)
        finally:
            hw.halt()
            hw.close()
