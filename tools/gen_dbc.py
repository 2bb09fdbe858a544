"""Generate ``services/base_driver/odrive/odrive_cansimple.dbc``, the CANSimple messages the base driver uses.

The DBC is committed (cantools and any CAN tool read it); this script is how it
was made, so a new message or node is a one-line change here and a rerun, not
hand-edited DBC text. ``tests/test_base_driver_protocol.py`` checks the
committed file equals what this script produces.

Layout follows the ODrive CANSimple protocol (firmware 0.6, ODrive Pro/S1):
11-bit ids ``node_id << 5 | cmd_id``, little-endian signals, IEEE floats.

    python tools/gen_dbc.py            # rewrite the committed file
"""

from __future__ import annotations

import sys
from pathlib import Path

from cantools.database import Database
from cantools.database.can import Message, Signal
from cantools.database.conversion import BaseConversion

NODE_IDS = range(8)  # enough for two wheels plus spares; the driver checks its configured ids
OUT = Path(__file__).resolve().parent.parent / "services" / "base_driver" / "odrive" / "odrive_cansimple.dbc"

AXIS_STATES = {0: "UNDEFINED", 1: "IDLE", 2: "STARTUP_SEQUENCE", 3: "FULL_CALIBRATION_SEQUENCE",
               4: "MOTOR_CALIBRATION", 6: "ENCODER_INDEX_SEARCH", 7: "ENCODER_OFFSET_CALIBRATION",
               8: "CLOSED_LOOP_CONTROL", 9: "LOCKIN_SPIN", 10: "ENCODER_DIR_FIND", 11: "HOMING",
               12: "ENCODER_HALL_POLARITY_CALIBRATION", 13: "ENCODER_HALL_PHASE_CALIBRATION"}
CONTROL_MODES = {0: "VOLTAGE_CONTROL", 1: "TORQUE_CONTROL", 2: "VELOCITY_CONTROL", 3: "POSITION_CONTROL"}
INPUT_MODES = {0: "INACTIVE", 1: "PASSTHROUGH", 2: "VEL_RAMP", 3: "POS_FILTER", 4: "MIX_CHANNELS",
               5: "TRAP_TRAJ", 6: "TORQUE_RAMP", 7: "MIRROR", 8: "TUNING"}

# (name, start bit, length, kind, unit, choices); kind: u = unsigned int, f = float32
_Sig = tuple[str, int, int, str, str, dict[int, str] | None]
#: cmd_id -> (message name, DLC, signals)
MESSAGES: dict[int, tuple[str, int, list[_Sig]]] = {
    0x001: ("Heartbeat", 8, [("Axis_Error", 0, 32, "u", "", None),
                             ("Axis_State", 32, 8, "u", "", AXIS_STATES),
                             ("Procedure_Result", 40, 8, "u", "", None),
                             ("Trajectory_Done_Flag", 48, 1, "u", "", None)]),
    0x002: ("Estop", 0, []),
    0x003: ("Get_Error", 8, [("Active_Errors", 0, 32, "u", "", None),
                             ("Disarm_Reason", 32, 32, "u", "", None)]),
    0x007: ("Set_Axis_State", 4, [("Axis_Requested_State", 0, 32, "u", "", AXIS_STATES)]),
    0x009: ("Get_Encoder_Estimates", 8, [("Pos_Estimate", 0, 32, "f", "rev", None),
                                         ("Vel_Estimate", 32, 32, "f", "rev/s", None)]),
    0x00B: ("Set_Controller_Mode", 8, [("Control_Mode", 0, 32, "u", "", CONTROL_MODES),
                                       ("Input_Mode", 32, 32, "u", "", INPUT_MODES)]),
    0x00D: ("Set_Input_Vel", 8, [("Input_Vel", 0, 32, "f", "rev/s", None),
                                 ("Input_Torque_FF", 32, 32, "f", "Nm", None)]),
    0x00F: ("Set_Limits", 8, [("Velocity_Limit", 0, 32, "f", "rev/s", None),
                              ("Current_Limit", 32, 32, "f", "A", None)]),
    0x018: ("Clear_Errors", 1, [("Identify", 0, 8, "u", "", None)]),
}


def _signal(name: str, start: int, length: int, kind: str, unit: str,
            choices: dict[int, str] | None) -> Signal:
    is_float = kind == "f"
    conversion = BaseConversion.factory(scale=1, offset=0, choices=choices, is_float=is_float)
    return Signal(name=name, start=start, length=length, byte_order="little_endian",
                  is_signed=is_float, conversion=conversion, unit=unit or None)


def build() -> Database:
    messages = []
    for node in NODE_IDS:
        for cmd_id, (name, dlc, signals) in MESSAGES.items():
            messages.append(Message(frame_id=node << 5 | cmd_id, name=f"Axis{node}_{name}",
                                    length=dlc, signals=[_signal(*s) for s in signals],
                                    is_extended_frame=False))
    return Database(messages=messages)


def dbc_text() -> str:
    """The DBC file's text (cantools writes CRLF; the repository keeps LF)."""
    return build().as_dbc_string().replace("\r\n", "\n")


def main() -> int:
    OUT.write_text(dbc_text())
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
