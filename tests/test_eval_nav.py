"""`companion eval nav` (issue 7): navigation trials over worlds, pairs and seeds, on
ground-truth and on estimated depth, flown in parallel worker processes.

One run of the command, as a user runs it, is made once for the module: the shortest start/goal
pair of all worlds (the sewer's pair 3, 10.5 m straight across a room), one trial, both depth
sources side by side in two worker processes, every flight the real stack over MAVLink. The
other tests read its output or call the library's pure parts on made-up summaries; one flies
the same run again on a real two-node Ray cluster started on this machine (issue 26).
"""

from __future__ import annotations

import functools
import json
import math
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy
import pytest

from companion.cli import main
from companion.config import SIMULATOR_DEFAULTS, Config, load_config
from companion.tools import plot
from companion.tools.eval import executor, nav, nav_compare, provenance
from companion.tools.eval import records as eval_records
from companion.tools.eval.vio import EvaluationError
from drivers.sim.world import build_world
from ports import free_tcp_port

WORLD, PAIR = "sewer", 3  # a_far -> a_top: the shortest pair of the three worlds (seed 0)
KEYS = {"trials", "success", "collision", "timeout", "error", "mean_time_s", "mean_speed_mps",
        "least_clearance_m", "vins_error_median_m", "vins_error_worst_m"}


@pytest.fixture(scope="module")
def short_run(tmp_path_factory, opengl):
    """``(json, stderr, markdown, plot, runs)`` of one trial of the shortest pair, both depth
    sources in two workers."""
    out = tmp_path_factory.mktemp("nav")
    plot, markdown, runs = out / "nav.png", out / "nav.md", out / "runs.jsonl"
    run = _eval_nav_short("--workers", "2", "--plot", str(plot), "--markdown", str(markdown),
                          "--runs", str(runs))
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout), run.stderr, markdown.read_text(), plot, _lines(runs)


def _eval_nav_short(*options: str) -> subprocess.CompletedProcess:
    """``companion eval nav --json`` of one trial of the shortest pair, with ``options``."""
    return subprocess.run(
        [sys.executable, "-m", "companion", "eval", "nav", "--json", "--worlds", WORLD,
         "--pairs", str(PAIR), "--trials", "1", *options],
        capture_output=True, text=True, timeout=900)


