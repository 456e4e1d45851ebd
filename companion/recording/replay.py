"""``companion replay``: a recorded flight's camera and IMU through the VINS, the depth stage and
the planner again, under any config: the field engineer's tuning loop (docs/recording.md).

The recording is read in log-time order: the order in which the flight's stages handled its
messages (the recorder logs each when it is handled and publishes it at its own time). Each
IMU sample goes to the VINS when the flight fed it; each camera frame (decoded from the file,
so as the recorder stored it) goes through the VINS front-end and back-end where the flight's
VINS finished it (``/vins/health``), and through the depth source (the ``[depth_network]``
model, or for a simulated flight the synthetic stand-in on the recorded true depth, same seed)
and the rescaler where the flight's depth stage finished it (``/depth/fit``: the network takes
only the frames it is free for), its metric depth then joining the planner's history; each
planner round of the recording (``/planner/plan`` with its request) is asked again of the
replayed planner, with the round's recorded pose, velocity and goal. Nothing waits on a
clock: it runs as fast as the CPU allows. A simulated flight's recorded truth scores the
replayed VINS beside the recorded one where navigation ended; :data:`VINS_ONLY` replays the
VINS alone, the loop for a VINS option.

What "reproduces" means: the replay meets the messages in the order the flight's stages did,
so a lockstep simulated flight recorded with a lossless camera (``[recorder] camera_format =
"png"``) replays to its own VINS, depth and planner decisions. A JPEG camera image is not the
frame the flight saw: the VINS tracks slightly different corners, and the depth and the
decisions drift from the flight's, closely but not exactly. In real time, threads order some
messages differently from one run to the next, which a replay cannot know. So
:class:`ReplayReport` gives the agreement, and a change of config is read against the replay
of the recording's own config, not against the flight.
"""

from __future__ import annotations

import json
import math
import time
import tomllib
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import cv2
import foxglove.messages as fm
import numpy as np
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from autonomy.depth import metrics
from autonomy.depth.stage import MetricDepthStage
from autonomy.depth.synthetic import SyntheticNetwork
from autonomy.geometry import (PinholeCamera, make_pose, quat_to_rot, rot_z, so3_log,
                               yaw_alignment, yaw_of)
from autonomy.messages import Frame, ImuSample, RelativeDepth
from autonomy.navigation.behaviours import FLOWN_GROUND_REASONS
from autonomy.navigation.failsafes import BlindClock, Vitals, age, failsafe_reason
from autonomy.navigation.mission import (DISARMED_STATES, GUARDED_STATES, IN_PLACE_STATES,
                                        FlightState)
from autonomy.planning.planner import Planner
from autonomy.trajectory import DisplacementSplit, split_displacement
from autonomy.vins.estimator import Vins
from autonomy.vins.health import HealthState
from companion.config import config_from_toml, load_config
from companion.recording import topics
from companion.recording.writer import COMPANION_METADATA

if TYPE_CHECKING:
    from drivers.sim.record import FlownMotion

#: The schema of each of the recorder's topics, by name.
_SCHEMAS = {topic.name: topic.schema.name for topic in topics.TOPICS}
#: Frames the VINS finished that wait for the depth stage at most: the flight's network takes
#: the newest frame when it is free, so all but the last few are ones it skipped.
_AWAITING_DEPTH_MAX = 8
#: The camera's frames and what replay needs besides, by topic.
_READ = (topics.IMU.name, topics.CAMERA_IMAGE.name, topics.TRUTH_DEPTH.name,
         topics.VINS_HEALTH.name, topics.DEPTH_FIT.name, topics.DEPTH_METRIC.name,
         topics.PLAN.name, topics.CAMERA_CALIBRATION.name, topics.TRANSFORMS.name,
         topics.EVENTS.name)
#: What a replay of the VINS alone reads: not the true depth, depth or plans.
_READ_VINS = tuple(name for name in _READ if name not in (
    topics.TRUTH_DEPTH.name, topics.DEPTH_FIT.name, topics.DEPTH_METRIC.name, topics.PLAN.name))
#: The stages a replay runs, all of them or the VINS alone.
ALL_STAGES, VINS_ONLY = ("vins", "depth", "planner"), ("vins",)
#: Recorded states in which the failsafe rules apply (autonomy.navigation.mission.
#: GUARDED_STATES); the turn in place, through which the blind clock holds; and the states on
#: flown ground (the turn, the offset swing), where depth may lapse (IN_PLACE_STATES).
_GUARDED = {state.value for state in GUARDED_STATES}
_ALIGNING = FlightState.ALIGNING.value
_IN_PLACE = {state.value for state in IN_PLACE_STATES}
#: Recorded states on the ground, disarmed, where the VINS was told so (its zero-velocity
#: prior: autonomy/vins/stillness.py); "" is the flight's start, before any transition.
_ON_GROUND = {state.value for state in DISARMED_STATES} | {""}
#: Recorded failsafes: the transitions into these states.
_FAILSAFE_STATES = {FlightState.FAILSAFE_STOP.value, FlightState.LINK_LOST.value}
#: A recorded rotation further than this from a unit quaternion is not one (the recorder
#: writes doubles, off by about 1e-16).
_UNIT_QUATERNION_TOLERANCE = 1e-6


class ReplayError(RuntimeError):
    """The recording cannot be replayed; the message says why."""


class _NoTruth(Exception):
    """A simulated frame whose true depth the recorder dropped: the synthetic stand-in has
    nothing to distort, so the frame gets no depth (counted)."""


@dataclass
class ReplayReport:
    """What the replay found, against the recording. Depth accuracy (AbsRel, the mean of
    |z - z*| / z*) on the frames with true depth, at the recorded metric depth's resolution
    for both; planner agreement over the recorded rounds (same kind, and for arcs the same
    primitive); ``vins_same_frames``: frames whose VINS state, tracked features and landmarks
    are the flight's; ``recorded_failsafes`` (time, reason) and ``replayed_failsafe``: the
    first failsafe the rules (:func:`~autonomy.navigation.failsafes.failsafe_reason`) would
    have raised on the replayed VINS, depth and planner at a recorded round while the flight
    was guarded (see :meth:`_Replayer._failsafe_check` for what it can and cannot know);
    stage timings per frame, medians in milliseconds. ``frames_without_truth``:
    simulated frames whose true depth the recorder dropped, so no depth was made for them.
    ``vins_error``: the recorded and the replayed VINS against the simulator's truth where
    navigation ended (:func:`_vins_at_end`), None for a recording without the truth or the
    tie to PX4's local frame. ``stages``: those replayed (:data:`ALL_STAGES`, or
    :data:`VINS_ONLY`, when the depth, planner and failsafe fields stay empty).
    ``lossy_frames``: camera images the recorder stored lossy (JPEG), which are not the frames
    the flight tracked, so the replay drifts from the flight (module docstring)."""

    stages: tuple = ALL_STAGES
    frames: int = 0
    vins_same_frames: int = 0
    lossy_frames: int = 0
    frames_without_truth: int = 0
    frames_with_depth: dict = field(default_factory=lambda: {"recorded": 0, "replayed": 0})
    abs_rel: dict = field(default_factory=lambda: {"recorded": math.nan, "replayed": math.nan})
    rounds: int = 0
    same_decision: int = 0
    changed_rounds: list = field(default_factory=list)
    vins_lost_frames: int = 0
    depth_failures: dict = field(default_factory=dict)
    recorded_failsafes: list = field(default_factory=list)
    replayed_failsafe: dict | None = None
    timings_ms: dict = field(default_factory=dict)
    vins_error: dict | None = None

    def as_dict(self) -> dict:
        agreement = self.same_decision / self.rounds if self.rounds else None
        return {"stages": list(self.stages), "frames": self.frames,
                "vins_same_frames": self.vins_same_frames,
                "lossy_frames": self.lossy_frames,
                "frames_without_truth": self.frames_without_truth,
                "frames_with_depth": self.frames_with_depth,
                "abs_rel": {k: _rounded(v) for k, v in self.abs_rel.items()},
                "planner_rounds": self.rounds, "planner_agreement": agreement,
                "changed_rounds": self.changed_rounds[:20],
                "vins_lost_frames": self.vins_lost_frames,
                "failsafes": {"recorded": self.recorded_failsafes,
                              "replayed_first": self.replayed_failsafe},
                "depth_failures": self.depth_failures, "timings_ms": self.timings_ms,
                "vins_error": self.vins_error}


