"""The flight recorder's topics: each channel of the flight process as a Foxglove message.

One topic per message kind (docs/recording.md, "Topics", lists them). Where Foxglove has a
well-known schema (images, point clouds, poses, scene lines, logs) the topic uses it, encoded
as protobuf by foxglove-sdk, so Foxglove's panels show it as it is; the project's own records
(IMU samples, TIMESYNC, the depth fit, the planner's decision, setpoints, VINS health) are JSON
with a JSON schema. Frames: ``world`` is the VINS world ``W`` (z up), ``body`` the body FLU,
``camera`` the rectified camera, optical, ``local`` PX4's local frame ``L`` (ENU) (DESIGN.md,
"Conventions"), ``truth`` the body where the simulator truly had it (simulated flights only).

Every ``encode_*`` function turns one message into the bytes of its topic. They run on the
recorder's writer thread, never on the event loop (:mod:`companion.recording.writer`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import cv2
import foxglove
import foxglove.messages as fm
import numpy as np

from autonomy.geometry import PinholeCamera, rot_to_quat
from autonomy.messages import Frame, ImuSample, MetricDepth, Odometry, SparseMap
from autonomy.navigation.mission import FlightState, Transition
from autonomy.planning.planner import Plan, Setpoint
from autonomy.vins.estimator import FrameUpdate

WORLD, BODY, CAMERA, LOCAL, TRUTH = "world", "body", "camera", "local", "truth"

#: Every ``*_STRIDE``-th pixel in each direction is recorded, to keep a flight near 2 MB/s: a
#: 640x480 frame's metric depth is 160x120 millimetres (38 kB), its relative disparity 80x60
#: float32 (19 kB), its point cloud 40x30 points (19 kB).
METRIC_STRIDE, RELATIVE_STRIDE, CLOUD_STRIDE = 4, 8, 16
#: The largest depth a 16-bit millimetre image holds, metres.
MAX_DEPTH_MM = 65535
#: Points along each drawn primitive.
LINE_POINTS = 8


def _json_schema(name: str, properties: dict) -> foxglove.Schema:
    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(
        {"type": "object", "properties": properties}).encode())


_NUMBER, _STRING, _BOOL = {"type": "number"}, {"type": "string"}, {"type": "boolean"}
_VECTOR = {"type": "array", "items": _NUMBER}


@dataclass(frozen=True)
class Topic:
    """A topic's name, its schema, and whether the writer may drop its messages when the
    disk or the writer falls behind (the heavy images; never events or IMU)."""

    name: str
    schema: foxglove.Schema
    droppable: bool = False


CAMERA_IMAGE = Topic("/camera/image", fm.CompressedImage.get_schema(), droppable=True)
CAMERA_CALIBRATION = Topic("/camera/calibration", fm.CameraCalibration.get_schema())
TRANSFORMS = Topic("/tf", fm.FrameTransform.get_schema())
IMU = Topic("/imu", _json_schema("companion.ImuSample", {
    "t": _NUMBER, "gyro": _VECTOR, "accel": _VECTOR, "pressure_pa": _NUMBER}))
TIMESYNC = Topic("/mavlink/timesync", _json_schema("companion.Timesync", {
    "offset_s": _NUMBER, "rtt_s": _NUMBER, "used": _BOOL}))
ODOMETRY = Topic("/vins/odometry", _json_schema("companion.Odometry", {
    "t": _NUMBER, "position": _VECTOR, "quaternion_wxyz": _VECTOR, "velocity": _VECTOR,
    "angular_velocity_body": _VECTOR, "pose_sigma": _VECTOR}))
VINS_MAP = Topic("/vins/map", fm.PointCloud.get_schema())
VINS_HEALTH = Topic("/vins/health", _json_schema("companion.VinsHealth", {
    "t": _NUMBER, "keyframe": _BOOL, "state": _STRING, "reason": _STRING, "tracked": _NUMBER,
    "landmarks": _NUMBER, "parallax_px": _NUMBER, "time_offset_s": _NUMBER,
    "time_offset_sigma_s": _NUMBER, "correction_m": _NUMBER}))
DEPTH_RELATIVE = Topic("/depth/relative", fm.RawImage.get_schema(), droppable=True)
DEPTH_METRIC = Topic("/depth/metric", fm.RawImage.get_schema(), droppable=True)
DEPTH_POINTS = Topic("/depth/points", fm.PointCloud.get_schema(), droppable=True)
#: The renderer's true depth of each frame, full resolution (simulated flights only): what
#: replay measures depth accuracy against and feeds the synthetic network.
TRUTH_DEPTH = Topic("/truth/depth", fm.RawImage.get_schema(), droppable=True)
DEPTH_FIT = Topic("/depth/fit", _json_schema("companion.DepthFit", {
    "t": _NUMBER, "ok": _BOOL, "held": _BOOL, "fallback": _BOOL, "method": _STRING,
    "reason": _STRING, "anchors": _NUMBER, "anchors_used": _NUMBER, "residual_rms": _NUMBER,
    "fit_age_s": _NUMBER, "anchor_relative": _VECTOR, "anchor_depth": _VECTOR,
    "curve_relative": _VECTOR, "curve_metric_disparity": _VECTOR}))
PLAN_LINES = Topic("/planner/primitives", fm.SceneUpdate.get_schema())
PLAN = Topic("/planner/plan", _json_schema("companion.Plan", {
    "t": _NUMBER, "kind": _STRING, "reason": _STRING, "safe_count": _NUMBER,
    "clearance": _NUMBER, "speed": _NUMBER, "yaw_rate": _NUMBER, "vertical_speed": _NUMBER,
    "height_swing": _NUMBER, "chosen": _NUMBER, "safe": {"type": "array", "items": _BOOL},
    "blocked": {"type": "array", "items": _BOOL}, "radius": _NUMBER,
    "faster": {"type": "array", "items": {"type": "object", "properties": {
        "speed": _NUMBER, "blocked": _NUMBER, "unseen": _NUMBER}}},
    "start": _VECTOR, "start_yaw": _NUMBER, "request": {"type": "object", "properties": {
        "T_W_B": _VECTOR, "velocity": _VECTOR, "goal": _VECTOR, "stop_at_goal": _BOOL}}}))
SETPOINT = Topic("/command/setpoint", _json_schema("companion.Setpoint", {
    "velocity": _VECTOR, "yaw_rate": _NUMBER, "acceleration": _VECTOR, "position": _VECTOR}))
EVENTS = Topic("/flight/events", fm.Log.get_schema())
LOG = Topic("/log", fm.Log.get_schema())

TOPICS = (CAMERA_IMAGE, CAMERA_CALIBRATION, TRANSFORMS, IMU, TIMESYNC, ODOMETRY, VINS_MAP,
          VINS_HEALTH, DEPTH_RELATIVE, DEPTH_METRIC, DEPTH_POINTS, DEPTH_FIT, PLAN_LINES, PLAN,
          SETPOINT, EVENTS, LOG, TRUTH_DEPTH)

#: States whose entry is a failsafe or an abort: logged at warning level.
WARNING_STATES = frozenset({FlightState.FAILSAFE_STOP, FlightState.LINK_LOST,
                            FlightState.ABORTED})
#: Python logging levels to Foxglove's.
_LOG_LEVELS = ((40, fm.LogLevel.Error), (30, fm.LogLevel.Warning), (20, fm.LogLevel.Info))


def nanoseconds(t: float) -> int:
    """Companion-clock seconds as the integer nanoseconds MCAP stamps messages with."""
    return int(round(t * 1e9))


def _stamp(t: float) -> fm.Timestamp:
    ns = nanoseconds(t)
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _json(record: dict) -> bytes:
    """JSON with NaN and infinities as null (JSON has neither)."""
    return json.dumps(record, default=_plain, allow_nan=False).encode()


def _plain(value):
    if isinstance(value, np.ndarray):
        return [_finite(v) for v in value.ravel().tolist()]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _finite(value):
    return value if not isinstance(value, float) or math.isfinite(value) else None


def _clean(record: dict) -> dict:
    return {k: _finite(v) if isinstance(v, float) else v for k, v in record.items()}


def _identity_pose() -> fm.Pose:
    """Where a cloud or a line sits in its frame: at the frame itself."""
    return fm.Pose(position=fm.Vector3(x=0.0, y=0.0, z=0.0),
                   orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def encode_image(frame: Frame, image_format: str = "jpeg", jpeg_quality: int = 90) -> bytes:
    """The camera frame as ``jpeg`` or ``png`` (RGB in, so OpenCV is handed BGR)."""
    parameters = (cv2.IMWRITE_JPEG_QUALITY, jpeg_quality) if image_format == "jpeg" else ()
    ok, encoded = cv2.imencode("." + image_format,
                               cv2.cvtColor(frame.image, cv2.COLOR_RGB2BGR), parameters)
    if not ok:
        raise ValueError(f"{image_format} encoding failed for the frame at t={frame.t:.3f}")
    return fm.CompressedImage(timestamp=_stamp(frame.t), frame_id=CAMERA,
                              data=encoded.tobytes(), format=image_format).encode()


def encode_calibration(t: float, pinhole: PinholeCamera) -> bytes:
    """The rectified pinhole every stage sees (its images carry no distortion)."""
    K = [pinhole.fx, 0.0, pinhole.cx, 0.0, pinhole.fy, pinhole.cy, 0.0, 0.0, 1.0]
    P = [pinhole.fx, 0.0, pinhole.cx, 0.0, 0.0, pinhole.fy, pinhole.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return fm.CameraCalibration(
        timestamp=_stamp(t), frame_id=CAMERA, width=pinhole.width, height=pinhole.height,
        distortion_model="plumb_bob", D=[0.0] * 5, K=K,
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], P=P).encode()


def encode_transform(t: float, parent: str, child: str, T_parent_child: np.ndarray) -> bytes:
    T = np.asarray(T_parent_child, dtype=float)
    w, x, y, z = rot_to_quat(T[:3, :3])
    return fm.FrameTransform(
        timestamp=_stamp(t), parent_frame_id=parent, child_frame_id=child,
        translation=fm.Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
        rotation=fm.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))).encode()


def encode_imu(sample: ImuSample) -> bytes:
    """The sample; its ``pressure_pa`` only where it has one (recordings made before the
    barometer have none)."""
    record = {"t": sample.t, "gyro": np.asarray(sample.gyro), "accel": np.asarray(sample.accel)}
    if sample.pressure_pa is not None:
        record["pressure_pa"] = sample.pressure_pa
    return _json(record)


def encode_timesync(offset_s: float | None, rtt_s: float | None, used: bool) -> bytes:
    return _json({"offset_s": offset_s, "rtt_s": rtt_s, "used": used})


def encode_odometry(odometry: Odometry) -> bytes:
    covariance = np.asarray(odometry.pose_covariance, dtype=float)
    return _json({"t": odometry.t, "position": odometry.T_W_B[:3, 3],
                  "quaternion_wxyz": rot_to_quat(odometry.T_W_B[:3, :3]),
                  "velocity": np.asarray(odometry.velocity_W),
                  "angular_velocity_body": np.asarray(odometry.angular_velocity_B),
                  "pose_sigma": np.sqrt(np.abs(np.diag(covariance)))})


def _point_cloud(t: float, frame_id: str, columns: dict[str, np.ndarray]) -> bytes:
    """A Foxglove PointCloud of float32 columns (``x``, ``y``, ``z`` and any others)."""
    names = list(columns)
    data = np.column_stack([np.asarray(columns[n], dtype=np.float32) for n in names])
    fields = [fm.PackedElementField(name=n, offset=4 * i,
                                    type=fm.PackedElementFieldNumericType.Float32)
              for i, n in enumerate(names)]
    return fm.PointCloud(timestamp=_stamp(t), frame_id=frame_id, pose=_identity_pose(),
                         point_stride=4 * len(names), fields=fields,
                         data=np.ascontiguousarray(data).tobytes()).encode()


def encode_sparse_map(sparse_map: SparseMap) -> bytes:
    """The VINS landmarks in the frame's camera, with each one's depth sigma and whether this
    frame tracked it (1) or merely projected it (0)."""
    points = np.asarray(sparse_map.points_C, dtype=float).reshape(-1, 3)
    return _point_cloud(sparse_map.t, CAMERA, {
        "x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
        "depth_sigma": sparse_map.depth_sigma,
        "tracked": np.asarray(sparse_map.tracked, dtype=np.float32)})


def encode_vins_health(update: FrameUpdate) -> bytes:
    health = update.health
    return _json(_clean({"t": update.t, "keyframe": update.keyframe,
                         "state": health.state.value, "reason": health.reason,
                         "tracked": health.tracked, "landmarks": health.landmarks,
                         "parallax_px": float(health.parallax_px),
                         # the camera-IMU time offset in use, estimated or configured
                         "time_offset_s": update.time_offset.seconds,
                         "time_offset_sigma_s": update.time_offset.sigma,
                         # keyframes: how far the smoother moved the IMU-propagated position
                         "correction_m": update.correction_m}))


def encode_relative(t: float, disparity: np.ndarray) -> bytes:
    """The network's relative disparity, every :data:`RELATIVE_STRIDE`-th pixel, as
    Foxglove's ``32FC1``."""
    small = np.ascontiguousarray(disparity[::RELATIVE_STRIDE, ::RELATIVE_STRIDE],
                                 dtype=np.float32)
    return _raw_image(t, small, "32FC1")


