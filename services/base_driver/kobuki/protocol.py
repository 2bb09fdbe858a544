"""The Kobuki (TurtleBot 2) serial protocol: packets, Base Control, Basic Sensor Data.

Everything here is pure bytes and numbers (no port, no thread), so the host's
:mod:`ovamos.services.base_driver.kobuki.client` and the simulated robot in
:mod:`ovamos.services.base_driver.kobuki.sim` share one codec and the tests can check
it byte for byte.

Sources (public; cited by the figures they give):

* [SPEC] Kobuki protocol specification, kobuki_driver's "Appendix: Protocol
  Specification" (yujinrobot/kobuki_core, ``kobuki_driver/doxygen/english/
  en_appendix_protocol.dox``; rendered at https://docs.ros.org/en/kinetic/api/
  kobuki_driver/html/enAppendixProtocolSpecification.html):
  - a packet is ``0xAA 0x55 | length | payload | checksum``; length counts the
    payload only; the checksum is the XOR of every byte except the two headers
    (length + payload); "minimum value of [length] is 3";
  - the payload is a run of sub-payloads ``id | length | data``;
  - numbers are little endian ("LSB-first order");
  - Base Control: command id 1, data length 4, speed (mm/s) then radius (mm);
    the conversion table: pure translation -> radius 0, speed = v;
    pure rotation -> radius 1, speed = w * b / 2; translation + rotation ->
    speed = v * (R + b/2) / R for R > 1, v * (R - b/2) / R for R < -1; b, the
    wheel base, "fixed at 230 mm"; positive radius = the arc's centre on the
    robot's left;
  - Basic Sensor Data: feedback id 1, length 15, sent at 50 Hz: timestamp (ms,
    uint16, wraps), bumper (0x01 right, 0x02 centre, 0x04 left), wheel drop
    (0x01 right, 0x02 left), cliff (0x01 right, 0x02 centre, 0x04 left), left and
    right encoder (uint16 ticks, wrap, increments = forward), left and right PWM
    (signed byte), buttons, charger, battery (0.1 V), over-current
    (0x01 left, 0x02 right).
* [DIFF] kobuki_driver's ``DiffDrive`` (kobuki-base/kobuki_core,
  ``src/driver/diff_drive.cpp``): ``bias(0.23)`` wheel base m,
  ``wheel_radius(0.035)`` m, ``tick_to_rad(0.002436916871363930187454)``
  (= 2 pi / 2578.33 ticks per wheel revolution); ``velocityCommands(vx, wz)``
  (the body velocity -> speed / radius rules used here, including "radius less
  than or equal to 1.0 mm is a pure rotation"), ``bound()`` (clamp to int16,
  truncate toward zero), and ``update()`` (encoder differences taken as
  ``(short)((curr - last) & 0xffff)``: the wrap is undone by reading the 16-bit
  difference as signed).
* [CORE] ``CoreSensors::deserialise`` (kobuki-base/kobuki_core,
  ``src/driver/core_sensors.cpp``): a Basic Sensor Data sub-payload whose length
  is not exactly 15 is refused.
* [FINDER] ``Kobuki::init`` (kobuki-base/kobuki_core, ``src/driver/kobuki.cpp``):
  115200 baud 8N1; the packet finder is configured with a 1-byte length field,
  at most 256 payload bytes and a 1-byte checksum.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

__all__ = [
    "HEADER", "BASE_CONTROL_ID", "BASIC_SENSOR_DATA_ID", "BASIC_SENSOR_DATA_LEN", "MIN_PAYLOAD_LEN",
    "WHEEL_BASE_M", "WHEEL_RADIUS_M", "TICK_TO_RAD", "TICKS_PER_REV", "BAUDRATE",
    "ProtocolError", "checksum", "encode_packet", "encode_sub_payload", "split_sub_payloads",
    "encode_base_control", "decode_base_control", "body_to_speed_radius", "speed_radius_to_wheels",
    "BasicSensorData", "BUMPER_BITS", "WHEEL_DROP_BITS", "CLIFF_BITS", "OVERCURRENT_BITS",
    "names_from_bits", "bits_from_names", "PacketDecoder", "TickUnwrapper", "wrap_diff16",
]

HEADER = b"\xaa\x55"                 # [SPEC] header 0, header 1
BASE_CONTROL_ID = 1                  # [SPEC] command identifier 1
BASIC_SENSOR_DATA_ID = 1             # [SPEC] feedback identifier 1
BASIC_SENSOR_DATA_LEN = 15           # [SPEC] / [CORE]
MIN_PAYLOAD_LEN = 3                  # [SPEC] "minimum value of this field is 3"
BAUDRATE = 115200                    # [FINDER]
WHEEL_BASE_M = 0.230                 # [SPEC] b "fixed at 230 mm"; [DIFF] bias(0.23)
WHEEL_RADIUS_M = 0.035               # [DIFF] wheel_radius(0.035)
TICK_TO_RAD = 0.002436916871363930187454  # [DIFF] tick_to_rad
TICKS_PER_REV = 2.0 * math.pi / TICK_TO_RAD  # = 2578.33 ticks per wheel revolution

_INT16_MIN, _INT16_MAX = -32768, 32767
_BSD = struct.Struct("<HBBBHHbbBBBB")  # [SPEC] Basic Sensor Data field order and sizes (15 bytes)
assert _BSD.size == BASIC_SENSOR_DATA_LEN

# Bit -> name, per [SPEC]'s Basic Sensor Data table. Names as WheelFeedback uses them.
BUMPER_BITS: dict[int, str] = {0x01: "right", 0x02: "centre", 0x04: "left"}
WHEEL_DROP_BITS: dict[int, str] = {0x01: "right", 0x02: "left"}
CLIFF_BITS: dict[int, str] = {0x01: "right", 0x02: "centre", 0x04: "left"}
OVERCURRENT_BITS: dict[int, str] = {0x01: "left", 0x02: "right"}


class ProtocolError(ValueError):
    """Bytes that do not form what the specification says they should."""


def checksum(length_and_payload: bytes) -> int:
    """XOR of the length byte and the payload ([SPEC]: every byte except the headers)."""
    cs = 0
    for b in length_and_payload:
        cs ^= b
    return cs


def encode_sub_payload(sub_id: int, data: bytes) -> bytes:
    """One sub-payload: ``id | len(data) | data``."""
    if not 0 <= sub_id <= 255 or len(data) > 255:
        raise ProtocolError(f"sub-payload id {sub_id} / length {len(data)} out of range")
    return bytes((sub_id, len(data))) + data


def encode_packet(payload: bytes) -> bytes:
    """Frame a payload (one or more sub-payloads) as ``AA 55 len payload checksum``."""
    if not MIN_PAYLOAD_LEN <= len(payload) <= 255:
        raise ProtocolError(f"payload length {len(payload)} outside {MIN_PAYLOAD_LEN}..255")
    body = bytes((len(payload),)) + payload
    return HEADER + body + bytes((checksum(body),))


def split_sub_payloads(payload: bytes) -> list[tuple[int, bytes]]:
    """Split a payload into ``(id, data)``; the lengths must tile the payload exactly.

    Checking the tiling as well as the checksum matters because a 1-byte XOR
    passes one random byte string in 256: a "packet" that starts inside noise or
    a truncated packet must not reach the parsers.
    """
    out: list[tuple[int, bytes]] = []
    i = 0
    while i < len(payload):
        if i + 2 > len(payload):
            raise ProtocolError("sub-payload header cut short")
        sub_id, n = payload[i], payload[i + 1]
        if i + 2 + n > len(payload):
            raise ProtocolError(f"sub-payload {sub_id} claims {n} bytes, {len(payload) - i - 2} left")
        out.append((sub_id, payload[i + 2:i + 2 + n]))
        i += 2 + n
    return out


def _bound16(value: float) -> int:
    """[DIFF] ``bound()``: clamp to int16, then truncate toward zero (``static_cast<short>``)."""
    if value > _INT16_MAX:
        return _INT16_MAX
    if value < _INT16_MIN:
        return _INT16_MIN
    return int(value)


def encode_base_control(speed_mm_s: int, radius_mm: int) -> bytes:
    """A whole packet with one Base Control sub-payload ([SPEC]: id 1, length 4, int16 LE x2)."""
    data = struct.pack("<hh", _bound16(speed_mm_s), _bound16(radius_mm))
    return encode_packet(encode_sub_payload(BASE_CONTROL_ID, data))


def decode_base_control(data: bytes) -> tuple[int, int]:
    """Base Control data (4 bytes) -> (speed mm/s, radius mm)."""
    if len(data) != 4:
        raise ProtocolError(f"Base Control data is 4 bytes, got {len(data)}")
    speed, radius = struct.unpack("<hh", data)
    return speed, radius


def body_to_speed_radius(linear_m_s: float, angular_rad_s: float,
                         wheel_base_m: float = WHEEL_BASE_M) -> tuple[int, int]:
    """Body velocity -> Base Control (speed mm/s, radius mm), as kobuki_driver does it.

    The Kobuki does not take (v, w): it takes an arc. [DIFF] ``velocityCommands``:
    |w| < 1e-4 is straight (radius 0, speed = v); |v| < 1e-4 or an arc of radius
    <= 1 mm is a pure rotation (radius 1, speed = w b / 2, i.e. the right wheel's
    speed, signed: positive turns left); otherwise radius = v / w and speed is the
    *outer* wheel's speed, (R +- b/2) w, per [SPEC]'s conversion table.
    """
    eps = 0.0001
    if abs(angular_rad_s) < eps:
        return _bound16(1000.0 * linear_m_s), 0
    radius = linear_m_s * 1000.0 / angular_rad_s
    half_b_mm = 1000.0 * wheel_base_m / 2.0
    if abs(linear_m_s) < eps or abs(radius) <= 1.0:
        return _bound16(half_b_mm * angular_rad_s), 1
    if radius > 0.0:
        speed = (radius + half_b_mm) * angular_rad_s
    else:
        speed = (radius - half_b_mm) * angular_rad_s
    return _bound16(speed), _bound16(radius)


def speed_radius_to_wheels(speed_mm_s: float, radius_mm: float,
                           wheel_base_m: float = WHEEL_BASE_M) -> tuple[float, float]:
    """Base Control -> (left, right) wheel surface speeds in m/s: what the firmware does.

    The inverse of :func:`body_to_speed_radius` per [SPEC]'s conversion table:
    radius 0 -> both wheels at speed; radius +-1 -> pure rotation, the right wheel
    at +-speed and the left at -+speed; otherwise ``speed`` is the outer wheel, so
    w = speed / (R +- b/2) and each wheel runs at w (R -+ b/2).
    """
    v = speed_mm_s / 1000.0
    half_b = wheel_base_m / 2.0
    if radius_mm == 0:
        return v, v
    if radius_mm in (1, -1):
        return -radius_mm * v, radius_mm * v
    r = radius_mm / 1000.0
    w = v / (r + half_b) if r > 0 else v / (r - half_b)
    return w * (r - half_b), w * (r + half_b)


def names_from_bits(bits: int, table: dict[int, str]) -> tuple[str, ...]:
    """The names of the set bits, in the table's order."""
    return tuple(name for bit, name in table.items() if bits & bit)


