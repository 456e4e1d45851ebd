"""`companion sim serve` and `sim fly` as a user runs them: they say where to connect, refuse
bad links and missions, and warn of a realistic vehicle flown without its estimates."""

import logging
from pathlib import Path

from companion.cli import main


def test_serve_on_a_pty_in_lockstep_prints_the_device_and_the_flight(capsys):
    status = main(["sim", "serve", "--world", "sewer", "--seed", "1", "--mavlink", "pty",
                   "--clock", "lockstep", "--duration", "2"])
    out = capsys.readouterr().out
    assert status == 0
    assert "serving a simulated PX4 quadrotor in sewer (seed 1, lockstep clock) on /dev/" in out
    assert "served 2.0 s of simulated flight" in out


def test_serve_refuses_a_malformed_link_url(capsys):
    status = main(["sim", "serve", "--mavlink", "udpin://nowhere", "--duration", "1"])
    assert status == 1
    assert capsys.readouterr().err.startswith("sim serve: ")


def test_sim_commands_reject_unknown_worlds_and_negative_seeds(capsys):
    assert main(["sim", "record", "--world", "moon", "--out", "x"]) == 2
    assert "invalid choice: 'moon'" in capsys.readouterr().err
    assert main(["sim", "serve", "--seed", "-3"]) == 2
    assert "non-negative integer" in capsys.readouterr().err


def test_serve_names_a_serial_port_or_tcp_server_it_cannot_reach_in_one_line(capsys):
    import socket

    with socket.socket() as probe:  # a TCP port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    assert main(["sim", "serve", "--mavlink", "serial:///dev/ttyNOPE0:921600"]) == 1
    assert capsys.readouterr().err == (
        "sim serve: serial port /dev/ttyNOPE0 at 921600 baud: no such port; list them with "
        "`ls /dev/ttyTHS* /dev/ttyACM* /dev/ttyUSB*` or `companion devices`\n")
    assert main(["sim", "serve", "--mavlink", f"tcpout://127.0.0.1:{port}"]) == 1
    assert capsys.readouterr().err.startswith(
        f"sim serve: tcpout://127.0.0.1:{port}: cannot connect (Connection refused)")


def test_sim_fly_offers_the_udp_and_serial_links_only(capsys):
    assert main(["sim", "fly", "--link", "can"]) == 2
    assert "invalid choice: 'can' (choose from 'udp', 'serial')" in capsys.readouterr().err


def test_sim_fly_refuses_truth_tracks_through_the_realistic_camera(capsys):
    """The truth is projected through the configured camera: the realistic profile's lens,
    mounting error and late stamps would make it wrong, so the flight does not start."""
    for tracks in ("truth", "early-error", "late-error"):
        assert main(["sim", "fly", "--tracks", tracks, "--no-plot", "--no-record"]) == 1
        assert capsys.readouterr().err.startswith(
            "sim fly: truth tracks need the ideal profile ([sim] profile = \"ideal\")")
    assert main(["sim", "fly", "--tracks", "oracle"]) == 2
    assert ("invalid choice: 'oracle' (choose from 'tracker', 'truth', 'early-error', "
            "'late-error')") in capsys.readouterr().err


def test_sim_fly_names_the_realistic_vehicles_errors_its_vins_does_not_estimate(caplog):
    """A realistic vehicle flown without the estimates every real vehicle's configuration runs
    gets a warning naming them and the preset that runs them; the preset and the ideal profile
    get none, nor does ``sim fly``'s own default, which is the preset. (Each flight stops at
    once on a camera the simulator cannot render.)"""
    config = Path(__file__).resolve().parent.parent / "config"
    preset, defaults = str(config / "sim-realistic.toml"), str(config / "sim.toml")
    cannot_render = ["--set", "camera.calibration=device", "--no-plot", "--no-record"]
    flights = {
        "time offset": ["--config", defaults, "--set", "sim.profile=realistic"],
        "gyro": ["--config", defaults, "--set", "sim.profile=realistic",
                 "--set", "vins.estimate_time_offset=true"],
        "preset": ["--config", preset],
        "carried column": ["--config", preset, "--set", "vins.estimate_gyro_alignment=false",
                           "--set", "vins.gyro_alignment=[0.01, 0.0, 0.0]"],
        "ideal": ["--config", defaults],
        "default": [],
    }
    warned = {}
    for flight, argv in flights.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="companion.launch.simulated"):
            assert main(["sim", "fly", *argv, *cannot_render]) == 1
        warned[flight] = " ".join(r.getMessage() for r in caplog.records
                                  if r.name == "companion.launch.simulated")
    assert "estimate_time_offset" in warned["time offset"]
    assert "estimate_gyro_alignment" in warned["time offset"]
    assert "estimate_time_offset" not in warned["gyro"]
    assert "estimate_gyro_alignment" in warned["gyro"]
    assert "config/sim-realistic.toml" in warned["gyro"]
    assert warned["preset"] == warned["carried column"] == warned["ideal"] \
        == warned["default"] == ""
