"""TurtleBot 3 base: the OpenCR board over Dynamixel Protocol 2.0, through ROBOTIS' ``dynamixel-sdk``.

The OpenCR running the TurtleBot 3 ROS 2 firmware is itself a Dynamixel
device (id 200, model 0x5000) whose control table takes a body velocity and
reports the two wheel motors' positions and velocities; it drives the wheels
itself. This interface therefore sends body velocities (in the firmware's
0.01 m/s and 0.01 rad/s units) and reads the encoders, exactly as ROBOTIS'
``turtlebot3_node`` does; all figures and their sources are in
:mod:`table`.

Choices, and why:

* Feedback is polled in :meth:`feedback` (one Read of the block 18..143,
  rate-limited to ``poll_period_s``), on the controller's thread: the SDK's
  port is not thread-safe, and a half-duplex request/answer bus has no
  unsolicited messages a reader thread could wait for.
* Stale feedback is *visible*, not raised: when the board does not answer,
  :meth:`feedback` returns the last good message with its old ``stamp`` and
  counts a timeout; the controller's 200 ms staleness rule turns that into a
  fault. :meth:`set_velocity` raises :class:`HardwareError` when a command is
  not acknowledged, since a command that may not have arrived must not pass
  silently.
* Heartbeat: the firmware zeroes the commanded velocity when the heartbeat
  byte (19) has not changed for 500 ms (its own deadman). Every call writes an
  incremented heartbeat when 100 ms have passed (the ROS node's period), so a
  hung controller stops the robot within 0.5 s even with the host's deadman
  gone.
* :meth:`halt` writes zero velocity and then torque off (149 = 0): the
  firmware's way to let the wheels go (``motor_driver.set_torque``). The next
  :meth:`set_velocity` turns torque back on first.
* Velocity commands are rounded to the 0.01 unit (the ROS node truncates,
  which biases every command toward zero).
"""

from __future__ import annotations

import errno
import os
import termios
import time
from collections.abc import Callable
from typing import Any

import serial

from ovamos.services.base_driver.hardware import HardwareDefaults, HardwareError, WheelFeedback
from ovamos.services.base_driver.opencr import table as T
from ovamos.services.base_driver.opencr.config import OpenCRConfig

__all__ = ["OpenCRHardware"]

_INT32 = 2**32


# dynamixel_sdk's result codes (imported lazily with the SDK, so named here)
_RX_TIMEOUT = -3001  # COMM_RX_TIMEOUT: no (complete) status packet in time
_RX_CORRUPT = -3002  # COMM_RX_CORRUPT: bad CRC, partial packet


def _i32(data: list[int] | bytes, offset: int) -> int:
    return int.from_bytes(bytes(data[offset:offset + 4]), "little", signed=True)


