"""Every rescaling method on simulated flights, behind ``companion eval rescale`` (issue 7).

The paper's Table I (Yang, Tian, Goel, Tabib, Section IV) compares the rescaling methods in
three worlds, each method anchored twice: on the ground-truth depth at the VINS feature pixels
("GT") and on the VINS map's own depth ("VINS"). Here, per world:

1. a simulator flight is recorded as a EuRoC dataset with ``depth0`` (:func:`cached_dataset`),
   or reused from the cache, keyed by world, seed, frame count and the recording's options;
2. the VINS and the depth network (the synthetic stand-in, or the user's model) run once over
   its frames, as in flight;
3. at every frame with a sparse map, the anchors are the landmarks the metric depth stage would
   use (:meth:`~autonomy.depth.stage.MetricDepthStage.anchors`): their relative disparity x,
   and as metric depth either the landmark's VINS depth z or the ground truth z* at its pixel;
4. every method of :data:`~autonomy.depth.rescale.METHODS` is fitted on both anchor sets and,
   where all of them fit, each depth image is scored against ``depth0``
   (:func:`autonomy.depth.metrics.evaluate`).

So every number of a world is over the same frames, a paired comparison: a frame where one
fit fails (too few anchors, say: early in a flight, where the few anchors span a narrow depth
range and a fit that succeeds extrapolates badly) would otherwise count for some rows and not
others. Per world a metric is the mean over the frames scored, each frame weighing the same;
the weighted average over worlds weighs world w by its frames n_w: m = Σ n_w m_w / Σ n_w.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from autonomy.depth import metrics
from autonomy.depth.anchors import sample_nearest_surface
from autonomy.depth.rescale import METHODS, RescaleOptions, fit
from autonomy.depth.stage import MetricDepthStage, check_relative_disparity
from autonomy.messages import SparseMap
from autonomy.planning.height_wave import HeightWave
from autonomy.planning.speed_wave import SpeedWave
from companion.tools.eval import executor
from companion.tools.eval.depth import DepthEvalOptions, RelativeDepthSource, tracked_frames
from companion.report import mean_or_none, show
from companion.tools import plot
from companion.tools.eval.vio import EvaluationError, VioDataset, read_vio_dataset
from drivers.camera.options import CameraOptions
from drivers.sim.imu import ImuOptions
from drivers.sim.options import SimOptions, WORLD_NAMES
from drivers.sim.record import RecordError, record_dataset
from drivers.sim.sensor import SensorOptions
from drivers.sim.render import RenderError
from drivers.sim.quadrotor import VehicleOptions

log = logging.getLogger(__name__)

#: Frames per world in the paper's simulation datasets (Section IV).
PAPER_FRAMES = {"mine": 850, "sewer": 700, "dome": 1000}
#: Frames per world of ``--quick`` at 20 Hz: 2 s still on the ground, then 2 s of the climb
#: (the VINS has a map once the climb gives parallax, about 35 frames are scored).
QUICK_FRAMES = 80
#: Sources of the anchors' metric depth: ground truth at the feature pixels, the VINS map.
SOURCES = ("gt", "vins")
#: Methods beyond the paper's comparison (docs/rescaling.md, "Beyond the paper").
BEYOND_PAPER = ("ransac_affine",)
#: Issue 7's goal: the best method's AbsRel with VINS anchors within this factor of its AbsRel
#: with ground-truth anchors.
GOAL_RATIO = 1.3
#: The paper's weighted average for the monotone spline, (AbsRel, δ1) per source.
PAPER_MONOTONE_SPLINE = {"gt": (0.096, 0.917), "vins": (0.185, 0.748)}
#: The file a recording's folder holds once it is complete; a folder without it is not used.
COMPLETE = "recording.json"

#: Opens a fresh depth network for one world's frames (the stand-in keeps state per frame).
NetworkFactory = Callable[[], RelativeDepthSource]


@dataclass(frozen=True)
class Recording:
    """How the simulator datasets are made: the config's ``[camera]``, ``[vehicle]``, ``[imu]``,
    in the realistic profile the camera sensor ``[sim_camera]`` (None: ideal), and the waves
    the planner's flights fly, as ``sim record`` flies them (None: level, at a steady speed)."""

    camera: CameraOptions
    vehicle: VehicleOptions
    imu: ImuOptions
    sensor: SensorOptions | None = None
    speed_wave: SpeedWave | None = None
    height_wave: HeightWave | None = None


