"""`companion eval nav --calibration`: the VINS's error at the end of navigation fitted to the
calibration errors the simulator drew for each record's vehicle (issue 24)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from companion.cli import main
from companion.config import load_config
from companion.tools.eval.nav_calibration import calibration_fit
from companion.tools.eval.vio import EvaluationError
from drivers.mavlink.link import open_link
from drivers.sim.host import VehicleErrors, vehicle_errors
from drivers.sim.serve import SimulatedVehicle
from ports import free_tcp_port

#: Four made-up vehicles: the camera's yaw on the body (degrees), the accelerometer's z scale
#: error (fraction).
VEHICLES = {1: (-0.4, 0.005), 2: (-0.1, -0.002), 3: (0.2, 0.001), 4: (0.5, 0.003)}
BEARING_SLOPE, SCALE_SLOPE, SCALE_BIAS = -0.7, 0.6, -0.2  # per degree; per per cent; per cent
DISTANCE, HEIGHT = 50.0, 0.05


def _errors_of(seed: int) -> VehicleErrors:
    yaw, accel_z = VEHICLES[seed]
    return VehicleErrors((0.1, -0.1, yaw), (0.002, 0.002, accel_z))


def _records(spread: float = 0.05) -> list[dict]:
    """Two flights a vehicle whose bearing and scale follow the lines above, one ``spread``
    above and one below (degrees; per cent of scale), with their split and error."""
    records = []
    for seed, (yaw, accel_z) in VEHICLES.items():
        for depth, sign in (("gt", 1.0), ("estimated", -1.0)):
            bearing = BEARING_SLOPE * yaw + sign * spread
            scale = 1.0 + (SCALE_BIAS + SCALE_SLOPE * 100.0 * accel_z + sign * spread) / 100.0
            across = DISTANCE * math.sin(math.radians(bearing))
            along = DISTANCE * (scale - 1.0)
            records.append({
                "world": "dome", "pair": 0, "depth": depth, "index": 0, "seed": seed,
                "timeout_s": 120.0, "outcome": "success", "ended_early": False,
                "flight_time_s": 60.0, "path_length_m": 55.0,
                "position_error_m": math.hypot(across, along, HEIGHT),
                "position_error_split": {"distance_m": DISTANCE, "scale": scale,
                                         "bearing_deg": bearing, "along_m": along,
                                         "across_m": across, "height_m": HEIGHT,
                                         "start_m": 0.0}})
    return records


def test_the_fit_finds_what_the_calibration_explains_and_what_it_leaves():
    fit = calibration_fit(_records(), _errors_of)
    assert (fit["flights"], fit["vehicles"]) == (8, 4)
    bearing = fit["bearing_deg_on_mount_yaw_deg"]
    scale = fit["scale_error_pct_on_accel_z_error_pct"]
    assert bearing["slope"] == pytest.approx(BEARING_SLOPE, abs=1e-3)
    assert bearing["intercept"] == pytest.approx(0.0, abs=1e-3)
    assert scale["slope"] == pytest.approx(SCALE_SLOPE, abs=1e-3)
    assert scale["intercept"] == pytest.approx(SCALE_BIAS, abs=1e-3)
    assert (bearing["r_vehicles"], scale["r_vehicles"]) == pytest.approx((-1.0, 1.0))
    assert bearing["residual_sd"] == pytest.approx(0.05, abs=1e-3)  # the flights' own spread
    # taken out, the bearing is the spread alone and the scale its bias and spread
    for depth, sign in (("gt", 1.0), ("estimated", -1.0)):
        across = DISTANCE * math.sin(math.radians(sign * 0.05))
        along = DISTANCE * (SCALE_BIAS + sign * 0.05) / 100.0
        left = fit["end_error_m"][depth]["calibration_taken_out"]
        assert left["median"] == pytest.approx(math.hypot(across, along, HEIGHT), abs=1e-4)
        flown = [r["position_error_m"] for r in _records() if r["depth"] == depth]
        assert fit["end_error_m"][depth]["flown"]["worst"] == pytest.approx(max(flown), abs=1e-4)
    assert fit["vehicles_drawn"]["4"] == {"mount_yaw_deg": 0.5, "accel_z_scale_error_pct": 0.3}


def test_two_vehicles_give_no_correlation_of_their_means():
    two = [r for r in _records() if r["seed"] in (1, 2)]
    fit = calibration_fit(two, _errors_of)
    assert fit["vehicles"] == 2
    assert fit["bearing_deg_on_mount_yaw_deg"]["slope"] == pytest.approx(BEARING_SLOPE, abs=1e-3)
    assert fit["bearing_deg_on_mount_yaw_deg"]["r_vehicles"] is None  # two means: a line


NO_ERRORS = VehicleErrors((0.0,) * 3, (0.0,) * 3)


@pytest.mark.parametrize("records, errors_of, words", [
    (_records()[:2], _errors_of, "got 2 flights of 1 "),
    ([{**r, "position_error_split": None} for r in _records()], _errors_of,
     "got 0 flights of 0 "),
    # the ideal profile draws no errors, a vehicle seed one vehicle for every seed
    (_records(), lambda seed: NO_ERRORS, "got 8 flights of 1 .*give the runs' own --config"),
    (_records(), lambda seed: _errors_of(4), "got 8 flights of 1 "),
    ([{**r, "position_error_split": {"scale": 1.0}} for r in _records()], _errors_of,
     "dome pair 0 gt seed 1: its VINS error at the end lacks distance_m, bearing_deg"),
])
def test_what_cannot_be_fitted_is_refused(records, errors_of, words):
    with pytest.raises(EvaluationError, match=words):
        calibration_fit(records, errors_of)


def test_a_vehicles_errors_are_drawn_from_its_vehicle_seed():
    """The realistic profile's camera is 0.5 degrees off its configured mounting and PX4's
    calibration leaves each accelerometer axis a little off; a vehicle seed flies another
    seed's vehicle; the ideal profile has none."""
    realistic = load_config("config/sim-realistic.toml")
    errors = vehicle_errors(realistic, 12)
    assert np.linalg.norm(errors.mount_rotation_deg) == pytest.approx(
        realistic.sim_camera.mount_rotation_error_deg)
    assert 0.0 < max(abs(e) for e in errors.accel_scale_error) < 0.03
    assert vehicle_errors(realistic, 13) != errors
    kept = load_config("config/sim-realistic.toml", ["sim.vehicle_seed=12"])
    assert vehicle_errors(kept, 3) == errors
    assert vehicle_errors(load_config(None), 12) == VehicleErrors((0.0,) * 3, (0.0,) * 3)


