"""`companion fly --check` against the mock PX4 served over real MAVLink, as on a bench: every
check reported, nothing armed, the exit status saying whether the vehicle may fly."""

from __future__ import annotations

import dataclasses
import json
import re
import time
from types import SimpleNamespace

import pytest

from companion.cli import main
from companion.config import Config
from companion.flight.go import GoOptions
from companion.launch.check import PX4_PARAMETERS, _rc_switch
from companion.tools.testmodel import build_test_model
from drivers.sim.host import free_udp_port


def test_fly_check_reports_every_check_and_never_arms(served_vehicle, tmp_path, capsys):
    port, outcome = served_vehicle
    model = tmp_path / "model.onnx"
    model.write_bytes(build_test_model())
    status = main(["fly", "--check", "--json",
                   "--set", f"mavlink.url=udpout://127.0.0.1:{port}",
                   "--set", f"depth_network.model={model}",
                   "--set", "v4l2.device=/dev/video-none"])
    results = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert status == 1  # no camera on this machine: the vehicle may not fly
    assert not results["camera"]["ok"] and "/dev/video-none" in results["camera"]["detail"]
    assert results["depth network"]["ok"]
    for name in ("MAVLink link", "TIMESYNC", "IMU rate", "EKF2_EV_CTRL", "EKF2_HGT_REF",
                 "COM_OF_LOSS_T", "COM_OBL_RC_ACT"):
        assert results[name]["ok"], results[name]
    assert not results["MAVLink signing"]["ok"]  # off: anyone on the link could command it
    assert results["MAVLink signing"]["detail"].startswith("off: ")
    vehicle = outcome["sim"].px4.vehicle
    assert not vehicle.armed and vehicle.landed  # on the ground, disarmed, all along


def test_fly_check_without_a_flight_controller_fails_on_the_link(tmp_path, capsys):
    status = main(["fly", "--check", "--set", f"mavlink.url=udpout://127.0.0.1:{free_udp_port()}",
                   "--set", "v4l2.device=/dev/video-none"])
    out = capsys.readouterr().out
    assert status == 1
    assert "FAIL  MAVLink link" in out and "no HEARTBEAT from PX4" in out
    assert "FAIL  depth network" in out and "[depth_network] model is empty" in out


def test_fly_check_fails_a_signing_key_that_cannot_be_used(tmp_path, capsys):
    status = main(["fly", "--check", "--set", f"mavlink.url=udpout://127.0.0.1:{free_udp_port()}",
                   "--set", f"mavlink.signing_key_file={tmp_path / 'absent.key'}",
                   "--set", "v4l2.device=/dev/video-none"])
    out = capsys.readouterr().out
    assert status == 1
    assert re.search(r"FAIL  MAVLink signing +MAVLink signing key file .*absent.key: no such "
                     r"file; make one with `companion signing keygen FILE`", out)


def test_a_px4_given_the_key_by_provision_passes_the_signing_check(served_vehicle, tmp_path,
                                                                   capsys):
    port, outcome = served_vehicle
    key = tmp_path / "mavlink-signing.key"
    link = ["--set", f"mavlink.url=udpout://127.0.0.1:{port}",
            "--set", f"mavlink.signing_key_file={key}"]
    assert main(["signing", "keygen", str(key)]) == 0
    assert main(["signing", "provision", *link]) == 0
    assert "PX4 (system 1 component 1) took the key" in capsys.readouterr().out
    assert outcome["sim"].px4.signing_key == bytes.fromhex(key.read_text())
    main(["fly", "--check", "--json", *link, "--set", "v4l2.device=/dev/video-none"])
    results = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert results["MAVLink link"]["ok"] and results["TIMESYNC"]["ok"]
    assert results["MAVLink signing"]["ok"], results["MAVLink signing"]
    assert results["MAVLink signing"]["detail"].startswith("on: PX4's messages verify")


def test_fly_check_fails_the_px4_parameters_a_flight_needs(served_vehicle, capsys):
    port, outcome = served_vehicle
    deadline = time.monotonic() + 10.0
    while "sim" not in outcome and time.monotonic() < deadline:
        time.sleep(0.05)
    px4 = outcome["sim"].px4
    px4.set_parameter("EKF2_HGT_REF", 1)    # barometer: height would not follow the odometry
    px4.set_parameter("COM_OF_LOSS_T", 5.0)  # a dead companion noticed only after 5 s
    status = main(["fly", "--check", "--json", "--set", f"mavlink.url=udpout://127.0.0.1:{port}",
                   "--set", "v4l2.device=/dev/video-none"])
    results = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert status == 1
    assert not results["EKF2_HGT_REF"]["ok"] and results["EKF2_HGT_REF"]["detail"].startswith("1;")
    assert not results["COM_OF_LOSS_T"]["ok"]
    assert results["EKF2_EV_CTRL"]["ok"] and results["COM_OBL_RC_ACT"]["ok"]


@pytest.mark.parametrize("value, ok", [(0, False), (3, False), (4, True), (5, True), (6, False),
                                       (7, False)])
def test_only_land_or_hold_passes_as_the_offboard_loss_action(value, ok):
    # commander_params.c: 0-2 hand the vehicle to the sticks, 3 Return, 6 Terminate, 7 Disarm
    assert PX4_PARAMETERS["COM_OBL_RC_ACT"].holds(value) is ok


@pytest.mark.parametrize("channels, ok, detail", [
    (None, False, "no RC_CHANNELS with channel 7 from PX4"),
    ((1500,) * 6, False, "no RC_CHANNELS with channel 7 from PX4"),
    ((1500,) * 6 + (None,), False, "channel 7 reported unused by the receiver"),
    ((1500,) * 6 + (1000,), True, "channel 7 at 1000 us"),
])
def test_the_rc_go_switch_check_fails_a_channel_missing_or_reported_unused(channels, ok, detail):
    config = dataclasses.replace(Config(), go=GoOptions(rc_channel=7))
    [result] = _rc_switch(SimpleNamespace(rc_channels_us=channels), config)
    assert (result.ok, result.detail) == (ok, detail)