def encode_metric(t: float, depth: np.ndarray, stride: int = METRIC_STRIDE) -> bytes:
    """Metric depth, every ``stride``-th pixel, as Foxglove's depth image convention ``16UC1``
    in millimetres, 0 where unknown."""
    small = depth[::stride, ::stride]
    millimetres = np.where(np.isfinite(small), np.clip(small * 1e3, 0, MAX_DEPTH_MM), 0)
    return _raw_image(t, np.ascontiguousarray(millimetres, dtype=np.uint16), "16UC1")


def encode_true_depth(t: float, depth: np.ndarray) -> bytes:
    """The renderer's true depth at full resolution, as Foxglove's ``32FC1`` in metres (inf
    where nothing is hit): exact, so a replay feeds the synthetic network what the flight
    did (millimetres would round it, and clip the far field at 65.5 m)."""
    return _raw_image(t, np.ascontiguousarray(depth, dtype=np.float32), "32FC1")


def _raw_image(t: float, image: np.ndarray, encoding: str) -> bytes:
    height, width = image.shape
    return fm.RawImage(timestamp=_stamp(t), frame_id=CAMERA, width=width, height=height,
                       encoding=encoding, step=image.itemsize * width,
                       data=image.tobytes()).encode()


def encode_depth_points(depth: MetricDepth, pinhole: PinholeCamera) -> bytes:
    """The metric depth as points in the camera frame, every :data:`CLOUD_STRIDE`-th pixel,
    with their confidence; unknown pixels left out."""
    v, u = np.mgrid[0:pinhole.height:CLOUD_STRIDE, 0:pinhole.width:CLOUD_STRIDE]
    z = depth.depth[::CLOUD_STRIDE, ::CLOUD_STRIDE]
    known = np.isfinite(z)
    z, u, v = z[known], u[known], v[known]
    return _point_cloud(depth.t, CAMERA, {
        "x": (u - pinhole.cx) / pinhole.fx * z, "y": (v - pinhole.cy) / pinhole.fy * z, "z": z,
        "confidence": depth.confidence[::CLOUD_STRIDE, ::CLOUD_STRIDE][known]})


