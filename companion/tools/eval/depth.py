"""Accuracy of the metric depth stage on a recorded dataset, behind ``companion eval depth``.

The whole depth path runs frame by frame as in flight: the VINS on the camera and IMU, the
depth network on the frame (the user's ONNX model on the image, or the synthetic stand-in on
the dataset's ground-truth depth), and the metric depth stage pairing the two. Each frame's
metric depth is scored against the ``depth0`` image with the rescaler's metrics (AbsRel, δ1,
RMSE, over-estimate rate of near obstacles; :mod:`autonomy.depth.metrics`), and the stage's
own time is measured here (network excluded), never in ``autonomy/``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from autonomy.depth import metrics
from autonomy.depth.network import DepthNetwork, NetworkOptions
from autonomy.depth.stage import DepthStageOptions, MetricDepthStage
from autonomy.depth.synthetic import (
    SyntheticDepthOptions, SyntheticNetwork, affine_fit_abs_rel,
)
from autonomy.messages import MetricDepth, RelativeDepth
from autonomy.planning.history import read_depth
from companion.report import finite_or_none, mean_or_none, median_or_none, show
from companion.tools.eval.vio import (
    EvaluationError, ImuFeed, VioDataset, VioFrame, build_vins, read_frame_depth, read_vio_dataset,
    vio_frames,
)

if TYPE_CHECKING:
    from autonomy.depth.rescale import RescaleOptions
    from autonomy.vins.frontend import FrontendOptions
    from autonomy.vins.options import VinsOptions
    from autonomy.vins.static_init import StaticInitOptions

#: Pixels whose confidence is at least this are "supported": two or more anchors lie within a
#: knot spacing of their relative disparity (:meth:`RescaleModel.confidence`).
SUPPORTED = 0.5

#: The planner's classes of pixels (:class:`~autonomy.planning.history.DepthReading`) whose
#: true over estimated depth ``true_over_estimated`` reports: confident within range, and the
#: rescaling's straight tails nearer and farther than every confident pixel; with the name
#: the text report gives each.
READING_CLASSES = {"in_range": "confident", "near_tail": "near tail", "far_tail": "far tail"}
#: Every this many pixels of a class (row-major) are kept for its percentiles.
RATIO_STRIDE = 16

#: A depth network as the evaluation drives it: (frame, its ground-truth depth) -> relative
#: disparity at the camera's resolution.
RelativeDepthSource = Callable[[VioFrame, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class DepthEvalOptions:
    """Everything :func:`run_depth` builds its estimator and stage from."""

    vins: VinsOptions
    rescale: RescaleOptions
    stage: DepthStageOptions = field(default_factory=DepthStageOptions)
    frontend: FrontendOptions | None = None
    static: StaticInitOptions | None = None
    #: the planner's ``min_confidence`` and ``max_range``: how its check reads the depth
    #: (``true_over_estimated``'s classes)
    min_confidence: float = 0.3
    max_range: float = 10.0


@dataclass
class DepthTrace:
    """What the stage produced over a dataset: one entry per frame with metric depth in the
    per-frame lists (``t``, ``metrics``, ``anchors``, ``residual_rms``, ``fit_age_s``,
    ``held``, ``fallback``), the stage's time for every frame in ``stage_ms``; ``no_fit`` and
    ``rejected`` are the stage's counts of frames without a fresh fit and of rejected network
    outputs, by reason."""

    frames: int = 0
    t: list[float] = field(default_factory=list)
    metrics: list[metrics.DepthMetrics] = field(default_factory=list)
    supported: list[metrics.DepthMetrics] = field(default_factory=list)
    supported_share: list[float] = field(default_factory=list)
    network_abs_rel: list[float] = field(default_factory=list)
    anchors: list[int] = field(default_factory=list)
    residual_rms: list[float] = field(default_factory=list)
    fit_age_s: list[float] = field(default_factory=list)
    held: list[bool] = field(default_factory=list)
    fallback: list[bool] = field(default_factory=list)
    stage_ms: list[float] = field(default_factory=list)
    ratios: dict[str, list[np.ndarray]] = field(
        default_factory=lambda: {name: [] for name in READING_CLASSES})
    no_fit: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    method: str = ""


def open_relative_depth_source(network: NetworkOptions, synthetic: SyntheticDepthOptions, *,
                               seed: int = 0) -> RelativeDepthSource:
    """The user's ONNX model on the frame's image when ``network.model`` is set (opened and
    checked now: :class:`~autonomy.depth.network.NetworkError` if it cannot run), else the
    synthetic stand-in on the frame's ground-truth depth."""
    if network.model:
        model = DepthNetwork.open(network)

        def infer(frame: VioFrame, truth: np.ndarray) -> np.ndarray:
            return model(frame.image, channels="rgb")  # the evaluation's frames are RGB
        return infer
    stand_in = SyntheticNetwork(synthetic, seed=seed)
    return lambda frame, truth: stand_in(truth, frame.image)


