"""Accuracy of the VINS on a recorded dataset, behind ``companion eval vio``.

The estimator runs frame by frame on a EuRoC/ASL dataset, real or simulated, exactly as it
would in flight (IMU samples up to each frame's time, then the frame), into a
:class:`VioTrace` (:func:`run_vins`), and the trace is scored against the dataset's ground
truth (:func:`score_vio`): trajectory error after alignment, scale, the consistency of its
covariance (NEES), the depth of its sparse landmarks against the ``depth0`` images, and its
static initialisation. The time each stage takes is measured here, never in ``autonomy/``.
"""

from __future__ import annotations

import math
import re
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import cv2
import numpy as np
from scipy.integrate import trapezoid

from autonomy.geometry import (
    PinholeCamera, invert_pose, make_pose, quat_to_rot, so3_log, yaw_alignment,
)
from autonomy.lens import CameraModel, Rectifier
from autonomy.messages import Frame, ImuSample, SparseMap
from autonomy.trajectory import (
    align_umeyama, ate_rmse, interpolate_poses, nees, path_length, pose_error_body,
    split_displacement,
)
from autonomy.vins.preintegration import ImuNoise
from autonomy.vins.time_offset import TimeOffset
from companion.report import finite_or_none, format_split, median_or_none, show
from companion.tools.eval.drag_fit import fit_drag
from companion.tools.eval.tracks import TrackErrors, track_error_summary
from companion.tools.eval.vio_bound import (
    BOUND_EVERY, FactorLog, batch_positions, bound_report,
)
from drivers.dataset.euroc import (
    CameraStream, CameraTruth, DatasetError, GroundTruthTable, ImuTable, read_camera,
    read_camera_truth, read_depth_png, read_groundtruth, read_imu, read_imu_noise,
)
from drivers.sim.truth_tracks import TruthTracks, replacement_for

if TYPE_CHECKING:
    from autonomy.vins.estimator import FrameUpdate, Vins
    from autonomy.vins.frontend import FrontendOptions
    from autonomy.vins.gyro_alignment import GyroAlignmentEstimate
    from autonomy.vins.options import VinsOptions
    from autonomy.vins.static_init import StaticInit, StaticInitOptions


class EvaluationError(Exception):
    """The dataset cannot be evaluated; the message names the file and the problem."""


@dataclass(frozen=True)
class VioDataset:
    """The streams of a dataset the evaluation needs, checked for use.

    ``depth`` maps a camera timestamp (ns) to its ground-truth depth image; it is None when the
    dataset has no ``depth0`` stream (the real EuRoC recordings). ``camera_truth``: a simulated
    recording's true exposure times and camera mounting, None elsewhere. ``rectifier``, when
    set, resamples every frame and depth image as they are read (:func:`rectified`).
    """

    root: Path
    camera: CameraStream
    imu: ImuTable
    truth: GroundTruthTable
    noise: ImuNoise
    depth: dict[int, Path] | None
    camera_truth: CameraTruth | None = None
    rectifier: Rectifier | None = None


@dataclass(frozen=True)
class VioFrame:
    """One camera frame as the estimator takes it in flight, stamped ``t`` (seconds since the
    first IMU sample): ``image`` (uint8 grey or RGB); ``depth_path``, its ground-truth depth
    image or None; ``exposure_t``, the true middle of its exposure where the recording holds
    the camera's truth, else ``t``. :class:`ImuFeed` gives the VINS the IMU before it."""

    t: float
    image: np.ndarray
    depth_path: Path | None
    exposure_t: float


class ImuFeed:
    """A dataset's IMU samples fed to a VINS in order, as in flight: before the frame stamped
    ``t``, every sample up to ``t`` and up to its exposure ``t - td`` (``Vins.exposure_time``),
    so a camera whose stamps lead the IMU (a negative offset ``td``) has its exposure covered
    too."""

    def __init__(self, data: "VioDataset"):
        imu = data.imu
        self._t = _seconds(imu.t_ns, imu.t_ns[0])
        self._gyro, self._accel = imu.gyro, imu.accel
        self._fed = 0

    def before_frame(self, vins: Vins, t: float) -> None:
        """Feed ``vins`` the samples not yet fed up to ``max(t, its exposure time)``."""
        upto = int(np.searchsorted(self._t, max(t, vins.exposure_time(t)), side="right"))
        for i in range(self._fed, upto):
            vins.add_imu(ImuSample(float(self._t[i]), self._gyro[i], self._accel[i]))
        self._fed = max(self._fed, upto)


@dataclass(frozen=True)
class KeyframeEstimate:
    """The smoother's newest keyframe as the odometry reports it: exposure time ``t``, pose
    ``T_W_B``, ``velocity_W``, and their marginal covariances (6x6 in the body frame, rotation
    first; 3x3 in the world frame); its accelerometer and gyro biases and the window's
    landmarks."""

    t: float
    T_W_B: np.ndarray
    velocity_W: np.ndarray
    pose_covariance: np.ndarray | None  # None: not traced (``run_vins``'s ``consistency``)
    velocity_covariance: np.ndarray | None
    accel_bias: np.ndarray
    landmarks: int  #: landmarks in the smoother's window
    gyro_bias: np.ndarray


@dataclass(frozen=True)
class Rebuild:
    """A smoother rebuild at keyframe time ``t`` (``failure``: why the update was refused),
    and ``before``, the last keyframe before it (None if there was none)."""

    t: float
    failure: str
    before: KeyframeEstimate | None


