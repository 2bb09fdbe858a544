"""ODrive CANSimple frames, encoded and decoded through the committed DBC with cantools.

Arbitration ids are 11 bits, ``node_id << 5 | cmd_id``; the DBC names each
message ``Axis<node>_<Command>``, so one lookup by frame id gives both the node
and the command. Everything that is not a well-formed frame of a configured
node raises :class:`ProtocolError`, telling malformed frames (bad length,
non-finite float) from unexpected ones (unknown id, remote/extended/error
frames the driver never asked for) so the driver can count them apart.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from pathlib import Path
from typing import Any, Literal

import can
import cantools

DBC_PATH = Path(__file__).with_name("odrive_cansimple.dbc")
CMD_BITS = 5
CMD_MASK = (1 << CMD_BITS) - 1


class Cmd(IntEnum):
    """CANSimple command ids used here (the low 5 bits of the arbitration id)."""

    HEARTBEAT = 0x001
    ESTOP = 0x002
    GET_ERROR = 0x003
    SET_AXIS_STATE = 0x007
    GET_ENCODER_ESTIMATES = 0x009
    SET_CONTROLLER_MODE = 0x00B
    SET_INPUT_VEL = 0x00D
    SET_LIMITS = 0x00F
    CLEAR_ERRORS = 0x018


# Command id -> the DBC's message name suffix.
_NAMES = {Cmd.HEARTBEAT: "Heartbeat", Cmd.ESTOP: "Estop", Cmd.GET_ERROR: "Get_Error",
          Cmd.SET_AXIS_STATE: "Set_Axis_State", Cmd.GET_ENCODER_ESTIMATES: "Get_Encoder_Estimates",
          Cmd.SET_CONTROLLER_MODE: "Set_Controller_Mode", Cmd.SET_INPUT_VEL: "Set_Input_Vel",
          Cmd.SET_LIMITS: "Set_Limits", Cmd.CLEAR_ERRORS: "Clear_Errors"}


class AxisState(IntEnum):
    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8


class ControlMode(IntEnum):
    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(IntEnum):
    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2


class ODriveError(IntFlag):
    """ODrive (firmware 0.6) axis error bits, as the heartbeat and Get_Error report them."""

    INITIALIZING = 0x1
    SYSTEM_LEVEL = 0x2
    TIMING_ERROR = 0x4
    MISSING_ESTIMATE = 0x8
    BAD_CONFIG = 0x10
    DRV_FAULT = 0x20
    MISSING_INPUT = 0x40
    DC_BUS_OVER_VOLTAGE = 0x100
    DC_BUS_UNDER_VOLTAGE = 0x200
    DC_BUS_OVER_CURRENT = 0x400
    DC_BUS_OVER_REGEN_CURRENT = 0x800
    CURRENT_LIMIT_VIOLATION = 0x1000
    MOTOR_OVER_TEMP = 0x2000
    INVERTER_OVER_TEMP = 0x4000
    VELOCITY_LIMIT_VIOLATION = 0x8000
    POSITION_LIMIT_VIOLATION = 0x10000
    WATCHDOG_TIMER_EXPIRED = 0x1000000
    ESTOP_REQUESTED = 0x2000000
    SPINOUT_DETECTED = 0x4000000
    BRAKE_RESISTOR_DISARMED = 0x8000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


def error_names(bits: int) -> list[str]:
    """The names of the set error bits; unknown bits appear as hex so nothing is hidden."""
    names = [e.name for e in ODriveError if e.name and bits & e.value]
    unknown = bits & ~sum(e.value for e in ODriveError)
    if unknown:
        names.append(f"0x{unknown:x}")
    return names


class ProtocolError(ValueError):
    """A frame the driver cannot use; ``kind`` says whether it was malformed or unexpected."""

    def __init__(self, kind: Literal["malformed", "unexpected"], message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class Frame:
    """A decoded CANSimple frame."""

    node_id: int
    cmd: Cmd
    signals: dict[str, Any]
    remote: bool = False


def arbitration_id(node_id: int, cmd: Cmd) -> int:
    return node_id << CMD_BITS | int(cmd)


class CanSimple:
    """Encoder/decoder for the given node ids (each must be in the DBC)."""

    def __init__(self, node_ids: Iterable[int], dbc_path: Path = DBC_PATH) -> None:
        self.db = cantools.database.load_file(str(dbc_path))
        self.node_ids = frozenset(node_ids)
        for node in self.node_ids:
            for cmd in Cmd:
                self._message(node, cmd)  # fails early for a node the DBC lacks

    def _message(self, node_id: int, cmd: Cmd) -> Any:
        try:
            return self.db.get_message_by_frame_id(arbitration_id(node_id, cmd))
        except KeyError:
            raise ValueError(f"{DBC_PATH.name} has no {_NAMES[cmd]} for node {node_id} "
                             f"(regenerate it with tools/gen_dbc.py)") from None

    def encode(self, node_id: int, cmd: Cmd, **signals: float) -> can.Message:
        """A data frame for ``cmd`` to ``node_id``; missing signals are an error (cantools)."""
        msg = self._message(node_id, cmd)
        return can.Message(arbitration_id=msg.frame_id, data=msg.encode(signals),
                           is_extended_id=False)

    def request(self, node_id: int, cmd: Cmd) -> can.Message:
        """A remote (RTR) frame asking ``node_id`` for ``cmd`` (Get_Error, Get_Encoder_Estimates)."""
        msg = self._message(node_id, cmd)
        return can.Message(arbitration_id=msg.frame_id, is_remote_frame=True, dlc=msg.length,
                           is_extended_id=False)

    def decode(self, frame: can.Message) -> Frame:
        """The frame's node, command and signal values; raises :class:`ProtocolError`."""
        if frame.is_error_frame:
            raise ProtocolError("unexpected", "CAN error frame")
        if frame.is_extended_id:
            raise ProtocolError("unexpected", f"extended id 0x{frame.arbitration_id:x}")
        node_id, cmd_id = frame.arbitration_id >> CMD_BITS, frame.arbitration_id & CMD_MASK
        if node_id not in self.node_ids or cmd_id not in Cmd._value2member_map_:
            raise ProtocolError("unexpected", f"id 0x{frame.arbitration_id:03x} (node {node_id}, "
                                              f"cmd 0x{cmd_id:02x}) is not for this driver")
        cmd = Cmd(cmd_id)
        if frame.is_remote_frame:
            return Frame(node_id, cmd, {}, remote=True)
        msg = self._message(node_id, cmd)
        if len(frame.data) != msg.length:
            raise ProtocolError("malformed", f"{msg.name}: {len(frame.data)} data bytes, "
                                             f"expected {msg.length}")
        try:
            signals = msg.decode(bytes(frame.data), decode_choices=False, scaling=True)
        except (cantools.database.DecodeError, ValueError) as exc:
            raise ProtocolError("malformed", f"{msg.name}: {exc}") from None
        if any(isinstance(v, float) and not math.isfinite(v) for v in signals.values()):
            raise ProtocolError("malformed", f"{msg.name}: non-finite value in {signals}")
        return Frame(node_id, cmd, signals)
