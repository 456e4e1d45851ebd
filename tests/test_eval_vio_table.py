"""``companion eval vio-table``: issue 24's seeds table in one command
(companion/tools/eval/vio_table.py)."""

import dataclasses
import json

import numpy as np
import pytest

from autonomy.planning.height_wave import HeightWave
from companion.cli import main
from companion.config import Config
from companion.tools.eval import vio_table
from companion.tools.eval.rescale import Recording, cached_dataset, dataset_key
from companion.tools.eval.vio import EvaluationError
from drivers.dataset.euroc import read_groundtruth


def _row(world, seed, ate=0.003, depth=0.01, resets=0, scale=1.0, bearing=0.2):
    return {"world": world, "seed": seed, "dataset": f"/cache/{world}-{seed}",
            "distance_m": 36.0, "ate_rmse_m": ate * 36.0, "ate_over_distance": ate,
            "scale": scale, "depth_rel_err_median": depth, "resets": resets,
            "nees_pose_median": 30.0, "nees_velocity_median": 3.0, "bearing_deg": bearing,
            "backend_ms_p95": 11.0}


def test_the_goal_is_met_only_when_every_recording_meets_all_three():
    passing = [_row("mine", 0), _row("mine", 1, scale=1.01), _row("dome", 0, bearing=None)]
    result = vio_table.summarise(passing)
    assert result["goal_met"]
    assert result["summary"]["mine"]["recordings"] == 2
    assert result["summary"]["all"]["ate_within_goal"] == 3
    assert result["summary"]["mine"]["scale_sd"] == pytest.approx(0.005)
    assert result["summary"]["all"]["bearing_abs_median_deg"] == pytest.approx(0.2)
    for failing, goal in ((_row("sewer", 7, ate=0.0060), "ate"),
                          (_row("sewer", 7, depth=0.021), "depth"),
                          (_row("sewer", 7, depth=None), "depth"),
                          (_row("sewer", 7, resets=1), "no_reset")):
        result = vio_table.summarise([*passing, failing])
        assert not result["goal_met"]
        assert not result["recordings"][-1]["goal"][goal]
        assert result["summary"]["sewer"]["ate_within_goal"] == int(goal != "ate")


def test_the_report_gives_each_world_all_of_them_and_every_recording():
    result = vio_table.summarise([_row("mine", 0, ate=0.0052), _row("dome", 3, depth=None)])
    text = vio_table.format_markdown(result, duration_s=40.0)
    assert "**not met**" in text
    assert "| mine | 1 | 0 | 0.52% |" in text
    assert "| all | 2 | 1 |" in text
    assert "| dome | 3 | 36.0 m |" in text and "| — |" in text


def test_a_flights_frames_are_its_duration_at_the_camera_rate_from_t_zero():
    assert vio_table.frames_for(40.0, 20.0) == 801
    for duration in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(EvaluationError, match="duration"):
            vio_table.frames_for(duration, 20.0)


@pytest.mark.parametrize("setting", ["sim.vehicle_seed=4", "sim.noise_seed=1"])
def test_settings_the_tables_flights_would_not_follow_are_refused(setting, tmp_path, capsys):
    assert main(["eval", "vio-table", "--worlds", "dome", "--seeds", "0", "--cache",
                 str(tmp_path), "--set", setting]) == 2
    assert setting.split("=")[0] in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_the_table_records_each_seed_once_scores_it_and_reuses_it(tmp_path, capsys):
    """Two short realistic dome flights: every row scored, the recordings kept in the cache
    and reused by the next run, which gives the same numbers (but the back-end's time)."""
    command = ["eval", "vio-table", "--worlds", "dome", "--seeds", "0", "1", "--duration", "6",
               "--cache", str(tmp_path), "--workers", "1", "--json"]
    assert main(command) == 0
    first = json.loads(capsys.readouterr().out)
    assert [(r["world"], r["seed"]) for r in first["recordings"]] == [("dome", 0), ("dome", 1)]
    for row in first["recordings"]:
        assert 0.0 < row["ate_over_distance"] < 0.05 and row["resets"] == 0
        assert row["depth_rel_err_median"] is not None
    recorded = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    assert len(recorded) == 2
    assert main(command) == 0
    again = json.loads(capsys.readouterr().out)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == recorded
    untimed = [[{k: v for k, v in row.items() if k != "backend_ms_p95"}
                for row in run["recordings"]] for run in (first, again)]
    assert untimed[0] == untimed[1]


def test_the_tables_flights_fly_the_planners_height_wave_under_their_own_name(tmp_path):
    """A recording with the height wave is another dataset than the level one, and flies the
    wave as sim record does: 8 cm up and down at the end of a 12 s dome flight."""
    config = Config()
    small = dataclasses.replace(config.camera, width=160, height=120)
    level = Recording(small, config.vehicle, config.imu)
    waved = dataclasses.replace(level, height_wave=HeightWave(0.08, 2.0))
    frames = vio_table.frames_for(12.0, small.rate_hz)
    assert dataset_key("dome", 1, frames, waved) != dataset_key("dome", 1, frames, level)
    heights = read_groundtruth(cached_dataset(tmp_path, "dome", 1, frames, waved)).position
    assert np.ptp(heights[-800:, 2]) == pytest.approx(0.16, abs=0.03)