def evaluate_depth(root: Path, options: DepthEvalOptions, network: RelativeDepthSource, *,
                   max_frames: int | None = None) -> dict:
    """Run the depth path over the dataset at ``root`` (:func:`run_depth`) and score it
    (:func:`score_depth`)."""
    data = read_vio_dataset(root)
    if data.depth is None:
        raise EvaluationError(f"{data.root}: no mav0/depth0 stream; metric depth is scored "
                              "against ground-truth depth (record one with 'companion sim "
                              "record')")
    return score_depth(run_depth(data, options, network, max_frames=max_frames), data)


def run_depth(data: VioDataset, options: DepthEvalOptions, network: RelativeDepthSource, *,
              max_frames: int | None = None) -> DepthTrace:
    """Feed every frame of ``data`` to the VINS, ``network`` and the stage, as in flight, and
    trace the stage's output scored against the frame's ground-truth depth."""
    stage = MetricDepthStage(options.rescale, options.stage)
    trace = DepthTrace(method=options.rescale.method)
    for frame, update, truth in tracked_frames(data, options, max_frames):
        relative = RelativeDepth(frame.t, network(frame, truth))
        start = time.perf_counter()
        result = stage.process(relative, update.sparse_map)
        trace.stage_ms.append(1e3 * (time.perf_counter() - start))
        _record(trace, result, truth, relative.disparity, options)
    trace.no_fit, trace.rejected = dict(stage.no_fit), dict(stage.rejected)
    return trace


def tracked_frames(data: VioDataset, options: DepthEvalOptions, max_frames: int | None = None):
    """Each of the first ``max_frames`` frames of ``data`` (all by default) with the VINS's
    update after it and its ground-truth depth: ``(frame, update, truth)``; the VINS fed the
    frame's IMU samples and image as in flight. EvaluationError for a frame without depth0."""
    vins = build_vins(data, options.vins, frontend=options.frontend, static=options.static)
    imu = ImuFeed(data)
    for frame in vio_frames(data, max_frames):
        if frame.depth_path is None:
            raise EvaluationError(f"{data.root}: frame at t={frame.t:.3f} s has no depth0 image")
        imu.before_frame(vins, frame.t)
        update = vins.add_frame(frame.t, vins.track(frame.image))
        yield frame, update, read_frame_depth(frame.depth_path, data)


def _record(trace: DepthTrace, result: MetricDepth, truth: np.ndarray,
            relative: np.ndarray, options: DepthEvalOptions) -> None:
    trace.frames += 1
    if not result.ok:
        return
    trace.t.append(result.t)
    scored = metrics.evaluate(result.depth, truth)
    supported = result.confidence >= SUPPORTED
    trace.metrics.append(scored)
    trace.supported.append(metrics.evaluate(result.depth, truth, mask=supported))
    known = np.isfinite(truth) & (truth > 0)
    trace.supported_share.append(float(np.count_nonzero(supported & known))
                                 / max(1, np.count_nonzero(known)))
    trace.network_abs_rel.append(affine_fit_abs_rel(relative, truth))
    trace.anchors.append(result.diagnostics.anchors)
    trace.residual_rms.append(result.diagnostics.residual_rms)
    trace.fit_age_s.append(result.diagnostics.fit_age_s)
    trace.held.append(result.held)
    trace.fallback.append(result.diagnostics.fallback)
    _record_ratios(trace, result, truth, options)


def _record_ratios(trace: DepthTrace, result: MetricDepth, truth: np.ndarray,
                   options: DepthEvalOptions) -> None:
    """Every :data:`RATIO_STRIDE`-th true over estimated depth of each of the planner's
    :data:`READING_CLASSES` of the frame's pixels, where the truth has a surface."""
    reading = read_depth(result.depth, result.confidence, options.min_confidence,
                         options.max_range)
    surface = np.isfinite(truth) & (truth > 0.0)
    masks = {"in_range": reading.in_range, "near_tail": reading.near_tail(result.depth),
             "far_tail": reading.far_tail(result.depth)}
    for name, mask in masks.items():
        pixels = np.flatnonzero(mask & surface)[::RATIO_STRIDE]
        trace.ratios[name].append(truth.flat[pixels] / result.depth.flat[pixels])


def ratio_percentiles(ratios: list[np.ndarray]) -> dict:
    """``pixels`` (those sampled) and the 1st, 5th and 50th percentiles of true over
    estimated depth (None without pixels): below 1 the depth was read too far."""
    both = np.concatenate(ratios) if ratios else np.empty(0)
    if both.size == 0:
        return {"pixels": 0, "p1": None, "p5": None, "p50": None}
    p1, p5, p50 = np.percentile(both, [1, 5, 50])
    return {"pixels": int(both.size), "p1": float(p1), "p5": float(p5), "p50": float(p50)}


