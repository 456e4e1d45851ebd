"""The flight recorder: every channel of a flight into one MCAP file (DESIGN.md, "Recording
and replay"; docs/recording.md).

:class:`FlightRecorder` taps the flight process's channels
(:class:`~companion.flight.context.Channels`), the autopilot's TIMESYNC round trips and the
application's log. A tap runs on the publisher's thread and only hands the message, by
reference (they are immutable), to the writer's bounded queue with the function that encodes
it; JPEG compression, protobuf and JSON encoding and the file all happen on the writer's
thread (:class:`~companion.recording.writer.RecordingWriter`). So recording costs the loop
one queue append per message, and the writer drops camera and depth images first when it
falls behind, never IMU samples or events.
"""

from __future__ import annotations

import logging
from typing import Callable

from autonomy.geometry import PinholeCamera
from autonomy.messages import Frame, MetricDepth
from autonomy.vins.estimator import FrameUpdate
from companion.recording import topics
from companion.recording.topics import nanoseconds

log = logging.getLogger(__name__)


class FlightRecorder:
    """Taps one :class:`~companion.flight.app.FlightApp` into ``writer``."""

    def __init__(self, writer, clock, *, camera_format: str = "jpeg", jpeg_quality: int = 90):
        self.writer, self.clock = writer, clock
        self.camera_format, self.jpeg_quality = camera_format, jpeg_quality
        self.pinhole: PinholeCamera | None = None
        self._detach: list[Callable[[], None]] = []
        for topic in topics.TOPICS:
            writer.add_channel(topic.name, topic.schema, droppable=topic.droppable)

    def attach(self, app) -> "FlightRecorder":
        """Record ``app`` from now until :meth:`detach`: the camera model and mounting once,
        then every message of every channel."""
        now, self.pinhole = self.clock.now(), app.pinhole
        self.put(topics.CAMERA_CALIBRATION, now, topics.encode_calibration, now, app.pinhole)
        self.put(topics.TRANSFORMS, now, topics.encode_transform, now, topics.BODY,
                 topics.CAMERA, app.T_B_C)
        channels = app.channels
        taps = ((channels.frames, self._on_frame), (channels.imu, self._on_imu),
                (channels.vins, self._on_vins), (channels.depth, self._on_depth),
                (channels.odometry, self._on_odometry), (channels.plan, self._on_plan),
                (channels.setpoints, self._on_setpoint),
                (channels.transitions, self._on_transition),
                (channels.alignment, self._on_alignment))
        self._detach = [channel.subscribe(tap) for channel, tap in taps]
        autopilot = app.autopilot
        autopilot.on_timesync = self._on_timesync_of(autopilot)
        self._detach.append(lambda: setattr(autopilot, "on_timesync", None))
        handler = _LogTap(self)
        logging.getLogger().addHandler(handler)
        self._detach.append(lambda: logging.getLogger().removeHandler(handler))
        return self

    def detach(self) -> None:
        """Stop recording (the writer keeps what it has; closing it is its owner's)."""
        for undo in self._detach:
            undo()
        self._detach = []

    def put(self, topic: topics.Topic, t: float, encode, *args) -> None:
        """``encode(*args)`` onto ``topic``, encoded later on the writer's thread: logged now
        (when the flight handled it, so a replay meets the messages in the order the stages
        did) and published at ``t`` (when it was measured)."""
        self.writer.put(topic.name, nanoseconds(self.clock.now()), lambda: encode(*args),
                        nanoseconds(t))

    def _on_frame(self, frame: Frame) -> None:
        self.put(topics.CAMERA_IMAGE, frame.t, topics.encode_image, frame, self.camera_format,
                 self.jpeg_quality)
        if frame.truth_depth is not None:
            self.put(topics.TRUTH_DEPTH, frame.t, topics.encode_true_depth, frame.t,
                     frame.truth_depth)
        if frame.truth_pose is not None:
            self.put(topics.TRANSFORMS, frame.t, topics.encode_transform, frame.t,
                     topics.LOCAL, topics.TRUTH, frame.truth_pose)

    def _on_imu(self, sample) -> None:
        self.put(topics.IMU, sample.t, topics.encode_imu, sample)

    def _on_timesync_of(self, autopilot):
        def tap(now: float, used: bool) -> None:
            sync = autopilot.timesync
            self.put(topics.TIMESYNC, now, topics.encode_timesync, sync.offset, sync.rtt, used)
        return tap

    def _on_vins(self, update: FrameUpdate) -> None:
        self.put(topics.VINS_HEALTH, update.t, topics.encode_vins_health, update)
        if update.sparse_map is not None:
            self.put(topics.VINS_MAP, update.t, topics.encode_sparse_map, update.sparse_map)
        if update.T_W_B is not None:
            self.put(topics.TRANSFORMS, update.t, topics.encode_transform, update.t,
                      topics.WORLD, topics.BODY, update.T_W_B)

    def _on_depth(self, depth: MetricDepth) -> None:
        self.put(topics.DEPTH_FIT, depth.t, topics.encode_depth_fit, depth)
        if depth.relative is not None:
            self.put(topics.DEPTH_RELATIVE, depth.t, topics.encode_relative, depth.t,
                     depth.relative)
        if depth.ok:
            self.put(topics.DEPTH_METRIC, depth.t, topics.encode_metric, depth.t, depth.depth)
            self.put(topics.DEPTH_POINTS, depth.t, topics.encode_depth_points, depth,
                      self.pinhole)

    def _on_odometry(self, odometry) -> None:
        if odometry is not None:
            self.put(topics.ODOMETRY, odometry.t, topics.encode_odometry, odometry)

    def _on_plan(self, plan) -> None:
        self.put(topics.PLAN, plan.t, topics.encode_plan, plan)
        self.put(topics.PLAN_LINES, plan.t, topics.encode_plan_lines, plan)

    def _on_setpoint(self, setpoint) -> None:
        self.put(topics.SETPOINT, self.clock.now(), topics.encode_setpoint, setpoint)

    def _on_alignment(self, alignment) -> None:
        """The tie of the VINS world to PX4's local frame, made once on the ground."""
        now = self.clock.now()
        self.put(topics.TRANSFORMS, now, topics.encode_transform, now, topics.LOCAL,
                 topics.WORLD, alignment.T_L_W)

    def _on_transition(self, transition) -> None:
        self.put(topics.EVENTS, transition.t, topics.encode_transition, transition)


class _LogTap(logging.Handler):
    """The application's log records (INFO and above) onto ``/log``, stamped on the flight's
    clock; the writer's own records are left out, so a failing disk cannot feed itself."""

    def __init__(self, recorder: FlightRecorder):
        super().__init__(logging.INFO)
        self.recorder = recorder

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.startswith("companion.recording"):
            return
        now = self.recorder.clock.now()
        self.recorder.put(topics.LOG, now, topics.encode_log, now, record.levelno, record.name,
                          record.getMessage())