def encode_depth_fit(depth: MetricDepth) -> bytes:
    """The frame's fit (Yang et al., Section III-B): its anchors, the curve from relative to
    metric disparity over their range, and the diagnostics."""
    d, fit = depth.diagnostics, depth.fit
    record = _clean({"t": depth.t, "ok": depth.ok, "held": depth.held,
                     "fallback": d.fallback, "method": d.method, "reason": d.reason,
                     "anchors": d.anchors, "anchors_used": d.anchors_used,
                     "residual_rms": float(d.residual_rms), "fit_age_s": float(d.fit_age_s)})
    if fit is not None:
        record.update(anchor_relative=fit.anchor_relative, anchor_depth=fit.anchor_depth,
                      curve_relative=fit.curve_relative,
                      curve_metric_disparity=fit.curve_metric_disparity)
    return _json(record)


def encode_plan(plan: Plan) -> bytes:
    """The planner's decision: the primitive flown, and the height wave's amplitude it is
    flown with (``height_swing``, 0 when level); for an arc, the tier it was chosen from
    (which were safe, which blocked by an observed surface, which one was chosen, the sphere's
    radius they were checked with; for "no safe primitive" the slowest tier, chosen -1; why
    each faster tier had nothing safe, ``faster``: its primitives blocked and unseen); for a
    round of the planner, what it was asked (the body's pose as 16 row-major numbers,
    velocity, goal), which replay asks again."""
    p, candidates = plan.primitive, plan.candidates
    record = _clean({"t": plan.t, "kind": plan.kind, "reason": plan.reason,
                     "safe_count": plan.safe_count, "clearance": float(plan.clearance),
                     "speed": float(p.speed), "yaw_rate": float(p.yaw_rate),
                     "vertical_speed": float(p.vertical_speed),
                     "height_swing": 0.0 if plan.height_wave is None
                     else plan.height_wave.amplitude,
                     "start": plan.T_W_S[:3, 3],
                     "start_yaw": math.atan2(plan.T_W_S[1, 0], plan.T_W_S[0, 0])})
    if candidates is not None:
        record.update(chosen=candidates.chosen, safe=candidates.safe.tolist(),
                      blocked=candidates.blocked.tolist(), radius=candidates.radius,
                      faster=[tier._asdict() for tier in candidates.faster])
    if plan.request is not None:
        request = plan.request
        record["request"] = {"T_W_B": request.T_W_B, "velocity": request.velocity_W,
                             "goal": request.goal_W, "stop_at_goal": request.stop_at_goal}
    return _json(record)