def _rounded(value: float):
    return None if not math.isfinite(value) else round(value, 4)


def recorded_config(path: Path, overrides=(), config_path: Path | None = None):
    """The config to replay with: the recording's own (its ``companion`` metadata), or the
    file ``config_path``, with ``overrides`` on top; and the simulated mission, if any."""
    metadata = _metadata(path)
    if config_path is not None:
        config = load_config(config_path, overrides)
    elif "config" in metadata:
        config = config_from_toml(metadata["config"], f"{path} (recorded config)", overrides)
    else:
        raise ReplayError(f"{path} holds no config; give one with --config")
    mission = _mission(metadata["mission"], path) if "mission" in metadata else None
    return config, mission


def _mission(text: str, path: Path) -> dict:
    """The recorded simulated mission: a JSON object with an integer ``seed`` at least."""
    try:
        mission = json.loads(text)
    except ValueError as error:
        raise ReplayError(f"{path}: its mission is not JSON ({error})") from None
    if not (isinstance(mission, dict) and isinstance(mission.get("seed"), int)):
        raise ReplayError(f"{path}: its mission is not a simulated mission with a seed")
    return mission


def _metadata(path: Path) -> dict[str, str]:
    try:
        with open(path, "rb") as file:
            for record in make_reader(file).iter_metadata():
                if record.name == COMPANION_METADATA:
                    return dict(record.metadata)
    except FileNotFoundError:
        raise ReplayError(f"{path}: no such file") from None
    except Exception as error:  # noqa: BLE001 - whatever the MCAP reader makes of bad bytes
        raise _unreadable(path, error) from None
    return {}


def _decoded(file, topics_read) -> Iterator[tuple]:
    """mcap's ``(schema, channel, message, decoded)`` of ``file``, as :func:`_read` takes them."""
    reader = make_reader(file, decoder_factories=[_Decoders()])
    yield from reader.iter_decoded_messages(topics=list(topics_read), log_time_order=True)


def _unreadable(path: Path, error: Exception) -> ReplayError:
    return ReplayError(f"{path} is not a readable MCAP recording ({type(error).__name__}: "
                       f"{error}); a truncated one can be recovered with `companion log "
                       "recover`")


def _read(path: Path, topics_read, *, stamp: str = "publish_time") \
        -> Iterator[tuple[str, int, object]]:
    """``(topic, time in ns, decoded message)`` of the recording's messages on ``topics_read``,
    in log-time order; the time is the message's ``stamp``: ``publish_time`` (when it was
    measured) or ``log_time`` (when the flight handled it). Whatever the MCAP reader or a
    decoder (zstd, protobuf, JSON) raises on bytes it cannot read is a :class:`ReplayError`:
    the file is damaged; a file that cannot be opened (missing, a folder, no permission) is
    one too."""
    try:
        file = open(path, "rb")
    except OSError as error:
        raise ReplayError(f"{path}: cannot read: {error.strerror or error}") from None
    with file:
        messages = _decoded(file, topics_read)
        while True:
            try:
                schema, channel, message, decoded = next(messages)
            except StopIteration:
                return
            except Exception as error:  # noqa: BLE001 - the reader's and decoders' errors
                raise _unreadable(path, error) from None
            expected = _SCHEMAS[channel.topic]
            if getattr(schema, "name", None) != expected:
                raise ReplayError(f"{path}: {channel.topic} holds {getattr(schema, 'name', None)}"
                                  f" messages, not the recorder's {expected}")
            yield channel.topic, getattr(message, stamp), decoded


