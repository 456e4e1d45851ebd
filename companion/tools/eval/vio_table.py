"""The VINS over simulated flights of every world at several seeds: issue 24's table, one command.

``companion eval vio-table`` records a ``duration``-second flight of each world from each seed,
as ``companion sim record --world W --seed S --duration D`` records it, the planner's speed and
height waves included (or reuses it from the
cache, :func:`~companion.tools.eval.rescale.cached_dataset`), runs the VINS over each with the
config's ``[vins]``, ``[vins_frontend]`` and ``[vins_init]`` (:func:`~companion.tools.eval.vio.
evaluate_vio`), the recordings side by side as tasks of an executor, and tabulates what issue 24
holds the estimator to on every recording: the trajectory error after SE(3) alignment over the
distance flown (ATE / distance ≤ :data:`GOAL_ATE_SHARE`), the map points' median relative depth
error (≤ :data:`GOAL_DEPTH_ERROR`) and no reset; beside them the path's scale (its spread over
the recordings is what an option worth adopting narrows, docs/vins.md), the median pose and
velocity NEES (honest: 6 and 3) and the bearing at the end.

Each row carries what scored it (the code's revision, the config's hash, the library versions:
:mod:`~companion.tools.eval.provenance`) and the flights' frame count; with ``--resume FILE``
every row is added to FILE as its recording is scored, and a run stopped part way goes on with
the recordings the file lacks, scored by the same code and config (:func:`resumed_rows`).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from autonomy.vins.frontend import FrontendOptions
from autonomy.vins.options import VinsOptions
from autonomy.vins.static_init import StaticInitOptions
from companion.config import Config
from companion.tools.eval import executor
from companion.tools.eval.records import parse_object
from companion.tools.eval.rescale import Recording, cached_dataset
from companion.tools.eval.vio import EvaluationError, evaluate_vio
from drivers.sim.options import WORLD_NAMES

#: Issue 24's goals for every recording: ATE over distance, map points' median depth error.
GOAL_ATE_SHARE = 0.005
GOAL_DEPTH_ERROR = 0.02
#: The table's seeds and flight length (issue 24: seeds 0-9, 40 s).
DEFAULT_SEEDS = tuple(range(10))
DEFAULT_DURATION_S = 40.0
#: A row's numbers: always given, and given where the recording has them (else null).
ROW_NUMBERS = ("frames", "distance_m", "ate_rmse_m", "ate_over_distance", "scale", "resets")
ROW_OPTIONAL_NUMBERS = ("depth_rel_err_median", "nees_pose_median", "nees_velocity_median",
                        "bearing_deg", "backend_ms_p95")
#: What scored a row (:func:`companion.tools.eval.provenance.stamp`).
STAMP_KEYS = ("revision", "config_hash", "libraries")


@dataclass(frozen=True)
class TableJob:
    """What every recording's task shares: the cache, the flights' frame count and how they
    are recorded, and the VINS's options (picklable: the task may run in another process)."""

    cache: Path
    frames: int
    recording: Recording
    vins: VinsOptions
    frontend: FrontendOptions
    static: StaticInitOptions

    @classmethod
    def of(cls, config: Config, cache: Path, duration_s: float) -> "TableJob":
        """The job of ``config``: its flights recorded as ``companion sim record`` records them
        in its profile (its camera, vehicle, IMU, camera sensor and the planner's waves), each
        ``duration_s`` long, in ``cache``, and scored with its VINS; EvaluationError for a
        duration that is not a positive number."""
        return cls(cache, frames_for(duration_s, config.camera.rate_hz),
                   Recording(config.camera, config.vehicle, config.imu,
                             config.sim_camera.for_profile(config.sim.profile),
                             *config.planner.waves),
                   config.vins, config.vins_frontend, config.vins_init)


def frames_for(duration_s: float, rate_hz: float) -> int:
    """Frames of a ``duration_s`` flight from t = 0 at ``rate_hz``: the recorder flies
    ``(frames - 1) / rate_hz`` seconds (:func:`~companion.tools.eval.rescale.cached_dataset`)."""
    if not (math.isfinite(duration_s) and duration_s > 0.0):
        raise EvaluationError(f"the flights' duration must be a positive number of seconds, "
                              f"got {duration_s}")
    return int(round(duration_s * rate_hz)) + 1