def bits_from_names(names: tuple[str, ...] | list[str] | set[str], table: dict[int, str]) -> int:
    """The inverse of :func:`names_from_bits` (for the simulator); unknown names are errors."""
    by_name = {name: bit for bit, name in table.items()}
    bits = 0
    for name in names:
        if name not in by_name:
            raise ValueError(f"unknown sensor {name!r}: one of {sorted(by_name)}")
        bits |= by_name[name]
    return bits


@dataclass(frozen=True)
class BasicSensorData:
    """Basic Sensor Data, field for field as [SPEC] lists them (raw device units)."""

    timestamp_ms: int = 0      # uint16, wraps
    bumper: int = 0
    wheel_drop: int = 0
    cliff: int = 0
    left_encoder: int = 0      # uint16 ticks, wraps
    right_encoder: int = 0
    left_pwm: int = 0          # signed: negative = backward
    right_pwm: int = 0
    buttons: int = 0
    charger: int = 0
    battery_dv: int = 0        # 0.1 V
    overcurrent: int = 0

    @classmethod
    def parse(cls, data: bytes) -> "BasicSensorData":
        """Parse the 15 data bytes of sub-payload 1 ([CORE] refuses any other length)."""
        if len(data) != BASIC_SENSOR_DATA_LEN:
            raise ProtocolError(f"Basic Sensor Data is {BASIC_SENSOR_DATA_LEN} bytes, got {len(data)}")
        return cls(*_BSD.unpack(data))

    def encode(self) -> bytes:
        """The whole sub-payload (id, length, data): what the firmware (the simulator) sends."""
        data = _BSD.pack(self.timestamp_ms & 0xFFFF, self.bumper, self.wheel_drop, self.cliff,
                         self.left_encoder & 0xFFFF, self.right_encoder & 0xFFFF,
                         max(-128, min(127, self.left_pwm)), max(-128, min(127, self.right_pwm)),
                         self.buttons, self.charger, self.battery_dv, self.overcurrent)
        return encode_sub_payload(BASIC_SENSOR_DATA_ID, data)


