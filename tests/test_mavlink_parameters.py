"""PX4's parameter protocol: the bytewise encoding, the mock PX4 answering as
mavlink_parameters.cpp does (over pymavlink), and the companion reading named parameters
through its Autopilot (lockstep, real loopback UDP)."""

import asyncio
import math
import struct

import pytest

from drivers.clock import SimClock
from drivers.mavlink import px4_protocol
from drivers.mavlink.link import mavlink, open_link
from drivers.mavlink.parameters import (ParameterReader, check_name, decode_value,
                                        encode_value)
from drivers.sim.mock_px4 import PARAMETER_NAMES, MockPx4, Px4Options, default_parameters
from drivers.sim.quadrotor import Quadrotor
from tests.test_autopilot import fly
from tests.test_mock_px4 import Bench

INT32, REAL32 = mavlink.MAV_PARAM_TYPE_INT32, mavlink.MAV_PARAM_TYPE_REAL32


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def param_values(messages):
    return [m for m in messages if m.get_type() == "PARAM_VALUE"]


def read(bench, name="", index=-1, target_system=1):
    bench.client.mav.param_request_read_send(target_system, 1, name.encode(), index)
    return param_values(bench.run(0.02))


def set_param(bench, name, value, param_type):
    bench.client.mav.param_set_send(1, 1, name.encode(), encode_value(value, param_type),
                                    param_type)
    return param_values(bench.run(0.02))


# -------------------------------------------------------------------- the encoding

def test_an_int32_travels_as_its_bytes_not_as_a_converted_float():
    wire = encode_value(3, INT32)
    assert wire == struct.unpack("<f", struct.pack("<i", 3))[0] and wire != 3.0
    assert decode_value(wire, INT32) == 3 and isinstance(decode_value(wire, INT32), int)
    assert decode_value(encode_value(0.5, REAL32), REAL32) == 0.5
    assert decode_value(encode_value(200, mavlink.MAV_PARAM_TYPE_UINT8),
                        mavlink.MAV_PARAM_TYPE_UINT8) == 200


def test_negative_ints_survive_pymavlinks_float_round_trip():
    """-1 is a NaN bit pattern as a float: it must come out of PARAM_VALUE as -1."""
    sender, receiver = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 255, 190)
    message = sender.param_value_encode(b"COM_OBL_RC_ACT", encode_value(-1, INT32), INT32, 1, 0)
    decoded = receiver.parse_char(message.pack(sender))
    assert math.isnan(decoded.param_value) and decode_value(decoded.param_value, INT32) == -1


@pytest.mark.parametrize("value, param_type", [(1.5, INT32), (2**31, INT32), (True, INT32),
                                               (1, mavlink.MAV_PARAM_TYPE_REAL64)])
def test_values_a_type_cannot_carry_are_refused(value, param_type):
    with pytest.raises(ValueError, match="MAV_PARAM_TYPE"):
        encode_value(value, param_type)


@pytest.mark.parametrize("name", ["", "X" * 17, "EKF2_\u00e9", "A\nB", 3])
def test_names_that_cannot_be_a_param_id_are_refused(name):
    with pytest.raises(ValueError, match="parameter name"):
        check_name(name)


# -------------------------------------------------------------------- the mock PX4

def test_the_mock_answers_a_read_by_name_and_by_index_as_px4_does(bench):
    [value] = read(bench, "EKF2_HGT_REF")
    assert (value.param_id, value.param_type, value.param_count) == ("EKF2_HGT_REF", INT32,
                                                                   len(PARAMETER_NAMES))
    assert value.param_value != 3.0 and decode_value(value.param_value, INT32) == 3  # Vision
    assert value.param_index == PARAMETER_NAMES.index("EKF2_HGT_REF")
    [first] = read(bench, index=0)
    assert (first.param_id, first.param_type, first.param_value) == ("COM_DISARM_LAND",
                                                                      REAL32, 2.0)
    assert read(bench, "NOT_A_PARAM") == []  # PX4 answers nothing for an unknown name
    assert read(bench, "EKF2_HGT_REF", target_system=0) == []  # nor another system's
    assert read(bench, index=99) == [] and "[pm] unknown param ID: 99" in bench.texts()


def test_a_list_request_gets_the_hash_then_every_parameter_in_index_order(bench):
    bench.client.mav.param_request_list_send(1, 1)
    values = param_values(bench.run(0.02))
    assert (values[0].param_id, values[0].param_index) == ("_HASH_CHECK", 65535)  # -1
    assert values[0].param_type == mavlink.MAV_PARAM_TYPE_UINT32
    assert [v.param_index for v in values[1:]] == list(range(len(PARAMETER_NAMES)))
    table = {v.param_id: decode_value(v.param_value, v.param_type) for v in values[1:]}
    assert table == pytest.approx(default_parameters(Px4Options()))  # REAL32: float32
    assert table["COM_OBL_RC_ACT"] == 5 and table["EKF2_EV_CTRL"] == 15  # Hold; all of vision


def test_param_set_changes_what_the_mock_does(bench):
    [reply] = set_param(bench, "COM_OBL_RC_ACT", 4, INT32)  # offboard loss: Land
    assert decode_value(reply.param_value, INT32) == 4
    bench.arm()
    bench.send_velocity((0.0, 0.0, -1.0))
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    bench.run(1.1)
    assert bench.px4.mode == px4_protocol.AUTO_LAND