def settings_not_flown(config) -> list[str]:
    """The ``SECTION.KEY`` settings of ``config`` that ``sim record`` would fly and the table's
    recordings do not (:func:`~companion.tools.eval.rescale.cached_dataset` flies each seed's
    own vehicle and noise): the table refuses them rather than score a flight other than the
    one asked for. The planner's waves it flies, as ``sim record`` does."""
    set_ = {"sim.vehicle_seed": config.sim.vehicle_seed >= 0,
            "sim.noise_seed": config.sim.noise_seed >= 0}
    return [name for name, given in set_.items() if given]


def evaluate_table(worlds, seeds, *, job: TableJob, stamp: dict[str, str],
                   workers: int | None = None, cluster: str | None = None,
                   done: Sequence[dict] = (), on_row: Callable[[dict], None] | None = None) -> dict:
    """Score the VINS on every world's flight from every seed (:func:`score_recording`) and
    summarise them (:func:`summarise`): ``{"recordings": [row...], "summary": {group:
    {...}}, "goal_met": bool}``, the rows in the order of ``worlds`` then ``seeds``, each with
    ``stamp`` (what scores it) and the flights' frame count. ``done``: rows of this table
    scored before (a run resumed), not scored again (:func:`resumed_rows`); ``on_row`` is
    given each new row as its recording is scored."""
    items = [(world, seed) for world in dict.fromkeys(worlds) for seed in dict.fromkeys(seeds)]
    if not items:
        raise EvaluationError("no recording to score: give at least one world and one seed")
    rows = resumed_rows(done, items, stamp, job.frames)
    pending = [item for item in items if item not in rows]
    if pending:
        runner = executor.open_executor(cluster, workers, len(pending))
        for k, row in runner.run(score_recording, job, pending):
            rows[pending[k]] = row = {**row, **stamp, "frames": job.frames}
            if on_row is not None:
                on_row(row)
    return summarise([rows[item] for item in items if item in rows])


def resumed_rows(done: Sequence[dict], items: list[tuple[str, int]], stamp: dict[str, str],
                 frames: int) -> dict[tuple[str, int], dict]:
    """The rows of a run resumed, by ``(world, seed)``; EvaluationError for one this run
    would not score (another world or seed, another flight length, another code revision,
    config or library versions: ``stamp``) or one given twice, naming it."""
    rows: dict[tuple[str, int], dict] = {}
    for row in done:
        key = (row["world"], row["seed"])
        name = f"the row of {row['world']} seed {row['seed']}"
        if key in rows:
            raise EvaluationError(f"{name} is in the file twice")
        if key not in items:
            raise EvaluationError(f"{name} is not in this table; resume with the worlds and "
                                  "seeds the run was started with")
        if row["frames"] != frames:
            raise EvaluationError(f"{name} was scored on {row['frames']} frames, this run's "
                                  f"flights have {frames}: resume with its --duration")
        for key_name in STAMP_KEYS:
            if row.get(key_name) != stamp[key_name]:
                raise EvaluationError(
                    f"{name} was scored with another {key_name.replace('_', ' ')} "
                    f"({row.get(key_name)}, this run's {stamp[key_name]}): resume with the "
                    "code, config and libraries the run was started with, or start a new file")
        rows[key] = row
    return rows


def parse_row(line: str, where: str) -> dict:
    """One row of a ``--resume`` file (``where``: its file and line, for the error)."""
    row = parse_object(line, where, "table row")
    if row.get("world") not in WORLD_NAMES:
        raise EvaluationError(f"{where}: world {row.get('world')!r} is not one of "
                              f"{', '.join(WORLD_NAMES)}")
    if type(row.get("seed")) is not int or row["seed"] < 0:
        raise EvaluationError(f"{where}: seed must be a non-negative integer, "
                              f"got {row.get('seed')!r}")
    for key in ROW_NUMBERS + ROW_OPTIONAL_NUMBERS:
        value = row.get(key)
        given_as_null = key in ROW_OPTIONAL_NUMBERS and key in row and value is None
        if type(value) not in (int, float) and not given_as_null:
            raise EvaluationError(f"{where}: {key} must be a number, got {value!r}")
    return row


def score_recording(job: TableJob, item: tuple[str, int]) -> dict:
    """One recording's task: its flight from the cache of the machine it runs on (recorded
    there first if missing), scored by the VINS; the table's row."""
    world, seed = item
    root = cached_dataset(job.cache, world, seed, job.frames, job.recording)
    return table_row(world, seed, root,
                     evaluate_vio(root, job.vins, frontend=job.frontend, static=job.static))