@dataclass
class VioTrace:
    """What the estimator produced over a dataset, one entry per frame in each list.

    ``t``: frame exposure time (its stamp less the camera-IMU time offset in use), seconds
    since the dataset's first IMU sample. ``positions``: the body
    position in the world, None while the estimator has no pose. ``keyframe``: the smoother
    ran on the frame. ``frontend_ms``/``backend_ms``: wall time of tracking and of the frame
    update. ``health``: the name of the health state. ``depth_errors``: one array of
    :func:`depth_relative_errors` per frame with both a sparse map and a depth image (so not
    one per frame). ``static_init``: the estimator's static initialisation (None if it never
    initialised); ``resets``: how many times it reset; ``time_offset``: the camera-IMU time
    offset at the end; ``gyro_alignment``: the gyro's response to the yaw rate it was
    corrected by at the end (None when none); ``camera_mounting``: the mounting ``T_B_C`` the
    smoother estimated, at the end (None unless ``estimate_camera_mounting``);
    ``rest_accel_scale_error``: the accelerometer's z sensitivity error read at rest and divided
    out (None unless ``rest_accel_scale_share``: :mod:`autonomy.vins.accel_scale`);
    ``corrections_m``: each keyframe's correction
    (:attr:`~autonomy.vins.estimator.FrameUpdate.correction_m`); ``keyframes``: each
    keyframe's estimate with its covariances, taken when it was the newest; ``rebuilds``:
    each rebuild of the smoother; ``track_errors``: the front-end's tracks against the truth
    (:meth:`~companion.tools.eval.tracks.TrackErrors.summary`), and what the truth was seen
    through, ``track_error_reference``: ``"camera truth"``, a simulated recording's true
    exposure times and mounting, or ``"calibration"``, the stamps and the configured mounting,
    whose hidden errors a realistic recording's track errors then include
    (:mod:`companion.tools.eval.tracks`).
    """

    t: list[float] = field(default_factory=list)
    positions: list[np.ndarray | None] = field(default_factory=list)
    keyframe: list[bool] = field(default_factory=list)
    frontend_ms: list[float] = field(default_factory=list)
    backend_ms: list[float] = field(default_factory=list)
    health: list[str] = field(default_factory=list)
    depth_errors: list[np.ndarray] = field(default_factory=list)
    static_init: StaticInit | None = None
    resets: int = 0
    time_offset: TimeOffset = field(default_factory=TimeOffset)
    gyro_alignment: GyroAlignmentEstimate | None = None
    camera_mounting: np.ndarray | None = None
    rest_accel_scale_error: float | None = None
    corrections_m: list[float] = field(default_factory=list)
    keyframes: list[KeyframeEstimate] = field(default_factory=list)
    rebuilds: list[Rebuild] = field(default_factory=list)
    track_errors: dict = field(default_factory=lambda: {**track_error_summary([], [], []),
                                                        "track_error_by_texture": None,
                                                        "track_error_reference": None})


