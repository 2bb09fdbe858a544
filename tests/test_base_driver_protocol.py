"""CANSimple framing: known bytes, the committed DBC, decoding and what is refused."""

from __future__ import annotations

import importlib.util
import math
import struct
from pathlib import Path

import can
import pytest

from ovamos.services.base_driver.odrive.protocol import (
    DBC_PATH,
    AxisState,
    CanSimple,
    Cmd,
    ODriveError,
    ProtocolError,
    arbitration_id,
    error_names,
)

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def proto() -> CanSimple:
    return CanSimple([0, 1])


def test_set_input_vel_known_bytes(proto: CanSimple) -> None:
    msg = proto.encode(0, Cmd.SET_INPUT_VEL, Input_Vel=1.5, Input_Torque_FF=0.0)
    assert msg.arbitration_id == 0x00D and not msg.is_extended_id
    assert bytes(msg.data).hex() == "0000c03f00000000"
    # node 1 shifts the id by 5 bits; the payload is the same
    assert proto.encode(1, Cmd.SET_INPUT_VEL, Input_Vel=1.5, Input_Torque_FF=0.0).arbitration_id == 0x02D


def test_the_committed_dbc_is_what_the_generator_makes() -> None:
    spec = importlib.util.spec_from_file_location("gen_dbc", ROOT / "tools" / "gen_dbc.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert DBC_PATH.read_text() == gen.dbc_text()


@pytest.mark.parametrize("cmd", list(Cmd))
def test_every_command_is_in_the_dbc_for_both_nodes(proto: CanSimple, cmd: Cmd) -> None:
    for node in (0, 1):
        message = proto.db.get_message_by_frame_id(arbitration_id(node, cmd))
        assert message.name.startswith(f"Axis{node}_")


def test_decode_round_trip_and_little_endian_layout(proto: CanSimple) -> None:
    hb = proto.encode(1, Cmd.HEARTBEAT, Axis_Error=ODriveError.WATCHDOG_TIMER_EXPIRED,
                      Axis_State=AxisState.CLOSED_LOOP_CONTROL, Procedure_Result=0, Trajectory_Done_Flag=1)
    assert hb.arbitration_id == 0x021
    assert bytes(hb.data) == struct.pack("<IBBB", 0x1000000, 8, 0, 1) + b"\x00"
    frame = proto.decode(hb)
    assert (frame.node_id, frame.cmd) == (1, Cmd.HEARTBEAT)
    assert frame.signals["Axis_State"] == 8 and frame.signals["Axis_Error"] == 0x1000000
    enc = proto.decode(can.Message(arbitration_id=0x009, data=struct.pack("<ff", 2.5, -0.75),
                                   is_extended_id=False))
    assert enc.signals == {"Pos_Estimate": 2.5, "Vel_Estimate": -0.75}
    req = proto.decode(proto.request(0, Cmd.GET_ERROR))
    assert req.remote and req.cmd is Cmd.GET_ERROR


def test_error_bits_are_named_and_unknown_bits_kept() -> None:
    assert error_names(0) == []
    assert error_names(0x1000000 | 0x20) == ["DRV_FAULT", "WATCHDOG_TIMER_EXPIRED"]
    assert error_names(0x80) == ["0x80"]


@pytest.mark.parametrize(("frame", "kind"), [
    (can.Message(arbitration_id=0x001, data=b"\x00\x00", is_extended_id=False), "malformed"),
    (can.Message(arbitration_id=0x009, data=struct.pack("<ff", math.nan, 0.0), is_extended_id=False),
     "malformed"),
    (can.Message(arbitration_id=5 << 5 | 0x001, data=bytes(8), is_extended_id=False), "unexpected"),
    (can.Message(arbitration_id=0x01F, data=bytes(8), is_extended_id=False), "unexpected"),
    (can.Message(arbitration_id=0x001, data=bytes(8), is_extended_id=True), "unexpected"),
    (can.Message(arbitration_id=0, is_error_frame=True), "unexpected"),
])
def test_bad_frames_are_refused_with_their_kind(proto: CanSimple, frame: can.Message, kind: str) -> None:
    with pytest.raises(ProtocolError) as err:
        proto.decode(frame)
    assert err.value.kind == kind


def test_a_node_missing_from_the_dbc_fails_at_construction() -> None:
    with pytest.raises(ValueError, match="node 40"):
        CanSimple([0, 40])
