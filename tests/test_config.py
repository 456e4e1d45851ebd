"""The config loader: what an operator sees for each kind of bad config, and what a good one
loads to."""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from autonomy.depth.options import RescaleOptions
from autonomy.geometry import R_BODY_CAMERA
from autonomy.options import OptionError, field_types
from companion.config import (SIMULATOR_DEFAULTS, Config, ConfigError, dump_toml, load_config,
                              parse_override)
from drivers.camera.options import CameraOptions
from drivers.sim.camera import T_BODY_CAMERA

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

SIM_TOML = Path(__file__).resolve().parent.parent / "config" / "sim.toml"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "flight.toml"
    path.write_text(text, encoding="utf-8")
    return path


def load_error(path: Path, overrides: tuple[str, ...] = ()) -> str:
    with pytest.raises(ConfigError) as caught:
        load_config(path, overrides)
    return str(caught.value)


# --- errors in a file: each names the file, the dotted key and what is wrong ----------------

def test_missing_file_is_named(tmp_path):
    path = tmp_path / "absent.toml"
    assert load_error(path) == f"{path}: no such file"


def test_unreadable_file_is_named(tmp_path):
    assert load_error(tmp_path).startswith(f"{tmp_path}: cannot read: ")


def test_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes("[log]\nlevel = \"caf\xe9\"\n".encode("latin-1"))
    assert load_error(path).startswith(f"{path}: not UTF-8 text")


def test_toml_syntax_error_keeps_line_and_column(tmp_path):
    path = write(tmp_path, "[rescale]\nkappa = \n")
    message = load_error(path)
    assert message.startswith(f"{path}: invalid TOML: ")
    assert "line 2, column" in message


def test_unknown_section_suggests_the_closest(tmp_path):
    path = write(tmp_path, "[rescal]\nkappa = 1.0\n")
    assert load_error(path) == f"{path}: rescal: unknown section; did you mean 'rescale'?"


def test_unknown_key_suggests_the_closest(tmp_path):
    path = write(tmp_path, "[rescale]\nkapa = 1.0\n")
    assert load_error(path) == f"{path}: rescale.kapa: unknown key; did you mean 'kappa'?"


def test_unknown_key_without_a_close_match_lists_the_known_ones(tmp_path):
    path = write(tmp_path, "[log]\ncolour = true\n")
    assert load_error(path) == f"{path}: log.colour: unknown key; known: level"


def test_section_that_is_not_a_table(tmp_path):
    path = write(tmp_path, "rescale = 3\n")
    assert load_error(path) == f"{path}: rescale: must be a table [rescale], got 3"


@pytest.mark.parametrize("line, problem", [
    ('kappa = "big"', "rescale.kappa: must be a number, got 'big'"),
    ("kappa = true", "rescale.kappa: must be a number, got True"),
    ("segments = 2.5", "rescale.segments: must be an integer, got 2.5"),
    ("outlier_rejection = 1", "rescale.outlier_rejection: must be a boolean, got 1"),
    ("method = 3", "rescale.method: must be a string, got 3"),
])
def test_wrong_type(tmp_path, line, problem):
    path = write(tmp_path, f"[rescale]\n{line}\n")
    assert load_error(path) == f"{path}: {problem}"


@pytest.mark.parametrize("line, problem", [
    ("kappa = -1", "rescale.kappa: must be >= 0, got -1.0"),
    ("ransac_threshold = 1.0", "rescale.ransac_threshold: must be < 1, got 1.0"),
    ("kappa = inf", "rescale.kappa: must be a finite number, got inf"),
    ('method = "cubic"', "rescale.method: must be one of poly1,"),
])
def test_out_of_range(tmp_path, line, problem):
    path = write(tmp_path, f"[rescale]\n{line}\n")
    assert load_error(path).startswith(f"{path}: {problem}")


def test_bad_log_level(tmp_path):
    path = write(tmp_path, '[log]\nlevel = "LOUD"\n')
    assert load_error(path) == (
        f"{path}: log.level: must be one of DEBUG, INFO, WARNING, ERROR; got 'LOUD'")


def test_cross_field_error(tmp_path):
    path = write(tmp_path, "[rescale]\nmin_depth = 10.0\nmax_depth = 5.0\n")
    assert load_error(path) == f"{path}: rescale.min_depth: must be < max_depth (5), got 10"


# --- overrides -----------------------------------------------------------------------------

