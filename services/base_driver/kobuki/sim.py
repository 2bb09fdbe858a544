"""A simulated Kobuki on a pseudo-terminal pair, speaking the protocol byte for byte.

The host's :class:`ovamos.services.base_driver.kobuki.KobukiHardware` opens the pty's
slave path with real pyserial, exactly as it opens ``/dev/kobuki`` on a robot;
this object plays the firmware on the master side: it reads Base Control
packets (through the same streaming decoder, so it survives garbage too),
turns (speed, radius) into two wheel speeds by the specification's conversion
table, integrates the wheels, and every 20 ms (the Kobuki's 50 Hz) sends a
packet with Basic Sensor Data (wrapping uint16 timestamp and encoder ticks,
bumper / wheel drop / cliff / over-current bits) followed by a Docking IR
sub-payload, as the real base sends several sub-payloads per packet.

Faults can be injected: bumpers, wheel drops, cliffs, over-current; stale
feedback (stop sending); noise bytes, a bad checksum, a partial packet on the
line; and unplugging (closing the pty, after which the slave path is gone).
``left_travel_m`` / ``right_travel_m`` are the true wheel travel for tests.

A ``physics`` hook, called after every step with ``(dt_s, left_m, right_m)``
wheel travel, lets a simulated robot move with the wheels; returning False
(the robot is blocked) undoes the step, as a stalled motor would.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import tty
from collections.abc import Callable

from ovamos.services.base_driver.kobuki.protocol import (
    BASE_CONTROL_ID,
    BUMPER_BITS,
    CLIFF_BITS,
    OVERCURRENT_BITS,
    TICK_TO_RAD,
    WHEEL_BASE_M,
    WHEEL_DROP_BITS,
    WHEEL_RADIUS_M,
    BasicSensorData,
    PacketDecoder,
    ProtocolError,
    bits_from_names,
    decode_base_control,
    encode_packet,
    encode_sub_payload,
    speed_radius_to_wheels,
    split_sub_payloads,
)
from ovamos.shared.simtime import MemoryLine

__all__ = ["SimKobuki", "Physics"]

log = logging.getLogger("ovamos.kobuki_sim")

#: physics(dt_s, left wheel travel m, right wheel travel m) -> False when the robot is blocked
Physics = Callable[[float, float, float], bool]

_DOCK_IR_ID = 3  # [SPEC] feedback id 3, Docking IR, 3 data bytes (sent by default)


class SimKobuki:
    """The firmware side of a Kobuki on a pty. Use as a context manager or start() / close()."""

    def __init__(self, *, period_s: float = 0.02, wheel_radius_m: float = WHEEL_RADIUS_M,
                 wheel_base_m: float = WHEEL_BASE_M, start_ticks: tuple[int, int] = (0, 0),
                 start_timestamp_ms: int = 0, battery_v: float = 16.5,
                 physics: Physics | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = period_s
        self._clock = clock
        self.wheel_radius_m = wheel_radius_m
        self.wheel_base_m = wheel_base_m
        self.physics = physics
        self._start_ticks = start_ticks
        self._timestamp_ms = start_timestamp_ms & 0xFFFF
        self._clock_ms = float(start_timestamp_ms)  # the firmware's millisecond clock, before the wrap
        self._last_step = clock()
        self._battery_dv = int(round(battery_v * 10))
        self._lock = threading.Lock()
        self._decoder = PacketDecoder()
        self._left_m = 0.0
        self._right_m = 0.0
        self._wheel_speeds = (0.0, 0.0)
        self.last_command: tuple[int, int] | None = None  # (speed mm/s, radius mm) as received
        self.commands_received = 0
        self.packets_sent = 0
        self._bumper = self._wheel_drop = self._cliff = self._overcurrent = 0
        self._sending = True
        self._pending_garbage: list[bytes] = []
        self._corrupt_next = 0
        self._master: int | None = None
        self._slave: int | None = None
        self.port = ""
        self._line: MemoryLine | None = None  # in simulated time, the line in place of the pty
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> "SimKobuki":
        """Open the pty pair (raw, so the line discipline neither echoes nor translates) and run."""
        master, slave = os.openpty()
        tty.setraw(slave)  # before any byte flows: an echoing pty would loop feedback back as commands
        os.set_blocking(master, False)  # a full pty buffer (nobody reading) must not hang the firmware loop
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-kobuki", daemon=True)
        self._thread.start()
        return self

    def memory_line(self) -> MemoryLine:
        """The serial line for simulated time, in place of :meth:`start`'s pty: the benchmark runs
        :meth:`firmware_tick` every ``period_s`` itself."""
        self._line = MemoryLine(self._receive, name="simtime:kobuki")
        self.port = self._line.name
        return self._line

    def close(self) -> None:
        """Stop and close both ends (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self._close_fds()

    def __enter__(self) -> "SimKobuki":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_fds(self) -> None:
        with self._lock:
            fds, self._master, self._slave = (self._master, self._slave), None, None
        for fd in fds:
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # -- truth -------------------------------------------------------------------------

    @property
    def left_travel_m(self) -> float:
        """True distance the left wheel's surface has rolled (forward positive)."""
        with self._lock:
            return self._left_m

    @property
    def right_travel_m(self) -> float:
        with self._lock:
            return self._right_m

    @property
    def wheel_speeds_m_s(self) -> tuple[float, float]:
        """(left, right) as the firmware runs them now."""
        with self._lock:
            return self._wheel_speeds

    def counters(self) -> dict[str, int]:
        """The simulated firmware's own decoder counters, plus commands and packets."""
        with self._lock:
            return {**self._decoder.counters(), "commands": self.commands_received, "sent": self.packets_sent}

    # -- fault injection ---------------------------------------------------------------

    def press_bumper(self, *names: str) -> None:
        """Hold these bumpers ("left", "centre", "right") pressed; none releases them all."""
        with self._lock:
            self._bumper = bits_from_names(names, BUMPER_BITS)

    def lift_wheel(self, *names: str) -> None:
        """Wheels ("left", "right") off the ground; none puts them back."""
        with self._lock:
            self._wheel_drop = bits_from_names(names, WHEEL_DROP_BITS)

    def set_cliff(self, *names: str) -> None:
        """Cliff sensors ("left", "centre", "right") seeing a drop; none clears them."""
        with self._lock:
            self._cliff = bits_from_names(names, CLIFF_BITS)

    def set_overcurrent(self, *names: str) -> None:
        """Over-current flags on these wheels ("left", "right")."""
        with self._lock:
            self._overcurrent = bits_from_names(names, OVERCURRENT_BITS)

    def stop_sending(self) -> None:
        """Stale feedback: the wheels keep running, the feedback stops."""
        with self._lock:
            self._sending = False

    def resume_sending(self) -> None:
        with self._lock:
            self._sending = True

    def send_noise(self, data: bytes | None = None, n: int = 32) -> None:
        """Put garbage on the line before the next packet (random bytes unless given)."""
        with self._lock:
            self._pending_garbage.append(data if data is not None else os.urandom(n))

    def send_bad_checksum(self, count: int = 1) -> None:
        """The next ``count`` packets go out with their checksum byte flipped."""
        with self._lock:
            self._corrupt_next += count

    def send_partial_packet(self) -> None:
        """Put the first half of a valid packet on the line, then carry on with whole ones."""
        packet = self._feedback_packet(self._snapshot_sensors())
        with self._lock:
            self._pending_garbage.append(packet[: len(packet) // 2])

    def unplug(self) -> None:
        """Pull the cable: stop and close the pty; the host's port and its path are gone."""
        self.close()

    # -- the firmware loop -------------------------------------------------------------

    def _snapshot_sensors(self) -> BasicSensorData:
        with self._lock:
            lt = self._start_ticks[0] + round(self._left_m / (self.wheel_radius_m * TICK_TO_RAD))
            rt = self._start_ticks[1] + round(self._right_m / (self.wheel_radius_m * TICK_TO_RAD))
            vl, vr = self._wheel_speeds
            return BasicSensorData(
                timestamp_ms=self._timestamp_ms, bumper=self._bumper, wheel_drop=self._wheel_drop,
                cliff=self._cliff, left_encoder=lt & 0xFFFF, right_encoder=rt & 0xFFFF,
                left_pwm=int(max(-100, min(100, vl * 200))), right_pwm=int(max(-100, min(100, vr * 200))),
                battery_dv=self._battery_dv, overcurrent=self._overcurrent)

    @staticmethod
    def _feedback_packet(bsd: BasicSensorData) -> bytes:
        return encode_packet(bsd.encode() + encode_sub_payload(_DOCK_IR_ID, b"\x00\x00\x00"))

    def firmware_tick(self) -> None:
        """One period of the firmware: the wheels up to now, then Basic Sensor Data."""
        self._advance(self._clock())
        self._send_feedback()

    def _run(self) -> None:
        next_tick = self._clock() + self.period_s
        self._last_step = self._clock()
        while not self._stop.is_set():
            master = self._master
            if master is None:
                return
            timeout = max(0.0, next_tick - self._clock())
            try:
                ready, _, _ = select.select([master], [], [], timeout)
                if ready:
                    self._receive(os.read(master, 512))
            except OSError:
                # EIO: no process has the slave open right now (the host closed it). Not fatal.
                time.sleep(min(timeout, self.period_s) or 0.001)
            now = self._clock()
            if now < next_tick:
                continue
            self.firmware_tick()
            next_tick += self.period_s
            if next_tick < now:  # starved of CPU: do not burst to catch up
                next_tick = now + self.period_s

    def _receive(self, data: bytes) -> None:
        with self._lock:
            payloads = self._decoder.feed(data)
        for payload in payloads:
            try:
                subs = split_sub_payloads(payload)
            except ProtocolError:
                continue
            for sub_id, sub in subs:
                if sub_id != BASE_CONTROL_ID or len(sub) != 4:
                    continue  # sound, LEDs, gains, ...: not simulated
                speed, radius = decode_base_control(sub)
                wheels = speed_radius_to_wheels(speed, radius, self.wheel_base_m)
                self._advance(self._clock())  # the old speeds up to now, the new ones from now
                with self._lock:
                    self.last_command = (speed, radius)
                    self.commands_received += 1
                    self._wheel_speeds = wheels

    def _advance(self, now: float) -> None:
        """Integrate the wheels up to ``now`` (so a command's time of arrival is exact)."""
        dt = now - self._last_step
        if dt <= 0:
            return
        self._last_step = now
        with self._lock:
            vl, vr = self._wheel_speeds
            dl, dr = vl * dt, vr * dt
            self._clock_ms += dt * 1000.0
            self._timestamp_ms = int(self._clock_ms) & 0xFFFF
        if self.physics is not None and (dl or dr) and not self.physics(dt, dl, dr):
            return  # blocked: the wheels stall
        with self._lock:
            self._left_m += dl
            self._right_m += dr

    def _send_feedback(self) -> None:
        with self._lock:
            sending, garbage, self._pending_garbage = self._sending, self._pending_garbage, []
            corrupt = self._corrupt_next > 0
            if sending and corrupt:
                self._corrupt_next -= 1
        if not sending:
            return
        packet = bytearray(self._feedback_packet(self._snapshot_sensors()))
        if corrupt:
            packet[-1] ^= 0xFF
        self._write(b"".join(garbage) + bytes(packet))
        with self._lock:
            self.packets_sent += 1

    def _write(self, data: bytes) -> None:
        if self._line is not None:
            self._line.put(data)
            return
        master = self._master
        if master is None:
            return
        try:
            os.write(master, data)
        except OSError as exc:  # the pty buffer is full with nobody reading: drop, as a UART would
            log.debug("sim kobuki write: %s", exc)