def _lines(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


# ---------------------------------------------------------------- the command, flown

def test_stdout_is_the_json_shape_issue_7_gives_with_issue_26s_error_count(short_run):
    result, *_ = short_run
    assert list(result) == ["gt", "estimated"]
    for source in result.values():
        assert list(source) == [WORLD]
        numbers = source[WORLD]
        assert set(numbers) == KEYS
        assert numbers["trials"] == 1
        assert numbers["success"] + numbers["collision"] + numbers["timeout"] == 1
        assert numbers["error"] == 0
        assert numbers["mean_time_s"] is None or numbers["mean_time_s"] > 0


def test_the_ground_truth_depth_trial_reaches_its_goal_without_collision(short_run):
    result, _, _, _, records = short_run
    counts = {key: result["gt"][WORLD][key] for key in ("trials", *nav.OUTCOMES)}
    assert counts == {"trials": 1, "success": 1, "collision": 0, "timeout": 0, "error": 0}
    gt = next(r for r in records if r["depth"] == "gt")
    assert gt["reached_goal"] and gt["collisions"] == 0 and gt["failsafes"] == [], gt
    assert result["gt"][WORLD]["mean_time_s"] == gt["flight_time_s"]
    assert result["gt"][WORLD]["least_clearance_m"] == gt["min_clearance_m"] > 0
    assert result["gt"][WORLD]["vins_error_worst_m"] == gt["position_error_m"] >= 0
    # the record keeps that error split over the path flown (its parts add up to it)
    split = gt["position_error_split"]
    assert 0 < split["distance_m"] <= gt["path_length_m"]
    assert math.hypot(split["along_m"], split["across_m"], split["height_m"]) == pytest.approx(
        gt["position_error_m"], abs=1e-6)
    assert 0 < gt["time_to_goal_s"] < gt["flight_time_s"]


def test_every_trial_is_recorded_with_its_seed_and_counted_once(short_run):
    result, _, _, _, records = short_run
    assert [(r["depth"], r["world"], r["pair"], r["index"], r["seed"]) for r in records] == [
        ("gt", WORLD, PAIR, 0, nav.trial_seed(0, 0)),
        ("estimated", WORLD, PAIR, 0, nav.trial_seed(0, 0))]
    assert nav.summarise(records) == result
    start = build_world(WORLD, 0).routes[PAIR].start
    for record in records:
        assert record["outcome"] == nav.outcome(record)
        assert record["timeout_s"] == nav.TIMEOUT_S  # what a merge of parts checks
        assert record["start"] == pytest.approx(list(start), abs=0.01)  # the pair's own start
        assert record["path_length_m"] > 5.0  # it flew across the room


def test_progress_goes_to_stderr_as_trials_finish(short_run):
    _, stderr, *_ = short_run
    assert "2 trials on 2 worker processes" in stderr
    assert "1/2" in stderr and "2/2" in stderr
    assert f"last: {WORLD} pair {PAIR}" in stderr


def test_markdown_and_plot_are_written(short_run):
    _, _, markdown, plot, _ = short_run
    assert markdown.startswith("## Navigation in simulated flights (1 per start/goal pair")
    assert f"| {WORLD} | GT | 1 | 1 | 0 | 0 |" in markdown
    assert f"| {WORLD} | estimated | 1 |" in markdown
    image = cv2.imread(str(plot))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 200


# ---------------------------------------------------------------- the command's errors

@pytest.mark.parametrize("argv, words", [
    (["--worlds", "moon"], "invalid choice: 'moon'"),
    (["--trials", "0"], "expected a positive integer, got '0'"),
    (["--workers", "0"], "expected a positive integer, got '0'"),
    (["--plot", "nav.jpg"], "expected a .png file name"),
])
def test_bad_arguments_are_usage_errors_with_a_one_line_reason(capsys, argv, words):
    assert main(["eval", "nav", *argv]) == 2
    err = capsys.readouterr().err
    assert words in err.splitlines()[-1] and "Traceback" not in err


def test_a_pair_the_world_lacks_fails_with_one_line_before_any_flight(capsys):
    assert main(["eval", "nav", "--worlds", "dome", "mine", "--pairs", "0", "9"]) == 1
    captured = capsys.readouterr()
    assert captured.err.splitlines() == ["eval nav: dome has start/goal pairs 0..5, not 9"]
    assert captured.out == ""


@pytest.mark.parametrize("argv, expected", [
    ([], dict(worlds=["mine", "sewer", "dome"], pairs=None, trials=5, seed=0, timeout_s=120.0,
              workers=None, cluster=None)),
    (["--quick"], dict(worlds=["dome"], pairs=[0], trials=1)),
    (["--quick", "--worlds", "mine", "sewer", "--trials", "3"],
     dict(worlds=["mine"], pairs=[0], trials=1)),
    (["--seed", "4", "--set", "sim.seed=9", "--pairs", "2", "1", "--timeout", "60",
      "--workers", "3"], dict(pairs=[2, 1], seed=4, timeout_s=60.0, workers=3)),
    (["--cluster", "ray://10.0.0.2:10001"], dict(cluster="ray://10.0.0.2:10001", workers=None)),
    (["--set", "sim.seed=9"], dict(seed=9)),
])
def test_the_command_passes_its_options_to_the_library(monkeypatch, capsys, argv, expected):
    calls = []

    def evaluate(config, **kwargs):
        calls.append(kwargs)
        return nav.summarise([]), []
    monkeypatch.setattr(nav, "evaluate_navigation", evaluate)
    assert main(["eval", "nav", "--json", *argv]) == 0
    assert expected.items() <= calls[0].items()
    assert json.loads(capsys.readouterr().out) == {"gt": {}, "estimated": {}}


def test_a_realistic_evaluation_without_the_vehicles_estimates_says_so_once(monkeypatch,
                                                                             capsys):
    """The trials' workers log errors only, so the command warns once, before them, of a
    realistic vehicle flown without a real vehicle's estimates (the ideal defaults of
    config/sim.toml with the realistic profile); the preset, and the command's own defaults,
    fly without one."""
    monkeypatch.setattr(nav, "evaluate_navigation",
                        lambda config, **kwargs: (nav.summarise([]), []))
    config = Path(__file__).resolve().parent.parent / "config"
    assert main(["eval", "nav", "--json", "--config", str(config / "sim.toml"),
                 "--set", "sim.profile=realistic"]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warnings) == 1
    assert warnings[0].startswith("eval nav: warning: the realistic profile's vehicle is flown "
                                  "without estimating the camera's time offset")
    for argv in (["--config", str(config / "sim-realistic.toml")], []):
        assert main(["eval", "nav", "--json", *argv]) == 0
        assert "warning" not in capsys.readouterr().err


# ---------------------------------------------------------------- seeds and trials

def test_trial_k_flies_the_base_seed_plus_k():
    assert [nav.trial_seed(7, k) for k in range(4)] == [7, 8, 9, 10]
    assert nav.trial_seed(7, 2) == nav.trial_seed(7, 2)  # a pure function
    with pytest.raises(ValueError):
        nav.trial_seed(-1, 0)


def test_both_depth_sources_fly_the_same_seeds_of_every_pair():
    trials = nav.plan_trials(["dome", "sewer", "dome"], [1, 0, 1], 3, seed=5)
    assert len(trials) == 2 * 2 * 3 * 2  # worlds x pairs x trials x depth sources
    assert list(dict.fromkeys(t.world for t in trials)) == ["dome", "sewer"]
    for trial in trials:
        assert trial.seed == 5 + trial.index
    gt = [(t.world, t.pair, t.seed) for t in trials if t.depth == "gt"]
    assert gt == [(t.world, t.pair, t.seed) for t in trials if t.depth == "estimated"]
    mission = trials[1].mission()
    assert (mission.world, mission.pair, mission.seed, mission.depth, mission.clock) == (
        "dome", 1, 5, "estimated", "lockstep")
    assert trials[0].mission().depth == "truth"


def test_every_pair_by_default():
    trials = nav.plan_trials(["dome"], None, 1, seed=0)
    assert sorted({t.pair for t in trials}) == list(range(len(build_world("dome", 0).routes)))


def test_the_vins_flies_the_tracks_asked_for_the_trackers_by_default():
    assert {t.mission().tracks for t in nav.plan_trials(["dome"], [0], 2, seed=0)} == {"tracker"}
    truth = nav.plan_trials(["dome"], [0], 2, seed=0, tracks="truth")
    assert {t.mission().tracks for t in truth} == {"truth"}
    assert {nav.trial_record(t, _summary(), timeout_s=120.0)["tracks"] for t in truth} == {
        "truth"}


def test_truth_tracks_on_the_realistic_profile_are_refused_before_any_flight(monkeypatch):
    monkeypatch.setattr(nav, "run_trials", lambda *a, **k: pytest.fail("flew"))
    realistic = load_config(None, ["sim.profile=realistic"])
    with pytest.raises(EvaluationError, match="truth tracks need the ideal profile"):
        nav.evaluate_navigation(realistic, worlds=["dome"], pairs=[0], trials=1,
                                tracks="truth")
    with pytest.raises(EvaluationError, match="tracks must be one of"):
        nav.evaluate_navigation(Config(), worlds=["dome"], pairs=[0], trials=1,
                                tracks="oracle")


def test_eval_nav_tells_the_user_truth_tracks_need_the_ideal_config(capsys):
    assert main(["eval", "nav", "--quick", "--tracks", "truth"]) == 1
    assert "truth tracks need the ideal profile" in capsys.readouterr().err
    assert main(["eval", "nav", "--compare", "a.jsonl", "b.jsonl", "--tracks", "truth"]) == 2
    assert "--compare flies nothing; drop --tracks" in capsys.readouterr().err


def test_runs_on_different_tracks_do_not_merge_and_the_report_names_the_truths(tmp_path):
    truth = [{**r, "tracks": "truth"} for r in _flown_records(1, 1)]
    parts = [_write(tmp_path / "tracker.jsonl", _flown_records(0, 1)),
             _write(tmp_path / "truth.jsonl", truth)]
    with pytest.raises(EvaluationError, match=r"different track sources \(tracker, truth\)"):
        nav.read_runs(parts)
    records = nav.read_runs(parts[1:])
    assert "seed 1, 120 s to reach the goal, the VINS on truth tracks" in nav.format_markdown(
        nav.summarise(records), records)
    # a record from before the tracks were kept is the tracker's
    old = [{k: v for k, v in r.items() if k != "tracks"} for r in _flown_records(2, 1)]
    merged = nav.read_runs([_write(tmp_path / "old.jsonl", old), parts[0]])
    assert sorted({r["seed"] for r in merged}) == [0, 2] and len(merged) == 2 * len(old)


@pytest.mark.parametrize("kwargs, words", [
    (dict(worlds=["moon"]), "unknown world 'moon'"),
    (dict(worlds=[]), "no world"),
    (dict(trials=0), "trials must be at least 1"),
    (dict(pairs=[6]), "dome has start/goal pairs 0..5, not 6"),
])
def test_plan_trials_refuses_what_cannot_be_flown(kwargs, words):
    arguments = dict(worlds=["dome"], pairs=None, trials=1, seed=0) | kwargs
    with pytest.raises(EvaluationError, match=words):
        nav.plan_trials(**arguments)


def test_the_time_limit_is_the_applications_mission_timeout():
    config = nav.trial_config(Config(), 42.0)
    assert config.flight.mission_timeout_s == 42.0
    assert config.flight.goal_tolerance == Config().flight.goal_tolerance
    with pytest.raises(EvaluationError, match="positive"):
        nav.trial_config(Config(), 0.0)


def test_workers_must_be_at_least_one():
    with pytest.raises(EvaluationError, match="workers"):
        nav.run_trials(Config(), nav.plan_trials(["dome"], [0], 1, 0), workers=0)


# ---------------------------------------------------------------- outcomes and counts

def _summary(*, reached=False, collisions=0, failsafes=(), flight_time=30.0, path=20.0,
             clearance=1.2, vins_error=0.5):
    transitions = [{"t": 10.0, "from": "entering_offboard", "to": "navigating",
                    "reason": "Offboard"}]
    if reached:
        transitions.append({"t": 35.0, "from": "navigating", "to": "stopping",
                            "reason": "goal reached"})
    return {"reached_goal": reached, "collisions": collisions, "failsafes": list(failsafes),
            "final_state": "landed", "flight_time_s": flight_time, "navigation_time_s": 26.0,
            "path_length_m": path, "min_clearance_m": clearance, "closest_to_goal_m": 0.6,
            "position_error_m": vins_error, "transitions": transitions}


@pytest.mark.parametrize("summary, expected, early", [
    (_summary(reached=True), "success", False),
    (_summary(reached=True, collisions=1), "collision", False),
    (_summary(collisions=1, failsafes=["mission timeout"]), "collision", False),
    (_summary(failsafes=["mission timeout"]), "timeout", False),
    (_summary(failsafes=["no safe primitive"]), "timeout", True),
    (_summary(), "timeout", True),  # landed, but the truth did not confirm the goal
])
def test_outcome_of_a_trial(summary, expected, early):
    assert nav.outcome(summary) == expected
    assert nav.ended_early(summary) == early


def test_time_to_goal_counts_from_offboard():
    assert nav.time_to_goal(_summary(reached=True)) == 25.0
    assert nav.time_to_goal(_summary()) is None
    # the offset swing first (docs/flight.md, CALIBRATING): its time is the flight's too
    swung = _summary(reached=True)
    swung["transitions"][:1] = [
        {"t": 10.0, "from": "entering_offboard", "to": "calibrating",
         "reason": "Offboard; swinging in place until the camera's time offset is known"},
        {"t": 11.0, "from": "calibrating", "to": "navigating",
         "reason": "the camera's time offset known: 18.2 ms"}]
    assert nav.time_to_goal(swung) == 25.0


def _records():
    trial = nav.Trial("dome", 0, "estimated", 0, 0)
    summaries = [_summary(reached=True, flight_time=30.0, path=20.0, vins_error=0.2),
                 _summary(reached=True, flight_time=40.0, path=39.0, vins_error=0.4),
                 _summary(collisions=1, clearance=0.0, vins_error=0.3),
                 _summary(failsafes=["no safe primitive"], vins_error=2.5)]
    records = [nav.trial_record(nav.Trial("dome", 0, "gt", k, k), s, timeout_s=120.0)
               for k, s in enumerate(summaries)]
    timed_out = _summary(failsafes=["mission timeout"])
    return records + [nav.trial_record(trial, timed_out, timeout_s=120.0)]


def test_counts_and_the_numbers_of_the_issues_goals():
    """Mean time and speed (path over 26 s of navigation) of the successes; least clearance
    and the VINS error at the end (median, worst) of every trial."""
    result = nav.summarise(_records())
    assert result == {
        "gt": {"dome": {"trials": 4, "success": 2, "collision": 1, "timeout": 1, "error": 0,
                        "mean_time_s": 35.0, "mean_speed_mps": pytest.approx(59.0 / 52.0),
                        "least_clearance_m": 0.0, "vins_error_median_m": pytest.approx(0.35),
                        "vins_error_worst_m": 2.5}},
        "estimated": {"dome": {"trials": 1, "success": 0, "collision": 0, "timeout": 1,
                               "error": 0, "mean_time_s": None, "mean_speed_mps": None,
                               "least_clearance_m": 1.2, "vins_error_median_m": 0.5,
                               "vins_error_worst_m": 0.5}}}


def test_a_trial_that_raises_is_an_error_record_with_its_traceback_and_the_run_goes_on():
    """Pair 99 of the dome does not exist: the flight raises in its worker."""
    config = nav.trial_config(Config(), 30.0)
    broken = [nav.Trial("dome", 99, depth, 0, 0) for depth in nav.DEPTH_SOURCES]
    records = nav.run_trials(config, broken, workers=2)
    assert [r["outcome"] for r in records] == ["error", "error"]
    for record in records:
        assert record["traceback"].startswith("Traceback (most recent call last)")
        assert record["error"] == record["traceback"].strip().splitlines()[-1]
        assert "99" in record["error"] and record["flight_time_s"] is None
    result = nav.summarise(records)
    assert result["gt"]["dome"] == {"trials": 1, "success": 0, "collision": 0, "timeout": 0,
                                    "error": 1, "mean_time_s": None, "mean_speed_mps": None,
                                    "least_clearance_m": None, "vins_error_median_m": None,
                                    "vins_error_worst_m": None}
    assert "| dome | GT | 1 | 0 | 0 | 0 | 1 | 0 | 0% | n/a | n/a | n/a | n/a | n/a / n/a |" \
        in nav.format_markdown(result, records)
    assert nav.merge_records(records) == records  # an error is a result like the others


def test_markdown_counts_the_timeouts_that_ended_early():
    records = _records()
    text = nav.format_markdown(nav.summarise(records), records)
    assert "(1 to 4 per start/goal pair and depth source, seeds 0..3, 120 s to reach the goal)" \
        in text
    assert "| dome | GT | 4 | 2 | 1 | 1 | 0 | 1 | 50% | 35.0 | 29.5 | 1.13 | 0.00 | 0.35 / 2.50 |" \
        in text
    assert ("| dome | estimated | 1 | 0 | 0 | 1 | 0 | 0 | 0% | n/a | n/a | n/a | 1.20 | "
            "0.50 / 0.50 |") in text
    assert "**all**" not in text  # one world: its rows are the totals


def test_the_plot_is_a_png_with_a_bar_per_world_and_source(tmp_path):
    records = _records()
    out = nav.plot_navigation(nav.summarise(records), records, tmp_path / "deep" / "nav.png")
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] > 150
    assert (image != 255).any(axis=2).mean() > 0.02  # bars drawn, not a blank canvas
    with pytest.raises(ValueError, match="png"):
        nav.plot_navigation(nav.summarise(records), records, tmp_path / "nav.jpg")