@pytest.mark.parametrize("text, value", [
    ("rescale.segments=3", 3),
    ("rescale.kappa=1e6", 1e6),
    ("rescale.bridge_gaps=true", True),
    ('rescale.method="poly1"', "poly1"),
    ("rescale.method=monotone_spline", "monotone_spline"),
    ("rescale.method=", ""),
    (" rescale.kappa = 2.5 ", 2.5),
    ("rescale.segments=[1, 2]", [1, 2]),
])
def test_override_value_is_read_as_toml_or_else_a_bare_string(text, value):
    assert parse_override(text).value == value


def test_override_names_its_section_key_and_source():
    override = parse_override("rescale.kappa=3")
    assert override == ("rescale", "kappa", 3, "--set rescale.kappa=3")


def test_override_value_with_a_newline_is_one_string_not_two_keys():
    assert parse_override("rescale.method=poly1\nkappa = 3").value == "poly1\nkappa = 3"


@pytest.mark.parametrize("text", ["rescale.kappa", "kappa=3", "rescale.=3", ".kappa=3",
                                  "rescale.kappa.x=3"])
def test_malformed_override(text):
    with pytest.raises(ConfigError) as caught:
        parse_override(text)
    assert str(caught.value) == f"--set {text}: expected SECTION.KEY=VALUE, got {text!r}"


def test_arrays_nested_too_deep_for_the_toml_parser_are_a_config_error(tmp_path):
    """tomllib recurses into nested arrays; 1000 levels exceed Python's recursion limit
    (fuzz/regressions/config_set/*-nested-too-deep)."""
    deep = "[" * 1000
    assert load_error(write(tmp_path, f"[rescale]\nkappa = {deep}\n")).endswith(
        "invalid TOML: arrays or tables nested too deeply")
    assert "rescale.kappa: must be a number, got '[[[" in load_error(
        None, (f"rescale.kappa={deep}",))


def test_an_override_that_is_not_utf8_is_refused():
    """Python keeps a command line's undecodable bytes as surrogates, which no TOML file nor
    recording can hold (fuzz/regressions/config_set/set-not-utf8)."""
    message = load_error(None, (os.fsdecode(b"recorder.directory=/flights/\xff"),))
    assert message == "--set recorder.directory=/flights/\\xff: not UTF-8 text"


def test_a_clamped_rescaling_tail_with_the_planners_near_tail_is_refused(tmp_path):
    """A clamped tail is no near bound: the planner's near tail would fly on it."""
    message = load_error(None, ("planner.near_tail_share=0.9", "rescale.extrapolation=clamp"))
    assert message.startswith("--set rescale.extrapolation=clamp: rescale.extrapolation: a "
                              "clamped tail reads every pixel nearer")
    assert "planner.near_tail_share = 0" in message
    clamped = tmp_path / "clamped.toml"
    clamped.write_text('[rescale]\nextrapolation = "clamp"\n')
    assert load_error(clamped, ("planner.near_tail_share=0.9",)).startswith(f"{clamped}: ")
    assert load_error(None, ("planner.near_tail_share=0.9", "rescale.extrapolation=linear",
                             "rescale.extrapolation=clamp")) == message
    assert load_config(None, ("rescale.extrapolation=clamp",))  # the share is 0 by default


def test_override_with_unknown_key_names_the_override():
    message = load_error(None, ("rescale.kapa=3",))
    assert message == "--set rescale.kapa=3: rescale.kapa: unknown key; did you mean 'kappa'?"


def test_override_beats_file_and_later_override_beats_earlier(tmp_path):
    path = write(tmp_path, "[rescale]\nkappa = 5.0\nsegments = 12\n")
    config = load_config(path, ["rescale.kappa=7", "rescale.segments=20", "rescale.segments=30"])
    assert (config.rescale.kappa, config.rescale.segments) == (7.0, 30)


def test_bad_override_is_blamed_not_the_file(tmp_path):
    path = write(tmp_path, "[rescale]\nkappa = 5.0\n")
    message = load_error(path, ("rescale.kappa=-1",))
    assert message == "--set rescale.kappa=-1: rescale.kappa: must be >= 0, got -1.0"


def test_the_simulated_vehicles_cross_field_error_is_a_config_error(tmp_path):
    """It was a plain ValueError out of load_config (found by fuzz/mcap_reader.py in a
    recording's config; fuzz/regressions/config_set/vehicle-thrust-max-below-hover)."""
    path = write(tmp_path, "[vehicle]\nthrust_max = 0.1\n")
    assert load_error(path) == (f"{path}: vehicle.thrust_max: must exceed thrust_hover (0.5), "
                                "or the vehicle cannot climb; got 0.1")