def frames_per_world(worlds, *, quick: bool) -> dict[str, int]:
    """``{world: frames}`` in the order given, duplicates dropped: the paper's counts, or
    :data:`QUICK_FRAMES` each with ``quick``; EvaluationError for an unknown world."""
    unknown = [w for w in worlds if w not in WORLD_NAMES]
    if unknown:
        raise EvaluationError(f"unknown world {unknown[0]!r}; choose from "
                              f"{', '.join(WORLD_NAMES)}")
    return {w: QUICK_FRAMES if quick else PAPER_FRAMES[w] for w in dict.fromkeys(worlds)}


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/companion/eval``, ``~/.cache/companion/eval`` when that is unset."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "companion" / "eval"


# --------------------------------------------------------------------------------------------
# Datasets, recorded once and cached

def dataset_key(world: str, seed: int, frames: int, recording: Recording) -> str:
    """The cache name of a recording: world, seed, frames, and a digest of the recording's
    options (another camera rate or IMU noise is another dataset)."""
    made = dataclasses.asdict(recording)
    for wave in ("speed_wave", "height_wave"):  # a level flight keeps its name from before
        if made[wave] is None:
            del made[wave]
    options = json.dumps(made, sort_keys=True, default=str)
    digest = hashlib.sha256(options.encode()).hexdigest()[:12]
    return f"{world}-seed{seed}-{frames}f-{digest}"


def cached_dataset(cache: Path, world: str, seed: int, frames: int,
                   recording: Recording) -> Path:
    """The folder of the ``frames``-frame flight in ``world`` from ``seed``, recorded into
    ``cache`` unless a complete recording is there already.

    A recording is made in a partial folder and renamed into place only once complete (its
    :data:`COMPLETE` file written), so an interrupted run never leaves a folder that is used.
    """
    final = Path(cache) / dataset_key(world, seed, frames, recording)
    if (final / COMPLETE).is_file():
        log.info("%s: reusing %s", world, final)
        return final
    _make_cache(Path(cache))
    try:
        _record_into(final, world, seed, frames, recording)
    except OSError as error:
        raise EvaluationError(f"cannot record into the cache {cache}: "
                              f"{error.strerror or error}") from None
    return final


def _make_cache(cache: Path) -> None:
    if cache.exists() and not cache.is_dir():
        raise EvaluationError(f"cannot use {cache} as the dataset cache: not a folder")
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise EvaluationError(f"cannot use {cache} as the dataset cache: "
                              f"{error.strerror or error}") from None


def _record_into(final: Path, world: str, seed: int, frames: int, recording: Recording) -> None:
    """Record into ``.partial-<key>.<pid>`` beside ``final``, then rename it to ``final``
    (atomic on one file system); a folder at ``final`` without :data:`COMPLETE` is removed."""
    _sweep_partials(final)
    partial = final.with_name(f".partial-{final.name}.{os.getpid()}")
    partial.mkdir()
    try:
        summary = _record(partial, world, seed, frames, recording)
        (partial / COMPLETE).write_text(json.dumps(dataclasses.asdict(summary)) + "\n")
        if final.exists() and not (final / COMPLETE).is_file():
            log.warning("%s: removing an incomplete recording", final)
            shutil.rmtree(final)
        try:
            os.rename(partial, final)
        except OSError:
            if not (final / COMPLETE).is_file():  # else another process finished it first
                raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)  # gone already after the rename


