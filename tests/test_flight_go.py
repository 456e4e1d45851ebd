"""The operator's go: a vehicle never arms until a person says to fly (companion/flight/go.py).

A whole simulated flight waits, disarmed, until `companion go` writes to the real go socket;
the gate's sources (socket, RC switch edge) and its refusals on their own."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time

import pytest

from companion.cli import main
from companion.config import Config
from companion.flight.app import format_flight
from companion.flight.go import GoError, GoOptions, OperatorGate, send_go
from companion.launch import simulated
from drivers.clock import MonotonicClock
from drivers.mavlink.autopilot import Autopilot as RealAutopilot
from drivers.mavlink.autopilot import MavlinkOptions
from drivers.mavlink.link import mavlink, open_link
from drivers.sim.host import SimMission, free_udp_port
from drivers.sim.mock_px4 import Px4Options
from flights import SHORT_DOME_GOAL

WAIT_WALL_S = 4.0


def test_a_simulated_vehicle_waits_disarmed_for_companion_go_then_flies(tmp_path):
    """... with MAVLink signing on at both ends, as the vehicle presets fly."""
    key = bytes(range(32)).hex()
    config = Config()
    socket_path = tmp_path / "go.sock"
    config = dataclasses.replace(config, go=GoOptions(socket=str(socket_path)),
                                 mavlink=MavlinkOptions(signing_key=key),
                                 px4=Px4Options(signing_key=key))
    mission = simulated.SimMission(world="dome", goal=SHORT_DOME_GOAL)
    sent = []

    def operator():  # another process's view: the CLI, once the socket exists, after a while
        deadline = time.monotonic() + 60.0
        while not socket_path.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(WAIT_WALL_S)
        sent.append(main(["go", "--set", f"go.socket={socket_path}"]))

    thread = threading.Thread(target=operator, daemon=True)
    thread.start()
    summary = asyncio.run(simulated.fly(config, mission, go_given_by=""))
    thread.join(5.0)
    assert sent == [0]
    states = [(t["to"], t["t"]) for t in summary["transitions"]]
    names = [name for name, _ in states]
    assert names[:3] == ["initialising", "awaiting_go", "taking_off"], names
    # The take-off is the go's: the operator sent it WAIT_WALL_S wall seconds after the socket
    # appeared, and the simulated time that is depends on the host's load (lockstep runs as
    # fast as the CPU allows; a loaded CI host gave 0.96 s), so the proof is the reason, not
    # a duration.
    assert states[2][1] > states[1][1]
    assert summary["transitions"][2]["reason"] == "go from companion go"
    assert "operator's go" in summary["transitions"][1]["reason"]
    assert summary["final_state"] == "landed" and summary["collisions"] == 0
    assert not socket_path.exists()  # the application removes its socket
    assert summary["mavlink_signing"] == {"on": True, "unsigned": 0, "bad_signature": 0}
    assert "MAVLink signing   on: 0 unsigned and 0 badly signed messages ignored" in \
        format_flight(summary)


def test_a_vehicle_standing_for_a_late_go_flies_with_its_vins_at_rest_meanwhile():
    """`sim fly --go-after 8`: the vehicle stands 8 simulated seconds for the go. Before the
    zero-velocity prior (autonomy/vins/stillness.py) the VINS rebuilt its smoother while it
    stood (2 rebuilds with a 10 s wait, 9 and a failsafe with 20 s; docs/vins.md)."""
    config = Config()
    mission = SimMission(world="dome", goal=SHORT_DOME_GOAL, go_after_s=8.0)
    summary = asyncio.run(simulated.fly(config, mission))
    waiting, taking_off = summary["transitions"][1:3]
    assert (waiting["to"], taking_off["to"]) == ("awaiting_go", "taking_off")
    assert taking_off["t"] - waiting["t"] == pytest.approx(8.0, abs=0.1)
    assert taking_off["reason"] == "go from sim fly --go-after 8"
    # the prior held the wait: 55 keyframes measured (one every 0.15 s on the ground), none in
    # the air (only the ground's are counted)
    assert summary["vins_resets"] == 0 and summary["vins_still_keyframes"] >= 5 * 8.0
    assert summary["reached_goal"] and summary["collisions"] == 0


def test_a_negative_go_after_is_refused_before_anything_starts(capsys):
    mission = SimMission(world="dome", goal=SHORT_DOME_GOAL, go_after_s=-1.0)
    with pytest.raises(simulated.SimError, match="--go-after must be 0 seconds or more"):
        asyncio.run(simulated.fly(Config(), mission))
    assert main(["sim", "fly", "--go-after", "-1"]) == 2
    assert "--go-after: expected a non-negative number, got '-1'" in capsys.readouterr().err


class Autopilot:
    rc_channels_us = None


def _gate(tmp_path, **options) -> OperatorGate:
    gate = OperatorGate(GoOptions(socket=str(tmp_path / "go.sock"), **options), Autopilot())
    gate.open()
    return gate


def test_a_go_sent_before_the_vehicle_was_ready_is_discarded(tmp_path):
    gate = _gate(tmp_path)
    try:
        send_go(str(tmp_path / "go.sock"))
        gate.start_waiting()
        assert gate.poll() == ""
        send_go(str(tmp_path / "go.sock"))
        assert gate.poll() == "companion go"
    finally:
        gate.close()


def test_the_rc_switch_gives_the_go_only_on_a_low_to_high_edge_while_waiting(tmp_path):
    gate = _gate(tmp_path, rc_channel=7)
    try:
        Autopilot.rc_channels_us = [1500] * 6 + [2000]  # left high since power-up
        gate.start_waiting()
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [1000]
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [1900]
        assert gate.poll() == "RC channel 7"
        assert "RC channel 7 switched above 1800 us" in gate.describe()
    finally:
        gate.close()
        Autopilot.rc_channels_us = None


def test_an_rc_channel_reported_unused_is_no_go_and_needs_a_fresh_low(tmp_path):
    gate = _gate(tmp_path, rc_channel=7)
    try:
        gate.start_waiting()
        Autopilot.rc_channels_us = [1500] * 6 + [1000]
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [None]  # RC_CHANNELS' UINT16_MAX: unused
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [1900]  # back, high: not an edge seen whole
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [1000]
        assert gate.poll() == ""
        Autopilot.rc_channels_us = [1500] * 6 + [1900]
        assert gate.poll() == "RC channel 7"
    finally:
        gate.close()
        Autopilot.rc_channels_us = None


def test_a_mavlink_go_counts_only_while_waiting(tmp_path):
    gate = _gate(tmp_path)
    try:
        assert not gate.command("MAVLink from 255/190")
        gate.start_waiting()
        assert gate.command("MAVLink from 255/190")
        assert gate.poll() == "MAVLink from 255/190"
        assert not gate.command("MAVLink from 255/190")  # given once
    finally:
        gate.close()


def test_an_unusable_socket_path_is_a_clear_error(tmp_path):
    gate = OperatorGate(GoOptions(socket=str(tmp_path / "missing" / "go.sock")), Autopilot())
    with pytest.raises(GoError, match="RuntimeDirectory=companion"):
        gate.open()


def test_companion_go_says_when_nobody_listens(tmp_path, capsys):
    assert main(["go", "--set", f"go.socket={tmp_path / 'go.sock'}"]) == 1
    assert "is `companion fly` running" in capsys.readouterr().err


class GroundStation:
    """Real MAVLink bytes: a ground station (system 255, component 190) on loopback UDP and a
    companion's autopilot driver (signing with ``key``, None: off) polled by hand, with the
    operator's gate taking the driver's go commands."""

    def __init__(self, key: bytes | None = None):
        port = free_udp_port()
        self.link = open_link(f"udpin://127.0.0.1:{port}", source_system=255,
                              source_component=190)
        self.autopilot = RealAutopilot.open(
            MavlinkOptions(url=f"udpout://127.0.0.1:{port}", signing_key=key.hex() if key else ""),
            MonotonicClock())
        self.gate = OperatorGate(GoOptions(socket=""), self.autopilot)
        self.autopilot._poll(self.autopilot.clock.now())  # our HEARTBEAT: the GCS learns where
        time.sleep(0.05)
        self.link.receive_pending()

    def mission_start(self, wait_s: float = 2.0) -> int | None:
        """Send MAV_CMD_MISSION_START to the companion; the result of its COMMAND_ACK, None
        when none came in ``wait_s``."""
        self.link.mav.command_long_send(1, 191, mavlink.MAV_CMD_MISSION_START, 0, *[0] * 7)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline:
            self.autopilot._poll(self.autopilot.clock.now())
            for message in self.link.receive_pending():
                if message.get_type() == "COMMAND_ACK":
                    assert (message.target_system, message.target_component) == (255, 190)
                    return message.result
            time.sleep(0.01)
        return None

    def close(self) -> None:
        self.autopilot.close()
        self.link.close()


def test_a_ground_stations_mission_start_is_the_go_and_is_acknowledged():
    """The driver hands the ground station's MAV_CMD_MISSION_START to the gate and acknowledges
    it to the sender: TEMPORARILY_REJECTED before the vehicle waits, ACCEPTED while it waits."""
    gcs = GroundStation()
    try:
        assert gcs.mission_start() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        gcs.gate.start_waiting()
        assert gcs.mission_start() == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.gate.poll() == "MAV_CMD_MISSION_START from 255/190"
    finally:
        gcs.close()


def test_with_signing_only_a_go_signed_with_the_vehicles_key_counts(caplog):
    """A rogue system's go, unsigned or signed with another key, is ignored (no go, no ACK)
    and counted, with one warning naming it; the same go signed with the key is taken."""
    key = bytes(range(32))
    gcs = GroundStation(key)
    try:
        gcs.gate.start_waiting()
        assert gcs.mission_start(wait_s=0.5) is None
        assert gcs.autopilot.signing == {"on": True, "unsigned": 1, "bad_signature": 0}
        gcs.link.setup_signing(bytes(32 * [9]))  # another key
        assert gcs.mission_start(wait_s=0.5) is None
        assert gcs.autopilot.signing == {"on": True, "unsigned": 1, "bad_signature": 1}
        assert gcs.gate.poll() == "" and gcs.autopilot.counts["commands_to_us"] == 0
        warnings = [r.getMessage() for r in caplog.records if "MAVLink signing" in r.getMessage()]
        assert warnings == ["MAVLink signing: ignored an unsigned COMMAND_LONG from system 255 "
                            "component 190 (1 unsigned and 0 badly signed messages so far); a "
                            "sender without this vehicle's key"]  # one per burst
        gcs.link.setup_signing(key)
        assert gcs.mission_start() == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.gate.poll() == "MAV_CMD_MISSION_START from 255/190"
    finally:
        gcs.close()