def score_depth(trace: DepthTrace, data: VioDataset) -> dict:
    """The trace as plain numbers for JSON (None where a metric cannot be computed).

    ``abs_rel``, ``delta1``, ``rmse_m`` and ``overestimate_rate`` are means over the frames
    with metric depth, each frame weighing the same (as the paper's per-world figures); the
    over-estimate rate over the frames with near pixels only. ``supported`` repeats them over
    the pixels the stage is confident in (confidence >= :data:`SUPPORTED`: their relative
    disparity lies among anchors, not extrapolated beyond them), with ``share``, the mean
    share of ground-truth pixels that are supported. ``network_affine_abs_rel`` is the
    network's own error on the same frames, the floor of any affine rescaling: AbsRel after the
    best affine fit of its output to the true disparity at every pixel
    (:func:`~autonomy.depth.synthetic.affine_fit_abs_rel`). ``frames_with_depth`` counts
    those frames and ``frames_held`` those among them that used an earlier frame's fit,
    ``frames_fallback`` those given the affine fallback on their few anchors, with their
    ``fallback_abs_rel`` (their mean AbsRel); ``no_fit`` counts the frames without a fresh
    fit by reason (held, on the fallback or without depth). ``true_over_estimated``: for the
    planner's reading of the frames (:data:`READING_CLASSES`: confident within range, the
    near tail and the far tail), the percentiles of true over estimated depth
    (:func:`ratio_percentiles`); a tail that errs toward the vehicle no more often than
    confident depth does has the same low percentiles (docs/planner.md, the tails).
    """
    per_frame = trace.metrics
    near = [m.overestimate_rate for m in per_frame if m.near_pixels > 0]
    stage_ms = np.asarray(trace.stage_ms)
    return {
        "dataset": str(data.root),
        "method": trace.method,
        "frames": trace.frames,
        "frames_with_depth": len(per_frame),
        "frames_held": int(sum(trace.held)),
        "frames_fallback": int(sum(trace.fallback)),
        "fallback_abs_rel": mean_or_none([m.abs_rel for m, fallback
                                          in zip(per_frame, trace.fallback) if fallback]),
        "no_fit": trace.no_fit,
        "rejected": trace.rejected,
        "abs_rel": mean_or_none([m.abs_rel for m in per_frame]),
        "delta1": mean_or_none([m.delta1 for m in per_frame]),
        "rmse_m": mean_or_none([m.rmse for m in per_frame]),
        "overestimate_rate": mean_or_none(near),
        "supported": {
            "share": mean_or_none(trace.supported_share),
            "abs_rel": mean_or_none([m.abs_rel for m in trace.supported]),
            "delta1": mean_or_none([m.delta1 for m in trace.supported]),
            "overestimate_rate": mean_or_none([m.overestimate_rate for m in trace.supported
                                        if m.near_pixels > 0]),
        },
        "network_affine_abs_rel": mean_or_none(trace.network_abs_rel),
        "anchors_median": median_or_none(trace.anchors),
        "residual_rms_median": median_or_none(trace.residual_rms),
        "stage_ms_median": median_or_none(stage_ms),
        "stage_ms_p95": finite_or_none(np.percentile(stage_ms, 95)) if stage_ms.size else None,
        "true_over_estimated": {name: ratio_percentiles(trace.ratios[name])
                                for name in READING_CLASSES},
    }


def format_depth_report(result: dict) -> str:
    """The evaluation result as a few lines a person reads."""
    supported = result["supported"]
    no_fit = ", ".join(f"{reason} {count}" for reason, count in result["no_fit"].items())
    rejected = ", ".join(f"{reason} {count}" for reason, count in result["rejected"].items())
    return "\n".join([
        f"{result['dataset']}: {result['frames']} frames, {result['frames_with_depth']} with "
        f"metric depth ({result['frames_held']} on a held fit, {result['frames_fallback']} on "
        f"the affine fallback, AbsRel {show(result['fallback_abs_rel'], '.3f')}), method "
        f"{result['method']}",
        f"accuracy: AbsRel {show(result['abs_rel'], '.3f')}, delta1 "
        f"{show(result['delta1'], '.3f')}, RMSE {show(result['rmse_m'], '.2f', ' m')}, "
        f"over-estimate rate {show(result['overestimate_rate'], '.3f')}",
        f"where supported by anchors ({show(supported['share'], '.0%')} of pixels): AbsRel "
        f"{show(supported['abs_rel'], '.3f')}, delta1 {show(supported['delta1'], '.3f')}, "
        f"over-estimate rate {show(supported['overestimate_rate'], '.3f')}",
        f"the network's own error (AbsRel after the best affine fit to the truth): "
        f"{show(result['network_affine_abs_rel'], '.3f')}",
        f"fit: {show(result['anchors_median'], '.0f')} anchors median, residual "
        f"{show(result['residual_rms_median'], '.4f', ' 1/m')} RMS median",
        f"stage: {show(result['stage_ms_median'], '.2f', ' ms')} median, "
        f"{show(result['stage_ms_p95'], '.2f', ' ms')} p95 (network excluded)",
        "frames without a fresh fit: " + (no_fit or "none") + "; rejected network outputs: "
        + (rejected or "none"),
        "true over estimated depth, 1st / 5th percentile: " + ", ".join(
            _percentiles_text(label, result["true_over_estimated"][name])
            for name, label in READING_CLASSES.items()),
    ])


def _percentiles_text(label: str, ratios: dict) -> str:
    return f"{label} {show(ratios['p1'], '.3f')} / {show(ratios['p5'], '.3f')}"