class _Replayer:
    """The stages of one replay and what they are compared with."""

    def __init__(self, config, mission: dict | None, stages: tuple = ALL_STAGES):
        self.config, self.mission = config, mission
        self.report = ReplayReport(stages=stages)
        self.pinhole: PinholeCamera | None = None
        self.T_B_C: np.ndarray | None = None
        self.vins: Vins | None = None
        self.stage = MetricDepthStage(config.rescale, config.depth)
        self.network = self._network() if "depth" in stages else None
        # by the frame's published time in nanoseconds (on_message):
        self.frames: dict[int, np.ndarray] = {}  # decoded images, until the VINS takes them
        # (frame, VINS update) of the frames the VINS finished, until the depth stage takes one
        self.awaiting_depth: dict[int, tuple[Frame, object]] = {}
        self.truth: dict[int, np.ndarray] = {}  # full resolution, until its frame is done
        self.truth_small: dict[int, np.ndarray] = {}  # at the recorded depth's resolution
        self.errors = {"recorded": _AbsRel(), "replayed": _AbsRel()}
        self.timings: dict[str, list[float]] = defaultdict(list)
        self.planner: Planner | None = None
        self.state = ""  # the recorded flight's state
        self.vins_health = None  # the replayed VINS's newest health
        self.last_depth_t: float | None = None  # newest replayed depth in the planner
        self.no_path_since: float | None = None  # replayed rounds with nothing safe since
        self.blind = BlindClock()  # how long the replayed VINS has been flown on blind
        # what the VINS is scored on, by frame: its poses (T_W_B), the true positions in
        # PX4's local frame; the recorded tie of the two frames (its time, T_L_W); the
        # navigation phase's start and end (published times, ns)
        self.poses: dict[str, dict[int, np.ndarray]] = {"recorded": {}, "replayed": {}}
        self.true_positions: dict[int, np.ndarray] = {}
        self.tie: tuple[int, np.ndarray] | None = None
        self.navigation: list[int | None] = [None, None]

    def _network(self):
        config = self.config
        if config.depth_network.model:
            from autonomy.depth.network import DepthNetwork

            model = DepthNetwork.open(config.depth_network,
                                      (config.camera.height, config.camera.width))
            return lambda frame: model(frame.image, channels="rgb")
        if self.mission is None:
            raise ReplayError("the recording is not of a simulated flight and [depth_network] "
                              "model is empty: name the ONNX model the flight used")
        stand_in = SyntheticNetwork(config.synthetic_depth.for_profile(config.sim.profile),
                                    seed=self.mission["seed"])

        def synthetic(frame: Frame):
            if frame.truth_depth is None:
                raise _NoTruth(frame.t)
            return stand_in(frame.truth_depth, frame.image)
        return synthetic

    def _start(self) -> None:
        """The VINS and planner, once the recording's camera model and mounting are read."""
        if self.pinhole is None or self.T_B_C is None:
            raise ReplayError("the recording has no /camera/calibration or body->camera /tf "
                              "before its first frame")
        config = self.config
        self.vins = Vins(self.pinhole, (0.0,) * 4, self.T_B_C, config.vins_imu, config.vins,
                         frontend=config.vins_frontend, static=config.vins_init)
        self.planner = Planner(self.pinhole, config.planner)

    def on_message(self, topic: str, t: int, message) -> None:
        """One message, ``t`` its published time in nanoseconds (a frame's exposure, a
        sample's): the key that ties a frame's messages together. The times the stages are
        given are the records' own float seconds, where they have one, so that the replay's
        comparisons of times (an IMU sample at a frame's instant) fall as the flight's did."""
        handler = getattr(self, "_on_" + topic.strip("/").replace("/", "_"))
        if topic in _RECORDS:
            _check_record(topic, message, _RECORDS[topic])
        handler(t, message)

    def finish(self) -> ReplayReport:
        for name, errors in self.errors.items():
            self.report.frames_with_depth[name] = errors.frames
            self.report.abs_rel[name] = errors.value
        self.report.timings_ms = {stage: round(float(np.median(values)) * 1e3, 2)
                                  for stage, values in self.timings.items()}
        self.report.depth_failures = dict(self.stage.no_fit)
        self.report.vins_error = _vins_at_end(self.poses, self.true_positions, self.tie,
                                              self.navigation[1])
        return self.report

    # what the recording holds

    def _on_camera_calibration(self, t, message) -> None:
        self.pinhole = _pinhole(message)

    def _on_tf(self, t, message) -> None:
        frames = (message.parent_frame_id, message.child_frame_id)
        if frames == (topics.BODY, topics.CAMERA):
            self.T_B_C = _transform(message)
        elif frames == (topics.WORLD, topics.BODY):
            self.poses["recorded"][t] = _transform(message)
        elif frames == (topics.LOCAL, topics.TRUTH):
            self.true_positions[t] = _transform(message)[:3, 3]
        elif frames == (topics.LOCAL, topics.WORLD):
            self.tie = (t, _transform(message))

    def _on_imu(self, t, record) -> None:
        if self.vins is None:
            self._start()
        try:
            self.vins.add_imu(ImuSample(record["t"], np.array(record["gyro"]),
                                        np.array(record["accel"]), record.get("pressure_pa")))
        except ValueError:
            pass  # refused in flight too (out of order, a gap): the VINS says why in debug

    def _on_camera_image(self, t, message) -> None:
        bgr = cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ReplayError(f"the camera image at t={t * 1e-9:.3f} does not decode")
        self.report.lossy_frames += message.format != "png"
        self.frames[t] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _on_truth_depth(self, t, message) -> None:
        self.truth[t] = _metres(message)

    def _on_vins_health(self, t, record) -> None:
        """The flight's VINS finished the frame at ``t`` here: so does the replay's."""
        image = self.frames.pop(t, None)
        if image is None:  # the recorder dropped the image
            self.truth.pop(t, None)
            return
        frame = Frame(record["t"], image, self.truth.pop(t, None))
        if frame.truth_depth is not None:  # what the recorded depth is scored on, if any
            self.truth_small[t] = _small(frame.truth_depth)
        update = self._vins(frame)
        if update.T_W_B is not None:
            self.poses["replayed"][t] = update.T_W_B
        health = update.health
        if (health.tracked, health.landmarks, health.state.value) == \
                (record["tracked"], record["landmarks"], record["state"]):
            self.report.vins_same_frames += 1
        self.awaiting_depth[t] = (frame, update)
        while len(self.awaiting_depth) > _AWAITING_DEPTH_MAX:  # frames the network skipped
            del self.awaiting_depth[min(self.awaiting_depth)]

    def _on_depth_fit(self, t, record) -> None:
        """The flight's depth stage finished the frame at ``t`` here and handed its depth to the
        planner: so does the replay's. Older frames it never took are dropped."""
        awaiting = self.awaiting_depth.pop(t, None)
        for skipped in [key for key in self.awaiting_depth if key < t]:
            del self.awaiting_depth[skipped]
        if awaiting is None:  # the recorder dropped the image
            return
        depth = self._depth(*awaiting)
        if depth is not None:
            self.planner.add_depth(*depth)
            self.last_depth_t = record["t"]

    def _on_flight_events(self, t, message) -> None:
        try:
            source, self.state, reason = topics.parse_transition(message.message)
        except ValueError as error:
            raise ReplayError(f"{topics.EVENTS.name}: {error}") from None
        if self.state in _FAILSAFE_STATES:
            self.report.recorded_failsafes.append({"t": round(t * 1e-9, 3), "reason": reason})
        start, end = self.navigation
        if start is None and self.state in _PHASE_STARTS:
            self.navigation[0] = t
        elif start is not None and end is None and self.state not in _PHASE_ACTIVITY:
            self.navigation[1] = t

    def _on_depth_metric(self, t, message) -> None:
        """The flight's depth of the frame at ``t``, scored on its truth; truth older than it
        is of frames the flight had no depth for."""
        truth = self.truth_small.pop(t, None)
        if truth is not None:
            depth = _metres(message)
            if depth.shape != truth.shape:
                raise ReplayError(f"{topics.DEPTH_METRIC.name}: an image of {depth.shape}, "
                                  f"its frame's true depth at its stride {truth.shape}")
            self.errors["recorded"].add(depth, truth)
        for older in [key for key in self.truth_small if key < t]:
            del self.truth_small[older]

    def _on_planner_plan(self, t, record) -> None:
        request = record.get("request")
        if request is None or self.planner is None:
            return
        _check_record(f"{topics.PLAN.name} request", request, _REQUEST)
        started = time.perf_counter()
        plan = self.planner.plan(record["t"], np.array(request["T_W_B"]).reshape(4, 4),
                                 np.array(request["velocity"]), np.array(request["goal"]),
                                 stop_at_goal=request["stop_at_goal"])
        self.timings["planner"].append(time.perf_counter() - started)
        chosen = plan.candidates.chosen if plan.kind == "arc" else None
        self._failsafe_check(record, plan)
        report = self.report
        report.rounds += 1
        if plan.kind == record["kind"] and chosen == (
                record.get("chosen") if record["kind"] == "arc" else None):
            report.same_decision += 1
        else:
            report.changed_rounds.append({"t": round(record["t"], 3), "recorded": record["kind"],
                                          "replayed": plan.kind, "reason": plan.reason})

    def _failsafe_check(self, record: dict, plan) -> None:
        """The failsafe rules at this round, on what the replay changes: the VINS's health,
        how long it has been flown on blind, the age of the newest metric depth, how long
        nothing has been safe. What the recording fixes is taken from it: the state (guarded
        or not), flown ground (aligning, or a recorded glide). What a replay cannot know reads
        as healthy: loop lag, the setpoint watchdog, camera and IMU silence (the recording's
        own failsafes list them), and the turn in place the flight allows once when blocked.
        Only the first failsafe is reported: after it, the flight it would have been is not
        the recorded one."""
        now = record["t"]
        self.no_path_since = (None if plan.reason != "no safe primitive"
                              else now if self.no_path_since is None else self.no_path_since)
        health = self.vins_health
        flown_on_vins = self.state in _GUARDED and self.state != _ALIGNING
        self.blind.update(now, None if health is None else health.landmarks, flown_on_vins,
                          self.config.flight)
        if self.report.replayed_failsafe is not None or self.state not in _GUARDED:
            return
        vitals = Vitals(
            stop_requested="", loop_lag_s=0.0, watchdog_in_charge=False, camera_age_s=0.0,
            imu_age_s=0.0,
            vins_problem=(f"VINS lost ({health.reason})"
                          if health is not None and health.state == HealthState.LOST else ""),
            depth_age_s=age(self.last_depth_t, now), depth_reason="",
            blind_s=self.blind.blind_s, blind_expired=self.blind.expired(self.config.flight),
            on_flown_ground=self.state in _IN_PLACE or record["reason"] in FLOWN_GROUND_REASONS,
            no_path_expired=self.no_path_since is not None
            and now - self.no_path_since > self.config.flight.no_path_timeout_s)
        reason = failsafe_reason(vitals, self.config.flight)
        if reason:
            self.report.replayed_failsafe = {"t": round(now, 3), "reason": reason}

    # the stages

    def _vins(self, frame: Frame):
        """The frame through the VINS; its update."""
        if self.vins is None:
            self._start()
        self._check_frame(frame)
        self.report.frames += 1
        started = time.perf_counter()
        update = self.vins.add_frame(frame.t, self.vins.track(frame.image),
                                     on_ground=self.state in _ON_GROUND)
        self.timings["vins"].append(time.perf_counter() - started)
        self.vins_health = update.health
        if update.health.state == HealthState.LOST:
            self.report.vins_lost_frames += 1
        return update

    def _check_frame(self, frame: Frame) -> None:
        """ReplayError for a frame whose image or true depth is not the camera's size."""
        size = (self.pinhole.height, self.pinhole.width)
        for name, image in (("image", frame.image), ("true depth", frame.truth_depth)):
            if image is not None and image.shape[:2] != size:
                raise ReplayError(f"the camera {name} at t={frame.t:.3f} is "
                                  f"{image.shape[1]}x{image.shape[0]}, the calibration "
                                  f"{size[1]}x{size[0]}")

    def _depth(self, frame: Frame, update) -> tuple | None:
        """The frame's metric depth from the network and its VINS update's sparse map, scored
        on its truth: ``(metric depth, T_W_C)`` for the planner, None without depth."""
        started = time.perf_counter()
        try:
            relative = RelativeDepth(frame.t, self.network(frame))
        except _NoTruth:
            self.report.frames_without_truth += 1
            return None
        self.timings["network"].append(time.perf_counter() - started)
        started = time.perf_counter()
        metric = self.stage.process(relative, update.sparse_map)
        self.timings["rescale"].append(time.perf_counter() - started)
        usable = metric.ok and update.T_W_B is not None
        if usable and frame.truth_depth is not None:
            self.errors["replayed"].add(_small(metric.depth), _small(frame.truth_depth))
        return (metric, update.T_W_B @ self.T_B_C) if usable else None