def table_row(world: str, seed: int, root: Path, result: dict) -> dict:
    """The table's row of one recording from its ``eval vio`` ``result``."""
    split = result.get("end_split") or {}
    return {"world": world, "seed": seed, "dataset": str(root),
            "distance_m": result["distance_m"], "ate_rmse_m": result["ate_rmse_m"],
            "ate_over_distance": result["ate_over_distance"], "scale": result["scale"],
            "depth_rel_err_median": result["depth_rel_err_median"],
            "resets": result["resets"], "nees_pose_median": result["nees_pose_median"],
            "nees_velocity_median": result["nees_velocity_median"],
            "bearing_deg": split.get("bearing_deg"),
            "backend_ms_p95": result["backend_ms_p95"]}


def meets_goal(row: dict) -> dict[str, bool]:
    """Which of issue 24's goals one recording meets (a map with no scored point does not)."""
    depth = row["depth_rel_err_median"]
    return {"ate": row["ate_over_distance"] <= GOAL_ATE_SHARE,
            "depth": depth is not None and depth <= GOAL_DEPTH_ERROR,
            "no_reset": row["resets"] == 0}


def summarise(rows: list[dict]) -> dict:
    """The rows with their goals, each world's summary and all of them together."""
    for row in rows:
        row["goal"] = meets_goal(row)
    groups = {world: [r for r in rows if r["world"] == world]
              for world in dict.fromkeys(r["world"] for r in rows)}
    groups["all"] = rows
    summary = {name: _group_summary(members) for name, members in groups.items()}
    return {"recordings": rows, "summary": summary,
            "goal_met": all(all(r["goal"].values()) for r in rows)}


def _group_summary(rows: list[dict]) -> dict:
    ate = [r["ate_over_distance"] for r in rows]
    scales = [r["scale"] for r in rows]
    return {
        "recordings": len(rows),
        "ate_within_goal": sum(r["goal"]["ate"] for r in rows),
        "ate_over_distance_median": statistics.median(ate),
        "ate_over_distance_mean": statistics.fmean(ate),
        "ate_over_distance_worst": max(ate),
        "scale_sd": statistics.pstdev(scales),
        "depth_within_goal": sum(r["goal"]["depth"] for r in rows),
        "resets": sum(r["resets"] for r in rows),
        "nees_pose_median": _median(r["nees_pose_median"] for r in rows),
        "nees_velocity_median": _median(r["nees_velocity_median"] for r in rows),
        "bearing_abs_median_deg": _median(abs(r["bearing_deg"]) for r in rows
                                          if r["bearing_deg"] is not None),
    }


def _median(values) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def format_markdown(result: dict, *, duration_s: float) -> str:
    """The summary per world and over all, then every recording, as Markdown tables."""
    lines = [f"`eval vio` over {duration_s:g} s simulated flights; issue 24's goals on every "
             f"recording: ATE ≤ {GOAL_ATE_SHARE:.1%} of distance, map depth error ≤ "
             f"{GOAL_DEPTH_ERROR:.0%}, no reset: **{'met' if result['goal_met'] else 'not met'}"
             f"**.", "",
             "| recordings | n | ATE ≤ 0.5 % | median | mean | worst | SD of scale "
             "| map depth ≤ 2 % | resets | pose NEES | velocity NEES | \\|bearing\\| |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in result["summary"].items():
        lines.append(
            f"| {name} | {s['recordings']} | {s['ate_within_goal']} "
            f"| {s['ate_over_distance_median']:.2%} | {s['ate_over_distance_mean']:.2%} "
            f"| {s['ate_over_distance_worst']:.2%} | {s['scale_sd']:.4f} "
            f"| {s['depth_within_goal']} | {s['resets']} | {_number(s['nees_pose_median'], 0)} "
            f"| {_number(s['nees_velocity_median'], 1)} "
            f"| {_number(s['bearing_abs_median_deg'], 2, '°')} |")
    lines += ["", "| world | seed | distance | ATE | ATE / distance | scale | map depth error "
                  "| resets | pose NEES | bearing |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["recordings"]:
        depth = r["depth_rel_err_median"]
        lines.append(
            f"| {r['world']} | {r['seed']} | {r['distance_m']:.1f} m | {r['ate_rmse_m']:.3f} m "
            f"| {r['ate_over_distance']:.2%} | {r['scale']:.3f} "
            f"| {'—' if depth is None else f'{depth:.1%}'} | {r['resets']} "
            f"| {_number(r['nees_pose_median'], 0)} | {_number(r['bearing_deg'], 2, '°')} |")
    return "\n".join(lines)


def _number(value: float | None, digits: int, unit: str = "") -> str:
    return "—" if value is None else f"{value:.{digits}f}{unit}"