def test_param_set_refuses_what_the_mock_cannot_honour_and_names_unknown_ones(bench):
    [reply] = set_param(bench, "COM_OBL_RC_ACT", 0, INT32)  # Position mode: not flown here
    assert decode_value(reply.param_value, INT32) == 5
    assert "flies only 4 (Land) and 5 (Hold)" in "".join(bench.texts())  # one text, chunked
    assert set_param(bench, "NOT_A_PARAM", 1.0, REAL32) == []
    assert "[pm] unknown param: NOT_A_PARAM" in bench.texts()


def test_the_vision_position_follows_only_the_axes_ekf2_ev_ctrl_fuses():
    bench = Bench(parameters={"EKF2_EV_CTRL": 1})  # horizontal position only
    try:
        bench.run(0.5, lambda: bench.send_vision(3.0, 4.0, -2.0))
        position = bench.last("LOCAL_POSITION_NED")
        assert (position.x, position.y) == (pytest.approx(3.0, abs=0.1),
                                            pytest.approx(4.0, abs=0.1))
        assert position.z == pytest.approx(0.0, abs=0.1)
    finally:
        bench.close()


def test_vision_below_ekf2_ev_qmin_is_not_fused_and_the_estimate_stays_where_it_left():
    """EKF2's quality_sufficient (ev_control.cpp): with EKF2_EV_QMIN 1, the companion's
    quality -1 (failed: its VINS lost or blind) is not fused, nor is 0 (unknown); at
    EKF2_EV_QMIN 0 every sample is."""
    bench = Bench()
    try:
        bench.run(0.5, lambda: bench.send_vision(3.0, 4.0, -2.0))
        bench.run(0.5, lambda: bench.send_vision(9.0, 9.0, -2.0, -1))  # a drifting, blind VINS
        bench.run(0.5, lambda: bench.send_vision(9.0, 9.0, -2.0, 0))
        position = bench.last("LOCAL_POSITION_NED")
        assert (position.x, position.y) == (pytest.approx(3.0, abs=0.1),
                                            pytest.approx(4.0, abs=0.1))
        assert not bench.px4.external_vision_active  # timed out: nothing fusable came
    finally:
        bench.close()
    bench = Bench(parameters={"EKF2_EV_QMIN": 0})
    try:
        bench.run(0.5, lambda: bench.send_vision(9.0, 9.0, -2.0, 0))
        position = bench.last("LOCAL_POSITION_NED")
        assert (position.x, position.y) == (pytest.approx(9.0, abs=0.1),
                                            pytest.approx(9.0, abs=0.1))
    finally:
        bench.close()


@pytest.mark.parametrize("parameters, match", [
    ({"NOT_A_PARAM": 1}, "unknown parameter"), ({"EKF2_HGT_REF": 1.5}, "integer"),
    ({"COM_OF_LOSS_T": math.nan}, "finite"), ({"COM_OBL_RC_ACT": 2}, "flies only"),
    ({"MAV_SYS_ID": 2}, "Px4Options.system_id")])
def test_a_misconfiguration_the_mock_cannot_present_is_refused(parameters, match):
    with open_link("pty") as link, pytest.raises(ValueError, match=match):
        MockPx4(link, Quadrotor(), parameters=parameters)


# -------------------------------------------------------------------- the companion's reader

NAMES = ("EKF2_EV_CTRL", "EKF2_HGT_REF", "COM_OF_LOSS_T", "COM_OBL_RC_ACT")


def test_the_autopilot_reads_named_parameters_decoded():
    async def body(flight):
        assert await flight.connected()
        start = flight.clock.now()
        values = await flight.autopilot.read_parameters(NAMES + ("NOT_A_PARAM",), 1.0)
        assert values == {"EKF2_EV_CTRL": 15, "EKF2_HGT_REF": 3, "COM_OF_LOSS_T": 1.0,
                          "COM_OBL_RC_ACT": 5}
        assert isinstance(values["EKF2_HGT_REF"], int)
        # waited for the one not answered, to the timeout (and a few 5 ms ticks of lockstep)
        assert flight.clock.now() - start == pytest.approx(1.0, abs=0.03)
        assert await flight.autopilot.read_parameters(NAMES[:2], 1.0) == {"EKF2_EV_CTRL": 15,
                                                                          "EKF2_HGT_REF": 3}
    fly(body)


def test_a_misconfigured_vehicle_is_read_as_it_is():
    def misconfigure(sim):
        sim.px4.set_parameter("EKF2_HGT_REF", 0)  # barometer

    async def body(flight):
        misconfigure(flight.sim)
        assert await flight.connected()
        assert await flight.autopilot.read_parameters(["EKF2_HGT_REF"], 1.0) == {
            "EKF2_HGT_REF": 0}
    fly(body)


def test_a_lost_request_is_asked_again():
    requests = []

    async def body(flight):
        handler = flight.sim.px4._handle_param_request_read

        def lose_the_first(message):
            requests.append(flight.clock.now())
            if len(requests) > 1:
                handler(message)
        flight.sim.px4._handle_param_request_read = lose_the_first
        assert await flight.connected()
        values = await flight.autopilot.read_parameters(["EKF2_HGT_REF"], 2.0)
        assert values == {"EKF2_HGT_REF": 3}
        assert len(requests) == 2
        assert requests[1] - requests[0] == pytest.approx(0.5, abs=0.02)  # retry_interval_s
    fly(body)


def test_the_reader_refuses_bad_arguments():
    reader = ParameterReader(lambda message: None, SimClock())
    with pytest.raises(ValueError, match="parameter name"):
        asyncio.run(reader.read(["X" * 17], 1.0))
    with pytest.raises(ValueError, match="timeout_s"):
        asyncio.run(reader.read(["EKF2_HGT_REF"], 0.0))
    with pytest.raises(ValueError, match="retry_interval_s"):
        ParameterReader(lambda message: None, SimClock(), retry_interval_s=0.0)