def read_vio_dataset(root: Path) -> VioDataset:
    """The camera, IMU, ground truth, IMU noise model and (if present) depth of ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise EvaluationError(f"{root}: no such folder")
    try:
        camera, imu, truth = read_camera(root), read_imu(root), read_groundtruth(root)
        noise = read_imu_noise(root)
        has_depth = (root / "mav0" / "depth0").is_dir()
        depth = read_camera(root, "depth0") if has_depth else None
        camera_truth = read_camera_truth(root, camera)
    except DatasetError as error:
        raise EvaluationError(str(error)) from None
    if len(camera.t_ns) == 0:
        raise EvaluationError(f"{root / 'mav0' / 'cam0' / 'data.csv'}: no frames")
    if len(truth.t_ns) < 2:
        raise EvaluationError(f"{root / 'mav0' / 'state_groundtruth_estimate0' / 'data.csv'}: "
                              "ground truth needs at least 2 samples")
    depth_paths = dict(zip(depth.t_ns.tolist(), depth.paths)) if depth is not None else None
    return VioDataset(root, camera, imu, truth, noise, depth_paths, camera_truth)


def rectified(data: VioDataset) -> VioDataset:
    """``data`` as the flight application sees its camera: every frame and depth image
    resampled through the lens onto the ideal pinhole of the lens's intrinsics
    (:class:`autonomy.lens.Rectifier`, which ``drivers.camera.calibration`` runs on each frame
    before any stage sees it), the camera then without distortion; ``data`` itself where the
    lens has none. Without it the VINS tracks the raw frames and undistorts its points, as
    VINS-Mono does on EuRoC."""
    stream = data.camera
    if not any(stream.distortion):
        return data
    model = CameraModel(stream.camera, "radtan", stream.distortion)
    return replace(data, camera=replace(stream, distortion=(0.0,) * len(stream.distortion)),
                   rectifier=Rectifier(model, model.rectified()))


def evaluate_vio(root: Path, options: VinsOptions, *, frontend: FrontendOptions | None = None,
                 static: StaticInitOptions | None = None, max_frames: int | None = None,
                 consistency: bool = True, bound: bool = False,
                 track_source: str = "tracker", rectify: bool = False) -> dict:
    """Run the VINS over the dataset at ``root`` (:func:`run_vins`) and score it
    (:func:`score_vio`); ``consistency`` false skips the NEES and the marginal covariance it
    needs at every keyframe (a quarter of the time); ``bound`` adds ``bound``, what the
    smoother's own factors allow (:func:`bound_vio`); ``track_source`` other than the tracker's
    runs it on the tracker's tracks with every pixel the truth's, or with part of the
    tracker's error (:func:`run_vins`); ``rectify`` runs it on the frames rectified as in
    flight (:func:`rectified`)."""
    data = read_vio_dataset(root)
    if rectify:
        data = rectified(data)
    log = FactorLog() if bound else None
    trace = run_vins(data, options, frontend=frontend, static=static, max_frames=max_frames,
                     consistency=consistency, factor_log=log, track_source=track_source)
    result = score_vio(trace, data)
    if log is not None:
        result["bound"] = bound_vio(log, trace, data)
    return result


def bound_vio(log: FactorLog, trace: VioTrace, data: VioDataset) -> dict:
    """The trajectory error and scale of the fixed-lag smoother, the causal batch and the
    whole-flight batch over the same factors, on every :data:`BOUND_EVERY`-th keyframe
    (:mod:`companion.tools.eval.vio_bound`); a ``note`` instead where there is nothing to
    bound."""
    if trace.resets:
        return {"note": f"not bounded: the smoother was rebuilt {trace.resets} time(s), and a "
                        "rebuild's priors would pin the batch's scale"}
    truth_t = _seconds(data.truth.t_ns, data.imu.t_ns[0])
    fixed_lag = {kf.t: kf.T_W_B[:3, 3] for kf in _inside_truth(trace.keyframes, truth_t)}
    if len(fixed_lag) < 3:
        return {"note": f"not bounded: {len(fixed_lag)} keyframes with ground truth"}
    keyframes = batch_positions(log, fixed_lag, BOUND_EVERY)
    true_positions, _ = interpolate_poses(keyframes.t, truth_t, data.truth.position,
                                          data.truth.q_W_B)
    try:
        return bound_report(keyframes, true_positions)
    except ValueError as error:  # a path too short or too straight to align
        return {"note": f"not bounded on {len(keyframes.t)} keyframes: {error}"}


def run_vins(data: VioDataset, options: VinsOptions, *, frontend: FrontendOptions | None = None,
             static: StaticInitOptions | None = None, max_frames: int | None = None,
             consistency: bool = True, factor_log: FactorLog | None = None,
             track_source: str = "tracker") -> VioTrace:
    """Run a :class:`Vins` built with ``options``, ``frontend`` and ``static`` over the frames
    of ``data`` (:func:`vio_frames`) and trace its output, timing each stage; each keyframe's
    covariances are traced for the NEES only with ``consistency``; ``factor_log`` is given
    every factor of the smoother's (the gauge hold's last prior left out at the end).

    With ``track_source`` ``"truth"`` the smoother is given the tracker's tracks, born, kept and
    lost where the tracker has them, with each pixel the true projection of the point it was
    born on (:class:`drivers.sim.truth_tracks.TruthTracks`, as ``sim fly --tracks truth``): on
    the same images and IMU, what the tracker's error costs the estimate; with
    ``"early-error"`` or ``"late-error"``, what the part of it gathered before or after a
    track's sixth frame costs (:data:`drivers.sim.truth_tracks.ERROR_SPLIT_AGE`). These need a
    recording whose camera is the one the truth is projected through: no lens distortion (the
    ideal profile's) and a depth image with every frame."""
    stream = data.camera
    exact = _truth_tracks(data, track_source)
    vins = build_vins(data, options, frontend=frontend, static=static)
    if factor_log is not None:
        vins.backend.update_listener = factor_log.record
    trace = VioTrace()
    imu = ImuFeed(data)
    # the tracks are measured through the camera's truth where the recording holds it
    camera_truth = data.camera_truth
    tracking = TrackErrors(stream.camera, stream.distortion,
                           stream.T_B_C if camera_truth is None else camera_truth.T_B_C,
                           vins.tracker.options.fit_window)
    truth_t = _seconds(data.truth.t_ns, data.imu.t_ns[0])
    for frame in vio_frames(data, max_frames):
        imu.before_frame(vins, frame.t)
        start = time.perf_counter()
        tracks = vins.track(frame.image)
        frontend_ms = 1e3 * (time.perf_counter() - start)
        truth_known = truth_t[0] <= frame.t <= truth_t[-1]  # a late stamp can pass its end
        depth = None
        if exact is not None:  # not timed: no stage of the estimator's
            depth = _exact_frame_depth(frame, truth_known, data)
            true_pose = _true_pose(frame.t, truth_t, data.truth) if truth_known else None
            tracks = exact(Frame(frame.t, frame.image, depth, true_pose), tracks)
        resets_before = vins.backend.resets
        middle = time.perf_counter()
        update = vins.add_frame(frame.t, tracks)
        _record(trace, update, frontend_ms, 1e3 * (time.perf_counter() - middle))
        if vins.backend.resets > resets_before:
            trace.rebuilds.append(Rebuild(vins.backend.latest.t, vins.backend.last_failure,
                                          trace.keyframes[-1] if trace.keyframes else None))
        if update.keyframe:
            trace.keyframes.append(_newest_keyframe(vins, consistency))
        born = truth_known and bool((np.asarray(tracks.ages) == 1).any())
        if (depth is None and frame.depth_path is not None
                and (born or update.sparse_map is not None)):
            depth = read_frame_depth(frame.depth_path, data)
        if truth_known:  # the body's pose when the frame was exposed
            tracking.observe(tracks, _true_pose(frame.exposure_t, truth_t, data.truth), depth,
                             frame.image)
        if update.sparse_map is not None and depth is not None:
            trace.depth_errors.append(depth_relative_errors(update.sparse_map, depth))
    trace.static_init, trace.resets = vins.static_init, int(vins.resets)
    trace.time_offset = vins.time_offset
    trace.gyro_alignment = vins.gyro_alignment
    trace.rest_accel_scale_error = vins.rest_accel_scale_error
    if options.estimate_camera_mounting:
        trace.camera_mounting = vins.backend.camera_mounting
    trace.track_errors = {**tracking.summary(), "track_error_reference":
                          "calibration" if camera_truth is None else "camera truth"}
    if factor_log is not None and not vins.backend.resets:
        factor_log.drop_slot(vins.backend.gauge_hold_slot)
    return trace


def _truth_tracks(data: VioDataset, source: str) -> TruthTracks | None:
    """The replacement of the tracks ``source`` names for ``data``'s camera (:func:`run_vins`;
    None for the tracker's own), or :class:`EvaluationError` where the truth cannot be
    projected through the recorded camera; ValueError for an unknown ``source``."""
    stream = data.camera
    replacement = replacement_for(source, stream.camera, stream.T_B_C)
    if replacement is None:
        return None
    if data.depth is None:
        raise EvaluationError(f"{data.root}: truth tracks need the true depth of every frame "
                              "(depth0/, which 'companion sim record' writes)")
    if any(stream.distortion) or data.rectifier is not None:
        raise EvaluationError(f"{data.root}: truth tracks need an exact camera, and this one's "
                              "lens is distorted: record the ideal profile ('companion sim "
                              "record --set sim.profile=ideal')")
    return replacement


def _exact_frame_depth(frame: VioFrame, truth_known: bool, data: VioDataset) -> np.ndarray:
    """The true depth a truth-track frame needs, or :class:`EvaluationError` naming what is
    missing."""
    if frame.depth_path is None or not truth_known:
        raise EvaluationError(f"truth tracks: the frame at {frame.t:.3f} s has no "
                              + ("depth image" if frame.depth_path is None else "ground truth"))
    return read_frame_depth(frame.depth_path, data)


def build_vins(data: VioDataset, options: VinsOptions, *, frontend: FrontendOptions | None = None,
               static: StaticInitOptions | None = None) -> Vins:
    """A :class:`Vins` for the camera and IMU of ``data``, built with the given options."""
    # Imported here: reading and checking a dataset does not need the whole estimator.
    from autonomy.vins.estimator import Vins

    stream = data.camera
    return Vins(stream.camera, stream.distortion, stream.T_B_C, data.noise, options,
                frontend=frontend, static=static)


def vio_frames(data: VioDataset, max_frames: int | None = None) -> Iterator[VioFrame]:
    """The camera frames of ``data`` in order (the first ``max_frames``); an image of the wrong
    size or format raises :class:`EvaluationError` naming its file."""
    stream = data.camera
    frame_t = _seconds(stream.t_ns, data.imu.t_ns[0])
    exposure_t = (frame_t if data.camera_truth is None
                  else _seconds(data.camera_truth.exposed_ns, data.imu.t_ns[0]))
    count = len(stream.paths) if max_frames is None else min(max_frames, len(stream.paths))
    for k in range(count):
        depth_path = data.depth.get(int(stream.t_ns[k])) if data.depth is not None else None
        image = _read_image(stream.paths[k], stream.camera)
        if data.rectifier is not None:
            image = data.rectifier(image)
        yield VioFrame(float(frame_t[k]), image, depth_path, float(exposure_t[k]))


def score_vio(trace: VioTrace, data: VioDataset) -> dict:
    """Score ``trace`` against the ground truth of ``data``; a dict of plain numbers (None where
    a metric cannot be computed), ready for JSON.

    ``ate_rmse_m``: RMS position error of the traced body positions against the ground truth
    interpolated at the frame times, after the best rigid (SE(3)) alignment; ``scale_error``:
    ``|s - 1|`` of the best similarity (Sim(3)) alignment of the same positions onto the
    truth, and ``scale`` its signed ``1 / s``, the estimate's size over the truth's (above 1:
    the VINS overestimates distances, and depths with them);
    ``distance_m``: ground-truth path length over those frames. ``ate_sim3_rmse_m``: the ATE
    after the similarity alignment instead, so with the scale error taken out (what is left is
    the heading's drift and the path's shape). ``heading_drift_deg``: the last keyframe's yaw
    error against the truth aligned at the first keyframe (:func:`_heading_drift`).
    ``gyro_bias``: the smoother's gyro bias against the truth, per body axis
    (:func:`_gyro_bias_metrics`). ``end_split``: the last keyframe's error through the first
    keyframe's gauge, split over the path (:func:`_end_split`). ``depth_rel_err_median``:
    median of the traced depth errors (None when the dataset has no ``depth0``);
    ``track_error_*``: the front-end's tracks against the truth
    (:mod:`companion.tools.eval.tracks`; None without ``depth0``), but
    ``track_error_reference``, what the truth was seen through (:class:`VioTrace`). Back-end
    times
    are over the keyframes (where the smoother ran), as are ``correction_m_median`` and
    ``correction_m_max`` (how far the smoother moved a keyframe from the IMU's propagation,
    metres). ``nees_pose_*``/``nees_velocity_*``: mean and median NEES of the newest
    keyframe's pose (6 dimensions) and velocity (3) against the truth, over the keyframes
    (:func:`_consistency_metrics`); 6 and 3 when the covariance is honest. ``init`` compares
    the static initialisation with the ground truth at its end: the angle between the
    estimated and true up-vectors in the body, and the relative gyro-bias error.
    ``scale_by_time``: the scale again, over each 8 s of the flight (:func:`_scale_by_time`).
    ``drag_fit``: the rotor drag coefficient fitted on the estimate
    (:mod:`companion.tools.eval.drag_fit`; None when the flight is too short or too even).
    ``gyro_alignment``: the gyro's response to the yaw rate it was corrected by at the end
    (``column``, ``sigma``, ``pairs``, and the whole ``matrix`` and ``matrix_sigma`` by rows
    when more than the yaw column is corrected; None when neither
    ``estimate_gyro_alignment`` nor a ``gyro_alignment`` calibration is given).
    ``camera_mounting``: the mounting the smoother estimated, as its offset from the configured
    one in the configured camera's frame (``rotation_deg``, a rotation vector, and
    ``translation_mm``; None unless ``estimate_camera_mounting``).
    ``rest_accel_scale_error``: the accelerometer's z sensitivity error the VINS read at rest
    and divided out (a fraction; None unless ``rest_accel_scale_share``).
    """
    truth_t = _seconds(data.truth.t_ns, data.imu.t_ns[0])
    backend = [ms for ms, key in zip(trace.backend_ms, trace.keyframe) if key]
    depth_errors = np.concatenate(trace.depth_errors) if trace.depth_errors else np.empty(0)
    return {
        "dataset": str(data.root),
        "frames": len(trace.t),
        "keyframes": sum(trace.keyframe),
        **_trajectory_metrics(trace, truth_t, data.truth),
        **_consistency_metrics(trace.keyframes, truth_t, data.truth),
        "heading_drift_deg": _heading_drift(trace.keyframes, truth_t, data.truth),
        "gyro_bias": _gyro_bias_metrics(trace.keyframes, truth_t, data.truth),
        "end_split": _end_split(trace.keyframes, truth_t, data.truth),
        "rebuilds": [_rebuild_report(rebuild, truth_t, data.truth) for rebuild in trace.rebuilds],
        "depth_rel_err_median": None if data.depth is None else median_or_none(depth_errors),
        "depth_points": len(depth_errors),
        **trace.track_errors,
        "resets": int(trace.resets),
        "correction_m_median": median_or_none(trace.corrections_m),
        "correction_m_max": max(trace.corrections_m, default=None),
        "frontend_ms_median": median_or_none(trace.frontend_ms),
        "backend_ms_median": median_or_none(backend),
        "backend_ms_p95": finite_or_none(np.percentile(backend, 95)) if backend else None,
        "health": dict(Counter(trace.health)),
        "init": _init_metrics(trace.static_init, truth_t, data.truth),
        "time_offset_ms": 1e3 * trace.time_offset.seconds,
        "time_offset_sigma_ms": None if trace.time_offset.sigma is None
        else 1e3 * trace.time_offset.sigma,
        "drag_fit": _drag_fit(trace.keyframes, data),
        "gyro_alignment": None if trace.gyro_alignment is None
        else trace.gyro_alignment.as_dict(),
        "camera_mounting": None if trace.camera_mounting is None
        else _mounting_offset(data.camera.T_B_C, trace.camera_mounting),
        "rest_accel_scale_error": trace.rest_accel_scale_error,
    }


def _mounting_offset(configured: np.ndarray, estimated: np.ndarray) -> dict:
    """``estimated`` in the frame of ``configured`` (``T_C_configured^-1 T_B_C``): its rotation
    vector in degrees and its translation in millimetres."""
    offset = invert_pose(np.asarray(configured, float)) @ estimated
    return {"rotation_deg": np.degrees(so3_log(offset[:3, :3])).tolist(),
            "translation_mm": (1e3 * offset[:3, 3]).tolist()}


def _drag_fit(keyframes: list[KeyframeEstimate], data: VioDataset) -> dict | None:
    """The rotor drag coefficient fitted on the VINS's own keyframes
    (:mod:`companion.tools.eval.drag_fit`); None when too few flew, or at too even a speed."""
    fit = fit_drag([k.t for k in keyframes], [k.T_W_B[:3, :3] for k in keyframes],
                   [k.velocity_W for k in keyframes], _seconds(data.imu.t_ns, data.imu.t_ns[0]),
                   data.imu.accel)
    return None if fit is None else fit.as_dict()


def _seconds(t_ns: np.ndarray, t0_ns: int) -> np.ndarray:
    """Dataset nanoseconds as float seconds since ``t0_ns`` (subtracted in integers first, so
    the float keeps nanosecond precision)."""
    return (np.asarray(t_ns, dtype=np.int64) - np.int64(t0_ns)) * 1e-9


def _record(trace: VioTrace, update: FrameUpdate, frontend_ms: float, backend_ms: float) -> None:
    """Append one frame's update and stage times to ``trace`` (the pose at the time it holds
    for: the frame's exposure, its stamp less the camera-IMU time offset)."""
    trace.t.append(update.t_exposure)
    trace.positions.append(None if update.T_W_B is None else np.array(update.T_W_B[:3, 3]))
    trace.keyframe.append(bool(update.keyframe))
    trace.frontend_ms.append(frontend_ms)
    trace.backend_ms.append(backend_ms)
    trace.health.append(update.health.state.name)
    if update.correction_m is not None:
        trace.corrections_m.append(update.correction_m)


def _newest_keyframe(vins: Vins, covariances: bool) -> KeyframeEstimate:
    backend = vins.backend
    state = backend.latest
    return KeyframeEstimate(state.t, state.T_W_B, state.velocity,
                            backend.pose_covariance() if covariances else None,
                            backend.velocity_covariance() if covariances else None,
                            state.bias_a, len(backend.landmarks.ids), state.bias_g)


def _read_image(path: Path, camera: PinholeCamera) -> np.ndarray:
    """A camera image as the front-end takes it: uint8 grey, or RGB (OpenCV reads BGR)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise EvaluationError(f"{path}: not a readable image")
    if image.dtype != np.uint8 or not (image.ndim == 2 or image.shape[2] == 3):
        raise EvaluationError(f"{path}: expected 8-bit grey or colour, got {image.dtype} "
                              f"with shape {image.shape}")
    _check_size(path, image, camera)
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_frame_depth(path: Path, data: VioDataset) -> np.ndarray:
    """A frame's ground-truth depth image of ``data``'s camera (float32 metres, NaN unknown),
    checked for size, rectified with the frames where they are."""
    try:
        depth = read_depth_png(path)
    except DatasetError as error:
        raise EvaluationError(str(error)) from None
    _check_size(path, depth, data.camera.camera)
    return depth if data.rectifier is None else data.rectifier.depth(depth)


def _check_size(path: Path, image: np.ndarray, camera: PinholeCamera) -> None:
    height, width = image.shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise EvaluationError(f"{path}: image is {width}x{height}, the camera's sensor.yaml "
                              f"says {camera.width}x{camera.height}")


def depth_relative_errors(sparse_map: SparseMap, depth: np.ndarray) -> np.ndarray:
    """``|z_i - z_gt| / z_gt`` for each tracked landmark ``i`` of ``sparse_map``, ``z_i`` its
    depth (``points_C[i, 2]``) and ``z_gt`` the ground-truth ``depth`` (metres, NaN unknown)
    at the nearest pixel to where it was seen; landmarks off the image or on unknown depth are
    left out."""
    tracked = np.asarray(sparse_map.tracked, dtype=bool)
    u, v = np.rint(np.asarray(sparse_map.pixels, dtype=float)[tracked]).T
    z = np.asarray(sparse_map.points_C, dtype=float)[tracked, 2]
    height, width = depth.shape
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    z_gt = depth[v[inside].astype(int), u[inside].astype(int)].astype(float)
    known = np.isfinite(z_gt)
    return np.abs(z[inside][known] - z_gt[known]) / z_gt[known]


#: ``scale_by_time``'s windows and the displacement steps within them, seconds, and the least
#: true distance a window must cover to be scored, metres.
SCALE_WINDOW_S = 8.0
SCALE_STEP_S = 1.0
SCALE_MIN_DISTANCE_M = 2.0


def _trajectory_metrics(trace: VioTrace, truth_t: np.ndarray, truth: GroundTruthTable) -> dict:
    """ATE (SE(3)), scale error (Sim(3)) and distance over the frames with a pose inside the
    ground truth's time span."""
    chosen = [k for k, p in enumerate(trace.positions)
              if p is not None and truth_t[0] <= trace.t[k] <= truth_t[-1]]
    estimated = np.array([trace.positions[k] for k in chosen]).reshape(-1, 3)
    true_positions, _ = interpolate_poses([trace.t[k] for k in chosen], truth_t,
                                          truth.position, truth.q_W_B)
    distance = path_length(true_positions)
    try:
        ate = ate_rmse(estimated, true_positions)
        scale = align_umeyama(estimated, true_positions, with_scale=True).s
    except ValueError as error:
        return {"ate_rmse_m": None, "distance_m": distance, "ate_over_distance": None,
                "ate_sim3_rmse_m": None, "scale_error": None, "scale": None,
                "scale_by_time": [],
                "note": f"no trajectory error from {len(chosen)} poses: {error}"}
    return {"ate_rmse_m": ate, "distance_m": distance,
            "ate_over_distance": ate / distance if distance > 0.0 else None,
            "ate_sim3_rmse_m": ate_rmse(estimated, true_positions, with_scale=True),
            "scale_error": finite_or_none(abs(scale - 1.0)),
            "scale": finite_or_none(1.0 / scale) if scale > 0.0 else None,
            "scale_by_time": _scale_by_time(np.array([trace.t[k] for k in chosen]), estimated,
                                            true_positions)}


def _heading_drift(keyframes: list[KeyframeEstimate], truth_t: np.ndarray,
                   truth: GroundTruthTable) -> float | None:
    """The heading's drift over the flight, degrees: the yaw of the last keyframe's estimate
    less the truth's, in the estimator's world (the truth turned onto the first keyframe: yaw
    is unobservable, so all it has of it is its start); positive is counter-clockwise; over
    the keyframes inside the truth's span (None without any)."""
    keyframes = _inside_truth(keyframes, truth_t)
    if not keyframes:
        return None
    true_last = _truth_in_world(keyframes, truth_t, truth)[-1][0]
    error = _yaw(keyframes[-1].T_W_B) - _yaw(true_last)
    return math.degrees(math.atan2(math.sin(error), math.cos(error)))


def _inside_truth(keyframes: list[KeyframeEstimate],
                  truth_t: np.ndarray) -> list[KeyframeEstimate]:
    """The keyframes stamped inside the ground truth's span (a late stamp can pass its end)."""
    return [kf for kf in keyframes if truth_t[0] <= kf.t <= truth_t[-1]]


def _end_split(keyframes: list[KeyframeEstimate], truth_t: np.ndarray,
               truth: GroundTruthTable) -> dict | None:
    """The error of the last keyframe inside the truth's span, with the truth put in the
    estimator's world by the first one's yaw and shift (as a flight's navigation frame is
    fixed at its start, not by a best fit), split over the horizontal path flown between them
    (``autonomy.trajectory.split_displacement``: the path's scale and bearing, metres along,
    across and in height): what ``eval nav`` splits at the end of a flight, where the ATE's
    alignment takes a constant bearing out. None with fewer than two such keyframes, or where
    the truth ends within ``DISPLACEMENT_MIN_M`` of its start horizontally (a loop)."""
    inside = _inside_truth(keyframes, truth_t)
    if len(inside) < 2:
        return None
    ends = [inside[0], inside[-1]]
    (first, _), (last, _) = _truth_in_world(ends, truth_t, truth)
    split = split_displacement(first[:3, 3], last[:3, 3], ends[0].T_W_B[:3, 3],
                               ends[1].T_W_B[:3, 3])
    return None if split is None else asdict(split)


def _gyro_bias_metrics(keyframes: list[KeyframeEstimate], truth_t: np.ndarray,
                       truth: GroundTruthTable, window_s: float = SCALE_WINDOW_S) -> dict | None:
    """The smoother's gyro bias ``b`` against the true one, per body axis (x, y, z), deg/s,
    each keyframe's as it was when newest, over the keyframes inside the truth's span (None
    without two of them).

    ``mean_error`` and ``rms_error`` of ``b - b_true``; ``true_mean``; ``heading_deg``, the
    heading the z error turns over the flight, ``-∫ (b_z - b_true,z) dt`` (trapezoid over the
    keyframes): the drift the bias would give where the gyro alone set the yaw between
    keyframes, beside ``heading_drift_deg``, the drift the estimate has. The truth is the
    sensor's additive bias; the estimate also takes in what the scale and cross-axis errors
    add at the rates flown, ``(M_g - I) ω``, so turns show in its error.
    ``error_by_time``: the mean error over each whole ``window_s`` (``t`` its start) that
    holds a keyframe, where a bias held wrong after a turn shows as a step.
    """
    inside = _inside_truth(keyframes, truth_t)
    if len(inside) < 2:
        return None
    t = np.array([kf.t for kf in inside])
    true = np.degrees([_truth_at(kf.t, truth_t, truth.gyro_bias) for kf in inside])
    error = np.degrees([kf.gyro_bias for kf in inside]) - true
    windows = [(start, (t >= start) & (t < start + window_s))
               for start in np.arange(t[0], t[-1] - window_s + 1e-9, window_s)]
    by_time = [{"t": float(start), "mean_error": error[chosen].mean(axis=0).tolist()}
               for start, chosen in windows if chosen.any()]
    return {"mean_error": error.mean(axis=0).tolist(),
            "rms_error": np.sqrt((error**2).mean(axis=0)).tolist(),
            "true_mean": true.mean(axis=0).tolist(),
            "heading_deg": float(-trapezoid(error[:, 2], t)),
            "error_by_time": by_time}


def _yaw(T_W_B: np.ndarray) -> float:
    """The heading of the body's x axis in the world's horizontal plane, radians."""
    return math.atan2(T_W_B[1, 0], T_W_B[0, 0])


def _scale_by_time(t: np.ndarray, estimated: np.ndarray, true: np.ndarray) -> list[dict]:
    """How the estimate's size over the truth's changes through the flight: for each whole
    :data:`SCALE_WINDOW_S` of it (``t`` its start; the remainder at the end is left out), the
    length of the estimated path sampled every :data:`SCALE_STEP_S` over the true one's
    (lengths need no alignment). Windows where the truth moved under
    :data:`SCALE_MIN_DISTANCE_M` are left out."""
    if len(t) < 2:
        return []
    steps = np.searchsorted(t, np.arange(t[0], t[-1], SCALE_STEP_S))
    per_window = int(round(SCALE_WINDOW_S / SCALE_STEP_S))
    windows = []
    for first in range(0, len(steps) - per_window, per_window):
        chosen = steps[first:first + per_window + 1]
        true_length = path_length(true[chosen])
        if true_length >= SCALE_MIN_DISTANCE_M:
            windows.append({"t": float(t[chosen[0]]),
                            "scale": float(path_length(estimated[chosen]) / true_length)})
    return windows


def _consistency_metrics(keyframes: list[KeyframeEstimate], truth_t: np.ndarray,
                         truth: GroundTruthTable) -> dict:
    """NEES of each keyframe's pose and velocity (``autonomy.trajectory``) against the truth
    at its time, over the keyframes inside the truth's span.

    The truth is put in the estimator's world by the yaw and translation that take the first
    such keyframe's true pose onto its estimate (``yaw_alignment``), not by a best fit over
    the whole path: position and yaw are unobservable, so their covariance grows from the
    gauge prior at the start, and only an error measured from there is the one it describes.
    ``nees_pose_by_axis``: the mean of ``e_i^2 / P_ii`` for each pose axis (roll, pitch, yaw
    about the body axes, then x, y, z in the body), 1 where that axis's variance is honest:
    which part of the estimate is overconfident. A keyframe with an unusable covariance is
    left out and counted in ``nees_refused``.
    """
    inside = [kf for kf in _inside_truth(keyframes, truth_t) if kf.pose_covariance is not None]
    empty = {"nees_pose_mean": None, "nees_pose_median": None, "nees_velocity_mean": None,
             "nees_velocity_median": None, "nees_pose_by_axis": None, "nees_keyframes": 0,
             "nees_refused": 0}
    if not inside:
        return empty
    pose_nees, velocity_nees, by_axis, refused = [], [], [], 0
    for kf, (true_pose, true_velocity) in zip(inside, _truth_in_world(inside, truth_t, truth)):
        error = pose_error_body(kf.T_W_B, true_pose)
        try:
            pose = nees(error, kf.pose_covariance)
            velocity = nees(true_velocity - kf.velocity_W, kf.velocity_covariance)
        except ValueError:
            refused += 1
            continue
        pose_nees.append(pose)
        velocity_nees.append(velocity)
        by_axis.append(error**2 / np.diag(kf.pose_covariance))
    if not pose_nees:
        return {**empty, "nees_refused": refused}
    return {"nees_pose_mean": float(np.mean(pose_nees)),
            "nees_pose_median": float(np.median(pose_nees)),
            "nees_velocity_mean": float(np.mean(velocity_nees)),
            "nees_velocity_median": float(np.median(velocity_nees)),
            "nees_pose_by_axis": np.mean(by_axis, axis=0).tolist(),
            "nees_keyframes": len(pose_nees), "nees_refused": refused}


def _rebuild_report(rebuild: Rebuild, truth_t: np.ndarray, truth: GroundTruthTable) -> dict:
    """What the window was like just before a rebuild (docs/vins.md, the resets): the
    variable GTSAM named in its failure, and of the last keyframe before it the reported
    position and yaw (about the body's z) sigma, the landmarks in the window, and its speed
    and accelerometer-bias errors against the truth (frame-free, so no alignment)."""
    named = re.search(r"Symbol: (\w+)", rebuild.failure)
    report = {"t": rebuild.t, "variable": named.group(1) if named else None,
              "position_sigma_m": None, "yaw_sigma_deg": None, "landmarks": None,
              "speed_error_m_s": None, "accel_bias_error_m_s2": None}
    before = rebuild.before
    if before is None:
        return report
    true_velocity = _truth_at(before.t, truth_t, truth.velocity)
    true_bias = _truth_at(before.t, truth_t, truth.accel_bias)
    covariance = before.pose_covariance
    if covariance is not None:
        report.update(position_sigma_m=finite_or_none(np.sqrt(np.trace(covariance[3:, 3:]))),
                      yaw_sigma_deg=finite_or_none(np.degrees(np.sqrt(covariance[2, 2]))))
    return {**report, "landmarks": before.landmarks,
            "speed_error_m_s": float(np.linalg.norm(before.velocity_W)
                                     - np.linalg.norm(true_velocity)),
            "accel_bias_error_m_s2": float(np.linalg.norm(before.accel_bias - true_bias))}


def _true_pose(t: float, truth_t: np.ndarray, truth: GroundTruthTable) -> np.ndarray:
    """The true body pose ``T_W_B`` (4x4) at time ``t``, interpolated."""
    positions, quaternions = interpolate_poses([t], truth_t, truth.position, truth.q_W_B)
    return make_pose(quat_to_rot(quaternions[0]), positions[0])


def _truth_at(t: float, truth_t: np.ndarray, table: np.ndarray) -> np.ndarray:
    """A ground-truth vector table (N, k) interpolated at time ``t``, column by column."""
    return np.array([np.interp(t, truth_t, column) for column in table.T])


def _truth_in_world(keyframes: list[KeyframeEstimate], truth_t: np.ndarray,
                    truth: GroundTruthTable) -> list[tuple[np.ndarray, np.ndarray]]:
    """The true pose and velocity at each keyframe's time, in the estimator's world: turned
    and shifted by the ``yaw_alignment`` that takes the first one onto its estimate."""
    positions, quaternions = interpolate_poses([kf.t for kf in keyframes], truth_t,
                                               truth.position, truth.q_W_B)
    velocities = [_truth_at(kf.t, truth_t, truth.velocity) for kf in keyframes]
    poses = [make_pose(quat_to_rot(q), p) for p, q in zip(positions, quaternions)]
    T_W_G = yaw_alignment(keyframes[0].T_W_B, poses[0])
    return [(T_W_G @ pose, T_W_G[:3, :3] @ velocity) for pose, velocity in zip(poses, velocities)]


def _init_metrics(static_init: StaticInit | None, truth_t: np.ndarray,
                  truth: GroundTruthTable) -> dict | None:
    """The static initialisation against the ground truth at its end time ``t_end``: angle
    between the estimated up-vector in the body and the true one, ``R_W_B^T e_z``, and
    ``|b - b_true| / |b_true|`` of the gyro bias (None for a bias-free IMU)."""
    if static_init is None:
        return None
    t = float(static_init.t_end)
    try:
        _, q = interpolate_poses([t], truth_t, truth.position, truth.q_W_B)
    except ValueError:  # initialised outside the ground truth's span: nothing to compare
        return {"t": t, "gravity_err_deg": None, "gyro_bias_err_rel": None}
    up_true = quat_to_rot(q[0]).T @ np.array([0.0, 0.0, 1.0])
    bias_true = _truth_at(t, truth_t, truth.gyro_bias)
    bias_norm = float(np.linalg.norm(bias_true))
    bias_error = float(np.linalg.norm(np.asarray(static_init.gyro_bias) - bias_true))
    return {"t": t, "gravity_err_deg": math.degrees(_angle(static_init.gravity_B, up_true)),
            "gyro_bias_err_rel": bias_error / bias_norm if bias_norm > 0.0 else None}


def _angle(a, b) -> float:
    """The angle between two vectors, ``atan2(|a x b|, a . b)`` (accurate near zero)."""
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b)))