def _vins_at_end(poses: dict[str, dict[int, np.ndarray]], true_positions: dict[int, np.ndarray],
                 tie: tuple[int, np.ndarray] | None, end_ns: int | None) -> dict | None:
    """The recorded and the replayed VINS against the truth at the last frame both posed
    before navigation ended (or, a recording that never ended it, their last frame), as the
    simulated flight's summary scores it (``drivers.sim.host``'s ``position_error_m`` and
    ``position_error_split``): the distance from the true position in PX4's local frame, and
    that error split over the path since the tie, both estimates taken to have started where
    the vehicle was then. The replayed VINS is tied as the flight tied its own
    (:func:`autonomy.geometry.yaw_alignment`, at the frame the recorded tie was made after,
    to the local pose that tie gave that frame), so that a config that moves its world frame
    is scored alike. None without a tie or a frame both VINS posed where the truth is."""
    if tie is None:
        return None
    tie_ns, T_L_W = tie
    scored = sorted(set(poses["recorded"]) & set(poses["replayed"]) & set(true_positions))
    tied = [t for t in scored if t <= tie_ns]
    ended = [t for t in scored if end_ns is None or t <= end_ns]
    if not tied or not ended:
        return None
    tied, last = tied[-1], ended[-1]
    T_L_B = T_L_W @ poses["recorded"][tied]
    ties = {"recorded": T_L_W, "replayed": yaw_alignment(T_L_B, poses["replayed"][tied])}
    start, truth = true_positions[tied], true_positions[last]
    result = {"t": round(last * 1e-9, 3),
              "at": "the last frame" if end_ns is None else "navigation's end"}
    for name, tie_of in ties.items():
        believed = (tie_of @ poses[name][last])[:3, 3]
        split = split_displacement(start, truth, start, believed)
        result[name] = {"error_m": round(float(np.linalg.norm(believed - truth)), 4),
                        "split": None if split is None else
                        {key: round(value, 4) for key, value in asdict(split).items()}}
    return result


class _AbsRel:
    """AbsRel (mean of |z - z*| / z* over valid pixels) over frames, kept as sums."""

    def __init__(self):
        self.frames, self.pixels, self.total = 0, 0, 0.0

    def add(self, depth: np.ndarray, truth: np.ndarray) -> None:
        predicted, true = metrics.valid_pairs(depth, truth)
        self.frames += 1
        self.pixels += len(true)
        self.total += float(np.sum(np.abs(predicted - true) / true))

    @property
    def value(self) -> float:
        return self.total / self.pixels if self.pixels else math.nan


def _small(depth: np.ndarray) -> np.ndarray:
    """``depth`` at the recorded metric depth's resolution, where both are scored."""
    return depth[::topics.METRIC_STRIDE, ::topics.METRIC_STRIDE]


