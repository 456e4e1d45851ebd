"""``companion eval vio-table``: issue 24's seeds table in one command
(companion/tools/eval/vio_table.py)."""

import dataclasses
import json
from pathlib import Path

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


def test_the_table_records_each_seed_once_scores_it_resumes_and_reuses_it(tmp_path, capsys):
    """Two short realistic dome flights. A run stopped after seed 0 (its row kept in the
    --resume file, then a line torn by the interruption) goes on with seed 1 alone, and not
    with another config; a new run reuses the recordings kept in the cache and gives the same
    numbers (but the back-end's time)."""
    cache, rows = tmp_path / "cache", tmp_path / "rows.jsonl"
    command = ["eval", "vio-table", "--worlds", "dome", "--duration", "6", "--cache",
               str(cache), "--workers", "1", "--json"]
    assert main([*command, "--seeds", "0", "--resume", str(rows)]) == 0
    stopped = json.loads(capsys.readouterr().out)["recordings"]
    assert main([*command, "--seeds", "0", "1", "--resume", str(rows), "--set",
                 "vins.extra_iterations=1"]) == 1
    assert "another config hash" in capsys.readouterr().err
    with open(rows, "a") as stream:
        stream.write('{"world": "dome", "se')  # the interruption, mid-line
    assert main([*command, "--seeds", "0", "1", "--resume", str(rows)]) == 0
    out = capsys.readouterr()
    assert "a torn last record" in out.err
    first = json.loads(out.out)
    assert [(r["world"], r["seed"]) for r in first["recordings"]] == [("dome", 0), ("dome", 1)]
    assert first["recordings"][0] == stopped[0]  # read back, not scored again
    kept = [json.loads(line) for line in rows.read_text().splitlines()]
    assert kept == [{k: v for k, v in row.items() if k != "goal"}
                    for row in first["recordings"]]
    for row in first["recordings"]:
        assert 0.0 < row["ate_over_distance"] < 0.05 and row["resets"] == 0
        assert row["depth_rel_err_median"] is not None
        assert row["frames"] == 121 and len(row["config_hash"]) == 16
    recorded = {p.name: p.stat().st_mtime_ns for p in cache.iterdir()}
    assert len(recorded) == 2
    assert main([*command, "--seeds", "0", "1"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert {p.name: p.stat().st_mtime_ns for p in cache.iterdir()} == recorded
    untimed = [[{k: v for k, v in row.items() if k != "backend_ms_p95"}
                for row in run["recordings"]] for run in (first, again)]
    assert untimed[0] == untimed[1]


def _job(frames=121):
    config = Config()
    return vio_table.TableJob(Path("/nonexistent"), frames, Recording(
        config.camera, config.vehicle, config.imu), config.vins, config.vins_frontend,
        config.vins_init)


STAMP = {"revision": "abc", "config_hash": "0123456789abcdef", "libraries": "python 3.11"}


@pytest.mark.parametrize("row, words", [
    ({**_row("mine", 0), **STAMP, "frames": 121}, "mine seed 0 is not in this table"),
    ({**_row("dome", 0), **STAMP, "frames": 801}, "scored on 801 frames"),
    ({**_row("dome", 0), **STAMP, "frames": 121, "revision": "def"}, "another revision"),
    ({**_row("dome", 0), **STAMP, "frames": 121, "libraries": "x"}, "another libraries"),
])
def test_a_resumed_row_this_run_would_not_score_is_refused_before_scoring(row, words):
    with pytest.raises(EvaluationError, match=words):
        vio_table.evaluate_table(["dome"], [0, 1], job=_job(), stamp=STAMP, done=[row])


def test_a_row_twice_in_the_file_is_refused():
    row = {**_row("dome", 0), **STAMP, "frames": 121}
    with pytest.raises(EvaluationError, match="dome seed 0 is in the file twice"):
        vio_table.evaluate_table(["dome"], [0, 1], job=_job(), stamp=STAMP, done=[row, row])


def test_a_table_resumed_with_every_row_scores_nothing_and_reports_them_all():
    done = [{**_row("dome", seed), **STAMP, "frames": 121} for seed in (0, 1)]
    result = vio_table.evaluate_table(["dome"], [0, 1], job=_job(), stamp=STAMP, done=done)
    assert [r["seed"] for r in result["recordings"]] == [0, 1] and result["goal_met"]


@pytest.mark.parametrize("line, words", [
    ("[1]", "rows.jsonl:3: not a table row"),
    ('{"world": "moon", "seed": 0}', "world 'moon'"),
    ('{"world": "dome", "seed": -1}', "seed must be a non-negative integer"),
    (json.dumps({k: v for k, v in _row("dome", 0).items() if k != "scale"} | {"frames": 1}),
     "scale must be a number, got None"),
    (json.dumps(_row("dome", 0) | {"frames": "121"}), "frames must be a number"),
])
def test_a_bad_row_is_named_by_its_file_and_line(line, words):
    with pytest.raises(EvaluationError, match=words):
        vio_table.parse_row(line, "rows.jsonl:3")


def test_a_row_may_lack_what_its_recording_did_not_give():
    row = _row("dome", 0, depth=None, bearing=None) | {"frames": 121}
    assert vio_table.parse_row(json.dumps(row), "rows.jsonl:1") == row


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