def _alignment_text(alignment: dict | None) -> str:
    """The gyro alignment's line: none, a calibration given (no pairs), or the estimate."""
    if alignment is None:
        return "not corrected"
    column = " ".join(f"{c:+.4f}" for c in alignment["column"])
    if alignment.get("matrix") is not None:
        column += " (the whole matrix by rows: " + "; ".join(
            " ".join(f"{c:+.4f}" for c in row) for row in alignment["matrix"]) + ")"
    if not alignment["pairs"]:
        return f"{column} as given ([vins] gyro_alignment), not estimated"
    return f"{column} over {alignment['pairs']} frame pairs"


def _texture_text(by_texture: dict | None) -> str:
    """The track errors by their predicted noise, a line
    (:func:`~companion.tools.eval.tracks.texture_summary`)."""
    if by_texture is None:
        return "none scored"
    bins = ", ".join(f"{b['predicted_median']:.2f}: {b['median_px']:.2f} px"
                     for b in by_texture["bins"])
    return (f"median error in {len(by_texture['bins'])} bins of the predicted relative noise "
            f"({bins}); rank correlation {show(by_texture['spearman'], '.2f')}")


def _gyro_bias_text(bias: dict | None) -> str:
    """The gyro bias's line: its mean and RMS error per axis and the heading they turn."""
    if bias is None:
        return "too few keyframes"
    mean = ", ".join(f"{v:+.4f}" for v in bias["mean_error"])
    rms = ", ".join(f"{v:.4f}" for v in bias["rms_error"])
    return (f"mean error ({mean}) deg/s, RMS ({rms}); the z error turns the heading "
            f"{bias['heading_deg']:+.2f} deg over the flight")