def _metres(message) -> np.ndarray:
    """A depth image as metres: ``32FC1`` as it is, ``16UC1`` millimetres (the recorded metric
    depth, and the true depth of recordings before it was kept exact) NaN where 0."""
    dtype = {"32FC1": np.float32, "16UC1": np.uint16}.get(message.encoding)
    if dtype is None:
        raise ReplayError(f"a depth image encoded {message.encoding!r}, not 32FC1 or 16UC1")
    try:
        image = np.frombuffer(message.data, dtype).reshape(message.height, message.width)
    except ValueError:
        raise ReplayError(f"a {message.width}x{message.height} depth image of "
                          f"{len(message.data)} bytes") from None
    if dtype is np.float32:
        return image
    return np.where(image > 0, image.astype(np.float32) * 1e-3, np.float32(np.nan))


class _Decoders:
    """mcap's decoder-factory protocol for the recorder's messages: JSON, and protobuf by the
    project's own schema of the name the file gives, not by the file's schema (a damaged or
    foreign one could rename or retype what replay reads); an unknown name decodes nothing."""

    def __init__(self):
        self._protobuf = DecoderFactory()
        self._schemas = {topic.schema.name: Schema(
            id=number, name=topic.schema.name, encoding=topic.schema.encoding,
            data=topic.schema.data) for number, topic in enumerate(topics.TOPICS)}

    def decoder_for(self, message_encoding: str, schema):
        if message_encoding == "json":
            return json.loads
        own = self._schemas.get(getattr(schema, "name", None))
        return None if own is None else self._protobuf.decoder_for(message_encoding, own)


def replay(path: Path, config, mission: dict | None, until_s: float | None = None,
           stages: tuple = ALL_STAGES) -> ReplayReport:
    """Replay the recording at ``path`` under ``config`` (module docstring); with ``until_s``,
    only its first ``until_s`` seconds (by published time, from its first message replayed),
    the recording's side of every comparison cut at the same instant; ``stages``
    :data:`VINS_ONLY`, the VINS alone (neither the true depth nor the depth and plans read)."""
    if until_s is not None and not (math.isfinite(until_s) and until_s > 0.0):
        raise ValueError(f"until_s must be a number of seconds above 0, got {until_s}")
    if stages not in (ALL_STAGES, VINS_ONLY):
        raise ValueError(f"stages must be {ALL_STAGES} or {VINS_ONLY}, got {stages}")
    replayer = _Replayer(config, mission, stages)
    end = None
    for topic, t, message in _read(path, _READ if stages == ALL_STAGES else _READ_VINS):
        if until_s is not None:
            end = t + round(until_s * 1e9) if end is None else end
            if t > end:
                continue  # log-time order: a message published earlier may still come
        replayer.on_message(topic, t, message)
    return replayer.finish()


def plot(path: Path, mission: dict | None, config, out: Path) -> None:
    """The recorded flight's estimated path (the VINS odometry, in PX4's local frame) over
    its simulated world, as ``companion sim fly`` draws it (:func:`companion.tools.plot.
    top_view`); only a simulated flight has a world to draw it on."""
    from companion.tools.eval.provenance import code_revision
    from companion.tools.plot import flight_caption, top_view
    from drivers.sim.host import SimError, mission_waypoints
    from drivers.sim.world import build_world

    if mission is None:
        raise ReplayError("the top view needs a simulated flight's world; this recording is of "
                          "a real one")
    T_L_W, times, positions_W = _estimated_path(path)
    if T_L_W is None or not positions_W:
        raise ReplayError(f"{path} has no VINS path tied to PX4's local frame to draw")
    sim_mission = simulated_mission(mission)
    try:
        world = build_world(sim_mission.world, sim_mission.seed, config.sim.profile)
        start, waypoints, _ = mission_waypoints(build_world(sim_mission.world,
                                                            sim_mission.seed),
                                                sim_mission, config.flight.takeoff_altitude)
    except (SimError, ValueError, TypeError) as error:
        raise ReplayError(f"the recorded mission cannot be drawn: {error}") from None
    positions_L = np.asarray(positions_W) @ T_L_W[:3, :3].T + T_L_W[:3, 3]
    top_view(world, positions_L, times=times, start=start, goal=waypoints[-1],
             waypoints=waypoints[:-1], out=out,
             title=f"{world.name} pair {sim_mission.pair}: recorded VINS path",
             caption=f"Recording {Path(path).name}, flown: {flight_caption(sim_mission)}; "
                     f"drawn by code revision {code_revision()}.")


def simulated_mission(mission: dict):
    """The recording's ``mission`` record (a ``SimMission`` as a dict, its faults as dicts) as
    the :class:`~drivers.sim.host.SimMission` it was; ReplayError naming what is wrong with
    it (a damaged or foreign file must not raise anything else)."""
    from drivers.sim.faults import Fault
    from drivers.sim.host import SimMission

    try:
        faults = tuple(Fault(**fault) for fault in mission.get("faults", ()))
        goal = mission.get("goal")  # JSON's lists back to the tuples they were
        via = tuple(tuple(point) for point in mission.get("via", ()))
        return SimMission(**{**mission, "faults": faults, "via": via,
                             "goal": None if goal is None else tuple(goal)})
    except (TypeError, ValueError, AttributeError) as error:
        raise ReplayError(f"the recording's mission record is not a simulated mission: "
                          f"{error}") from None


def _estimated_path(path: Path) -> tuple[np.ndarray | None, list, list]:
    """PX4's local frame to the VINS world (``local``->``world`` on ``/tf``), and the times
    (seconds) and VINS positions of ``/vins/odometry`` in time order."""
    T_L_W, times, positions = None, [], []
    for topic, _, decoded in _read(path, (topics.TRANSFORMS.name, topics.ODOMETRY.name)):
        if topic == topics.ODOMETRY.name:
            _check_record(topic, decoded, _ODOMETRY)
            times.append(decoded["t"])
            positions.append(decoded["position"])
        elif (decoded.parent_frame_id, decoded.child_frame_id) == (topics.LOCAL, topics.WORLD):
            T_L_W = _transform(decoded)
    return T_L_W, times, positions


def _pinhole(message) -> PinholeCamera:
    """The rectified pinhole of a ``/camera/calibration`` message; ReplayError if it is none."""
    K = np.asarray(message.K, dtype=float)
    try:
        if K.shape != (9,) or not np.isfinite(K).all():
            raise ValueError(f"K must be 9 finite numbers, got {message.K}")
        return PinholeCamera(message.width, message.height, K[0], K[4], K[2], K[5])
    except ValueError as error:
        raise ReplayError(f"{topics.CAMERA_CALIBRATION.name}: not a camera model "
                          f"({error})") from None


def _landmarks(message) -> tuple[np.ndarray, np.ndarray]:
    """A ``/vins/map`` cloud's points ``(N, 3)`` in the camera and whether this frame tracked
    each; ReplayError when its layout is not the recorder's (float32 x, y, z first)."""
    names = [field.name for field in message.fields]
    float32 = fm.PackedElementFieldNumericType.Float32
    if (names[:3] != ["x", "y", "z"] or "tracked" not in names
            or any(field.offset != 4 * i or field.type != float32
                   for i, field in enumerate(message.fields))
            or message.point_stride != 4 * len(names) or len(message.data) % (4 * len(names))):
        raise ReplayError(f"a {topics.VINS_MAP.name} cloud that is not the recorder's: fields "
                          f"{names}, stride {message.point_stride}, {len(message.data)} bytes")
    values = np.frombuffer(message.data, np.float32).reshape(-1, len(names)).astype(float)
    return values[:, :3], values[:, names.index("tracked")] > 0.5