def test_the_plots_bars_stack_each_outcomes_count_per_world_and_source():
    records = _flown_records(0, 2)
    records[0] = {**records[0], "outcome": "collision"}  # dome pair 0 GT seed 0
    records[-1] = {**records[-1], "outcome": "error"}  # sewer pair 1 estimated seed 1
    result = nav.summarise(records)
    axes = nav.navigation_figure(result, records).axes[0]
    order = [(world, source) for world in ("dome", "sewer") for source in ("gt", "estimated")]
    assert [c.get_label() for c in axes.containers] == list(nav.OUTCOMES)
    below = [0] * len(order)
    for name, bars in zip(nav.OUTCOMES, axes.containers):
        counts = [result[source][world][name] for world, source in order]
        assert [bar.get_height() for bar in bars] == counts, name
        assert [bar.get_y() for bar in bars] == below, name  # stacked on the outcomes before
        below = [b + n for b, n in zip(below, counts)]
    assert below == [4, 4, 4, 4]  # every trial counted once
    assert [t.get_text() for t in axes.get_xticklabels()] == ["GT", "estimated"] * 2
    assert [t.get_text() for t in axes.get_xticklabels(minor=True)] == ["dome", "sewer"]
    assert [t.get_text() for t in axes.get_legend().get_texts()] == list(nav.OUTCOMES)
    assert axes.get_ylabel() == "trials" and "higher success is better" in axes.get_title()
    means = [f"{result[source][world]['mean_time_s']:.0f} s" for world, source in order]
    assert set(means) <= {t.get_text() for t in axes.texts}  # the successes' mean time