def test_cross_field_error_on_a_default_key_blames_the_last_source(tmp_path):
    path = write(tmp_path, "[rescale]\nkappa = 5.0\n")
    message = load_error(path, ("rescale.max_depth=0.01",))
    assert message == ("--set rescale.max_depth=0.01: rescale.min_depth: "
                       "must be < max_depth (0.01), got 0.05")


# --- what a good config loads to -----------------------------------------------------------

def test_no_file_gives_the_defaults():
    assert load_config(None) == Config()


def test_integer_is_accepted_where_a_number_is_expected(tmp_path):
    config = load_config(write(tmp_path, "[rescale]\nmax_depth = 40\n"))
    assert config.rescale.max_depth == 40.0
    assert type(config.rescale.max_depth) is float


def test_dump_toml_round_trips(tmp_path):
    config = load_config(None, ["log.level=DEBUG", "rescale.method=poly3", "rescale.ridge=1e-12",
                                "rescale.bridge_gaps=false", "rescale.segments=17"])
    assert load_config(write(tmp_path, dump_toml(config))) == config


@settings(max_examples=50, deadline=None)
@given(kappa=st.floats(min_value=0.0, allow_infinity=False),
       min_depth=st.floats(min_value=1e-300, max_value=64.0))
def test_dump_toml_keeps_every_float_exactly(kappa, min_depth):
    config = Config(rescale=RescaleOptions(kappa=kappa, min_depth=min_depth))
    assert tomllib.loads(dump_toml(config))["rescale"] == dataclasses.asdict(config.rescale)


def test_sim_toml_loads_and_lists_every_key_of_every_section():
    load_config(SIM_TOML)
    document = tomllib.loads(SIM_TOML.read_text(encoding="utf-8"))
    assert {section: set(table) for section, table in document.items()} == {
        section: {f.name for f in dataclasses.fields(kind)}
        for section, kind in field_types(Config).items()
    }


def test_the_camera_mounting_defaults_to_the_simulators_and_turns_as_named():
    np.testing.assert_allclose(Config().camera.T_B_C(), T_BODY_CAMERA)
    np.testing.assert_allclose(T_BODY_CAMERA[:3, :3], R_BODY_CAMERA)
    np.testing.assert_allclose(T_BODY_CAMERA[:3, 3], [0.10, 0.0, 0.05])
    view = lambda **mount: CameraOptions(**mount).T_B_C()[:3, 2]  # noqa: E731 - optical axis
    down = math.radians(20.0)
    np.testing.assert_allclose(view(mount_pitch_deg=20.0), [math.cos(down), 0, -math.sin(down)],
                               atol=1e-12)
    np.testing.assert_allclose(view(mount_yaw_deg=90.0), [0, 1, 0], atol=1e-12)
    with pytest.raises(OptionError, match="mount_pitch_deg"):
        CameraOptions(mount_pitch_deg=120.0)


def test_the_estimators_imu_defaults_to_the_flight_controllers_whatever_is_set():
    """[vins_imu]'s default is the Pixhawk 6C/6X's ICM-42688-P, not the EuRoC figures
    ImuNoise() defaults to: a key set leaves the others at the section's own default."""
    from autonomy.vins.preintegration import ImuNoise

    assert load_config(None).vins_imu == ImuNoise.icm42688p() != ImuNoise()
    config = load_config(None, ["vins_imu.gyro_random_walk=1e-4"])
    assert config.vins_imu == dataclasses.replace(ImuNoise.icm42688p(), gyro_random_walk=1e-4)


@pytest.mark.parametrize("preset", ["orin-d455.toml", "orin-oak.toml"])
def test_vehicle_presets_pass_config_check_and_fly_their_camera_over_serial(preset, capsys):
    """The presets an operator installs (docs/operations.md, section 8): valid, their camera's
    driver with the device's own calibration, PX4 over a UART, MAVLink signing with the key in
    a file, the operator's go required."""
    from companion.cli import main

    path = SIM_TOML.parent / preset
    assert main(["config", "check", str(path)]) == 0
    assert capsys.readouterr().out.strip() == f"{path}: ok"
    config = load_config(path)
    assert config.camera.driver == preset.removeprefix("orin-").removesuffix(".toml").replace(
        "d455", "realsense")
    assert config.camera.calibration == "device"
    assert config.mavlink.url.startswith("serial:///dev/ttyTHS")
    assert config.mavlink.signing_key_file == "mavlink-signing.key"  # signing on
    assert config.mavlink.signing_key == ""  # the key itself never in the file
    assert config.go.required


