"""The monocular VINS: front-end, static initialisation, keyframes, smoother, propagation, map.

One :class:`Vins` per camera + IMU pair. The caller feeds every IMU sample (:meth:`Vins.add_imu`)
and every frame: first :meth:`Vins.track` (the front-end, image work only), then
:meth:`Vins.add_frame` with the frame's time (everything else). The two are separate so that the
application can time and schedule them apart; nothing here reads a clock.

Per frame, once initialised:

1. the body state at the frame time is the last keyframe's smoothed estimate carried forward
   through the IMU (:class:`autonomy.vins.imu_buffer.Propagator`);
2. the frame becomes a keyframe when ``keyframe_interval_s`` has passed since the last one, or
   sooner (not before ``keyframe_min_interval_s``) when the features have moved by
   ``keyframe_parallax_px`` on average; a keyframe goes to the smoother with the IMU
   preintegrated since the last, and with a zero-velocity prior when the caller says the
   vehicle is on the ground and it stands still (:mod:`autonomy.vins.stillness`: waiting for
   the go);
3. the sparse map is the window's landmarks carried into this frame's camera through the
   paper's chain (Yang et al., Section III-A): ``p_C = T_C_B T_B_W(t) p_W``, with
   ``T_W_B(t)`` from step 1 (or the smoothed keyframe itself) and ``T_B_C`` the camera mounting.

Initialisation is static (:mod:`autonomy.vins.static_init`): the first frame after a still IMU
window becomes keyframe 0 with gravity-aligned attitude, zero position and velocity, and the
window's mean gyro as bias; the take-off's acceleration then makes the scale metric. When the
estimate is LOST, the estimator keeps propagating the IMU and, as soon as tracking is back,
re-initialises in flight from the propagated state with a wide velocity prior (a reset). When
it was LOST because the IMU fell silent, it gives no odometry until it re-initialises from
what the camera and the IMU observe once the IMU is back: relocalised on the map, propagated
across a short gap, or standing still (:mod:`autonomy.vins.imu_gap`).

Frame times: a frame's stamp ``t`` may be late by the camera-IMU time offset ``td`` (an
unsynchronised camera). Everything above runs at the frame's exposure time on the IMU's clock,
``t - td``: ``td`` is ``time_offset_s``, or, with ``estimate_time_offset``, estimated online by
:mod:`autonomy.vins.time_offset` (the camera's rotation between frames against the gyro's) and
applied from the next frame on; with ``retime_window``, when it has moved by more than
:data:`RETIME_TOLERANCE_S` since a keyframe of the window was filed, the window's keyframes are
moved to the exposure times it now gives their stamps and the IMU between them is
preintegrated again (:meth:`Vins._retime_window`); with ``takeoff_window_s`` too, the window
stops sliding when the vehicle first moves and keeps its keyframes until the offset is known
(:meth:`Vins._keep_window_open`). The caller keeps using its stamps:
:class:`FrameUpdate` and its sparse map carry ``t``, with the offset that was subtracted.

Gyro samples: with ``estimate_gyro_alignment`` the gyro's response to the yaw rate (or, with
``gyro_alignment_rates = "all"``, to every rate) is estimated on the time offset's frame pairs
and every sample is corrected by it before use (:mod:`autonomy.vins.gyro_alignment`), starting
from ``gyro_alignment``, a calibration carried over from an earlier flight (which alone is a
fixed correction); the time-offset estimator keeps the raw samples.

Accelerometer samples: with ``rest_accel_scale_share``, that share of the specific force's
excess over gravity in the static window is taken as the z axis's sensitivity error and
divided out of every sample from then on, the window's included
(:mod:`autonomy.vins.accel_scale`).

Barometer: with ``barometer_sigma_m``, an IMU sample's ``pressure_pa`` is kept, and each
keyframe takes the sample nearest its exposure time as a height (:mod:`autonomy.vins.barometer`)
once it is ``barometer_min_height_m`` above the ground the VINS started on: below, the rotors'
wash off the ground moves the pressure (PX4's EKF2 expects its barometer to read low up to
``EKF2_GND_MAX_HGT``, 0.5 m, by up to ``EKF2_GND_EFF_DZ``, 4 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from autonomy.geometry import PinholeCamera, distort_points, invert_pose, make_pose, yaw_of
from autonomy.messages import ImuSample, Odometry, SparseMap
from autonomy.vins.accel_scale import RestAccelScale
from autonomy.vins.backend import BackendError, KeyframeState, PriorSigmas, SlidingWindowSmoother
from autonomy.vins.barometer import PressureHistory, usable_pressure
from autonomy.vins.frontend import FeatureTracker, FrontendOptions, Tracks
from autonomy.vins.gyro_alignment import GyroAlignment, GyroAlignmentEstimate
from autonomy.vins.health import Health, HealthInputs, HealthState, assess
from autonomy.vins.imu_buffer import ImuBuffer, NavState, Propagator
from autonomy.vins.imu_gap import ImuGap, Restart
from autonomy.vins.options import VinsOptions
from autonomy.vins.preintegration import ImuNoise
from autonomy.vins.static_init import NotStill, StaticInit, StaticInitOptions, static_initialise
from autonomy.vins.stillness import ZeroVelocityDetector
from autonomy.vins.time_offset import PairRotations, TimeOffset, TimeOffsetEstimator

#: The time-offset estimator's work on a frame waits for a frame that is not a keyframe, so
#: that it never adds to the smoother's update: such a frame takes on up to
#: ``OFFSET_PER_FRAME`` waiting frames, oldest first. Of a run of keyframes longer than
#: ``OFFSET_BACKLOG`` (a fast turn), the estimator sees only the last ``OFFSET_BACKLOG`` frames.
OFFSET_PER_FRAME = 3
OFFSET_BACKLOG = 8
#: The window is moved to the offset in use once it differs by more than this from the offset
#: any of the window's keyframes was filed at, seconds (:meth:`Vins._retime_window`).
RETIME_TOLERANCE_S = 0.001


@dataclass(frozen=True)
class FrameUpdate:
    """What one frame produced.

    ``t``: the frame's time as the caller gave it (its stamp). ``keyframe``: the smoother was
    updated with this frame. ``T_W_B``/``velocity_W``: the body state when the frame was
    exposed, at :attr:`t_exposure` (None until initialised, or when the IMU does not reach
    it). ``sparse_map``: the window's landmarks in this frame's camera, stamped ``t`` (None until
    there is an estimate, and while LOST). ``time_offset``: the camera-IMU time offset
    subtracted from ``t`` (module docstring), with its uncertainty. ``correction_m``: on a
    keyframe, how far the smoother's update moved the keyframe's position from where the IMU
    propagated it, ``|p_smoother - p_imu|``: the estimator's disagreement with itself, small
    while the landmarks and the IMU agree (None on other frames).
    """

    t: float
    keyframe: bool
    T_W_B: np.ndarray | None
    velocity_W: np.ndarray | None
    sparse_map: SparseMap | None
    health: Health
    time_offset: TimeOffset = TimeOffset()
    correction_m: float | None = None

    @property
    def t_exposure(self) -> float:
        """The frame's exposure on the IMU's clock, ``t - time_offset.seconds``: the time of
        ``T_W_B`` and ``velocity_W``."""
        return self.t - self.time_offset.seconds


@dataclass(frozen=True)
class _Anchor:
    """The state propagation starts from, with the biases to propagate with."""

    state: NavState
    bias_g: np.ndarray
    bias_a: np.ndarray


class Vins:
    """Monocular visual-inertial odometry with a metric sparse map (module docstring)."""

    def __init__(self, camera: PinholeCamera, distortion, T_B_C, noise: ImuNoise,
                 options: VinsOptions | None = None, *, frontend: FrontendOptions | None = None,
                 static: StaticInitOptions | None = None):
        self.options = options or VinsOptions()
        self.camera = camera
        self.distortion = tuple(distortion)
        self.T_B_C = np.asarray(T_B_C, dtype=float)
        if self.T_B_C.shape != (4, 4) or not np.isfinite(self.T_B_C).all():
            raise ValueError(f"T_B_C must be a finite 4x4 pose, got shape {self.T_B_C.shape}")
        self.static_options = static or StaticInitOptions()
        self.tracker = FeatureTracker(camera, self.distortion, frontend)
        self.backend = SlidingWindowSmoother(camera, self.T_B_C, noise, self.options)
        self.static_init: StaticInit | None = None
        self.reinitialisations = 0
        self.refused_pressures = 0
        self.barometer_keyframes = 0  # keyframes given the barometer's height
        self._imu = ImuBuffer()
        self._pressures = PressureHistory()
        self._propagator = Propagator()
        self._anchor: _Anchor | None = None
        self._last_frame_t = -math.inf
        self._keyframe_tracks: Tracks | None = None
        self._lost_reason = ""
        self._lost_since: float | None = None
        self._starved_since: float | None = None
        self._last_reset_t = -math.inf
        self._moved = False
        self._update_ms: float | None = None
        self._last_exposure_t = -math.inf
        self._last_offset_s = self.options.time_offset_s
        self._fixed_offset = TimeOffset(self.options.time_offset_s)
        self._offset_estimator = (TimeOffsetEstimator(self.T_B_C, math.sqrt(camera.fx * camera.fy),
                                                      self.options)
                                  if self.options.estimate_time_offset else None)
        o = self.options
        self._alignment = (GyroAlignment(o.gyro_cross_axis_sigma, o.gyro_scale_sigma,
                                         o.gyro_alignment, o.gyro_alignment_rates)
                           if o.estimate_gyro_alignment or any(o.gyro_alignment) else None)
        self._offset_backlog: list[tuple[float, np.ndarray, np.ndarray]] = []
        #: the time offset each keyframe of the window was filed at, by keyframe index
        self._keyframe_offsets: dict[int, float] = {}
        #: the take-off's window (:meth:`_keep_window_open`) was kept and let go: once a flight
        self._window_kept_done = False
        self._gap: ImuGap | None = None
        self._stillness = ZeroVelocityDetector(self.options, math.sqrt(camera.fx * camera.fy))
        self._accel_scale: RestAccelScale | None = None
        self._on_ground = False
        self.zero_velocity_keyframes = 0

    # ------------------------------------------------------------------ inputs

    @property
    def resets(self) -> int:
        """Smoother rebuilds plus in-flight re-initialisations."""
        return self.backend.resets + self.reinitialisations

    @property
    def time_offset(self) -> TimeOffset:
        """The camera-IMU time offset the next frame's stamp is corrected by (module
        docstring)."""
        if self._offset_estimator is None:
            return self._fixed_offset
        return self._offset_estimator.offset

    def exposure_time(self, t: float) -> float:
        """When a frame stamped ``t`` was exposed, on the IMU's clock: the IMU should reach this
        (and ``t``) before :meth:`add_frame`."""
        return float(t) - self.time_offset.seconds

    @property
    def gyro_alignment(self) -> GyroAlignmentEstimate | None:
        """The gyro's response to the yaw rate it is corrected by (None when neither
        ``estimate_gyro_alignment`` nor a calibrated ``gyro_alignment`` is given; without the
        estimate, the calibration with no pairs): :mod:`autonomy.vins.gyro_alignment`."""
        return None if self._alignment is None else self._alignment.estimate

    @property
    def rest_accel_scale_error(self) -> float | None:
        """The accelerometer's z sensitivity error read at rest that samples are corrected by,
        a fraction (None before the static initialisation, or without
        ``rest_accel_scale_share``)."""
        return None if self._accel_scale is None else self._accel_scale.error

    def add_imu(self, sample: ImuSample) -> None:
        """One IMU sample, in time order; ValueError for a bad one (the sample is not used).
        With ``estimate_gyro_alignment`` or a calibrated ``gyro_alignment`` its gyro is
        corrected before use; the time-offset estimator gets it raw. With the barometer on, its
        pressure is kept for the keyframes; one no barometer reads is left out and counted
        (``refused_pressures``), the sample used."""
        raw_gyro = np.asarray(sample.gyro, dtype=float).reshape(-1)
        if self._alignment is not None and raw_gyro.shape == (3,):
            sample = replace(sample, gyro=self._alignment.correct(raw_gyro))
        if self._accel_scale is not None:
            sample = replace(sample, accel=self._accel_scale.correct(sample.accel))
        self._imu.add(sample)
        if sample.pressure_pa is not None and self.options.barometer_sigma_m > 0.0:
            self._keep_pressure(sample.t, sample.pressure_pa)
        if self._offset_estimator is not None:
            bias = self._anchor.bias_g if self._anchor is not None else np.zeros(3)
            if self._alignment is not None:
                bias = self._alignment.uncorrect(bias)
            self._offset_estimator.add_imu(self._imu.last_time, raw_gyro, bias)

    def _keep_pressure(self, t: float, pressure_pa) -> None:
        pressure = usable_pressure(pressure_pa)
        if pressure is None:
            self.refused_pressures += 1
        else:
            self._pressures.add(t, pressure)

    def track(self, image) -> Tracks:
        """The front-end on one image (uint8 grey or RGB, the camera's size)."""
        return self.tracker.track(image)

    def report_update_ms(self, milliseconds: float) -> None:
        """The caller's measurement of the last :meth:`add_frame`, judged by the health."""
        self._update_ms = float(milliseconds)

    def add_frame(self, t: float, tracks: Tracks, *, on_ground: bool = False) -> FrameUpdate:
        """Everything after the front-end for the frame stamped ``t`` (module docstring);
        ``on_ground``: the caller knows the vehicle is on the ground, disarmed (a keyframe
        standing still then gets a zero-velocity prior: :mod:`autonomy.vins.stillness`)."""
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"frame time must be a finite number of seconds, got {t}")
        if t <= self._last_frame_t:
            raise ValueError(f"frame time {t} is not after the previous frame "
                             f"({self._last_frame_t})")
        self._last_frame_t = t
        self._on_ground = bool(on_ground)
        offset = self.time_offset
        exposure = t - offset.seconds
        if exposure <= self._last_exposure_t:  # the estimate moved by more than the frame gap
            offset = replace(offset, seconds=self._last_offset_s)
            exposure = t - offset.seconds
        self._last_exposure_t, self._last_offset_s = exposure, offset.seconds
        update = self._add_frame_at(exposure, tracks)
        if self._offset_estimator is not None:
            self._estimate_offset(t, tracks, update.keyframe)
        if exposure == t:
            return update if offset == update.time_offset else replace(update, time_offset=offset)
        sparse_map = (None if update.sparse_map is None
                      else replace(update.sparse_map, t=t))
        return replace(update, t=t, sparse_map=sparse_map, time_offset=offset)

    def _estimate_offset(self, t: float, tracks: Tracks, keyframe: bool) -> None:
        """The frame to the time-offset estimator, on a later frame that is not a keyframe
        (:data:`OFFSET_BACKLOG`); the estimate applies from the frame after."""
        backlog = self._offset_backlog
        backlog.append((t, tracks.ids, tracks.normalised))
        if keyframe:
            del backlog[:-OFFSET_BACKLOG]
            return
        for frame in backlog[:OFFSET_PER_FRAME]:
            self._offset_estimator.add_frame(*frame)
            self._align_gyro(self._offset_estimator.latest_pair)
        del backlog[:OFFSET_PER_FRAME]

    def _align_gyro(self, pair: PairRotations | None) -> None:
        """The time offset's new frame pair to the gyro alignment, once the offset is known
        to ``time_offset_max_sigma_s`` (a pair made at a wrong offset is biased)."""
        if not self.options.estimate_gyro_alignment or pair is None:
            return
        sigma = self._offset_estimator.offset.sigma
        if sigma is not None and sigma <= self.options.time_offset_max_sigma_s:
            self._alignment.add_pair(pair)

    def _add_frame_at(self, t: float, tracks: Tracks) -> FrameUpdate:
        """:meth:`add_frame` at the frame's exposure time ``t`` on the IMU's clock."""
        if self.static_init is None:
            return self._try_static_init(t, tracks)
        silent = self._imu_gap(t)
        if silent:
            self._observe_gap(t, tracks)
            return self._lost(t, tracks, silent)
        self._update_starvation(t, tracks)
        if self._lost_reason:
            if len(tracks) < self.options.min_tracked_ok:
                return self._lost(t, tracks, self._lost_reason)
            waiting = self._reinitialise(t, tracks)
            if waiting:
                return self._lost(t, tracks, waiting)
        return self._track_frame(t, tracks)

    # ------------------------------------------------------------------ outputs

    def odometry(self) -> Odometry | None:
        """The body state at the newest IMU sample (None until initialised, and from an IMU
        gap until the re-initialisation after it: nothing carries the state across)."""
        if self._anchor is None or self._imu.last_time is None or self._gap is not None:
            return None
        t = max(self._imu.last_time, self._anchor.state.t)
        state = self._propagate_to(t)
        rate = self._imu.last_gyro - self._anchor.bias_g
        usable = self.backend.started and not self._lost_reason
        covariance = (self.backend.pose_covariance(self.options.covariance_period_s) if usable
                      else np.full((6, 6), np.nan))
        return Odometry(t, make_pose(state.R_W_B, state.position), state.velocity, rate,
                        covariance)

    # ------------------------------------------------------------------ steps

    def _try_static_init(self, t: float, tracks: Tracks) -> FrameUpdate:
        o = self.static_options
        window = self._imu.window(t - o.window_s * (1.0 + 1e-6), t)
        result = (static_initialise(*window, o) if len(window[0]) >= 2
                  else NotStill("waiting for IMU samples", t, t))
        self._imu.discard_before(t - o.window_s * 2.0)
        if isinstance(result, StaticInit) and self.options.rest_accel_scale_share > 0.0:
            result = self._correct_accel_scale(result, window)
        if isinstance(result, NotStill):
            return FrameUpdate(t, False, None, None, None, Health(
                HealthState.INITIALISING, f"static initialisation: {result.reason}",
                tracked=len(tracks)))
        self.static_init = result
        zero = np.zeros(3)
        state = KeyframeState(0, t, make_pose(result.R_W_B, zero), zero, result.gyro_bias, zero)
        self._start(state, self._start_sigmas(self.options.prior_velocity_sigma), tracks)
        return self._result(t, tracks, True, self._anchor.state)

    def _correct_accel_scale(self, result: StaticInit, window) -> StaticInit | NotStill:
        """The static window judged again with the z sensitivity it reads divided out
        (:mod:`autonomy.vins.accel_scale`): its gravity direction and norm move with it. Still
        so, the correction applies to the buffered samples and every one after."""
        scale = RestAccelScale.from_rest(result.accel_norm, self.options.rest_accel_scale_share)
        t, gyro, accel = window
        corrected = static_initialise(t, gyro, scale.correct(accel), self.static_options)
        if isinstance(corrected, StaticInit):
            self._accel_scale = scale
            self._imu.correct_accel(scale.correct)
        return corrected

    def _start_sigmas(self, velocity_sigma: float, tilt: float | None = None) -> PriorSigmas:
        """Priors of a (re)start: ``tilt`` (radians; default the options' tilt), the world's
        gauge fixed in yaw and position."""
        o = self.options
        tilt = math.radians(o.prior_tilt_sigma_deg) if tilt is None else tilt
        return PriorSigmas.with_bias_priors(o, (tilt, tilt, o.gauge_yaw_sigma),
                                            o.gauge_position_sigma, velocity_sigma)

    def _start(self, state: KeyframeState, sigmas: PriorSigmas, tracks: Tracks) -> None:
        self.backend.start(state, sigmas, tracks.ids, tracks.normalised,
                           pressure_pa=self._keyframe_pressure(state.t, state.T_W_B[2, 3]),
                           noise_scale=tracks.noise_scale)
        self._keyframe_tracks = tracks
        self._filed_keyframe()
        self._set_anchor_from_backend()
        self._stillness.clear()
        self._stillness.add(state.t, state.T_W_B[:3, :3], tracks)

    def _reinitialise(self, t: float, tracks: Tracks) -> str:
        """Start a new smoother in flight at the IMU-propagated state with a wide velocity
        prior, or after a long IMU gap where :class:`~autonomy.vins.imu_gap.ImuGap` says;
        returns why it waits instead ("" when it started)."""
        restart = self._restart_after_gap(t, tracks) if self._gap is not None else None
        if isinstance(restart, str):
            return restart
        if restart is None:
            state = self._propagate_to(t)
            lost_s = 0.0 if self._lost_since is None else t - self._lost_since
            sigmas = self._start_sigmas(self.reinit_velocity_prior(lost_s))
        else:
            state = restart.state
            sigmas = self._start_sigmas(restart.velocity_sigma, restart.tilt_sigma)
        a = self._anchor
        keyframe = KeyframeState(self.backend.latest.index + 1, t,
                                 make_pose(state.R_W_B, state.position), state.velocity,
                                 a.bias_g, a.bias_a)
        self._start(keyframe, sigmas, tracks)
        self.reinitialisations += 1
        self._gap = None
        self._last_reset_t = t
        self._lost_reason = ""
        self._lost_since = None
        self._starved_since = None
        return ""

    def reinit_velocity_prior(self, lost_s: float) -> float:
        """The velocity prior of a re-initialisation from the IMU's propagation after
        ``lost_s`` seconds LOST, m/s: ``hypot(sigma_v, sigma_ba * lost_s)``, the last smoother
        state's velocity error ``sigma_v`` (``propagated_velocity_sigma``) and what an
        accelerometer bias off by ``sigma_ba`` (``prior_accel_bias_sigma``) adds while the IMU
        alone carries the state. Any wider and the new window takes its speed, so its map's
        scale, from its first images, in a cruise that says little of it (docs/vins.md,
        "The hallway's drift, taken apart")."""
        o = self.options
        return math.hypot(o.propagated_velocity_sigma,
                          o.prior_accel_bias_sigma * max(lost_s, 0.0))

    def _observe_gap(self, t: float, tracks: Tracks) -> None:
        """A frame while the IMU is silent or just back: to the gap's observations."""
        if self._gap is None:
            a = self._anchor
            self._gap = ImuGap(self._imu.last_time, a.state.position, yaw_of(a.state.R_W_B),
                               a.bias_a, self.options, math.sqrt(self.camera.fx * self.camera.fy))
        landmarks = self.backend.landmarks
        self._gap.observe(t, tracks, landmarks.ids, landmarks.points_W,
                          invert_pose(self.backend.camera_mounting))

    def _restart_after_gap(self, t: float, tracks: Tracks) -> Restart | str | None:
        """Where to restart after an IMU gap (:mod:`autonomy.vins.imu_gap`): None to
        propagate across it, when the map confirms the propagation or, without the map, when
        the gap lasted up to ``max_propagated_gap_s``; relocalised on the map; standing
        still; or why it waits."""
        o, gap = self.options, self._gap
        self._observe_gap(t, tracks)
        relocalised = gap.relocalised(t)
        if relocalised is not None:
            return None if self._propagation_agrees(t, relocalised) else relocalised
        imu_t, gyro, accel = self._imu.window(math.nextafter(gap.last_sample_t, math.inf), t)
        if len(imu_t) == 0:  # the samples after the gap are all later than this frame
            return "IMU back after a gap, not yet up to this frame"
        if imu_t[0] - gap.last_sample_t <= o.max_propagated_gap_s:
            return None
        # no propagation across this gap is used now: the samples held while it waits are
        # bounded
        self._imu.discard_before(t - o.reinit_imu_window_s)
        return gap.standing_still(t, imu_t, gyro - self._anchor.bias_g, accel)

    def _propagation_agrees(self, t: float, relocalised: Restart) -> bool:
        """The IMU's propagation to ``t`` (while its samples are held) is within
        ``max_propagation_disagreement_m`` of the relocalised position: the samples held
        across the gap did not mislead it, and it is the more precise of the two."""
        first = self._imu.first_time
        if first is None or first > self._anchor.state.t:
            return False
        propagated = self._propagate_to(t)
        return bool(np.linalg.norm(propagated.position - relocalised.state.position)
                    <= self.options.max_propagation_disagreement_m)

    def _track_frame(self, t: float, tracks: Tracks) -> FrameUpdate:
        keyframe = self.backend.latest.t < t and self._is_keyframe(t, tracks)
        correction = None
        if keyframe:
            before, predicted = self._anchor, self._propagate_to(t)
            try:
                self._add_keyframe(t, tracks, predicted)
            except BackendError as error:
                return self._lost(t, tracks, str(error))
            state = self._anchor.state
            correction = float(np.linalg.norm(state.position - predicted.position))
            if correction > self.options.max_keyframe_correction_m:
                # The window has moved its newest keyframe where the IMU, 0.05-0.2 s on,
                # cannot have gone: the smoother is diverging. Keep the propagation.
                self._anchor = _Anchor(predicted, before.bias_g, before.bias_a)
                return self._lost(t, tracks, (
                    f"diverging: the smoother moved a keyframe {correction:.3g} m from the "
                    f"IMU's propagation (> {self.options.max_keyframe_correction_m:g} m)"))
        else:
            state = self._propagate_to(t)
        speed = float(np.linalg.norm(state.velocity))
        self._moved = self._moved or speed > self.options.moving_speed
        return self._result(t, tracks, keyframe, state, correction)

    def _is_keyframe(self, t: float, tracks: Tracks) -> bool:
        since = t - self.backend.latest.t
        if since < self.options.keyframe_min_interval_s:
            return False
        return (since >= self.options.keyframe_interval_s
                or self._parallax_px(tracks) >= self.options.keyframe_parallax_px)

    def _add_keyframe(self, t: float, tracks: Tracks, predicted: NavState) -> None:
        """The frame at ``t`` to the smoother, with a zero-velocity prior when it stands still
        on the ground (:mod:`autonomy.vins.stillness`), by its tracks and the IMU's
        ``predicted`` attitude."""
        if self._offset_estimator is not None and self.options.retime_window:
            self._retime_window()
            self._keep_window_open(t)
        pim = self._preintegrate(self.backend.latest.t, t)
        still = self._on_ground and self._stillness.still(t, predicted.R_W_B, tracks)
        # the drag factor's free flight: off the ground (by the caller) and moved since the
        # start, so not waiting for the take-off (an armed vehicle just landed still counts)
        airborne = not self._on_ground and self._moved and not still
        pressure = self._keyframe_pressure(t, predicted.position[2])
        self.barometer_keyframes += pressure is not None
        if not self.backend.add_keyframe(t, pim, tracks.ids, tracks.normalised, still,
                                         airborne, pressure, tracks.noise_scale):
            self._last_reset_t = t
        self.zero_velocity_keyframes += still
        self._keyframe_tracks = tracks
        self._filed_keyframe()
        self._set_anchor_from_backend()
        self._stillness.add(t, self._anchor.state.R_W_B, tracks)

    def _keyframe_pressure(self, t: float, height: float) -> float | None:
        """The barometer's sample for a keyframe at ``t``, ``height`` above the ground the
        VINS started on (its world's z = 0); None below ``barometer_min_height_m``, in the
        rotors' ground effect."""
        pressure = self._pressures.take(t)
        return pressure if height >= self.options.barometer_min_height_m else None

    def _preintegrate(self, t0: float, t1: float):
        """The IMU from ``t0`` to ``t1`` preintegrated at the latest keyframe's biases (its
        gyro weighed by the interval's turn with ``gyro_axes_noise``)."""
        pieces = self._imu.pieces(t0, t1)
        pim = self.backend.preintegration(pieces.gyro, pieces.dt)
        for gyro, accel, dt in zip(pieces.gyro, pieces.accel, pieces.dt):
            pim.integrateMeasurement(accel, gyro, dt)
        return pim

    def _filed_keyframe(self) -> None:
        """Note the offset in use for the keyframe just filed; forget those out of the window."""
        window = {index for index, _ in self.backend.window_keyframes}
        self._keyframe_offsets = {index: offset for index, offset
                                  in self._keyframe_offsets.items() if index in window}
        self._keyframe_offsets[self.backend.latest.index] = self._last_offset_s

    def _retime_window(self) -> None:
        """Move the window's keyframes to the exposure times the offset in use gives their
        stamps, the IMU between them preintegrated again, once it differs by more than
        :data:`RETIME_TOLERANCE_S` from the offset one of them was filed at.

        Why: a vehicle's first flight starts from ``time_offset_s`` (0), and the take-off's
        climb, with no rotation, shows the offset nothing; its first estimate comes as the
        vehicle pitches into the cruise, when every keyframe of the window has been filed a
        whole offset (15-18 ms in the simulator's realistic camera) away from its exposure.
        From rest that skews the onset's baselines by ``2 td / dt``, the landmarks made from
        them set the scale, and the rest of the flight keeps it (docs/vins.md, "The window
        moved with the time offset"). The keyframe filed at offset ``o_k`` was stamped
        ``t_k + o_k``; at the offset ``o`` now in use it was exposed at ``t_k + o_k - o``.
        Keyframes already marginalised stay as filed: the climb's, whose error then shows as
        a long path (why it is off by default)."""
        offset = self._last_offset_s
        window = self.backend.window_keyframes
        filed = [self._keyframe_offsets.get(index) for index, _ in window]
        if None in filed or max(abs(o - offset) for o in filed) <= RETIME_TOLERANCE_S:
            return
        times = [t + o - offset for (_, t), o in zip(window, filed)]
        first = self._imu.first_time
        if first is None or first > times[0] or np.any(np.diff(times) <= 0.0):
            return  # the IMU does not reach back so far: the window stays as it was filed
        pims = [self._preintegrate(t0, t1) for t0, t1 in zip(times, times[1:])]
        if not self.backend.retime(times, pims):
            self._last_reset_t = times[-1]
        self._keyframe_offsets = {index: offset for index, _ in self.backend.window_keyframes}
        self._set_anchor_from_backend()

    def _keep_window_open(self, t: float) -> None:
        """With ``takeoff_window_s``: when the vehicle first moves with the time offset not yet
        known, the window stops sliding and keeps every keyframe it then holds and every one
        after; once the offset is known (its sigma within ``time_offset_max_sigma_s``, the
        window retimed to it just before), or ``takeoff_window_s`` after the window's start,
        the keyframe at ``t`` lets them go and the window is the lag's again. Once a flight.

        Why: the take-off's climb shows the offset nothing, so its keyframes are filed at the
        offset the flight started from; with the lag alone they are marginalised before
        anything shows it, and what they made of the landmarks' depths stays in the window's
        marginal, which the retiming cannot reach (docs/vins.md, "The window moved with the
        time offset"). Kept open, they are moved with the rest of the window."""
        if self.options.takeoff_window_s <= 0.0 or self._window_kept_done:
            return
        offset = self._offset_estimator.offset
        known = offset.sigma is not None and offset.sigma <= self.options.time_offset_max_sigma_s
        kept_from = self.backend.kept_from
        if kept_from is None:
            if self._moved and not known:
                self.backend.keep_window_from(self.backend.window_keyframes[0][1])
            elif self._moved:
                self._window_kept_done = True  # known before it moved: nothing to keep
            return
        if known or t - kept_from > self.options.takeoff_window_s:
            self.backend.keep_window_from(None)
            self._window_kept_done = True

    def _set_anchor_from_backend(self) -> None:
        s = self.backend.latest
        self._anchor = _Anchor(NavState(s.t, s.T_W_B[:3, :3], s.T_W_B[:3, 3], s.velocity),
                               s.bias_g, s.bias_a)
        self._imu.discard_before(self._imu_kept_from(s.t))

    def _imu_kept_from(self, latest_t: float) -> float:
        """The IMU is kept from the latest keyframe on, and with ``retime_window`` from the
        window's oldest, as far again as the offset may move, to retime the window."""
        if self._offset_estimator is None or not self.options.retime_window:
            return latest_t
        oldest = self.backend.window_keyframes[0][1]
        return oldest - 2.0 * self.options.max_time_offset_s

    def _propagate_to(self, t: float) -> NavState:
        a = self._anchor
        return self._propagator.propagate(a.state, self._imu.pieces(a.state.t, t), a.bias_g,
                                          a.bias_a)

    def _imu_gap(self, t: float) -> str:
        last = self._imu.last_time
        if last is None or last < t - self.options.max_imu_gap_s:
            return f"IMU silent: last sample at {last}, frame at {t:.3f}"
        return ""

    def _update_starvation(self, t: float, tracks: Tracks) -> None:
        if len(tracks) >= self.options.min_tracked_lost:
            self._starved_since = None
            return
        if self._starved_since is None:
            self._starved_since = t
        if t - self._starved_since >= self.options.lost_after_s:
            self._lost_reason = (f"only {len(tracks)} features tracked for "
                                 f"{t - self._starved_since:.2f} s")

    def _lost(self, t: float, tracks: Tracks, reason: str) -> FrameUpdate:
        """LOST: keep the state propagated (when the IMU reaches ``t`` and no gap lies
        between), no map."""
        self._lost_reason = reason
        if self._lost_since is None:
            self._lost_since = t
        pose = velocity = None
        if self._gap is None and not self._imu_gap(t):
            state = self._propagate_to(t)
            self._anchor = _Anchor(state, self._anchor.bias_g, self._anchor.bias_a)
            self._imu.discard_before(t)
            pose, velocity = make_pose(state.R_W_B, state.position), state.velocity
        health = Health(HealthState.LOST, reason, tracked=len(tracks), resets=self.resets,
                        update_ms=self._update_ms)
        return FrameUpdate(t, False, pose, velocity, None, health)

    # ------------------------------------------------------------------ results

    def _parallax_px(self, tracks: Tracks) -> float:
        """Mean displacement, pixels, of the features common to this frame and the last
        keyframe."""
        reference = self._keyframe_tracks
        if reference is None or len(tracks) == 0 or len(reference) == 0:
            return 0.0
        common, here, there = np.intersect1d(tracks.ids, reference.ids, return_indices=True)
        if len(common) == 0:
            return 0.0
        return float(np.linalg.norm(tracks.pixels[here] - reference.pixels[there], axis=1).mean())

    def _result(self, t: float, tracks: Tracks, keyframe: bool, state: NavState,
                correction_m: float | None = None) -> FrameUpdate:
        T_W_B = make_pose(state.R_W_B, state.position)
        sparse_map = self._sparse_map(t, T_W_B, tracks)
        latest = self.backend.latest
        health = assess(HealthInputs(
            tracked=len(tracks), landmarks=len(sparse_map), parallax_px=self._parallax_px(tracks),
            speed=float(np.linalg.norm(state.velocity)),
            gyro_bias=float(np.linalg.norm(latest.bias_g)),
            accel_bias=float(np.linalg.norm(latest.bias_a)), resets=self.resets,
            update_ms=self._update_ms, moved=self._moved,
            starved_s=0.0 if self._starved_since is None else t - self._starved_since,
            since_reset_s=t - self._last_reset_t), self.options)
        return FrameUpdate(t, keyframe, T_W_B, state.velocity, sparse_map, health,
                           correction_m=correction_m)

    def _sparse_map(self, t: float, T_W_B: np.ndarray, tracks: Tracks) -> SparseMap:
        """The window's landmarks in the camera at ``t``: ``p_C = T_C_B T_B_W(t) p_W``."""
        landmarks = self.backend.landmarks
        T_C_W = invert_pose(T_W_B @ self.backend.camera_mounting)
        points_C = landmarks.points_W @ T_C_W[:3, :3].T + T_C_W[:3, 3]
        sigma = self.backend.depth_sigma(points_C[:, 2])
        o = self.options
        keep = (points_C[:, 2] >= o.min_depth) & (points_C[:, 2] <= o.max_depth)
        ids, points_C, sigma = landmarks.ids[keep], points_C[keep], sigma[keep]
        pixels = distort_points(self.camera, self.distortion, points_C[:, :2] / points_C[:, 2:])
        _, here, there = np.intersect1d(ids, tracks.ids, return_indices=True)
        tracked = np.zeros(len(ids), bool)
        tracked[here] = True
        pixels[here] = tracks.pixels[there]
        return SparseMap(t, ids, points_C, sigma, pixels, tracked)