def test_the_plots_caption_says_what_was_flown_and_by_which_code():
    records = [{**r, "revision": "abc123", "config_hash": "f00d"} for r in _flown_records(0, 2)]
    caption = plot.caption_of(nav.navigation_figure(nav.summarise(records), records))
    assert caption == ("Flown: 2 per start/goal pair and depth source, seeds 0..1, 120 s to "
                       "reach the goal; code revision abc123; config hash f00d.")
    records = _records()  # made before the records carried their provenance
    caption = plot.caption_of(nav.navigation_figure(nav.summarise(records), records))
    assert caption.endswith("; code revision none recorded; config hash none recorded.")


def test_progress_bar_counts_outcomes_one_line_per_update_off_a_terminal():
    import io

    stream = io.StringIO()
    bar = nav.ProgressBar(2, stream)
    bar.start(2, "2 worker processes")
    for record in _records()[:2]:
        bar.update(record)
    bar.finish()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "2 trials on 2 worker processes" and len(lines) == 3
    assert "\r" not in stream.getvalue()  # a log: one line per trial, nothing redrawn
    # tqdm's meter (share, count, elapsed<ETA), the outcomes, the trials in flight, the last
    assert lines[1].startswith(" 50%|") and " 1/2 [00:00<00:00, " in lines[1], lines[1]
    assert lines[1].endswith("success 1 collision 0 timeout 0 error 0, 1 running; "
                             "last: dome pair 0 gt #0 success")
    assert lines[2].startswith("100%|##########| 2/2 [") and "0 running" in lines[2]


def test_on_a_terminal_the_progress_bar_is_redrawn_in_place():
    import io

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    stream = Terminal()
    bar = nav.ProgressBar(2, stream)
    bar.start(1, "1 worker process")
    for record in _records()[:2]:
        bar.update(record)
    bar.finish()
    text = stream.getvalue()
    assert text.startswith("2 trials on 1 worker process\n")
    assert text.count("\n") == 2 and "\r" in text  # one line, redrawn, then closed
    assert "2/2 [" in text and "success 2 collision 0 timeout 0 error 0, 0 running" in text


# ---------------------------------------------------------------- runs flown in parts, merged

def _flown_records(seed: int, trials: int, *, pairs=(0, 1), timeout_s=120.0) -> list[dict]:
    """The records one run of ``--worlds dome sewer --pairs PAIRS --seed SEED --trials N``
    would write, every flight made up: the goal reached on odd seeds only."""
    return [nav.trial_record(trial, _summary(reached=trial.seed % 2 == 1,
                                             flight_time=30.0 + trial.seed),
                             timeout_s=timeout_s, wall_s=60.0)
            for trial in nav.plan_trials(["dome", "sewer"], pairs, trials, seed)]


def _write(path, records):
    return eval_records.write_records(records, path)


def test_parts_flown_one_seed_each_merge_into_the_records_of_one_run(tmp_path):
    parts = [_write(tmp_path / f"seed{s}.jsonl", _flown_records(s, 1)) for s in (2, 0, 1)]
    assert nav.read_runs(parts) == _flown_records(0, 3)
    by_world = [_write(tmp_path / f"{world}.jsonl",
                       [r for r in _flown_records(0, 3)[::-1] if r["world"] == world])
                for world in ("dome", "sewer")]
    assert nav.read_runs(by_world) == _flown_records(0, 3)


def test_the_merged_report_says_how_many_trials_of_which_seeds(tmp_path):
    parts = [_write(tmp_path / f"seed{s}.jsonl", _flown_records(s, 1)) for s in (4, 0, 1)]
    records = nav.read_runs(parts)
    text = nav.format_markdown(nav.summarise(records), records)
    assert "(3 per start/goal pair and depth source, seeds 0, 1, 4, 120 s to reach" in text
    assert "| dome | GT | 6 | 2 | 0 | 4 | 0 | 4 | 33% | 31.0 | 20.0 | 0.77 | 1.20 | 0.50 / 0.50 |" \
        in text
    # two worlds: each depth source's rows are followed by their totals
    assert "| **all** | GT | 12 | 4 | 0 | 8 | 0 | 8 | 33% | 31.0 | 20.0 | 0.77 |" in text
    assert text.index("| sewer | GT") < text.index("| **all** | GT") \
        < text.index("| dome | estimated")


def test_eval_nav_merge_reports_the_parts_as_one_run(tmp_path, capsys):
    parts = [_write(tmp_path / f"seed{s}.jsonl", _flown_records(s, 1)) for s in (0, 1)]
    merged, markdown = tmp_path / "merged.jsonl", tmp_path / "nav.md"
    assert main(["eval", "nav", "--json", "--merge", *map(str, parts), "--runs", str(merged),
                 "--markdown", str(markdown)]) == 0
    result = json.loads(capsys.readouterr().out)
    one_run = _flown_records(0, 2)
    assert result == nav.summarise(one_run)
    assert result["gt"]["sewer"] == {"trials": 4, "success": 2, "collision": 0, "timeout": 2,
                                     "error": 0, "mean_time_s": 31.0,
                                     "mean_speed_mps": pytest.approx(20.0 / 26.0),
                                     "least_clearance_m": 1.2, "vins_error_median_m": 0.5,
                                     "vins_error_worst_m": 0.5}
    assert [json.loads(line) for line in merged.read_text().splitlines()] == one_run
    assert "seeds 0..1" in markdown.read_text()


def _record_file(tmp_path, records, name="bad.jsonl"):
    return str(_write(tmp_path / name, records))


@pytest.mark.parametrize("make_files, words", [
    (lambda d: [_record_file(d, _flown_records(0, 1))] * 2,
     "dome pair 0 gt seed 0 is in more than one record"),
    (lambda d: [_record_file(d, _flown_records(0, 1)),
                _record_file(d, _flown_records(1, 1, timeout_s=60.0), "b.jsonl")],
     "the runs flew different time limits (60 s, 120 s)"),
    (lambda d: [_record_file(d, [r for r in _flown_records(0, 1)
                                 if (r["pair"], r["depth"]) != (1, "estimated")])],
     "dome pair 1 gt seed 0 has no estimated flight of the same seed"),
    (lambda d: [str(d / "absent.jsonl")], "absent.jsonl: cannot read"),
    (lambda d: [_record_file(d, [])], "bad.jsonl: no trial records"),
])
def test_parts_that_do_not_make_one_evaluation_fail_with_one_line(tmp_path, capsys,
                                                                  make_files, words):
    assert main(["eval", "nav", "--merge", *make_files(tmp_path)]) == 1
    captured = capsys.readouterr()
    assert len(captured.err.splitlines()) == 1 and words in captured.err
    assert captured.out == ""


@pytest.mark.parametrize("line, words", [
    ("{not json", "bad.jsonl:2: not JSON"),
    ("[1, 2]", "bad.jsonl:2: not a trial record"),
    ('{"world": "dome"}', "bad.jsonl:2: trial record without pair, depth, index, seed"),
])
def test_a_record_that_cannot_be_read_is_named_by_file_and_line(tmp_path, line, words):
    good = json.dumps(_flown_records(0, 1)[0])
    path = tmp_path / "bad.jsonl"
    path.write_text(f"{good}\n{line}\n")
    with pytest.raises(EvaluationError, match=words.replace("[", "\\[")):
        nav.read_runs([path])