class OpenCRHardware(HardwareDefaults):
    """:class:`~ovamos.services.base_driver.hardware.BaseHardware` for a TurtleBot 3 (OpenCR firmware)."""

    name = "opencr"

    def __init__(self, config: OpenCRConfig | None = None, *, clock: Callable[[], float] = time.monotonic,
                 port_handler: Callable[[str], Any] | None = None) -> None:
        """``port_handler`` (a ``dynamixel_sdk.PortHandler`` class on another port than
        ``config.port``) and ``clock`` run it in simulated time (:mod:`ovamos.shared.simtime`)."""
        self.config = config or OpenCRConfig()
        self._clock, self._port_handler = clock, port_handler
        self.model = T.MODELS[self.config.model]
        self._port = None            # dynamixel_sdk.PortHandler
        self._ph = None              # dynamixel_sdk.PacketHandler(2.0)
        self._feedback: WheelFeedback | None = None
        self._last_poll = -1e9
        self._last_hb = -1e9
        self._hb_count = 0
        self._torque = False
        self._raw: list[int] | None = None      # last raw ticks (left, right), for unwrapping
        self._pos = [0.0, 0.0]                  # unwrapped ticks
        self.firmware_version: int | None = None
        self._counts = {"reads": 0, "writes": 0, "rx_timeouts": 0, "rx_corrupt": 0,
                        "device_errors": 0, "port_errors": 0, "heartbeats": 0, "opens": 0}

    # ---- port -------------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, ping id 200, check model and TurtleBot model, heartbeat, torque on."""
        import dynamixel_sdk as dxl

        self.close()
        cfg = self.config
        if self._port_handler is None and not os.path.exists(cfg.port):
            raise HardwareError(f"serial port {cfg.port} not found: is the OpenCR plugged in and are "
                                f"you in the dialout group?")
        port = (self._port_handler or dxl.PortHandler)(cfg.port)
        try:
            if not port.setBaudRate(cfg.baudrate):
                raise HardwareError(f"baud rate {cfg.baudrate} is not one the Dynamixel SDK supports")
        except (OSError, serial.SerialException) as exc:
            hint = (" (permission denied: add yourself to the dialout group and log in again)"
                    if getattr(exc, "errno", None) == errno.EACCES or "ermission" in str(exc) else "")
            raise HardwareError(f"cannot open serial port {cfg.port}: {exc}{hint}") from None
        self._port, self._ph = port, dxl.PacketHandler(2.0)
        self._counts["opens"] += 1
        try:
            model_number = self._ping(dxl)
            if model_number != T.MODEL_NUMBER:
                raise HardwareError(
                    f"device {cfg.device_id} on {cfg.port} is Dynamixel model 0x{model_number:04X}, not an "
                    f"OpenCR with the TurtleBot 3 firmware (0x{T.MODEL_NUMBER:04X})")
            info = self._read(T.ADDR_MODEL_INFORMATION, 5)
            found = T.MODEL_BY_INFORMATION.get(int.from_bytes(bytes(info[:4]), "little"))
            self.firmware_version = info[4]
            if found is None or found.name != cfg.model:
                raise HardwareError(
                    f"the OpenCR on {cfg.port} is set up for a TurtleBot 3 "
                    f"{found.name if found else 'of unknown model ' + str(info[:4])}, but the config says "
                    f"model = {cfg.model!r}: fix the config (or re-flash the firmware for the right model)")
            self._heartbeat(force=True)
            self._write(T.ADDR_CMD_VELOCITY_LINEAR_X, self._velocity_block(0, 0))
            self._write(T.ADDR_MOTOR_TORQUE_ENABLE, bytes([1]))
            self._torque = True
        except HardwareError:
            self.close()
            raise

    def _ping(self, dxl: object) -> int:
        cfg = self.config
        result_text = ""
        for _ in range(cfg.open_attempts):
            model_number, result, error = self._guard(lambda: self._ph.ping(self._port, cfg.device_id))
            if result == 0:   # COMM_SUCCESS
                return int(model_number)
            self._count_result(result)
            result_text = self._ph.getTxRxResult(result)
        raise HardwareError(f"no answer from the OpenCR (Dynamixel id {cfg.device_id}) on {cfg.port} at "
                            f"{cfg.baudrate} baud ({result_text}): is the TurtleBot 3 firmware flashed and "
                            f"the board powered?")

    def close(self) -> None:
        """Release the port (idempotent). Does not stop the wheels: :meth:`halt` does."""
        port, self._port = self._port, None
        if port is not None and getattr(port, "ser", None) is not None:
            try:
                port.closePort()
            except (OSError, termios.error, serial.SerialException):
                pass
        self._raw = None

    # ---- bus primitives ------------------------------------------------------------------
    def _guard(self, call):
        """Run one SDK call; a vanished port (unplugged) becomes a HardwareError and closes."""
        if self._port is None:
            raise HardwareError(f"OpenCR port {self.config.port} is not open")
        try:
            return call()
        except (OSError, termios.error, serial.SerialException, TypeError) as exc:
            # termios.error (not an OSError): tcflush on a vanished pty/USB device;
            # TypeError: pyserial's read on a closed fd in some versions
            self._counts["port_errors"] += 1
            self.close()
            raise HardwareError(f"serial port {self.config.port} lost (unplugged?): {exc}") from None

    def _count_result(self, result: int) -> None:
        if result == _RX_TIMEOUT:
            self._counts["rx_timeouts"] += 1
        elif result == _RX_CORRUPT:
            self._counts["rx_corrupt"] += 1

    def _read(self, addr: int, length: int) -> list[int]:
        data, result, error = self._guard(
            lambda: self._ph.readTxRx(self._port, self.config.device_id, addr, length))
        if result != 0:
            self._count_result(result)
            raise HardwareError(f"OpenCR read {addr}+{length}: {self._ph.getTxRxResult(result)}")
        if error:
            self._counts["device_errors"] += 1
            raise HardwareError(f"OpenCR refused read {addr}+{length}: {self._ph.getRxPacketError(error)}")
        self._counts["reads"] += 1
        return list(data)

    def _write(self, addr: int, data: bytes) -> None:
        for _ in range(self.config.write_attempts):
            result, error = self._guard(
                lambda: self._ph.writeTxRx(self._port, self.config.device_id, addr, len(data), list(data)))
            if result == 0:
                break
            self._count_result(result)
            if result != _RX_TIMEOUT:  # only an answer that did not come is worth asking again
                break
        if result != 0:
            raise HardwareError(f"OpenCR write {addr}+{len(data)}: {self._ph.getTxRxResult(result)}")
        if error:
            self._counts["device_errors"] += 1
            raise HardwareError(f"OpenCR refused write {addr}+{len(data)}: {self._ph.getRxPacketError(error)}")
        self._counts["writes"] += 1

    def _heartbeat(self, force: bool = False) -> None:
        now = self._clock()
        if not force and now - self._last_hb < self.config.heartbeat_period_s:
            return
        self._hb_count = self._hb_count % 255 + 1      # 1..255: never the firmware's initial 0
        self._write(T.ADDR_HEARTBEAT, bytes([self._hb_count]))
        self._last_hb = now
        self._counts["heartbeats"] += 1

    @staticmethod
    def _velocity_block(linear_m_s: float, angular_rad_s: float) -> bytes:
        """cmd_velocity linear x .. angular z (150..173) as the ROS node writes it: 6 int32, y/z zero."""
        lin = round(linear_m_s / T.CMD_VELOCITY_SCALE)
        ang = round(angular_rad_s / T.CMD_VELOCITY_SCALE)
        words = (lin, 0, 0, 0, 0, ang)
        return b"".join(int(w).to_bytes(4, "little", signed=True) for w in words)

    # ---- BaseHardware --------------------------------------------------------------------
    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        """Send a body velocity (clamped by the firmware to the model's limits)."""
        self._heartbeat()
        if not self._torque and (linear_m_s or angular_rad_s):
            self._write(T.ADDR_MOTOR_TORQUE_ENABLE, bytes([1]))
            self._torque = True
        self._write(T.ADDR_CMD_VELOCITY_LINEAR_X, self._velocity_block(linear_m_s, angular_rad_s))

    def halt(self) -> None:
        """Zero velocity, then torque off. Never raises."""
        for addr, data in ((T.ADDR_CMD_VELOCITY_LINEAR_X, self._velocity_block(0, 0)),
                           (T.ADDR_MOTOR_TORQUE_ENABLE, bytes([0]))):
            try:
                self._write(addr, data)
            except HardwareError:
                pass
        self._torque = False

    def feedback(self) -> WheelFeedback | None:
        """Poll the board (at most every ``poll_period_s``); the newest good feedback, or None."""
        now = self._clock()
        if self._port is None or now - self._last_poll < self.config.poll_period_s:
            return self._feedback
        self._last_poll = now
        try:
            self._heartbeat()
            data = self._read(T.FEEDBACK_ADDR, T.FEEDBACK_LEN)
        except HardwareError:
            return self._feedback           # stale: the stamp says how old
        self._feedback = self._decode(data, self._clock())
        return self._feedback

    def _decode(self, data: list[int], stamp: float) -> WheelFeedback:
        base = T.FEEDBACK_ADDR
        raw = [_i32(data, T.ADDR_PRESENT_POSITION_L - base), _i32(data, T.ADDR_PRESENT_POSITION_R - base)]
        if self._raw is None:
            self._pos = [float(r) for r in raw]
        else:
            for i in (0, 1):     # int32 tick counters wrap: take the short way round
                d = (raw[i] - self._raw[i]) % _INT32
                self._pos[i] += d - _INT32 if d >= _INT32 // 2 else d
        self._raw = raw
        vel = [_i32(data, a - base) * T.VELOCITY_UNIT_RAD_S
               for a in (T.ADDR_PRESENT_VELOCITY_L, T.ADDR_PRESENT_VELOCITY_R)]
        bumpers: tuple[str, ...] = ()
        if self.config.bumpers:
            bumpers = tuple(n for n, a in (("front", T.ADDR_BUMPER_1), ("back", T.ADDR_BUMPER_2))
                            if data[a - base])
        status = int.from_bytes(bytes([data[T.ADDR_DEVICE_STATUS - base]]), "little", signed=True)
        faults = ("wheel motors not connected (OpenCR device_status -1)",) if status == -1 else ()
        volts = int.from_bytes(bytes(data[T.ADDR_BATTERY_VOLTAGE - base:T.ADDR_BATTERY_VOLTAGE - base + 4]),
                               "little") / 100.0
        return WheelFeedback(stamp=stamp, left_pos_rad=self._pos[0] * T.TICK_TO_RAD,
                             right_pos_rad=self._pos[1] * T.TICK_TO_RAD, left_vel_rad_s=vel[0],
                             right_vel_rad_s=vel[1], bumpers=bumpers, faults=faults,
                             extra={"battery_v": volts})

    def counters(self) -> dict[str, int]:
        """Reads/writes done, timeouts, corrupt answers (bad CRC / partial), device errors, port losses."""
        return dict(self._counts)