#: Tracked landmarks with a true depth a frame needs for its map scale.
MAP_SCALE_MIN_LANDMARKS = 5


def _map_scale(points: np.ndarray, tracked: np.ndarray, pinhole: PinholeCamera,
               true_depth: np.ndarray) -> float | None:
    """The median over a frame's tracked landmarks of their depth over the true depth at the
    pixel each projects to: the VINS map's scale (None with too few)."""
    points = points[tracked & (points[:, 2] > 0) & np.isfinite(points).all(axis=1)]
    columns = np.rint(pinhole.fx * points[:, 0] / points[:, 2] + pinhole.cx)
    rows = np.rint(pinhole.fy * points[:, 1] / points[:, 2] + pinhole.cy)
    height, width = true_depth.shape
    inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
    truth = true_depth[rows[inside].astype(int), columns[inside].astype(int)]
    known = np.isfinite(truth) & (truth > 0)
    if known.sum() < MAP_SCALE_MIN_LANDMARKS:
        return None
    return float(np.median(points[inside][known, 2] / truth[known]))


@dataclass(frozen=True)
class VinsErrorSample:
    """The VINS against the simulator's truth at one frame: ``error_m`` the distance between
    the estimated and the true body position, ``heading_deg`` the yaw error (estimate less
    truth, within +-180), ``truth_position`` where the body truly was (metres) and
    ``truth_yaw_deg`` its true heading (within +-180), all in PX4's local frame; the VINS's
    health at that frame; ``map_scale`` (asked for, and where the true depth was recorded) the
    median of its tracked landmarks' depth over the true depth; ``estimate_position`` where
    the VINS had the body (metres); ``pitch_deg`` and ``roll_deg`` its tilt error
    (:func:`tilt_error_deg`)."""

    t: float
    truth_position: tuple[float, float, float]
    truth_yaw_deg: float
    error_m: float
    heading_deg: float
    state: str
    landmarks: int
    map_scale: float | None = None
    estimate_position: tuple[float, float, float] | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None


def tilt_error_deg(R_estimate: np.ndarray, R_truth: np.ndarray) -> tuple[float, float]:
    """The estimated body attitude's tilt error against the truth's (both body to PX4's local
    frame, z up), degrees: the rotation error in the local frame, ``log(R_estimate
    R_truth^T)``, about the true heading's left axis (``pitch``, positive: the estimate's nose
    lower) and its forward axis (``roll``, positive: its right side lower). A VINS's tilt
    error turns the path it reckons out of the horizontal: flying straight at ``v`` a pitch
    error ``e`` climbs ``-v sin e`` that the truth does not, which an accelerometer cannot show
    while the vehicle does not turn (its bias takes the gravity the tilt puts along the
    body)."""
    rotation = so3_log(np.asarray(R_estimate) @ np.asarray(R_truth).T)
    forward, left, _ = rot_z(yaw_of(R_truth)).T @ rotation  # in the true heading's axes
    return math.degrees(left), math.degrees(forward)


#: The true yaw rate above which `log vins` counts the vehicle as turning, degrees per second
#: (the planner's turns in place and its curved arcs; a straight arc's heading wanders by a
#: few degrees per second).
TURNING_RATE_DEG_S = 10.0


@dataclass(frozen=True)
class HeadingAccrual:
    """What the VINS's heading error did over the intervals of one kind of motion:
    ``seconds`` of them, the true yaw ``turned_deg`` in them (the sum of its absolute changes)
    and the heading error's change accrued over them, ``error_change_deg``."""

    seconds: float
    turned_deg: float
    error_change_deg: float


def heading_accrual(samples: list[VinsErrorSample],
                    turning_rate_deg_s: float = TURNING_RATE_DEG_S) -> dict[str, HeadingAccrual]:
    """The heading error's change split between ``turning`` and ``straight`` flight.

    Each interval between consecutive samples is turning when the true yaw changed faster
    than ``turning_rate_deg_s`` over it; its change of the heading error (wrapped to +-180)
    goes to that kind, so the two add up to the heading error's change from the first sample
    to the last (a reset's jump included, in its interval). Error accrued in turns points at
    what the gyro alone measures there (its yaw scale, the time offset, tracks lost in a fast
    turn); error accrued in straight flight at what the landmarks hand from keyframe to
    keyframe."""
    seconds, turned, change = ({"turning": 0.0, "straight": 0.0} for _ in range(3))
    for before, after in zip(samples, samples[1:]):
        dt = after.t - before.t
        yaw_step = _wrapped_deg(after.truth_yaw_deg - before.truth_yaw_deg)
        kind = "turning" if abs(yaw_step) > turning_rate_deg_s * dt else "straight"
        seconds[kind] += dt
        turned[kind] += abs(yaw_step)
        change[kind] += _wrapped_deg(after.heading_deg - before.heading_deg)
    return {kind: HeadingAccrual(seconds[kind], turned[kind], change[kind]) for kind in seconds}


#: The true horizontal speeds (m/s) that split `log vins`'s path length accrual: below the
#: first the vehicle hovers or turns in place (not counted), then the planner's tiers (1, 1.5
#: and 2 m/s, `[planner] speed`) each in its own band.
SPEED_BAND_EDGES_M_S = (0.3, 1.25, 1.75)
#: The stretch of flight each step of the accrual spans, seconds: long enough that the
#: estimate's noise from frame to frame is small against the step's length.
ACCRUAL_STEP_S = 0.5


@dataclass(frozen=True)
class LengthAccrual:
    """What the VINS made of the path's length over one band of true speed: ``seconds`` in
    it, ``flown_m`` the true horizontal distance, and ``along_m`` the estimate's steps along
    the true ones less their length, summed (negative: the estimate fell short); its ratio
    to ``flown_m`` is the band's scale error."""

    seconds: float
    flown_m: float
    along_m: float


