"""A simulated TurtleBot 3 OpenCR board on a pseudo-terminal, speaking Dynamixel Protocol 2.0 byte for byte.

The client under test (``OpenCRHardware`` through ROBOTIS' ``dynamixel-sdk``)
opens the pty's slave path exactly as it opens ``/dev/ttyACM0`` on a robot, so
the real SDK code runs: packet building, timeouts, CRC checks. The simulator
decodes instruction packets with its own decoder (this package's :mod:`protocol`),
answers as device id 200 with the firmware's control table (:mod:`table`), and
models what a client relies on: the write protection, the heartbeat timeout
(500 ms without a changing heartbeat zeroes the command, as the firmware
does), torque enable, the 0.01-unit velocity commands clamped to the model's
limits, the wheel motors' goal-velocity quantisation, and integration of the
wheel positions (4096 ticks per revolution) and velocities.

Fault injection: ``silent`` (reads packets, answers nothing: stale feedback),
``drop_answers`` (swallows the next n answers: a late or lost status packet),
``inject_noise`` (garbage before the next answer), ``corrupt_replies`` (the
next answers carry a wrong CRC), ``unplug`` / ``replug`` (the pty disappears;
with ``link`` the replugged device reappears at the same path, like a udev
symlink), ``bumper`` presses. Garbage *received* is skipped by the decoder and
counted (``counters()``).

A ``physics`` hook, called after every integration step with the wheels'
angle changes, lets a simulated robot move with the wheels; it returns False
when the robot is blocked, which stalls the wheels (the step is undone).
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

from ovamos.services.base_driver.opencr import table as T
from ovamos.services.base_driver.opencr.protocol import Decoder, Err, Inst, Packet, status_packet
from ovamos.shared.simtime import MemoryLine

log = logging.getLogger("ovamos.opencr_sim")

#: physics(dt_s, left_wheel_delta_rad, right_wheel_delta_rad) -> False when the robot is blocked
Physics = Callable[[float, float, float], bool]

FIRMWARE_VERSION = 7
#: A partial packet followed by this much silence is abandoned (the sender gave up).
INTER_BYTE_TIMEOUT_S = 0.05


class SimOpenCR:
    """The board: a thread that owns the pty master, the control table and the wheels."""

    def __init__(self, model: str = "burger", *, device_id: int = T.DEVICE_ID,
                 link: str | Path | None = None, physics: Physics | None = None,
                 step_s: float = 0.005, model_number: int = T.MODEL_NUMBER,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.model = T.MODELS[model]
        self.model_number = model_number   # another value: a different Dynamixel device on the port
        self.device_id = device_id
        self.link = Path(link) if link is not None else None
        self.physics = physics
        self.step_s = step_s
        self._clock = clock
        self.table = bytearray(T.TABLE_SIZE)
        self._lock = threading.RLock()
        # wheel state (rad, and goal velocity in motor units)
        self.left_rad = 0.0
        self.right_rad = 0.0
        self.left_units = 0
        self.right_units = 0
        self.torque = False
        self._cmd_lin = 0.0
        self._cmd_ang = 0.0
        self._hb_value = 0          # firmware's pre_data starts at 0
        self._hb_time = 0.0
        self.connected_to_host = False
        # faults
        self.silent = False
        self.drop_answers = 0  # answers still to swallow (a late or lost status packet)
        self._noise = bytearray()
        self._corrupt = 0
        self.bumpers = [False, False]
        self.motors_connected = True
        # counters of the device side
        self.decoder = Decoder()
        self.replies = 0
        self.foreign_ids = 0
        self.unanswered = 0
        self.access_errors = 0
        # pty
        self._master: int | None = None
        self._slave: int | None = None
        self.port = ""
        self._line: MemoryLine | None = None  # in simulated time, the line in place of the pty
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._init_table()

    # ---- control table -------------------------------------------------------------------
    def _put(self, addr: int, value: int, size: int, signed: bool = False) -> None:
        self.table[addr:addr + size] = int(value).to_bytes(size, "little", signed=signed)

    def _get(self, addr: int, size: int, signed: bool = False) -> int:
        return int.from_bytes(self.table[addr:addr + size], "little", signed=signed)

    def _init_table(self) -> None:
        self._put(T.ADDR_MODEL_NUMBER, self.model_number, 2)
        self._put(T.ADDR_MODEL_INFORMATION, self.model.model_information, 4)
        self._put(T.ADDR_FIRMWARE_VERSION, FIRMWARE_VERSION, 1)
        self._put(T.ADDR_ID, self.device_id, 1)
        self._put(T.ADDR_BAUDRATE, 3, 1)
        self._put(T.ADDR_BATTERY_VOLTAGE, 1200, 4)          # 12.00 V
        self.torque = self.motors_connected                 # begin(): set_torque(true) when connected
        self._sync_table(self._clock())

    def _sync_table(self, now: float) -> None:
        """Copy the simulated hardware into the table (the firmware's update_*_to_table)."""
        self._put(T.ADDR_MILLIS, int(now * 1000) & 0xFFFFFFFF, 4)
        self._put(T.ADDR_DEVICE_STATUS, 0 if self.motors_connected else -1, 1, signed=True)
        self._put(T.ADDR_BUMPER_1, int(self.bumpers[0]), 1)
        self._put(T.ADDR_BUMPER_2, int(self.bumpers[1]), 1)
        for addr, units in ((T.ADDR_PRESENT_VELOCITY_L, self.left_units),
                            (T.ADDR_PRESENT_VELOCITY_R, self.right_units)):
            self._put(addr, units, 4, signed=True)
        for addr, rad in ((T.ADDR_PRESENT_POSITION_L, self.left_rad),
                          (T.ADDR_PRESENT_POSITION_R, self.right_rad)):
            ticks = round(rad / T.TICK_TO_RAD)
            self._put(addr, ((ticks + 2**31) % 2**32) - 2**31, 4, signed=True)  # int32 wrap
        self._put(T.ADDR_MOTOR_TORQUE_ENABLE, int(self.torque), 1)

    # ---- firmware behaviour ----------------------------------------------------------------
    def _on_write(self, addr: int, length: int, now: float) -> None:
        """The firmware's dxl_slave_write_callback_func."""
        def covers(item: int, size: int) -> bool:
            return item >= addr and item + size <= addr + length
        if covers(T.ADDR_MOTOR_TORQUE_ENABLE, 1) and self.motors_connected:
            self.torque = bool(self.table[T.ADDR_MOTOR_TORQUE_ENABLE])
        if covers(T.ADDR_CMD_VELOCITY_LINEAR_X, 4):
            v = self._get(T.ADDR_CMD_VELOCITY_LINEAR_X, 4, signed=True) * T.CMD_VELOCITY_SCALE
            self._cmd_lin = max(-self.model.max_linear_m_s, min(self.model.max_linear_m_s, v))
        if covers(T.ADDR_CMD_VELOCITY_ANGULAR_Z, 4):
            w = self._get(T.ADDR_CMD_VELOCITY_ANGULAR_Z, 4, signed=True) * T.CMD_VELOCITY_SCALE
            self._cmd_ang = max(-self.model.max_angular_rad_s, min(self.model.max_angular_rad_s, w))

    def _heartbeat(self, now: float) -> None:
        """update_connection_state_with_ros2_node: a changed byte is a sign of life."""
        value = self.table[T.ADDR_HEARTBEAT]
        if value != self._hb_value:
            self._hb_value = value
            self._hb_time = now
            self.connected_to_host = True
        elif now - self._hb_time >= T.HEARTBEAT_TIMEOUT_S:
            self.connected_to_host = False

    def _wheel_units(self) -> tuple[int, int]:
        """control_motors(): body velocity -> goal velocity units, truncated and clamped."""
        lin, ang = (self._cmd_lin, self._cmd_ang) if self.connected_to_host else (0.0, 0.0)
        half = ang * self.model.track_m / 2.0
        out = []
        for v in (lin - half, lin + half):
            units = int(v * T.GOAL_VELOCITY_PER_M_S)      # C float -> int32 truncates
            out.append(max(-T.GOAL_VELOCITY_LIMIT, min(T.GOAL_VELOCITY_LIMIT, units)))
        return out[0], out[1]

    def step(self, dt: float, now: float) -> None:
        """Advance the wheels by ``dt`` seconds."""
        with self._lock:
            self._heartbeat(now)
            if self.torque and self.motors_connected:
                self.left_units, self.right_units = self._wheel_units()
            else:
                self.left_units = self.right_units = 0
            dl = self.left_units * T.VELOCITY_UNIT_RAD_S * dt
            dr = self.right_units * T.VELOCITY_UNIT_RAD_S * dt
            if (dl or dr) and self.physics is not None and not self.physics(dt, dl, dr):
                dl = dr = 0.0
                self.left_units = self.right_units = 0
            self.left_rad += dl
            self.right_rad += dr
            self._sync_table(now)

    # ---- packets ---------------------------------------------------------------------------
    def _handle(self, pkt: Packet, now: float) -> bytes | None:
        """One instruction packet -> the status packet to send (None: no answer)."""
        if pkt.id not in (self.device_id, 0xFE):
            self.foreign_ids += 1
            return None
        p = pkt.params
        if pkt.instruction == Inst.PING:
            return status_packet(self.device_id, Err.NONE,
                                 self.model_number.to_bytes(2, "little") + bytes([FIRMWARE_VERSION]))
        if pkt.id == 0xFE:           # broadcast read/write: no status packet (e-manual)
            return None
        if pkt.instruction == Inst.READ:
            if len(p) != 4:
                return status_packet(self.device_id, Err.DATA_LENGTH)
            addr, length = int.from_bytes(p[:2], "little"), int.from_bytes(p[2:4], "little")
            if addr + length > len(self.table):
                self.access_errors += 1
                return status_packet(self.device_id, Err.ACCESS)
            self.step(0.0, now)          # fresh values, as the firmware's tables are
            return status_packet(self.device_id, Err.NONE, bytes(self.table[addr:addr + length]))
        if pkt.instruction == Inst.WRITE:
            if len(p) < 3:
                return status_packet(self.device_id, Err.DATA_LENGTH)
            addr, data = int.from_bytes(p[:2], "little"), p[2:]
            if not any(addr >= a and addr + len(data) <= a + n for a, n in T.WRITABLE):
                self.access_errors += 1
                return status_packet(self.device_id, Err.ACCESS)
            with self._lock:
                self.table[addr:addr + len(data)] = data
                self._on_write(addr, len(data), now)
                self._heartbeat(now)
            return status_packet(self.device_id, Err.NONE)
        return status_packet(self.device_id, Err.INSTRUCTION)

    def _reply(self, frame: bytes) -> None:
        if self._noise:
            frame = bytes(self._noise) + frame
            self._noise.clear()
        if self._corrupt > 0:
            self._corrupt -= 1
            frame = frame[:-1] + bytes([frame[-1] ^ 0x5A])
        if self._line is not None:
            self._line.put(frame)
        else:
            assert self._master is not None
            os.write(self._master, frame)
        self.replies += 1

    def _serve(self, data: bytes, now: float) -> None:
        """Answer the instruction packets in ``data`` (raises OSError when the reply cannot go)."""
        for pkt in self.decoder.feed(data):
            answer = self._handle(pkt, now)
            if answer is None:
                continue
            if self.silent or self.drop_answers > 0:
                self.drop_answers -= 0 if self.silent else 1
                self.unanswered += 1
                continue
            self._reply(answer)

    def memory_line(self) -> MemoryLine:
        """The serial line for simulated time, in place of :meth:`start`'s pty: packets are
        answered as they are written; the benchmark runs :meth:`step` every ``step_s`` itself."""
        self._line = MemoryLine(lambda data: self._serve(data, self._clock()), name="simtime:opencr")
        self.port = self._line.name
        return self._line

    # ---- the thread ------------------------------------------------------------------------
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)     # no echo, no line discipline: bytes pass untouched
        tty.setraw(master)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.port)
            tmp.replace(self.link)

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    @property
    def path(self) -> str:
        """Where a client opens the device: the stable link when one is set, else the pty."""
        return str(self.link) if self.link is not None else self.port

    def start(self) -> SimOpenCR:
        """Create the pty and start answering."""
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-opencr", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        last = self._clock()
        last_rx = last
        master = self._master
        while not self._stop.is_set() and master is not None:
            try:
                ready, _, _ = select.select([master], [], [], self.step_s)
            except (OSError, ValueError):
                break
            now = self._clock()
            if now - last >= self.step_s:
                self.step(now - last, now)
                last = now
            if not ready:
                if self.decoder.pending() and now - last_rx > INTER_BYTE_TIMEOUT_S:
                    self.decoder.drop_partial()
                continue
            try:
                data = os.read(master, 4096)
            except OSError:          # EIO: no client has the slave open; keep waiting
                time.sleep(self.step_s)
                continue
            last_rx = now
            try:
                self._serve(data, now)
            except OSError:
                break

    def stop(self) -> None:
        """Stop the thread and remove the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_pty()

    # ---- fault injection ---------------------------------------------------------------------
    def unplug(self) -> None:
        """The USB cable is pulled: the pty (and the link's target) disappears."""
        self.stop()

    def replug(self) -> None:
        """Plugged back in: a new pty (at ``link`` when set); the board restarts its table."""
        self.stop()
        with self._lock:
            self._hb_value = 0
            self.connected_to_host = False
            self._cmd_lin = self._cmd_ang = 0.0
            self._init_table()
        self.start()

    def inject_noise(self, data: bytes = b"\x00\x13\xff\xff\x42\xfd\x99") -> None:
        """Garbage on the line before the next answer."""
        self._noise.extend(data)

    def corrupt_replies(self, n: int = 1) -> None:
        """The next ``n`` answers carry a wrong CRC."""
        self._corrupt += n

    def press_bumper(self, which: int, pressed: bool = True) -> None:
        """Bumper 1 (front) or 2 (back), the firmware's optional touch sensors."""
        with self._lock:
            self.bumpers[which - 1] = pressed

    # ---- inspection ----------------------------------------------------------------------------
    def wheel_travel_m(self) -> tuple[float, float]:
        """Distance each wheel has rolled (m)."""
        r = self.model.wheel_radius_m
        return self.left_rad * r, self.right_rad * r

    def counters(self) -> dict[str, int]:
        """The device side's counts: garbage skipped, CRC errors, answers, ..."""
        d = self.decoder
        return {"packets": d.packets, "skipped_bytes": d.skipped_bytes, "resyncs": d.resyncs,
                "crc_errors": d.crc_errors, "bad_lengths": d.bad_lengths,
                "partial_dropped": d.partial_dropped, "replies": self.replies,
                "unanswered": self.unanswered, "foreign_ids": self.foreign_ids,
                "access_errors": self.access_errors}

    def __enter__(self) -> SimOpenCR:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def body_from_wheels(model: str, dl_rad: float, dr_rad: float) -> tuple[float, float]:
    """(forward m, yaw rad) for wheel angle changes: differential drive, for tests and physics."""
    m = T.MODELS[model]
    sl, sr = dl_rad * m.wheel_radius_m, dr_rad * m.wheel_radius_m
    return (sl + sr) / 2.0, (sr - sl) / m.track_m


__all__ = ["SimOpenCR", "Physics", "body_from_wheels", "FIRMWARE_VERSION"]


def line_port_handler(line: MemoryLine) -> Callable[[str], object]:
    """A ``dynamixel_sdk.PortHandler`` class whose port is ``line`` (for ``OpenCRHardware``'s
    ``port_handler``): the SDK's own packet code runs, on bytes that never leave the process."""
    import dynamixel_sdk as dxl

    class LinePortHandler(dxl.PortHandler):
        def setupPort(self, cflag_baud: int) -> bool:
            line.is_open = True
            self.ser, self.is_open = line, True
            line.reset_input_buffer()
            self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
            return True

    return LinePortHandler