def test_the_simulator_commands_default_to_the_realistic_preset_under_the_file_and_set():
    """``sim fly``, ``sim record``, ``eval rescale`` and ``eval nav`` fly the realistic vehicle
    by default (issue 23): their defaults are config/sim-realistic.toml's settings, which a
    config file and ``--set`` override (config/sim.toml, every key at its default, gives the
    ideal profile back); the other commands keep the options' own defaults."""
    from companion.cli import _build_parser
    from companion.cli.common import load_effective_config

    preset = load_config(SIM_TOML.parent / "sim-realistic.toml")
    parser = _build_parser()
    for argv in (["sim", "fly"], ["sim", "record", "--out", "x"], ["eval", "rescale"],
                 ["eval", "nav"]):
        assert load_effective_config(parser.parse_args(argv)) == preset, argv
        ideal = load_effective_config(parser.parse_args([*argv, "--config", str(SIM_TOML)]))
        assert ideal == Config() and ideal.sim.profile == "ideal", argv
        overridden = load_effective_config(parser.parse_args([*argv, "--set",
                                                              "planner.near_tail_share=0.5"]))
        assert overridden.sim.profile == "realistic"
        assert overridden.planner.near_tail_share == 0.5
    for argv in (["sim", "soak"], ["sim", "serve"], ["eval", "vio", "x"]):
        assert load_effective_config(parser.parse_args(argv)) == Config(), argv


def test_a_bad_file_under_the_simulator_defaults_is_named_not_the_defaults(tmp_path):
    """A clamped tail is refused beside a counted near tail; with the simulator's default near
    tail under a file that clamps, the error names the file and says what to set."""
    path = tmp_path / "clamp.toml"
    path.write_text('[rescale]\nextrapolation = "clamp"\n')
    with pytest.raises(ConfigError, match=rf"^{path}: rescale.extrapolation: .*near_tail_share = 0"):
        load_config(path, (), SIMULATOR_DEFAULTS)
    assert load_config(path, ["planner.near_tail_share=0"], SIMULATOR_DEFAULTS).sim.profile \
        == "realistic"


def test_the_realistic_preset_estimates_what_the_vehicle_presets_estimate(capsys, tmp_path,
                                                                          monkeypatch):
    """config/sim-realistic.toml flies the simulator's realistic vehicle as the Orin presets fly
    a real one: valid, the realistic profile, the camera's time offset estimated as the presets
    estimate it, the gyro's misalignment, all of it, estimated as a preset's first flight (none
    kept yet) estimates it (docs/operations.md, section 6), the near tail counted as theirs, the
    tracks anchored as theirs are, and the accelerometer's z read at rest as theirs is."""
    from companion.cli import main
    from companion.launch.learned_calibration import start_from_learned

    path = SIM_TOML.parent / "sim-realistic.toml"
    assert main(["config", "check", str(path)]) == 0
    assert capsys.readouterr().out.strip() == f"{path}: ok"
    realistic = load_config(path)
    assert realistic.sim.profile == "realistic"
    monkeypatch.chdir(tmp_path)  # where the presets' learned files are not (yet)
    for preset in ("orin-d455.toml", "orin-oak.toml"):
        vehicle = load_config(SIM_TOML.parent / preset)
        first_flight = start_from_learned(vehicle).vins
        assert realistic.vins.estimate_time_offset == first_flight.estimate_time_offset is True
        assert realistic.vins.estimate_gyro_alignment == first_flight.estimate_gyro_alignment \
            is True
        assert realistic.vins.gyro_alignment_rates == first_flight.gyro_alignment_rates == "all"
        assert realistic.vins.rest_accel_scale_share == \
            first_flight.rest_accel_scale_share > 0.0
        assert realistic.planner.near_tail_share == vehicle.planner.near_tail_share > 0.0
        assert realistic.planner.far_tail_share == vehicle.planner.far_tail_share > 0.0
        for key in ("anchor_age", "anchor_warp"):
            assert getattr(realistic.vins_frontend, key) == getattr(vehicle.vins_frontend, key)
        assert realistic.vins_frontend.anchor_age > 0