def length_accrual(samples: list[VinsErrorSample],
                   step_s: float = ACCRUAL_STEP_S) -> dict[str, LengthAccrual]:
    """The estimated path's length error split by true speed (:data:`SPEED_BAND_EDGES_M_S`).

    The flight is cut into steps of at least ``step_s``; each step's true horizontal
    displacement ``D`` and estimated ``E`` give ``E . D / |D| - |D|``, the estimate's length
    along ``D`` less the truth's, which goes to the band of the step's speed ``|D| / dt``.
    A scale error the VINS makes at one speed shows in that band, whichever way the
    vehicle's heading turned meanwhile (a heading error shows across, not here)."""
    edges = SPEED_BAND_EDGES_M_S
    labels = [f"{low:g}-{high:g} m/s" for low, high in zip(edges, edges[1:])]
    labels.append(f"over {edges[-1]:g} m/s")
    totals = {label: [0.0, 0.0, 0.0] for label in labels}
    posed = [s for s in samples if s.estimate_position is not None]
    start = 0
    for end in range(1, len(posed)):
        first, last = posed[start], posed[end]
        dt = last.t - first.t
        if dt < step_s:
            continue
        flown = np.subtract(last.truth_position, first.truth_position)[:2]
        estimated = np.subtract(last.estimate_position, first.estimate_position)[:2]
        distance = float(np.linalg.norm(flown))
        band = int(np.searchsorted(edges, distance / dt, side="right")) - 1
        if band >= 0:
            total = totals[labels[band]]
            total[0] += dt
            total[1] += distance
            total[2] += float(estimated @ flown) / distance - distance
        start = end
    return {label: LengthAccrual(*total) for label, total in totals.items()}


def displacement_split(samples: list[VinsErrorSample]) -> DisplacementSplit | None:
    """The last sample's error split into the path's scale, bearing and height since the
    first sample (``autonomy.trajectory.split_displacement``); None without estimated
    positions or when the vehicle ended within ``DISPLACEMENT_MIN_M`` (1 m) of its first
    position horizontally."""
    if len(samples) < 2 or any(s.estimate_position is None for s in (samples[0], samples[-1])):
        return None
    return split_displacement(samples[0].truth_position, samples[-1].truth_position,
                              samples[0].estimate_position, samples[-1].estimate_position)


def _wrapped_deg(angle: float) -> float:
    """``angle`` (degrees) within +-180."""
    return (angle + 180.0) % 360.0 - 180.0


def flown_path(path: Path) -> FlownMotion:
    """The simulated flight of a recording: its world, seed and profile, and where the
    simulator truly had the vehicle at each frame, in time order (``local``->``truth`` on
    ``/tf``; the local frame is the world's in the simulator): what ``sim record --along``
    flies again. ReplayError for a recording of no simulated flight or without the truth."""
    from drivers.sim.record import FlownMotion

    metadata = _metadata(path)
    if "mission" not in metadata:
        raise ReplayError(f"{path}: not the recording of a simulated flight (no mission)")
    flown = simulated_mission(_mission(metadata["mission"], path))
    poses = {t: _transform(decoded) for topic, t, decoded in
             _read(path, [topics.TRANSFORMS.name])
             if (decoded.parent_frame_id, decoded.child_frame_id) == (topics.LOCAL, topics.TRUTH)}
    if not poses:
        raise ReplayError(f"{path}: no true pose (local -> truth on {topics.TRANSFORMS.name})")
    times = sorted(poses)
    return FlownMotion(
        world=flown.world, seed=flown.seed, profile=_recorded_profile(metadata, path),
        times=np.array(times) / 1e9, positions=np.array([poses[t][:3, 3] for t in times]),
        yaws=np.array([yaw_of(poses[t][:3, :3]) for t in times]))


def _recorded_profile(metadata: dict[str, str], path: Path) -> str:
    """The simulator's profile in a recording's config, read alone, so that a recording made
    by another version of the application (a config key since added or removed) still gives
    it."""
    from drivers.sim.options import PROFILES

    try:
        profile = tomllib.loads(metadata.get("config", "")).get("sim", {}).get("profile")
    except tomllib.TOMLDecodeError as error:
        raise ReplayError(f"{path}: its recorded config is not TOML ({error})") from None
    if profile not in PROFILES:
        raise ReplayError(f"{path}: its recorded config names no simulator profile "
                          f"({', '.join(PROFILES)})")
    return profile


def vins_error(path: Path, *, with_map: bool = False) -> list[VinsErrorSample]:
    """The VINS's error at every frame of a simulated flight's recording that has both its
    pose (``world``->``body`` on ``/tf``, in PX4's local frame through the ``local``->``world``
    tie) and the truth (``local``->``truth``), in time order; ``with_map``, each frame's map
    scale too (reads the true depth images: slower). ReplayError when the recording holds no
    truth (a real flight, or a simulated one recorded before 2026-11-28) or no tie."""
    T_L_W, estimates, truths, health, scales = None, {}, {}, {}, {}
    pinhole, true_depth, true_depth_t = None, None, None
    read = [topics.TRANSFORMS.name, topics.VINS_HEALTH.name]
    if with_map:
        read += [topics.CAMERA_CALIBRATION.name, topics.TRUTH_DEPTH.name, topics.VINS_MAP.name]
    for topic, t, decoded in _read(path, read):
        if topic == topics.VINS_HEALTH.name:
            _check_record(topic, decoded, _RECORDS[topic])
            health[t] = decoded
            continue
        if topic == topics.CAMERA_CALIBRATION.name:
            pinhole = _pinhole(decoded)
            continue
        if topic == topics.TRUTH_DEPTH.name:
            true_depth, true_depth_t = _metres(decoded), t  # its frame's map comes after it
            continue
        if topic == topics.VINS_MAP.name:
            if pinhole is not None and t == true_depth_t:
                scales[t] = _map_scale(*_landmarks(decoded), pinhole, true_depth)
            continue
        frames = (decoded.parent_frame_id, decoded.child_frame_id)
        if frames == (topics.LOCAL, topics.WORLD):
            T_L_W = _transform(decoded)
        elif frames == (topics.WORLD, topics.BODY) and T_L_W is not None:
            estimates[t] = T_L_W @ _transform(decoded)
        elif frames == (topics.LOCAL, topics.TRUTH):
            truths[t] = _transform(decoded)
    if not truths:
        raise ReplayError(f"{path}: no true pose (local -> truth on {topics.TRANSFORMS.name}): "
                          "only simulated flights recorded since 2026-11-28 have one")
    if T_L_W is None:
        raise ReplayError(f"{path}: the VINS was never tied to PX4's local frame (no local -> "
                          f"world on {topics.TRANSFORMS.name})")
    samples = []
    for t in sorted(set(estimates) & set(truths)):
        estimate, truth, vitals = estimates[t], truths[t], health.get(t, {})
        truth_yaw = math.degrees(yaw_of(truth[:3, :3]))
        pitch, roll = tilt_error_deg(estimate[:3, :3], truth[:3, :3])
        samples.append(VinsErrorSample(
            t=t / 1e9, truth_position=tuple(float(v) for v in truth[:3, 3]),
            truth_yaw_deg=truth_yaw,
            error_m=float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3])),
            heading_deg=_wrapped_deg(math.degrees(yaw_of(estimate[:3, :3])) - truth_yaw),
            state=vitals.get("state", "?"),
            landmarks=int(vitals.get("landmarks", 0)), map_scale=scales.get(t),
            estimate_position=tuple(float(v) for v in estimate[:3, 3]),
            pitch_deg=pitch, roll_deg=roll))
    return samples