def wrap_diff16(current: int, last: int) -> int:
    """[DIFF] ``(short)((curr - last) & 0xffff)``: the change of a wrapping uint16 counter."""
    d = (current - last) & 0xFFFF
    return d - 0x10000 if d >= 0x8000 else d


class TickUnwrapper:
    """Turns a wrapping uint16 encoder into a cumulative count, starting at 0.

    Correct as long as a wheel turns less than 32768 ticks (12.7 revolutions,
    2.8 m) between two readings: at 50 Hz that is 140 m/s.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self.total = 0

    def update(self, raw: int) -> int:
        """Feed a raw reading; returns the cumulative ticks since the first one."""
        if self._last is not None:
            self.total += wrap_diff16(raw, self._last)
        self._last = raw & 0xFFFF
        return self.total


class PacketDecoder:
    """A streaming packet finder: feed it bytes in any chunks, get whole verified payloads.

    Garbage (noise, a packet cut short, a bad checksum) must never stop the
    stream, and must not hide the good packets around it. A candidate packet
    that fails (length below the minimum, checksum, sub-payload tiling) is
    dropped by discarding only its first header byte and searching again from
    the next byte, so a real header inside the rejected bytes (the packet after
    a truncated one) is still found. Counters say what was skipped:

    * ``packets``: payloads returned;
    * ``malformed``: candidates rejected after a header was found;
    * ``resyncs``: times the stream was out of step (bytes skipped before a header);
    * ``bytes_skipped``: bytes thrown away, header bytes of rejected candidates included.
    """

    def __init__(self, max_payload: int = 255) -> None:
        self._buf = bytearray()
        self.max_payload = max_payload
        self.packets = 0
        self.malformed = 0
        self.resyncs = 0
        self.bytes_skipped = 0

    def counters(self) -> dict[str, int]:
        """A snapshot of the counters."""
        return {"packets": self.packets, "malformed": self.malformed, "resyncs": self.resyncs,
                "bytes_skipped": self.bytes_skipped}

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self.bytes_skipped += n

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the payloads of every complete, valid packet now in the buffer."""
        self._buf += data
        out: list[bytes] = []
        while True:
            start = self._buf.find(HEADER)
            if start < 0:
                # Keep a trailing 0xAA: it may be the first half of a header.
                keep = 1 if self._buf[-1:] == HEADER[:1] else 0
                n = len(self._buf) - keep
                if n > 0:
                    self.resyncs += 1
                    self._skip(n)
                return out
            if start > 0:
                self.resyncs += 1
                self._skip(start)
            if len(self._buf) < 3:
                return out
            length = self._buf[2]
            if length < MIN_PAYLOAD_LEN or length > self.max_payload:
                self.malformed += 1
                self._skip(1)
                continue
            total = 2 + 1 + length + 1
            if len(self._buf) < total:
                return out  # wait for the rest
            body = bytes(self._buf[2:2 + 1 + length])
            if checksum(body) != self._buf[total - 1]:
                self.malformed += 1
                self._skip(1)
                continue
            payload = body[1:]
            try:
                split_sub_payloads(payload)
            except ProtocolError:
                self.malformed += 1
                self._skip(1)
                continue
            del self._buf[:total]
            self.packets += 1
            out.append(payload)