@pytest.mark.parametrize("change, words", [
    (dict(world="moon"), "world 'moon' is not one of mine, sewer, dome"),
    (dict(outcome="crash"), "outcome 'crash' is not one of success, collision, timeout"),
    (dict(pair="2"), "pair must be a non-negative integer, got '2'"),
    (dict(seed=-1), "seed must be a non-negative integer, got -1"),
    (dict(timeout_s=None), "timeout_s must be a positive number of seconds, got None"),
    (dict(min_clearance_m="0.5"), "min_clearance_m must be a number or null, got '0.5'"),
    (dict(position_error_m=True), "position_error_m must be a number or null, got True"),
    (dict(outcome="success", path_length_m=None), "a success without path_length_m"),
])
def test_a_record_with_a_wrong_value_is_refused(tmp_path, change, words):
    path = _write(tmp_path / "bad.jsonl", [{**_flown_records(0, 1)[0], **change}])
    with pytest.raises(EvaluationError, match=f"bad.jsonl:1: {words}"):
        nav.read_runs([path])


def test_merge_flies_nothing_so_it_takes_no_flight_option(tmp_path, capsys):
    part = _write(tmp_path / "seed0.jsonl", _flown_records(0, 1))
    assert main(["eval", "nav", "--merge", str(part), "--trials", "5", "--quick"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == ["eval nav: --merge flies nothing; drop --trials, --quick"]


# ---------------------------------------------------------------- provenance and resuming

def test_every_record_carries_the_code_revision_and_the_config_hash(short_run):
    """The revision is a commit of this checkout (with the hash of any edit), so a record
    names the code that flew it; the tree may have moved on since, so it is not compared
    with the checkout's revision now."""
    *_, records = short_run
    flown = nav.trial_config(load_config(None, (), SIMULATOR_DEFAULTS), nav.TIMEOUT_S)
    for record in records:
        commit, _, edit = record["revision"].partition("+dirty.")
        assert len(commit) == 40 and set(commit + edit) <= set("0123456789abcdef")
        subprocess.run(["git", "-C", str(provenance.CHECKOUT), "cat-file", "-e",
                        commit + "^{commit}"], check=True)
        assert record["config_hash"] == provenance.config_hash(flown)
        assert record["libraries"] == provenance.library_versions()


def test_the_library_versions_name_each_flight_library_and_the_interpreter():
    versions = provenance.library_versions().split("; ")
    assert versions[0] == f"python {platform.python_version()}"
    assert f"numpy {numpy.__version__}" in versions
    # OpenCV is named by the wheel that installed it, whose version adds a build number to
    # OpenCV's own (5.1.0.95 for 5.1.0)
    opencv = [v for v in versions if v.startswith("opencv")]
    assert len(opencv) == 1 and opencv[0].split()[1].startswith(cv2.__version__)
    assert [v.split()[0] for v in versions if v.startswith(("gtsam", "onnxruntime", "moderngl"))] \
        == ["gtsam", "onnxruntime", "moderngl"]


def test_a_cluster_node_with_other_library_versions_refuses_the_task(monkeypatch):
    """The check each Ray task makes before flying (no cluster needed to call it; the
    worker's logging set-up left out, as it would reconfigure this process's)."""
    monkeypatch.setattr(executor, "_log_errors_only", lambda level: None)
    made_by = (provenance.code_revision(), provenance.library_versions())
    assert executor._checked_call(lambda shared, item: shared + item, 1, 2, made_by) == 3
    with pytest.raises(executor.ExecutorError, match="install the same versions on every node"):
        executor._checked_call(lambda shared, item: 0, None, None, (made_by[0], "python 0"))
    with pytest.raises(executor.ExecutorError, match="install the same code on every node"):
        executor._checked_call(lambda shared, item: 0, None, None, ("0" * 40, made_by[1]))


def test_the_revision_is_the_commit_and_names_an_uncommitted_edit(tmp_path):
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)
    assert provenance.code_revision(tmp_path) == provenance.UNKNOWN
    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", "code.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    head = subprocess.run(["git", "-C", str(tmp_path), "rev-parse", "HEAD"],
                          capture_output=True, text=True, check=True).stdout.strip()
    assert provenance.code_revision(tmp_path) == head
    (tmp_path / "code.py").write_text("x = 2\n")
    one_edit = provenance.code_revision(tmp_path)
    (tmp_path / "code.py").write_text("x = 3\n")
    other_edit = provenance.code_revision(tmp_path)
    assert one_edit.startswith(head + "+dirty.") and other_edit.startswith(head + "+dirty.")
    assert one_edit != other_edit


def test_the_config_hash_follows_the_config_not_how_it_was_written():
    assert provenance.config_hash(load_config(None, ["planner.speed=1.5"])) == \
        provenance.config_hash(load_config(None, ["planner.speed=1.0", "planner.speed=1.5"]))
    assert provenance.config_hash(load_config(None, [])) != \
        provenance.config_hash(load_config(None, ["planner.speed=1.5"]))


def _stamped(records, revision="abc", config_hash="123"):
    return [{**r, "revision": revision, "config_hash": config_hash} for r in records]


@pytest.mark.parametrize("parts, words", [
    ((_stamped(_flown_records(0, 1)), _stamped(_flown_records(1, 1), revision="def")),
     "different code revisions (abc, def)"),
    ((_stamped(_flown_records(0, 1)), _stamped(_flown_records(1, 1), config_hash="456")),
     "different configs (123, 456)"),
    ((_stamped(_flown_records(0, 1)), _flown_records(1, 1)),
     "different code revisions (abc, none recorded)"),
])
def test_parts_from_different_code_or_configs_are_not_merged(tmp_path, parts, words):
    files = [_write(tmp_path / f"part{k}.jsonl", records) for k, records in enumerate(parts)]
    with pytest.raises(EvaluationError, match=words.replace("(", "\\(").replace(")", "\\)")):
        nav.read_runs(files)
    assert nav.read_runs(files[:1])  # one part alone is one evaluation


def test_an_interrupted_runs_file_keeps_its_records_and_drops_only_a_torn_last_line(tmp_path):
    records = _stamped(_flown_records(0, 1))
    path = tmp_path / "runs.jsonl"
    for record in records[:3]:
        eval_records.append_record(record, path)
    read = functools.partial(eval_records.read_resumable, parse=nav.parse_record)
    assert read(path) == (records[:3], None)
    with open(path, "a") as stream:
        stream.write(json.dumps(records[3])[:40])  # the interruption, mid-line
    assert read(path) == (records[:3], f"{path}:4: a torn last record (the interruption) "
                                       "left out")
    path.write_text("{torn\n" + "".join(json.dumps(r) + "\n" for r in records[:2]))
    with pytest.raises(EvaluationError, match="runs.jsonl:1: not JSON"):
        read(path)
    assert read(tmp_path / "absent.jsonl") == ([], None)


def _resume_without_flying(monkeypatch, done, **options):
    """``evaluate_navigation`` of dome and sewer, pairs 0 and 1, seed 0, one trial, resumed
    from ``done``, with each trial "flown" as the made-up records say; what it flew too."""
    flown_now = []

    def fly(config, trials, *, provenance=None, on_record=None, **_):
        made_up = {(r["world"], r["pair"], r["depth"], r["seed"]): r
                   for r in _flown_records(0, 1)}
        records = [{**made_up[(t.world, t.pair, t.depth, t.seed)], **provenance}
                   for t in trials]
        flown_now.extend(records)
        for record in records:
            on_record(record)
        return records
    monkeypatch.setattr(nav, "run_trials", fly)
    appended = []
    result, records = nav.evaluate_navigation(
        Config(), worlds=["dome", "sewer"], pairs=[0, 1], trials=1, seed=0,
        done=done, on_record=appended.append, **options)
    return result, records, flown_now, appended


def test_a_resumed_run_flies_only_what_it_lacks_and_reports_the_whole(monkeypatch):
    stamp = provenance.stamp(nav.trial_config(Config(), nav.TIMEOUT_S))
    everything = [{**r, **stamp} for r in _flown_records(0, 1)]
    done = everything[:3]  # interrupted after three of eight trials
    result, records, flown_now, appended = _resume_without_flying(monkeypatch, done)
    assert records == everything and result == nav.summarise(everything)
    assert flown_now == everything[3:] == appended
    _, records, flown_now, _ = _resume_without_flying(monkeypatch, everything)
    assert records == everything and flown_now == []


@pytest.mark.parametrize("change, words", [
    (lambda done: [{**r, "revision": "0" * 40} for r in done], "different code revisions"),
    (lambda done: [{**r, "config_hash": "0" * 16} for r in done], "different configs"),
    (lambda done: [{**r, "libraries": "python 3.0"} for r in done], "different library versions"),
    (lambda done: [{**r, "tracks": "truth"} for r in done], "different track sources"),
    (lambda done: done + done[:1], "recorded more than once"),
    (lambda done: [{**done[0], "seed": 7}], "dome pair 0 gt seed 7 was flown but is not in "
                                            "this run's plan"),
])
def test_a_resume_that_does_not_continue_the_same_run_is_refused(monkeypatch, change, words):
    stamp = provenance.stamp(nav.trial_config(Config(), nav.TIMEOUT_S))
    done = [{**r, **stamp} for r in _flown_records(0, 1)[:2]]
    with pytest.raises(EvaluationError, match=words):
        _resume_without_flying(monkeypatch, change(done))


def test_a_runs_file_in_use_is_not_overwritten(tmp_path, capsys):
    runs = tmp_path / "runs.jsonl"
    runs.write_text(json.dumps(_flown_records(0, 1)[0]) + "\n")
    assert main(["eval", "nav", "--quick", "--runs", str(runs)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"eval nav: {runs} exists; --resume it, or choose a new --runs file"]
    assert main(["eval", "nav", "--quick", "--resume", str(runs), "--runs", str(runs)]) == 2
    assert "--resume adds to its own file; drop --runs" in capsys.readouterr().err


# ---------------------------------------------------------------- two runs compared

def _changed_run() -> list[dict]:
    """``_flown_records(0, 2)`` after a made-up change that touched only estimated depth:
    dome pair 0 seed 0 now reaches the goal, dome pair 1 seed 1 takes 0.8 of its time and
    passes 0.3 m from an obstacle, sewer pair 1 seed 1 collides."""
    def changed(record):
        trial = (record["world"], record["pair"], record["seed"])
        if record["depth"] != "estimated":
            return record
        if trial == ("dome", 0, 0):
            return {**record, "outcome": "success", "ended_early": False,
                    "time_to_goal_s": 40.0}
        if trial == ("dome", 1, 1):
            return {**record, "time_to_goal_s": 0.8 * record["time_to_goal_s"],
                    "flight_time_s": 26.0, "min_clearance_m": 0.3}
        if trial == ("sewer", 1, 1):
            return {**record, "outcome": "collision"}
        return record
    return [changed(r) for r in _flown_records(0, 2)]


def test_a_comparison_counts_what_changed_on_the_trials_both_runs_flew():
    comparison = nav_compare.compare_runs(_flown_records(0, 2), _changed_run())
    assert comparison["timeout_s"] == 120.0
    assert comparison["trials_only_before"] == comparison["trials_only_after"] == 0
    gt, estimated = comparison["sources"]["gt"], comparison["sources"]["estimated"]
    speed = pytest.approx(20.0 / 26.0)
    assert gt == {"trials": 8, "success": [4, 4], "collision": [0, 0],
                  "mean_speed_mps": [speed, speed], "least_clearance_m": [1.2, 1.2],
                  "vins_error_median_m": [0.5, 0.5], "identical": 8, "changed": [],
                  "time_ratio": {"median": 1.0, "min": 1.0, "max": 1.0, "trials": 4},
                  "vins_at_end": {"worst_m": [0.5, 0.5], "over_far": [0, 0], "long": [0, 0],
                                  "scale_off_median_pct": [None, None], "nearer": 0,
                                  "farther": 0, "sign_test_p": None,
                                  "change_median_m": 0.0, "seeds_nearer": 0,
                                  "seeds_farther": 0}}
    assert estimated["success"] == [4, 4] and estimated["collision"] == [0, 1]
    assert estimated["identical"] == 5
    assert estimated["changed"] == [
        {"trial": "dome pair 0 estimated seed 0", "before": "timeout", "after": "success"},
        {"trial": "sewer pair 1 estimated seed 1", "before": "success", "after": "collision"}]
    assert estimated["least_clearance_m"] == [1.2, 0.3]
    # of the three successes in both runs, one flew 0.8 of the time: the median is 1
    assert estimated["time_ratio"] == {"median": 1.0, "min": 0.8, "max": 1.0, "trials": 3}


def _ended(record: dict, error: float, scale: float | None) -> dict:
    split = None if scale is None else {"distance_m": 50.0, "scale": scale}
    return {**record, "position_error_m": error, "position_error_split": split}


def test_a_comparison_judges_the_vins_at_the_end_as_issue_24_does():
    """Worst, over 1 m, nearer and farther, paths made long and the median |scale - 1|, per
    run, on made-up errors at the end; a trial that raised has none and counts in neither."""
    before, after = _flown_records(1, 1), _flown_records(1, 1)  # 4 GT trials, 4 estimated
    gt = [i for i, r in enumerate(before) if r["depth"] == "gt"]
    for i, (b, a) in zip(gt, [((0.4, 1.01), (0.3, 0.995)), ((2.5, 0.95), (0.9, 1.02)),
                              ((0.6, None), (0.7, 1.03)), ((0.2, 1.002), (0.2, 1.002))]):
        before[i], after[i] = _ended(before[i], *b), _ended(after[i], *a)
    after[gt[3]] = nav.error_record(
        nav.Trial(**{k: after[gt[3]][k] for k in ("world", "pair", "depth", "index", "seed")}),
        "Traceback\nValueError: no such pair", timeout_s=120.0)
    end = nav_compare.compare_runs(before, after)["sources"]["gt"]["vins_at_end"]
    assert end["worst_m"] == [2.5, 0.9] and end["over_far"] == [1, 0]
    assert (end["nearer"], end["farther"]) == (2, 1)  # the trial that raised: neither
    assert end["long"] == [2, 2]  # 1.01, 1.002 before; 1.02, 1.03 after
    # |scale - 1| before 1.0, 5.0, 0.2 %; after 0.5, 2.0, 3.0 %
    assert end["scale_off_median_pct"] == [pytest.approx(1.0), pytest.approx(2.0)]


def _gt_errors_changed(after_errors: dict[int, list[float]]):
    """``_flown_records(0, 2)``'s GT trials ending 1 m off before, and after as given by seed
    (seeds 0 and 1, four trials each, in the run's order)."""
    before = [_ended(r, 1.0, None) if r["depth"] == "gt" else r for r in _flown_records(0, 2)]
    errors = {seed: iter(values) for seed, values in after_errors.items()}
    after = [_ended(r, next(errors[r["seed"]]), None) if r["depth"] == "gt" else r
             for r in before]
    return nav_compare.compare_runs(before, after)["sources"]["gt"]["vins_at_end"]


def test_a_comparison_weighs_the_nearer_trials_against_a_coin_and_counts_seeds():
    """The sign test's p, the median change and the seeds nearer, on made-up errors: seed 0
    nearer on three trials of four, seed 1 farther on two, one trial unchanged."""
    end = _gt_errors_changed({0: [0.5, 0.6, 0.7, 1.5], 1: [1.2, 1.3, 0.9, 1.0]})
    assert (end["nearer"], end["farther"]) == (4, 3)
    assert end["sign_test_p"] == pytest.approx(1.0)  # 4 of 7: no evidence either way
    # changes -0.5 -0.4 -0.3 -0.1 0 +0.2 +0.3 +0.5; seed 0's median -0.35, seed 1's +0.1
    assert end["change_median_m"] == pytest.approx(-0.05)
    assert (end["seeds_nearer"], end["seeds_farther"]) == (1, 1)
    every = _gt_errors_changed({0: [0.9] * 4, 1: [0.8] * 4})
    assert every["sign_test_p"] == pytest.approx(2 / 2 ** 8)  # 8 of 8 nearer, two-sided
    assert (every["seeds_nearer"], every["seeds_farther"]) == (2, 0)


def test_a_run_compared_with_itself_is_identical_but_for_the_trials_that_raised():
    run = _flown_records(0, 2)
    run[0] = nav.error_record(nav.Trial(**{k: run[0][k] for k in
                                           ("world", "pair", "depth", "index", "seed")}),
                              "Traceback\nValueError: no such pair", timeout_s=120.0)
    comparison = nav_compare.compare_runs(run, run)
    assert comparison["sources"]["gt"]["identical"] == 7  # an error flew nothing to compare
    assert comparison["sources"]["estimated"]["identical"] == 8
    assert comparison["sources"]["estimated"]["time_ratio"]["median"] == 1.0


@pytest.mark.parametrize("key", ["time_to_goal_s", "navigation_time_s", "position_error_m"])
def test_a_flight_that_differs_in_any_of_its_numbers_is_not_identical(key):
    after = _flown_records(1, 1)  # seed 1: every trial reaches the goal
    after[1] = {**after[1], key: after[1][key] + 0.01}
    comparison = nav_compare.compare_runs(_flown_records(1, 1), after)
    assert comparison["sources"]["estimated"]["identical"] == 3  # of 4
    assert comparison["sources"]["gt"]["identical"] == 4


def test_an_interrupted_run_is_compared_on_the_trials_it_flew():
    interrupted = _changed_run()[:5]
    comparison = nav_compare.compare_runs(_flown_records(0, 2), interrupted)
    assert (comparison["trials_only_before"], comparison["trials_only_after"]) == (11, 0)
    assert comparison["sources"]["gt"]["trials"] == 3
    assert comparison["sources"]["estimated"]["changed"] == [
        {"trial": "dome pair 0 estimated seed 0", "before": "timeout", "after": "success"}]


def test_eval_nav_compare_reports_the_comparison_of_two_runs_files(tmp_path, capsys):
    before = _write(tmp_path / "before.jsonl", _flown_records(0, 2))
    after = _write(tmp_path / "after.jsonl", _changed_run())
    markdown = tmp_path / "compare.md"
    assert main(["eval", "nav", "--compare", str(before), str(after), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == nav_compare.compare_runs(
        _flown_records(0, 2), _changed_run())
    assert main(["eval", "nav", "--compare", str(before), str(after),
                 "--markdown", str(markdown)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"## Navigation runs compared: {before} → {after}")
    assert ("| estimated | 8 | 5 | 4 → 4 | 0 → 1 | 0.77 → 0.77 | 1.20 → 0.30 | 0.50 → 0.50 | "
            "1.00 | 0.80–1.00 | 3 |") in text
    assert ("| estimated | 0.50 → 0.50 | 0.50 → 0.50 | 0 → 0 | 0 | 0 | n/a | +0.00 | 0 | 0 | "
            "0 → 0 | n/a → n/a |") in text
    assert "- sewer pair 1 estimated seed 1: success → collision" in text
    assert markdown.read_text() == text


def test_pairs_of_runs_of_two_revisions_pool_into_the_comparison_of_one_pair(tmp_path, capsys):
    """An arm weighed over seeds flown in two sessions (each pair of runs by one revision, on
    one host): each pair is matched on its own trials, and the pool is the comparison the
    whole runs would give, the sign test over all of them."""
    def seed(records, number):
        return [r for r in records if r["seed"] == number]

    before, after = _flown_records(0, 2), _changed_run()
    pooled = nav_compare.compare_runs(seed(before, 0), seed(after, 0),
                                      also=[(seed(before, 1), seed(after, 1))])
    assert pooled == nav_compare.compare_runs(before, after)
    files = [_record_file(tmp_path, _stamped(seed(run, number), revision=revision),
                          f"{name}{number}.jsonl")
             for number, revision in ((0, "abc"), (1, "def"))
             for run, name in ((before, "before"), (after, "after"))]
    assert main(["eval", "nav", "--compare", *files, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == pooled
    assert main(["eval", "nav", "--compare", *files]) == 0
    assert capsys.readouterr().out.startswith(
        f"## Navigation runs compared: {files[0]} → {files[1]}; {files[2]} → {files[3]}")


def test_a_trial_in_two_pooled_pairs_is_refused():
    run = _flown_records(0, 1)
    with pytest.raises(EvaluationError, match="dome pair 0 gt seed 0 is in two of the pairs"):
        nav_compare.compare_runs(run, run, also=[(run, run)])


@pytest.mark.parametrize("make_args, code, words", [
    (lambda d, run: ["--compare", run, run, run], 2,
     "eval nav: --compare takes runs in pairs, BEFORE AFTER [BEFORE AFTER ...]; got 3"),
    (lambda d, run: ["--compare", run, run, run, _record_file(d, _flown_records(1, 1))], 1,
     "eval nav: no trial is in both runs (other worlds, pairs or seeds?)"),
    (lambda d, run: ["--compare", run, run, "--trials", "5", "--runs", str(d / "x.jsonl")],
     2, "eval nav: --compare flies nothing; drop --trials, --runs"),
    (lambda d, run: ["--compare", run, run, "--merge", run],
     2, "eval nav: --compare flies nothing; drop --merge"),
    (lambda d, run: ["--compare", run, str(d / "absent.jsonl")], 1, "absent.jsonl: cannot read"),
    (lambda d, run: ["--compare", run, _record_file(d, _flown_records(1, 1))], 1,
     "eval nav: no trial is in both runs (other worlds, pairs or seeds?)"),
    (lambda d, run: ["--compare", run, _record_file(d, _flown_records(0, 1, timeout_s=60.0))],
     1, "the runs flew different time limits (60 s, 120 s); compare runs of one --timeout"),
    (lambda d, run: ["--compare", _record_file(d, _flown_records(0, 1) * 2), run], 1,
     "bad.jsonl: dome pair 0 gt seed 0 is in more than one record"),
    (lambda d, run: ["--compare", run, _record_file(
        d, _stamped(_flown_records(0, 1)) + _stamped(_flown_records(1, 1), revision="def"))],
     1, "bad.jsonl: the records come from different code revisions (abc, def)"),
])
def test_a_comparison_that_cannot_be_made_fails_with_one_line(tmp_path, capsys, make_args,
                                                              code, words):
    run = str(_write(tmp_path / "run.jsonl", _flown_records(0, 1)))
    assert main(["eval", "nav", *make_args(tmp_path, run)]) == code
    captured = capsys.readouterr()
    assert len(captured.err.splitlines()) == 1 and words in captured.err
    assert captured.out == ""


# ---------------------------------------------------------------- on a Ray cluster

RAY = str(Path(sys.executable).parent / "ray")
NODE_START_S = 120.0


class Node:
    """One ``ray start --block`` in a session of its own: every process of the node (its
    raylet, and the worker processes, which Ray puts in process groups of their own) stays in
    that session."""

    def __init__(self, *args: str, env: dict):
        self.process = subprocess.Popen([RAY, "start", "--block", "--num-cpus", "1",
                                         "--object-store-memory", str(100 * 2**20),
                                         "--disable-usage-stats", *args],
                                        env=env, start_new_session=True,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def processes(self, name: str = "") -> list[int]:
        """PIDs of this node's processes whose command line contains ``name``."""
        return [pid for pid, session, command in _processes()
                if session == self.process.pid and name in command]

    def stop(self) -> None:
        for pid in self.processes():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.process.wait(timeout=30)


def _processes():
    """(pid, session, command line) of every process readable in /proc."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except (OSError, IndexError):
                continue
            yield int(entry.name), int(fields[3]), command


@pytest.fixture(scope="module")
def cluster():
    """A head and a worker node on this machine, one CPU each, each in its own session (so
    that the module stops exactly its own cluster, and a node can be killed alone), their
    workers at the normal priority (Ray's default niceness 15 starves them on a host as busy
    as the test suite makes it); yields ``(address, worker node)``."""
    pytest.importorskip("ray", reason="ray (extra companion[cluster]) not installed")
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # Ray's socket paths must stay short
    port = free_tcp_port()
    env = {**os.environ, "RAY_worker_niceness": "0", "RAY_USAGE_STATS_ENABLED": "0"}
    head = Node("--head", "--port", str(port), "--temp-dir", temp,
                "--include-dashboard", "false", env=env)
    worker = Node("--address", f"127.0.0.1:{port}", env=env)
    try:
        _wait_for_nodes(f"127.0.0.1:{port}", 2)
        yield f"127.0.0.1:{port}", worker
    finally:
        worker.stop()
        head.stop()
        shutil.rmtree(temp, ignore_errors=True)


def _wait_for_nodes(address: str, count: int) -> None:
    deadline = time.monotonic() + NODE_START_S
    script = ("import ray; ray.init(address=%r, logging_level='ERROR'); "
              "print(sum(n['Alive'] for n in ray.nodes()))" % address)
    while time.monotonic() < deadline:
        alive = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        if alive.returncode == 0 and alive.stdout.strip() == str(count):
            return
        time.sleep(1.0)
    pytest.fail(f"the Ray cluster at {address} did not reach {count} nodes")


def test_a_ray_cluster_losing_a_node_mid_run_flies_exactly_the_local_records(
        short_run, cluster, tmp_path):
    """``--cluster`` with the worker node's raylet killed while it flies a trial: Ray flies
    that trial again on the head, and the run ends with every record as the local pool flew
    it (the wall time aside)."""
    address, worker = cluster
    killed = threading.Event()

    def kill_when_flying():
        deadline = time.monotonic() + NODE_START_S
        while time.monotonic() < deadline and not worker.processes("ray::_checked_call"):
            time.sleep(0.2)
        for pid in worker.processes("raylet/raylet"):
            os.kill(pid, signal.SIGKILL)
            killed.set()

    killer = threading.Thread(target=kill_when_flying, daemon=True)
    killer.start()
    runs = tmp_path / "runs.jsonl"
    run = _eval_nav_short("--cluster", address, "--runs", str(runs))
    killer.join(timeout=5)
    assert run.returncode == 0, run.stderr
    assert killed.is_set(), "the worker node never flew a trial"
    assert f"2 trials on the Ray cluster at {address} (2 CPUs)" in run.stderr
    local = short_run[4]
    assert [_without_wall_time(r) for r in _lines(runs)] == \
        [_without_wall_time(r) for r in local]
    assert json.loads(run.stdout) == short_run[0]


def _without_wall_time(record: dict) -> dict:
    """A record without its wall time, the one field that depends on the machine."""
    return {k: v for k, v in record.items() if k != "wall_s"}


@pytest.mark.parametrize("address, words", [
    ("127.0.0.1:{free}", "cannot reach the Ray cluster at 127.0.0.1:"),
    ("ray://127.0.0.1:{free}", "cannot reach the Ray cluster at ray://127.0.0.1:"),
    ("no-port-here", "a Ray cluster address is auto, HOST:PORT or ray://HOST:PORT")])
def test_a_cluster_address_nothing_answers_at_fails_at_once(capsys, address, words):
    """Said before ray.init, which retries an address nothing answers at for minutes (the
    message is this check's, not Ray's): nothing listens on a free port."""
    pytest.importorskip("ray", reason="ray (extra companion[cluster]) not installed")
    assert main(["eval", "nav", "--quick", "--cluster", address.format(free=free_tcp_port())]) == 1
    assert words in capsys.readouterr().err.splitlines()[-1]


def test_a_cluster_without_ray_fails_in_one_line_naming_the_extra(monkeypatch):
    trials = nav.plan_trials(["dome"], [0], 1, 0)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra were not installed
    with pytest.raises(EvaluationError, match=r"pip install 'companion\[cluster\]'"):
        nav.run_trials(Config(), trials, cluster="auto")
    with pytest.raises(EvaluationError, match="--workers sizes the local pool"):
        nav.run_trials(Config(), trials, cluster="auto", workers=2)


_ORPHAN_SCRIPT = '''
import os, sys, time
from companion.tools.eval.executor import LocalPool

def wait(folder, item):
    open(os.path.join(folder, str(os.getpid())), "w").close()
    time.sleep(120)
    return item

if __name__ == "__main__":
    for _ in LocalPool(2).run(wait, sys.argv[1], [0, 1]):
        pass
'''


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie left for its reaper is not)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_local_workers_end_with_a_run_killed_without_clean_up(tmp_path):
    """A run stopped by SIGKILL (or SIGTERM, neither runs a finally) leaves its workers in
    the middle of a task; each ends itself within a second or two, not when its task ends."""
    script, started = tmp_path / "run.py", tmp_path / "started"
    script.write_text(_ORPHAN_SCRIPT)
    started.mkdir()
    run = subprocess.Popen([sys.executable, str(script), str(started)],
                           env={**os.environ, "PYTHONPATH": str(provenance.CHECKOUT)})
    try:
        deadline = time.monotonic() + 90
        while len(list(started.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        workers = [int(p.name) for p in started.iterdir()]
        assert len(workers) == 2 and all(_running(pid) for pid in workers)
        run.kill()
        run.wait()
        deadline = time.monotonic() + 10
        while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_running(pid) for pid in workers)
    finally:
        run.kill()
        for pid in [int(p.name) for p in started.iterdir()]:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