#: The states of the navigation phase (from Offboard until the flight comes down), with the
#: activity their time is counted as; NAVIGATING's time goes to the plan being flown.
_PHASE_ACTIVITY = {FlightState.NAVIGATING.value: None,
                   FlightState.CALIBRATING.value: "the offset swing",
                   FlightState.ALIGNING.value: "turning in place",
                   FlightState.STOPPING.value: "stopping at the goal",
                   FlightState.FAILSAFE_STOP.value: "the failsafe's stop"}
#: The states the phase begins with, at the switch to Offboard: the offset swing, or navigating.
_PHASE_STARTS = (FlightState.CALIBRATING.value, FlightState.NAVIGATING.value)


@dataclass
class NavigationTime:
    """Where a flight's navigation phase went: ``seconds`` from the switch to Offboard until
    the flight left the phase (the summary's ``navigation_time_s``), split over
    ``activities`` (label -> seconds: the arcs by tier speed, each glide and stop by its
    reason, turning in place, the stops after the goal and a failsafe); ``plans`` published,
    ``arc_rounds`` of them arcs, and the median seconds between consecutive arc rounds;
    ``faster_tiers``: for each tier speed (label "2.0 m/s"), the planning rounds that found
    nothing safe in it and went slower or stopped, ``rounds``, and the median share of its
    primitives an observed surface blocked, ``blocked_share`` (the rest met only unseen
    space). Recordings made before the plans said why carry none."""

    seconds: float
    activities: dict[str, float]
    plans: int
    arc_rounds: int
    arc_round_gap_s: float | None
    faster_tiers: dict[str, dict]


def _activity(plan: dict) -> str:
    """What flying ``plan`` (a ``/planner/plan`` record) is counted as."""
    if plan["kind"] == "arc":
        return f"arcs at {float(plan.get('speed', math.nan)):.1f} m/s"
    return plan["reason"] or plan["kind"]


def navigation_time(path: Path) -> NavigationTime:
    """:class:`NavigationTime` of the recording at ``path``, from its state transitions
    (``/flight/events``) and plans (``/planner/plan``), each plan in charge from when the
    flight published it until the next one: log times, since a stop continuing the one the
    last round checked carries that round's time. ReplayError when the recording never
    reached Offboard."""
    timeline, plans, arc_times, blocked_shares = [], 0, [], defaultdict(list)
    for topic, t, decoded in _read(path, [topics.EVENTS.name, topics.PLAN.name],
                                   stamp="log_time"):
        if topic == topics.PLAN.name:
            _check_record(topic, decoded, _RECORDS[topic])
            plans += 1
            if decoded["kind"] == "arc":
                arc_times.append(t * 1e-9)
            for tier in _faster_tiers(topic, decoded):
                blocked_shares[tier["speed"]].append(
                    tier["blocked"] / max(1, tier["blocked"] + tier["unseen"]))
            timeline.append((t * 1e-9, "plan", _activity(decoded)))
            continue
        try:
            timeline.append((t * 1e-9, "state", topics.parse_transition(decoded.message)[1]))
        except ValueError as error:
            raise ReplayError(f"{topics.EVENTS.name}: {error}") from None
    start = next((t for t, what, value in timeline
                  if what == "state" and value in _PHASE_STARTS), None)
    if start is None:
        raise ReplayError(f"{path}: the flight never navigated (no transition to "
                          f"{' or '.join(_PHASE_STARTS)} on {topics.EVENTS.name})")
    activities: dict[str, float] = defaultdict(float)
    state, plan, since = None, "waiting for the first plan", start
    for t, what, value in timeline:
        if t >= start and state is not None:
            label = _PHASE_ACTIVITY[state] or plan
            activities[label] += t - since
            since = t
        if what == "plan":
            plan = value
        elif t >= start:
            if value not in _PHASE_ACTIVITY:
                break
            state = value
    gaps = np.diff(arc_times)
    faster = {f"{speed:.1f} m/s": {"rounds": len(shares),
                                   "blocked_share": float(np.median(shares))}
              for speed, shares in sorted(blocked_shares.items(), reverse=True)}
    return NavigationTime(seconds=since - start, activities=dict(activities), plans=plans,
                          arc_rounds=len(arc_times),
                          arc_round_gap_s=float(np.median(gaps)) if len(gaps) else None,
                          faster_tiers=faster)


def _transform(message) -> np.ndarray:
    """A ``foxglove.FrameTransform`` as the 4x4 pose of its child in its parent; ReplayError
    when it is not a pose (a translation not finite, a rotation not a unit quaternion)."""
    q, p = message.rotation, message.translation
    q_wxyz, position = np.array([q.w, q.x, q.y, q.z]), np.array([p.x, p.y, p.z])
    if not (np.isfinite(position).all()
            and abs(np.linalg.norm(q_wxyz) - 1.0) <= _UNIT_QUATERNION_TOLERANCE):
        raise ReplayError(f"{topics.TRANSFORMS.name}: {message.parent_frame_id} -> "
                          f"{message.child_frame_id} is not a pose")
    return make_pose(quat_to_rot(q_wxyz), position)


def _number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def _vector(size: int) -> Callable[[object], bool]:
    return lambda value: (isinstance(value, list) and len(value) == size
                          and all(map(_number, value)))


def _of(kind: type) -> Callable[[object], bool]:
    return lambda value: isinstance(value, kind)


#: What replay reads of each of the recorder's JSON records, by topic: key -> its check.
_RECORDS = {
    topics.IMU.name: {"t": _number, "gyro": _vector(3), "accel": _vector(3)},
    topics.VINS_HEALTH.name: {"t": _number, "tracked": _number, "landmarks": _number,
                              "state": _of(str)},
    topics.DEPTH_FIT.name: {"t": _number},
    topics.PLAN.name: {"t": _number, "kind": _of(str), "reason": _of(str)},
}
#: A faster tier's record in a plan (``/planner/plan``'s ``faster``).
_FASTER_TIER = {"speed": _number, "blocked": _number, "unseen": _number}
#: A planner round's request (``/planner/plan``'s ``request``), and the odometry top_view draws.
_REQUEST = {"T_W_B": _vector(16), "velocity": _vector(3), "goal": _vector(3),
            "stop_at_goal": _of(bool)}
_ODOMETRY = {"t": _number, "position": _vector(3)}


def _faster_tiers(topic: str, plan: dict) -> list[dict]:
    """A plan record's ``faster`` tiers (none in recordings made before plans carried them);
    ReplayError when malformed."""
    faster = plan.get("faster", [])
    if not isinstance(faster, list):
        raise ReplayError(f"a {topic} record whose 'faster' is {faster!r:.80}")
    for tier in faster:
        _check_record(f"{topic} faster", tier, _FASTER_TIER)
    return faster


def _check_record(topic: str, record, fields: dict) -> None:
    """ReplayError unless ``record`` is a JSON object whose ``fields`` pass their checks:
    the file holds something else than the recorder wrote."""
    if not isinstance(record, dict):
        raise ReplayError(f"a {topic} record that is not a JSON object: {record!r:.80}")
    for key, check in fields.items():
        if not check(record.get(key)):
            raise ReplayError(f"a {topic} record whose {key!r} is {record.get(key)!r:.80}")
