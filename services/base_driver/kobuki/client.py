"""The Kobuki (TurtleBot 2) base as a :class:`BaseHardware`: its serial protocol over pyserial.

A TurtleBot 2 is a Kobuki base with a laptop on its tray; the laptop reaches
the base through its USB serial adapter (FTDI; kobuki_ftdi's udev rule names it
``/dev/kobuki``, otherwise ``/dev/ttyUSB0``). The base streams Basic Sensor Data
at 50 Hz whether or not anyone listens, and takes Base Control (speed, radius)
commands. Packet layouts and unit conversions are in
:mod:`ovamos.services.base_driver.kobuki.protocol`, with their sources.

Threads: one reader thread owns the port's input. It decodes packets and keeps
the newest :class:`WheelFeedback` under a lock; the controller's thread writes
commands and reads that feedback. Nothing the wire sends can raise in the
controller: garbage is skipped and counted by the decoder.

Losing the port (the USB cable pulled; in tests the pty closed) is reported
this way: the reader thread stops and records why; the feedback then stops
changing, so its ``stamp`` ages and the controller's stale-feedback limit
faults within 200 ms; the next :meth:`KobukiHardware.set_velocity` raises
:class:`HardwareError` with the reason; :meth:`KobukiHardware.halt` never
raises; :meth:`KobukiHardware.open` reconnects (and raises while the port is
still missing). :meth:`KobukiHardware.feedback` never raises: it keeps
returning the last feedback.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import serial

from ovamos.services.base_driver.hardware import HardwareDefaults, HardwareError, WheelFeedback
from ovamos.services.base_driver.kobuki.config import KobukiConfig
from ovamos.services.base_driver.kobuki.protocol import (
    BASIC_SENSOR_DATA_ID,
    BUMPER_BITS,
    CLIFF_BITS,
    OVERCURRENT_BITS,
    WHEEL_DROP_BITS,
    BasicSensorData,
    PacketDecoder,
    ProtocolError,
    TickUnwrapper,
    body_to_speed_radius,
    encode_base_control,
    names_from_bits,
    split_sub_payloads,
    wrap_diff16,
)

__all__ = ["KobukiHardware"]

log = logging.getLogger("ovamos.kobuki")


class KobukiHardware(HardwareDefaults):
    """A Kobuki over pyserial. See the module docstring for how a lost port is reported."""

    name = "kobuki"

    def __init__(self, config: KobukiConfig | None = None, *, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep, open_port: Callable[[], Any] | None = None) -> None:
        """``open_port`` (a pyserial-like port in place of ``config.port``) makes the interface
        *polled*: no reader thread, :meth:`feedback` reads what has arrived; with ``clock`` and
        ``sleep`` that is how it runs in simulated time (:mod:`ovamos.shared.simtime`)."""
        self.config = config or KobukiConfig()
        self._clock, self._sleep, self._open_port = clock, sleep, open_port
        self._serial: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._decoder = PacketDecoder()
        self._feedback: WheelFeedback | None = None
        self._error: str | None = None
        self._left = TickUnwrapper()
        self._right = TickUnwrapper()
        self._last_ts: int | None = None
        self._last_ticks: tuple[int, int] = (0, 0)
        self._vel: tuple[float | None, float | None] = (None, None)
        self._counts = {"feedback": 0, "bad_sub_payloads": 0, "commands": 0, "port_errors": 0}

    # -- BaseHardware ------------------------------------------------------------------

    def open(self) -> None:
        """Open the port, start the reader and wait for the first Basic Sensor Data.

        Waiting for feedback makes a wrong port (another USB serial device, or a
        Kobuki switched off) an error here rather than a silent stale fault later.
        """
        self.close()
        port = self.config.port
        ser = self._open_port() if self._open_port is not None else self._open_serial(port)
        ser.reset_input_buffer()
        with self._lock:
            self._serial = ser
            self._error = None
            self._feedback = None
            self._decoder = PacketDecoder()
            # The unwrappers are kept: the base's encoder counters keep counting while the host is
            # away, so positions stay continuous across a reconnect (kobuki_driver's DiffDrive keeps
            # its last ticks the same way) and the controller's odometry does not jump.
            self._last_ts = None
            self._vel = (None, None)
        self._stop.clear()
        if self._open_port is None:
            self._thread = threading.Thread(target=self._read_loop, name="kobuki-reader", daemon=True)
            self._thread.start()
        deadline = self._clock() + self.config.first_feedback_timeout_s
        while self._clock() < deadline:
            if self._open_port is not None:
                self._read_arrived()
            with self._lock:
                if self._feedback is not None:
                    return
                error = self._error
            if error is not None:
                break
            self._sleep(0.005)
        self.close()
        raise HardwareError(f"no Basic Sensor Data from the Kobuki on {port} within "
                            f"{self.config.first_feedback_timeout_s:g} s"
                            + (f" ({error})" if error else ": is the base switched on, and is this its port?"))

    def _open_serial(self, port: str) -> serial.Serial:
        if not os.path.exists(port):
            raise HardwareError(f"serial port {port} not found: is the Kobuki plugged in "
                                f"and are you in the dialout group?")
        try:
            return serial.Serial(port, self.config.baudrate, bytesize=serial.EIGHTBITS,
                                 parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                 timeout=self.config.read_timeout_s, write_timeout=self.config.write_timeout_s)
        except PermissionError as exc:
            raise HardwareError(f"serial port {port}: permission denied: add yourself to the dialout "
                                f"group (sudo usermod -aG dialout $USER, then log in again)") from exc
        except (serial.SerialException, OSError) as exc:
            raise HardwareError(f"serial port {port} cannot be opened: {exc}") from exc

    def set_velocity(self, linear_m_s: float, angular_rad_s: float) -> None:
        """Send one Base Control packet for this body velocity (kobuki_driver's arc rules)."""
        speed, radius = body_to_speed_radius(linear_m_s, angular_rad_s, self.config.wheel_base_m)
        self._send(encode_base_control(speed, radius))

    def halt(self) -> None:
        """Speed 0, radius 0: the Kobuki's Base Control has no motor-off, so this is the stop."""
        try:
            self._send(encode_base_control(0, 0))
        except HardwareError as exc:
            log.debug("halt on a dead port: %s", exc)

    def feedback(self) -> WheelFeedback | None:
        """The newest feedback (never raises; after a lost port it is the last one, ageing)."""
        if self._open_port is not None:
            self._read_arrived()
        with self._lock:
            return self._feedback

    def counters(self) -> dict[str, int]:
        """Decoder counters (packets, malformed, resyncs, bytes_skipped) and this interface's."""
        with self._lock:
            return {**self._decoder.counters(), **self._counts}

    def close(self) -> None:
        """Stop the reader and release the port (idempotent)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        with self._lock:
            ser, self._serial = self._serial, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    # -- what else the controller and the service may show ----------------------------

    def stale_reason(self, now: float) -> str:
        """Why feedback stopped, when this interface knows (the controller's optional hook)."""
        return self.error or ""

    @property
    def error(self) -> str | None:
        """Why the port was lost, or None while it works."""
        with self._lock:
            return self._error

    # -- internals ---------------------------------------------------------------------

    def _send(self, packet: bytes) -> None:
        with self._lock:
            ser, error = self._serial, self._error
        if error is not None:
            raise HardwareError(error)
        if ser is None:
            raise HardwareError(f"Kobuki on {self.config.port} is not open")
        try:
            with self._write_lock:
                ser.write(packet)
                ser.flush()
        except (serial.SerialException, serial.SerialTimeoutException, OSError, TypeError,
                AttributeError) as exc:
            # TypeError / AttributeError: pyserial's fd is gone (closed by the reader's failure)
            reason = self._lost(f"write failed: {exc}")
            raise HardwareError(reason) from exc
        with self._lock:
            self._counts["commands"] += 1

    def _lost(self, what: str) -> str:
        """Record the first reason the port was lost; return it."""
        with self._lock:
            if self._error is None:
                self._error = (f"serial port {self.config.port} lost ({what}): "
                               f"was the Kobuki unplugged or switched off?")
                self._counts["port_errors"] += 1
            return self._error

    def _read_loop(self) -> None:
        ser = self._serial
        assert ser is not None
        while not self._stop.is_set():
            try:
                data = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._stop.is_set():
                    log.warning("%s", self._lost(f"read failed: {exc}"))
                return
            if not data:
                if not os.path.exists(self.config.port):
                    self._lost("the device node is gone")
                    return
                continue
            self._take(data)

    def _read_arrived(self) -> None:
        """Polled: decode what the port holds now."""
        ser = self._serial
        if ser is not None and ser.in_waiting:
            self._take(ser.read(ser.in_waiting))

    def _take(self, data: bytes) -> None:
        stamp = self._clock()
        with self._lock:
            payloads = self._decoder.feed(data)
        for payload in payloads:
            self._handle(payload, stamp)

    def _handle(self, payload: bytes, stamp: float) -> None:
        try:
            subs = split_sub_payloads(payload)
        except ProtocolError:  # the decoder checked this already; belt and braces
            with self._lock:
                self._counts["bad_sub_payloads"] += 1
            return
        for sub_id, data in subs:
            if sub_id != BASIC_SENSOR_DATA_ID:
                continue  # docking IR, inertia, cliff ADC, ...: not needed by the controller
            try:
                bsd = BasicSensorData.parse(data)
            except ProtocolError:
                with self._lock:
                    self._counts["bad_sub_payloads"] += 1
                continue
            self._update(bsd, stamp)

    def _update(self, bsd: BasicSensorData, stamp: float) -> None:
        """Unwrap the ticks, derive wheel rates from the device's own clock (as DiffDrive::update)."""
        k = self.config.tick_to_rad
        with self._lock:
            left = self._left.update(bsd.left_encoder)
            right = self._right.update(bsd.right_encoder)
            if self._last_ts is not None and bsd.timestamp_ms != self._last_ts:
                dt = wrap_diff16(bsd.timestamp_ms, self._last_ts) / 1000.0
                if dt > 0:
                    self._vel = ((left - self._last_ticks[0]) * k / dt, (right - self._last_ticks[1]) * k / dt)
            if self._last_ts is None or bsd.timestamp_ms != self._last_ts:
                self._last_ts = bsd.timestamp_ms
                self._last_ticks = (left, right)
            faults = tuple(f"overcurrent {name} wheel" for name in names_from_bits(bsd.overcurrent, OVERCURRENT_BITS))
            self._feedback = WheelFeedback(
                stamp=stamp,
                left_pos_rad=left * k,
                right_pos_rad=right * k,
                left_vel_rad_s=self._vel[0],
                right_vel_rad_s=self._vel[1],
                bumpers=names_from_bits(bsd.bumper, BUMPER_BITS),
                wheel_drops=names_from_bits(bsd.wheel_drop, WHEEL_DROP_BITS),
                cliffs=names_from_bits(bsd.cliff, CLIFF_BITS),
                faults=faults,
                extra={"battery_v": bsd.battery_dv / 10.0, "device_timestamp_ms": float(bsd.timestamp_ms),
                       "left_pwm": float(bsd.left_pwm), "right_pwm": float(bsd.right_pwm),
                       "charger": float(bsd.charger), "buttons": float(bsd.buttons),
                       "left_ticks": float(bsd.left_encoder), "right_ticks": float(bsd.right_encoder)},
            )
            self._counts["feedback"] += 1