def _sweep_partials(final: Path) -> None:
    """Remove the partial folders of ``final``'s recording whose process is gone."""
    for partial in final.parent.glob(f".partial-{final.name}.*"):
        pid = partial.suffix[1:]
        if not pid.isdigit() or int(pid) == os.getpid() or not _running(int(pid)):
            shutil.rmtree(partial, ignore_errors=True)


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists (signal 0 probes, it sends nothing)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, owned by another user
        pass
    return True


def _record(out: Path, world: str, seed: int, frames: int, recording: Recording):
    """Record ``frames`` camera frames: ``(frames - 1) / rate_hz`` seconds, the first frame at
    t = 0 (:func:`drivers.sim.record.fly`)."""
    duration = (frames - 1) / recording.camera.rate_hz
    log.info("%s: recording %d frames (%.2f s, seed %d) into %s", world, frames, duration, seed,
             out)
    try:
        profile = "ideal" if recording.sensor is None else "realistic"
        return record_dataset(out, SimOptions(world=world, seed=seed, profile=profile),
                              recording.camera, recording.vehicle, recording.imu,
                              duration=duration, sim_camera=recording.sensor,
                              wave=recording.speed_wave, height_wave=recording.height_wave)
    except (RecordError, RenderError) as error:
        raise EvaluationError(f"recording {world} (seed {seed}): {error}") from None


# --------------------------------------------------------------------------------------------
# Fitting every method on both anchor sets

@dataclass
class WorldScores:
    """One world's per-frame metrics: ``scores[method][source]`` holds one
    :class:`~autonomy.depth.metrics.DepthMetrics` per scored frame (every fit succeeded);
    ``frames`` counts the frames run, ``scored`` those scored."""

    frames: int
    scored: int
    scores: dict[str, dict[str, list[metrics.DepthMetrics]]]


@dataclass(frozen=True)
class WorldJob:
    """What every world's task shares: the flights' seed, the cache, how to record, the
    evaluation's options, and how to open a network (picklable: a module-level function or a
    ``functools.partial`` of one, since the task may run in another process or machine)."""

    seed: int
    cache: Path
    recording: Recording
    options: DepthEvalOptions
    open_network: NetworkFactory


def evaluate_rescaling(frames: dict[str, int], *, seed: int, cache: Path, recording: Recording,
                       options: DepthEvalOptions, open_network: NetworkFactory,
                       workers: int | None = None, cluster: str | None = None) -> dict:
    """Score every method in each world (:func:`score_cached_world`), the worlds side by side
    as tasks of an executor (local processes, or a Ray cluster at ``cluster``:
    :mod:`~companion.tools.eval.executor`), and summarise (:func:`summarise`). The network is
    opened here first, so that a model that cannot run fails before anything is recorded;
    each world then opens a fresh one (the stand-in keeps state per frame), so the result is
    the same however the worlds are spread."""
    open_network()
    job = WorldJob(seed, Path(cache), recording, options, open_network)
    items = list(frames.items())
    worlds: dict[str, WorldScores] = {}
    runner = executor.open_executor(cluster, workers, len(items))
    for k, scores in runner.run(score_cached_world, job, items):
        world = items[k][0]
        worlds[world] = scores
        log.info("%s: %d of %d frames scored (with a VINS map where every method fits with "
                 "both sparse depths)", world, scores.scored, scores.frames)
    return summarise({world: worlds[world] for world in frames})


def score_cached_world(job: WorldJob, world_frames: tuple[str, int]) -> WorldScores:
    """One world's task: its ``frames``-frame dataset from the cache of the machine it runs on
    (recorded there first if missing, :func:`cached_dataset`), scored by :func:`score_world`
    with a fresh network."""
    world, frames = world_frames
    root = cached_dataset(job.cache, world, job.seed, frames, job.recording)
    return score_world(read_vio_dataset(root), job.options, job.open_network(), frames)