_CHOSEN = fm.Color(r=0.1, g=0.9, b=0.2, a=1.0)
_SAFE = fm.Color(r=0.6, g=0.6, b=0.6, a=0.6)
_UNSAFE = fm.Color(r=0.9, g=0.1, b=0.1, a=0.6)


def encode_plan_lines(plan: Plan) -> bytes:
    """The plan in the 3D view: the primitive flown green, the tier's other safe ones grey,
    the unsafe ones red, in the tier's order, a stop after them (one scene entity per round,
    replacing the last)."""
    candidates = plan.candidates
    lines = [] if candidates is None else [
        (primitive, _CHOSEN if i == candidates.chosen else
         _SAFE if candidates.safe[i] else _UNSAFE)
        for i, primitive in enumerate(candidates.primitives)]
    if candidates is None or candidates.chosen < 0:
        lines.append((plan.primitive, _CHOSEN))
    entity = fm.SceneEntity(
        timestamp=_stamp(plan.t), frame_id=WORLD, id="plan",
        lines=[_line(plan.T_W_S, primitive, color) for primitive, color in lines])
    return fm.SceneUpdate(entities=[entity]).encode()


def _line(T_W_S: np.ndarray, primitive, color: fm.Color) -> fm.LinePrimitive:
    points_S = np.vstack([primitive.points_S, primitive.stop_points_S])
    keep = np.unique(np.linspace(0, len(points_S) - 1, LINE_POINTS).astype(int))
    points_W = points_S[keep] @ T_W_S[:3, :3].T + T_W_S[:3, 3]
    return fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=_identity_pose(),
                            thickness=0.03, scale_invariant=False,
                            points=[fm.Point3(x=float(x), y=float(y), z=float(z))
                                    for x, y, z in points_W], color=color)


