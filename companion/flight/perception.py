"""Perception: each camera frame through the VINS and the depth source to metric depth in the
planner's history; the VINS state on request.

Two loops (DESIGN.md, "The process"):

- the VINS loop takes every camera frame: it waits briefly for the IMU to reach the frame's
  exposure, then runs the VINS (front-end and back-end, on the ``vins`` worker). The tracker
  must see every frame: Lucas-Kanade across a skipped frame meets twice the motion and, under
  motion blur, loses most tracks (measured on a realistic-profile mine flight when the VINS
  ran only at the network's rate: 134 of 150 tracks lost in one frame as the vehicle pitched
  into its first acceleration);
- the depth loop takes the newest frame whenever the ``network`` worker is free (the network
  is slower than the camera: 15 Hz against 20-30 Hz on the paper's Orin), runs the depth
  source's inference beside the VINS, then makes the frame's metric depth with the sparse map
  of this very frame once the VINS has finished it, and puts it into the planner's history (on
  the ``planner`` worker, in order with planning). Once PX4 flies the vehicle on its own for
  good (its Hold after a failsafe, a lost link, the landing: ``DEPTH_UNUSED_STATES``) nothing
  reads depth any more, so the depth loop lets the frames go by: on the Orin the network's GPU
  rests, and in a simulated flight those seconds cost about a quarter of their CPU less on
  the realistic profile, two fifths on the ideal (docs/benchmarks.md).

The first VINS pose ties the VINS world to PX4's local frame.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import Callable, Generic, Protocol, TypeVar

import numpy as np

from autonomy.depth.options import RescaleOptions
from autonomy.depth.stage import DepthStageOptions, MetricDepthStage
from autonomy.geometry import yaw_alignment
from autonomy.messages import Frame, MetricDepth, Odometry, RelativeDepth, SparseMap
from autonomy.navigation.mission import DEPTH_UNUSED_STATES, DISARMED_STATES
from autonomy.planning.planner import Planner
from autonomy.vins.estimator import FrameUpdate, Vins
from companion.flight.context import Alignment, FlightContext

log = logging.getLogger(__name__)

T = TypeVar("T")

#: How often the wait for the IMU to reach a frame's time polls, seconds.
IMU_POLL_S = 0.002


class DepthSource(Protocol):
    """Where a frame's metric depth comes from, in two steps: :meth:`infer` on the frame alone
    (beside the VINS), then :meth:`metric` with the VINS sparse map of the same frame."""

    def infer(self, frame: Frame) -> object | None: ...

    def metric(self, inferred, sparse_map: SparseMap | None) -> MetricDepth | None: ...


class NetworkDepth:
    """The depth network's relative disparity, made metric by the rescaler on the frame's
    sparse map (Yang et al., Section III-B; :class:`~autonomy.depth.stage.MetricDepthStage`).
    ``network(frame) -> disparity`` is the ONNX model or, in simulation, its stand-in; one
    that fails on a frame (ValueError, RuntimeError) costs that frame (logged; the summary
    counts it among the depth failures). ``rescale`` and ``options`` are the ``[rescale]`` and
    ``[depth]`` tables."""

    def __init__(self, network: Callable[[Frame], np.ndarray], rescale: RescaleOptions,
                 options: DepthStageOptions):
        self.network, self.stage = network, MetricDepthStage(rescale, options)

    def infer(self, frame: Frame) -> RelativeDepth | None:
        try:
            return RelativeDepth(frame.t, self.network(frame))
        except (ValueError, RuntimeError) as error:
            log.warning("depth network failed on frame t=%.3f: %s", frame.t, error)
            return None

    def metric(self, relative: RelativeDepth | None,
               sparse_map: SparseMap | None) -> MetricDepth | None:
        return None if relative is None else self.stage.process(relative, sparse_map)


class NewestSlot(Generic[T]):
    """One item handed from a fast producer to a slower consumer: :meth:`put` replaces what
    the consumer has not taken yet, :meth:`take` waits for an item and empties the slot."""

    def __init__(self):
        self._item: T | None = None
        self._filled = asyncio.Event()

    def put(self, item: T) -> None:
        self._item = item
        self._filled.set()

    async def take(self) -> T:
        await self._filled.wait()
        self._filled.clear()
        item, self._item = self._item, None
        return item


class Perception:
    """The stage (module docstring). ``vins`` is changed on its worker only, in order (the
    other stages read its counters)."""

    def __init__(self, context: FlightContext, camera, vins: Vins, depth: DepthSource,
                 planner: Planner, T_B_C: np.ndarray, exact_tracks=None):
        self.context, self.camera, self.vins, self.depth = context, camera, vins, depth
        # a simulated flight's diagnostic (sim fly --tracks truth): (frame, tracks) -> tracks
        self.exact_tracks = exact_tracks
        self.planner, self.T_B_C = planner, np.asarray(T_B_C, dtype=float)
        self.last_depth_t: float | None = None  # newest depth in the planner's history
        self.last_fit_t: float | None = None  # newest depth rescaled by its own frame's fit
        self.last_depth_reason = ""  # why the newest frame without depth had none
        self._in_stale_run = False  # a stale run's first frame is logged, not every one
        # the IMU's newest stamp when a frame's wait for it last ran out (NaN: none has)
        self._imu_silent_since = math.nan

    @property
    def last_frame_t(self) -> float | None:
        frame = self.context.channels.frames.value
        return None if frame is None else frame.t

    async def run(self) -> None:
        """The VINS loop and the depth loop (module docstring), until cancelled."""
        for_depth: NewestSlot[tuple[Frame, asyncio.Future]] = NewestSlot()
        depth_loop = asyncio.ensure_future(self._depth_loop(for_depth))
        try:
            await self._vins_loop(for_depth)
        finally:
            depth_loop.cancel()
            await asyncio.gather(depth_loop, return_exceptions=True)

    async def _vins_loop(self, for_depth: NewestSlot[tuple[Frame, asyncio.Future]]) -> None:
        c = self.context
        while True:
            frame = await self.camera.next_frame()
            if not self._fresh(frame):
                continue
            c.channels.frames.publish(frame)
            c.stats.frames += 1
            c.stats.frame_age_s.append(c.clock.now() - frame.t)
            update = asyncio.get_running_loop().create_future()
            for_depth.put((frame, update))
            # the IMU up to the frame's exposure (its stamp less the camera-IMU time offset)
            await self._wait_for_imu(max(frame.t, self.vins.exposure_time(frame.t)))
            result = await c.workers["vins"].compute(self._track, frame)
            self._after_vins(result)
            update.set_result(result)

    def _fresh(self, frame: Frame) -> bool:
        """Whether ``frame`` is a new one, to take. Dropped and counted: one not after the last
        one taken (delivered twice or late: a driver re-queueing or reordering its buffers),
        since the VINS and the depth history only run forward in time; and one the device
        numbers as the last one taken, under a newer stamp (stale: a driver whose buffer
        stopped updating). Fed to the VINS, a stale image holds every feature still while the
        vehicle moves, and its landmarks drain away while it trusts the IMU alone; refused, the
        camera falls silent and the failsafe for that stops the flight. Only the same number
        is stale: a number that goes back (a driver restarting its stream) starts afresh, and
        a buffer cycling through two frames is not caught here (the VINS's blind failsafe
        remains)."""
        last = self.context.channels.frames.value
        if last is None:
            return True
        stats = self.context.stats
        if not frame.t > last.t:
            stats.frames_out_of_order += 1
            return False
        if frame.counter is not None and frame.counter == last.counter:
            if not self._in_stale_run:
                log.warning("camera: frame %d delivered again at t=%.3f s (stale); refused",
                            frame.counter, frame.t)
            stats.frames_stale += 1
            self._in_stale_run = True
            return False
        self._in_stale_run = False
        return True

    async def _depth_loop(self, for_depth: NewestSlot[tuple[Frame, asyncio.Future]]) -> None:
        network = self.context.workers["network"]
        while True:
            frame, update = await for_depth.take()
            if self.context.state in DEPTH_UNUSED_STATES:
                continue  # PX4 flies on its own: the network and the planner's history rest
            inferred = await network.compute(self.depth.infer, frame)
            vins = await update  # the VINS of this very frame
            metric = await network.run(self.depth.metric, inferred, vins.sparse_map)
            await self._after_depth(metric, vins)

    async def odometry(self) -> Odometry | None:
        """The VINS state at the newest IMU sample (published on ``odometry``); on the VINS
        worker, in order with its frames."""
        odometry = await self.context.workers["vins"].run(self._estimate)
        self.context.channels.odometry.publish(odometry)
        return odometry

    def _estimate(self) -> Odometry | None:
        self._feed_imu()
        return self.vins.odometry()

    async def _wait_for_imu(self, t: float) -> None:
        """Wait until the IMU reaches ``t``, for as long as the IMU may be late before the
        flight stops for it (``imu_timeout_s``): a late IMU (a busy host, a slow link) delays
        the frame instead of losing the VINS to a gap that is not there. Once a wait has run
        out, the frames after it do not wait while the IMU stays silent: waiting on each, the
        VINS saw one frame in every ``imu_timeout_s`` (0.29 s) through a gap, and the tracks it
        relocalises on when the IMU is back broke between them (docs/reliability.md)."""
        clock, autopilot = self.context.clock, self.context.autopilot
        if autopilot.last_imu_t == self._imu_silent_since:
            return

        def imu_behind() -> bool:
            return autopilot.last_imu_t is None or autopilot.last_imu_t < t

        give_up = clock.now() + self.context.options.imu_timeout_s
        while imu_behind() and clock.now() < give_up:
            await clock.sleep(IMU_POLL_S)
        if imu_behind():
            self._imu_silent_since = autopilot.last_imu_t

    def _feed_imu(self) -> None:
        imu = self.context.channels.imu
        for sample in self.context.autopilot.take_imu():
            imu.publish(sample)
            try:
                self.vins.add_imu(sample)
            except ValueError as error:
                log.debug("IMU sample refused: %s", error)

    def _track(self, frame: Frame) -> FrameUpdate:
        """The VINS on one frame, with the IMU up to it (on the VINS worker); on the ground
        while the mission is in a state before arming or after the landing."""
        self._feed_imu()
        tracks = self.vins.track(frame.image)
        if self.exact_tracks is not None:
            tracks = self.exact_tracks(frame, tracks)
        return self.vins.add_frame(frame.t, tracks,
                                   on_ground=self.context.state in DISARMED_STATES)

    def _after_vins(self, update: FrameUpdate) -> None:
        c = self.context
        c.channels.vins.publish(update)
        if update.correction_m is not None and c.stats.navigating:
            c.stats.vins_corrections_m.append(update.correction_m)
        state = c.autopilot.state
        if c.T_L_W is None and update.T_W_B is not None and state is not None:
            c.channels.alignment.publish(Alignment(yaw_alignment(state.T_L_B, update.T_W_B),
                                                   float(state.position_L[2])))

    async def _after_depth(self, metric: MetricDepth | None, update: FrameUpdate) -> None:
        c = self.context
        if metric is None:
            self._depth_failed("depth network failed")
            return
        c.channels.depth.publish(metric)
        if not metric.ok or update.T_W_B is None:
            self._depth_failed(metric.diagnostics.reason or "no VINS pose for the frame")
            return
        # on the planner's worker: the history is only touched there, in order with planning
        await c.workers["planner"].run(self.planner.add_depth, metric, update.T_W_B @ self.T_B_C)
        self.last_depth_t = metric.t
        if not metric.held:
            self.last_fit_t = metric.t
        if c.stats.navigating:
            c.stats.depth_ok += 1
            c.stats.depth_fallbacks += metric.diagnostics.fallback

    def _depth_failed(self, reason: str) -> None:
        self.last_depth_reason = reason
        kind = reason.split(":")[0]  # counted by kind, without the frame's own numbers
        reasons = self.context.stats.depth_reasons
        reasons[kind] = reasons.get(kind, 0) + 1