def _mounting_text(mounting: dict | None) -> str:
    """The mounting's line: not estimated, or the estimate's offset (camera axes)."""
    if mounting is None:
        return "not estimated"
    rotation = " ".join(f"{c:+.3f}" for c in mounting["rotation_deg"])
    translation = " ".join(f"{c:+.1f}" for c in mounting["translation_mm"])
    return f"rotation ({rotation}) deg, position ({translation}) mm, in the camera's axes"


def _bound_text(bound: dict) -> str:
    if "note" in bound:
        return f"what the factors allow: {bound['note']}"
    return f"what the factors allow, over {bound['keyframes']} keyframes: " + "; ".join(
        f"{label} ATE {show(bound[name]['ate_over_distance'], '.2%')}, scale "
        f"{show(bound[name]['scale'], '.4f')}"
        for name, label in (("fixed_lag", "the smoother"), ("causal_batch", "causal batch"),
                            ("whole_flight_batch", "whole-flight batch")))


def format_vio_report(result: dict) -> str:
    """The evaluation result as a few lines a person reads."""
    init = result["init"]
    note = f"; {result['note']}" if "note" in result else ""
    lines = [
        f"{result['dataset']}: {result['frames']} frames, {result['keyframes']} keyframes, "
        f"{result['resets']} resets; keyframe corrections "
        f"{show(result['correction_m_median'], '.4f', ' m')} median, "
        f"{show(result['correction_m_max'], '.4f', ' m')} at most",
        f"trajectory: ATE {show(result['ate_rmse_m'], '.3f', ' m')} over "
        f"{show(result['distance_m'], '.1f', ' m')} "
        f"({show(result['ate_over_distance'], '.2%')}), scale error "
        f"{show(result['scale_error'], '.2%')}; without the scale error ATE "
        f"{show(result['ate_sim3_rmse_m'], '.3f', ' m')}; heading drift "
        f"{show(result['heading_drift_deg'], '+.2f', ' deg')}{note}",
        "scale through the flight: " + (", ".join(
            f"{w['scale']:.3f} from {w['t']:.0f} s" for w in result["scale_by_time"]) or "none"),
        f"consistency: NEES of pose {show(result['nees_pose_mean'], '.1f')} mean, "
        f"{show(result['nees_pose_median'], '.1f')} median (6 if the covariance is honest), of "
        f"velocity {show(result['nees_velocity_mean'], '.1f')} mean, "
        f"{show(result['nees_velocity_median'], '.1f')} median (3), over "
        f"{result['nees_keyframes']} keyframes",
        "gyro bias against the truth (x, y, z): " + _gyro_bias_text(result["gyro_bias"]),
        "the last keyframe through the first's gauge: " + (
            "none (under two keyframes, or a path ending where it began)"
            if result["end_split"] is None else
            f"{result['end_split']['distance_m']:.1f} m flown"
            + format_split(result["end_split"])),
        f"depth: median relative error {show(result['depth_rel_err_median'], '.1%')} over "
        f"{result['depth_points']} landmarks",
        f"tracks: {show(result['track_error_px_median'], '.2f', ' px')} median error against "
        + ("the truth through the camera's true mounting and exposures ("
           if result.get("track_error_reference") == "camera truth" else
           "the truth through the calibration and the stamps (")
        + ", ".join(f"{bin_['ages']} frames old {show(bin_['median_px'], '.2f', ' px')}, "
                    f"outward {show(bin_['outward_mean_px'], '+.2f', ' px')} mean"
                    for bin_ in result["track_error_by_age"]) + ")",
        "tracks by texture: " + _texture_text(result.get("track_error_by_texture")),
        "init: none" if init is None else
        f"init at t={init['t']:.2f} s: gravity error "
        f"{show(init['gravity_err_deg'], '.2f', ' deg')}, gyro bias error "
        f"{show(init['gyro_bias_err_rel'], '.1%')}",
        f"time: front-end {show(result['frontend_ms_median'], '.1f', ' ms')} median, back-end "
        f"{show(result['backend_ms_median'], '.1f', ' ms')} median and "
        f"{show(result['backend_ms_p95'], '.1f', ' ms')} p95 per keyframe",
        "health: " + ", ".join(f"{name} {count}" for name, count in result["health"].items()),
        f"camera-IMU time offset: {result['time_offset_ms']:.2f} ms"
        + ("" if result["time_offset_sigma_ms"] is None
           else f" (sigma {result['time_offset_sigma_ms']:.2f} ms)"),
        "gyro's response to the yaw rate (x, y, z): " + _alignment_text(result["gyro_alignment"]),
        "camera mounting off the configured one: " + _mounting_text(result["camera_mounting"]),
        "accelerometer's z sensitivity read at rest: " + (
            "not read ([vins] rest_accel_scale_share 0)"
            if result.get("rest_accel_scale_error") is None
            else f"{result['rest_accel_scale_error']:+.3%}, divided out"),
        "rotor drag fitted on the estimate: " + (
            "too few keyframes in flight" if result["drag_fit"] is None else
            f"{result['drag_fit']['coefficient_per_s']:.3f} 1/s over "
            f"{result['drag_fit']['intervals']} keyframe intervals (residual "
            f"{result['drag_fit']['residual_std']:.3f} m/s^2, speeds spread "
            f"{result['drag_fit']['speed_spread']:.2f} m/s; [vins] drag_coefficient)"),
        *([] if "bound" not in result else [_bound_text(result["bound"])]),
        *(f"rebuild at t={r['t']:.2f} s near {r['variable'] or '?'}: before it "
          f"{show(r['landmarks'], 'd')} landmarks, position sigma "
          f"{show(r['position_sigma_m'], '.3f', ' m')}, speed error "
          f"{show(r['speed_error_m_s'], '+.3f', ' m/s')}" for r in result["rebuilds"]),
    ]
    return "\n".join(lines)