def encode_setpoint(setpoint: Setpoint) -> bytes:
    return _json({"velocity": np.asarray(setpoint.velocity_W),
                  "yaw_rate": _finite(float(setpoint.yaw_rate)),
                  "acceleration": np.asarray(setpoint.acceleration_W),
                  "position": None if setpoint.position_W is None
                  else np.asarray(setpoint.position_W)})


def encode_transition(transition: Transition) -> bytes:
    """A state transition; one into :data:`WARNING_STATES` at warning level."""
    return encode_log(transition.t, 30 if transition.target in WARNING_STATES else 20, "mission",
                      f"{transition.source.value}{_ARROW}{transition.target.value}"
                      f"{_BECAUSE}{transition.reason}")


_ARROW, _BECAUSE = " -> ", ": "


def parse_transition(text: str) -> tuple[str, str, str]:
    """``(source, target, reason)`` of an ``/flight/events`` message; ValueError if it is not
    one :func:`encode_transition` wrote."""
    source, arrow, rest = text.partition(_ARROW)
    target, because, reason = rest.partition(_BECAUSE)
    if not (arrow and because):
        raise ValueError(f"not a state transition: {text!r}")
    return source, target, reason


def encode_log(t: float, level: int, name: str, message: str) -> bytes:
    foxglove_level = next((fl for threshold, fl in _LOG_LEVELS if level >= threshold),
                          fm.LogLevel.Debug)
    return fm.Log(timestamp=_stamp(t), level=foxglove_level, message=message,
                  name=name).encode()

