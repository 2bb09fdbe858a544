"""Dynamixel Protocol 2.0 packets, written from the public specification, for the simulated devices.

The robot-side client never uses this module: it talks through ROBOTIS' own
``dynamixel-sdk`` (PortHandler / PacketHandler 2.0), so what runs in tests is
what runs on a TurtleBot 3. This module is the *other* end of the wire: the
simulated OpenCR decodes instruction packets and encodes status packets with
it, independently of the SDK, so that a disagreement between the two shows up
as a failed CRC or a refused packet instead of two copies of one bug agreeing.

Layout (https://emanual.robotis.com/docs/en/dxl/protocol2/, "Instruction
Packet" / "Status Packet")::

    FF FF FD 00 | ID | LEN_L LEN_H | INST | params... | CRC_L CRC_H

``LEN`` counts the instruction, the parameters (after byte stuffing) and the
two CRC bytes; a status packet's first parameter is the error byte. The CRC is
CRC-16 with polynomial 0x8005, initial value 0, no reflection, over everything
from the first header byte to the last parameter (the e-manual's "CRC
Calculation" page, https://emanual.robotis.com/docs/en/dxl/crc/). Byte
stuffing: in the instruction+parameters, every ``FF FF FD`` gets an extra
``FD`` so that a header can never appear inside a packet ("Packet Process").
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["HEADER", "Inst", "Err", "Packet", "crc16", "encode", "instruction_packet",
           "status_packet", "Decoder"]

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
#: Longest LEN accepted: the OpenCR's packet buffer is far smaller; a larger
#: value is a corrupt length field, and waiting for that many bytes would stall
#: the decoder behind a packet that will never come.
MAX_LENGTH = 1024


class Inst:
    """Instruction codes (e-manual Protocol 2.0, "Instruction")."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    REBOOT = 0x08
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class Err:
    """Status packet error numbers (e-manual Protocol 2.0, "Error")."""

    NONE = 0x00
    RESULT_FAIL = 0x01
    INSTRUCTION = 0x02
    CRC = 0x03
    DATA_RANGE = 0x04
    DATA_LENGTH = 0x05
    DATA_LIMIT = 0x06
    ACCESS = 0x07


def _make_table() -> tuple[int, ...]:
    """The 256-entry table for polynomial 0x8005, MSB first (the e-manual's table, derived
    here from the polynomial rather than copied, so the two can check each other)."""
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_TABLE = _make_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """The Dynamixel 2.0 CRC-16 of ``data`` (continue from ``crc`` to chain blocks)."""
    for byte in data:
        crc = ((crc << 8) ^ _TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def _stuff(body: bytes) -> bytes:
    """Add byte stuffing to instruction+parameters: ``FF FF FD`` -> ``FF FF FD FD``.

    The two bytes before the instruction (LEN_H, ID) take part in the pattern
    as the SDK's ``addStuffing`` does, but LEN_H is at most 0x04 and the ID is
    never 0xFF, so only patterns inside the body can match."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-2] == 0xFF and out[-3] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def _unstuff(body: bytes) -> bytes:
    """Remove byte stuffing (``FF FF FD FD`` -> ``FF FF FD``)."""
    out = bytearray()
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        if (b == 0xFD and i + 1 < len(body) and body[i + 1] == 0xFD and len(out) >= 3
                and out[-2] == 0xFF and out[-3] == 0xFF):
            i += 1  # skip the stuffed 0xFD
        i += 1
    return bytes(out)


def encode(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One complete packet (header, id, length, instruction, stuffed params, CRC)."""
    body = _stuff(bytes([instruction]) + bytes(params))
    head = HEADER + bytes([packet_id & 0xFF]) + (len(body) + 2).to_bytes(2, "little")
    frame = head + body
    return frame + crc16(frame).to_bytes(2, "little")


def instruction_packet(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction packet (host -> device)."""
    return encode(packet_id, instruction, params)


def status_packet(packet_id: int, error: int = Err.NONE, params: bytes = b"") -> bytes:
    """A status packet (device -> host): instruction 0x55, then the error byte."""
    return encode(packet_id, Inst.STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """One decoded packet: ``params`` are unstuffed; for a status packet ``params[0]`` is the error."""

    id: int
    instruction: int
    params: bytes


class Decoder:
    """Turns a byte stream into packets, re-synchronising on the header after garbage.

    A serial line carries noise, half packets (the other end gave up or was
    unplugged mid-packet) and corrupted bytes; none of that may raise or
    desynchronise the stream for good. Bytes before a header are skipped and
    counted; a packet whose CRC does not match is dropped by skipping *one*
    byte and searching again (a corrupted length must not swallow the good
    packets behind it), and counted.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.skipped_bytes = 0   # bytes thrown away while looking for a header
        self.resyncs = 0         # times garbage was skipped to reach a header
        self.crc_errors = 0      # complete packets whose CRC did not match
        self.bad_lengths = 0     # headers followed by an impossible LEN
        self.packets = 0         # good packets decoded
        self.partial_dropped = 0  # partial packets discarded by drop_partial()

    def pending(self) -> int:
        """Bytes held, waiting for the rest of a packet."""
        return len(self._buf)

    def drop_partial(self) -> None:
        """Forget a partial packet (the line went quiet mid-packet: it will never complete)."""
        if self._buf:
            self.partial_dropped += 1
            self.skipped_bytes += len(self._buf)
            self._buf.clear()

    def _skip(self, n: int) -> None:
        del self._buf[:n]
        self.skipped_bytes += n

    def feed(self, data: bytes) -> list[Packet]:
        """Add received bytes; return every complete, valid packet now in the buffer."""
        self._buf.extend(data)
        out: list[Packet] = []
        while True:
            at = self._buf.find(HEADER)
            if at < 0:
                # keep a tail that may be the start of a header split across reads
                keep = 0
                for k in (3, 2, 1):
                    if len(self._buf) >= k and self._buf[-k:] == HEADER[:k]:
                        keep = k
                        break
                if len(self._buf) > keep:
                    self.resyncs += 1
                    self._skip(len(self._buf) - keep)
                return out
            if at > 0:
                self.resyncs += 1
                self._skip(at)
            if len(self._buf) < 7:
                return out
            length = int.from_bytes(self._buf[5:7], "little")
            if length < 3 or length > MAX_LENGTH:
                self.bad_lengths += 1
                self._skip(1)
                continue
            total = 7 + length
            if len(self._buf) < total:
                return out
            frame = bytes(self._buf[:total])
            if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
                self.crc_errors += 1
                self._skip(1)
                continue
            del self._buf[:total]
            self.packets += 1
            body = _unstuff(frame[7:-2])
            out.append(Packet(id=frame[4], instruction=body[0], params=body[1:]))