def score_world(data: VioDataset, options: DepthEvalOptions, network: RelativeDepthSource,
                frames: int) -> WorldScores:
    """Run the VINS and ``network`` once over the first ``frames`` frames of ``data`` and, at
    each frame with a sparse map (and a network output the stage would accept:
    :func:`~autonomy.depth.stage.check_relative_disparity`), fit and score every method on
    both anchor sets (:func:`frame_anchors`)."""
    stage = MetricDepthStage(options.rescale, options.stage)
    methods = {m: dataclasses.replace(options.rescale, method=m) for m in METHODS}
    result = WorldScores(0, 0, {m: {s: [] for s in SOURCES} for m in METHODS})
    for frame, update, truth in tracked_frames(data, options, frames):
        disparity = np.asarray(network(frame, truth), dtype=np.float32)  # each frame, as in flight
        result.frames += 1
        if update.sparse_map is not None and check_relative_disparity(disparity) is None:
            anchors = frame_anchors(stage, update.sparse_map, disparity, truth)
            result.scored += score_frame(result, methods, anchors, disparity, truth)
    return result


def frame_anchors(stage: MetricDepthStage, sparse_map: SparseMap, disparity: np.ndarray,
                  truth: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{source: (x, z)}`` for the landmarks the stage takes from ``sparse_map``: x their
    relative disparity, z their VINS depth (``"vins"``) or the ground truth at their pixel
    (``"gt"``).

    The ground truth is read by the rule x is read by, the nearest surface of the four pixels
    around the feature (:func:`~autonomy.depth.anchors.sample_nearest_surface`):
    z* = 1 / max_ij(1 / z*_ij), NaN on sky, which the fit drops as an invalid anchor.
    """
    with np.errstate(divide="ignore"):
        z_true = 1.0 / sample_nearest_surface(1.0 / truth, np.reshape(sparse_map.pixels, (-1, 2)))
    points = np.array(sparse_map.points_C, dtype=float).reshape(-1, 3)
    points[:, 2] = z_true
    true_map = dataclasses.replace(sparse_map, points_C=points)
    return {"gt": stage.anchors(true_map, disparity),
            "vins": stage.anchors(sparse_map, disparity)}


def score_frame(result: WorldScores, methods: dict[str, RescaleOptions],
                anchors: dict[str, tuple[np.ndarray, np.ndarray]], disparity: np.ndarray,
                truth: np.ndarray) -> bool:
    """Fit each method on each anchor set and, if every fit succeeds (no
    :class:`~autonomy.depth.rescale.NoFit`), score each depth image against ``truth``.
    Whether the frame was scored."""
    fits = {(method, source): fit(x, z, options=options)
            for method, options in methods.items() for source, (x, z) in anchors.items()}
    if not all(model.ok for model in fits.values()):
        return False
    for (method, source), model in fits.items():
        result.scores[method][source].append(metrics.evaluate(model.depth(disparity), truth))
    return True


# --------------------------------------------------------------------------------------------
# Summaries

def summarise(worlds: dict[str, WorldScores]) -> dict:
    """The JSON result: per world its frames and per method and source the means
    (:func:`mean_metrics`), and their frame-weighted average over the worlds
    (:func:`weighted_average`)."""
    per_world = {
        world: {"frames": scores.frames,
                "methods": {m: {s: mean_metrics(scores.scores[m][s]) for s in SOURCES}
                            for m in METHODS}}
        for world, scores in worlds.items()}
    return {"worlds": per_world, "weighted": weighted_average(per_world)}


def mean_metrics(per_frame: list[metrics.DepthMetrics]) -> dict:
    """AbsRel and δ1 averaged over the frames, each weighing the same; the over-estimate
    rate over the frames with near pixels (z* < 5 m) only. None where there is no frame."""
    return {
        "absrel": mean_or_none([m.abs_rel for m in per_frame]),
        "delta1": mean_or_none([m.delta1 for m in per_frame]),
        "overestimate_rate": mean_or_none([m.overestimate_rate for m in per_frame
                                           if m.near_pixels > 0]),
    }


def weighted_average(per_world: dict[str, dict]) -> dict:
    """``{method: {source: {metric: Σ n_w m_w / Σ n_w}}}``, n_w the frames of world w, over
    the worlds where the metric is known (None where it is known in none)."""
    def average(method: str, source: str, metric: str) -> float | None:
        pairs = [(w["frames"], w["methods"][method][source][metric])
                 for w in per_world.values()]
        known = [(n, value) for n, value in pairs if value is not None and n > 0]
        if not known:
            return None
        return sum(n * value for n, value in known) / sum(n for n, _ in known)

    return {m: {s: {metric: average(m, s, metric)
                    for metric in ("absrel", "delta1", "overestimate_rate")}
                for s in SOURCES}
            for m in METHODS}


def goal(result: dict) -> dict | None:
    """Issue 7's goal on the weighted average: the method with the lowest AbsRel with VINS
    anchors, and the ratio of that AbsRel to the same method's with ground-truth anchors;
    ``met`` when the ratio is at most :data:`GOAL_RATIO`. None without numbers."""
    rows = [(numbers["vins"]["absrel"], numbers["gt"]["absrel"], method)
            for method, numbers in result["weighted"].items()
            if numbers["vins"]["absrel"] is not None and numbers["gt"]["absrel"]]
    if not rows:
        return None
    vins, gt, method = min(rows)
    return {"method": method, "vins_absrel": vins, "gt_absrel": gt, "ratio": vins / gt,
            "met": vins / gt <= GOAL_RATIO}


# --------------------------------------------------------------------------------------------
# Report

def format_markdown(result: dict, *, seed: int) -> str:
    """Markdown: Table I's shape (rows methods; per world and weighted, GT and VINS
    AbsRel / δ1), the over-estimate rates, and the goal line."""
    columns = [(world, numbers["methods"]) for world, numbers in result["worlds"].items()]
    columns.append(("weighted", result["weighted"]))
    return "\n".join([
        f"## Rescaling methods on simulated flights (seed {seed}; frames: {_frames(result)})",
        "",
        "AbsRel / δ1 with sparse depth from the ground truth at the VINS feature pixels (GT) "
        "and from the VINS map (VINS). Per world each frame weighs the same; *weighted* "
        "weighs each world by its frames. Scored: the frames with a VINS map where every "
        "method fits with both sparse depths. **Bold**: the lowest of the column (of AbsRel "
        "in the first table).",
        "",
        *_table(columns, lambda n: f"{show(n['absrel'], '.3f')} / {show(n['delta1'], '.3f')}",
                lambda n: n["absrel"], "AbsRel / δ1"),
        "",
        "Over-estimate rate: the share of pixels nearer than 5 m placed more than 25 % too far.",
        "",
        *_table(columns, lambda n: show(n["overestimate_rate"], ".2%"),
                lambda n: n["overestimate_rate"], "over-estimate"),
        "",
        _goal_line(goal(result)),
        _paper_line(),
    ])


def _frames(result: dict) -> str:
    """"mine 850, sewer 700": the frames run in each world."""
    return ", ".join(f"{world} {numbers['frames']}" for world, numbers in result["worlds"].items())


def _table(columns, cell, key, what: str) -> list[str]:
    """Rows of a Markdown table: one per method, one column per (group, source)."""
    header = [f"{group} {source.upper()} {what}" for group, _ in columns for source in SOURCES]
    best = {(group, source): _lowest(numbers, source, key) for group, numbers in columns
            for source in SOURCES}
    lines = ["| method | " + " | ".join(header) + " |",
             "|---|" + "---:|" * len(header)]
    for method in METHODS:
        label = method + (" (beyond the paper)" if method in BEYOND_PAPER else "")
        cells = []
        for group, numbers in columns:
            for source in SOURCES:
                text = cell(numbers[method][source])
                cells.append(f"**{text}**" if method in best[group, source] else text)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def _lowest(numbers: dict, source: str, key) -> set[str]:
    """The methods whose ``key`` for ``source`` is the lowest (ties all), none if none has one."""
    known = {m: key(n[source]) for m, n in numbers.items() if key(n[source]) is not None}
    return {m for m, value in known.items() if value == min(known.values())}


def _goal_line(reached: dict | None) -> str:
    if reached is None:
        return "Goal (best VINS AbsRel within 1.3x its GT AbsRel): no numbers."
    verdict = "met" if reached["met"] else "not met"
    return (f"Goal, best VINS AbsRel within {GOAL_RATIO}x the same method's GT AbsRel: "
            f"{reached['method']}, VINS {reached['vins_absrel']:.3f} / GT "
            f"{reached['gt_absrel']:.3f} = {reached['ratio']:.2f}x: **{verdict}**.")


def _paper_line() -> str:
    (gt_rel, gt_d1), (vins_rel, vins_d1) = PAPER_MONOTONE_SPLINE["gt"], \
        PAPER_MONOTONE_SPLINE["vins"]
    return (f"Paper, weighted average, monotone spline: GT {gt_rel} / {gt_d1}, VINS "
            f"{vins_rel} / {vins_d1} ({vins_rel / gt_rel:.2f}x).")


# --------------------------------------------------------------------------------------------
# Plot

#: The bars' colours and legend labels, by source.
_BARS = {"gt": ("tab:blue", "GT sparse depth"), "vins": ("tab:orange", "VINS sparse depth")}


def plot_absrel(result: dict, out: Path, *, seed: int, revision: str) -> Path:
    """Draw :func:`absrel_figure` as a PNG at ``out`` (parent folders created). ValueError
    for a name that does not end in .png, :class:`~companion.tools.plot.MissingExtra` without
    matplotlib."""
    return plot.save(absrel_figure(result, seed=seed, revision=revision), out)


def absrel_figure(result: dict, *, seed: int, revision: str):
    """The matplotlib Figure of the weighted AbsRel: per method (top to bottom in the order
    of :data:`~autonomy.depth.rescale.METHODS`) a GT and a VINS bar, each labelled with its
    value ("no fit" where none); the caption names the worlds and their frames, the ``seed``
    and the code's ``revision``."""
    weighted = result["weighted"]
    rows = np.arange(len(weighted))
    figure = plot.new_figure(9.0, 1.6 + 0.45 * len(weighted),
                             f"Seed {seed}; frames run per world: {_frames(result)} (the "
                             f"average weighs each world by its frames); code revision "
                             f"{revision}.")
    axes = figure.add_subplot()
    for k, (source, (colour, label)) in enumerate(_BARS.items()):
        values = [numbers[source]["absrel"] for numbers in weighted.values()]
        container = axes.barh(rows + (k - 0.5) * 0.4, [v or 0.0 for v in values], 0.4,
                              color=colour, label=label)
        axes.bar_label(container, ["no fit" if v is None else f"{v:.3f}" for v in values],
                       padding=3, fontsize=8)
    known = [n[s]["absrel"] for n in weighted.values() for s in SOURCES
             if n[s]["absrel"] is not None]
    axes.set_yticks(rows, [m + (" (beyond the paper)" if m in BEYOND_PAPER else "")
                           for m in weighted])
    axes.invert_yaxis()
    axes.set(xlim=(0.0, max([1e-3, *known]) * 1.2), xlabel="AbsRel (lower is better)",
             title="AbsRel per rescaling method, weighted over " + ", ".join(result["worlds"]))
    axes.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return figure