def test_a_vehicles_accelerometer_is_the_one_its_flight_serves():
    """The errors are drawn as the simulated vehicle behind the mock PX4 draws its IMU."""
    config = load_config("config/sim-realistic.toml", ["sim.vehicle_seed=12"])
    link = open_link(f"udpout://127.0.0.1:{free_tcp_port()}", source_system=1,
                     source_component=1)  # the mock's link: nobody at the other end
    try:
        served = SimulatedVehicle(link, None, seed=config.sim.noise_for(3),
                                  vehicle_seed=config.sim.vehicle_for(3),
                                  imu_options=config.imu.for_profile(config.sim.profile))
    finally:
        link.close()
    np.testing.assert_allclose(np.diag(served.imu.accel_matrix) - 1.0,
                               vehicle_errors(config, 3).accel_scale_error, rtol=0, atol=1e-15)


def test_eval_nav_calibration_reads_runs_files(tmp_path, capsys):
    run = tmp_path / "run.jsonl"
    run.write_text("".join(json.dumps(r) + "\n" for r in _records()))
    args = ["eval", "nav", "--config", "config/sim-realistic.toml", "--calibration", str(run)]
    assert main(args + ["--json"]) == 0
    fit = json.loads(capsys.readouterr().out)
    realistic = load_config("config/sim-realistic.toml")
    assert fit == calibration_fit(_records(), lambda seed: vehicle_errors(realistic, seed))
    assert main(args) == 0
    assert "| gt | " in capsys.readouterr().out
    assert main(args + ["--trials", "2"]) == 2
    assert "--calibration flies nothing; drop --trials" in capsys.readouterr().err
    other = tmp_path / "other.jsonl"
    other.write_text("".join(json.dumps({**r, "seed": r["seed"] + 10, "config_hash": "abc"})
                             + "\n" for r in _records()))
    assert main(args + [str(other)]) == 1
    assert "the runs were flown with different configs (None, abc)" in capsys.readouterr().err
    assert main(args + [str(run)]) == 1
    assert "dome pair 0 gt seed 1 is in more than one record" in capsys.readouterr().err
    assert main(["eval", "nav", "--config", "config/sim.toml", "--calibration", str(run)]) == 1
    assert "give the runs' own --config and --set" in capsys.readouterr().err
