"""The VINS back-end: a GTSAM fixed-lag smoother over keyframes and landmarks.

Variables, per keyframe ``k``: the body pose ``X(k) = T_W_B``, the velocity ``V(k)`` and the IMU
biases ``B(k)``; per landmark: its world position ``L(id)``, keyed by the front-end's track id.
Factors:

- ``CombinedImuFactor`` between consecutive keyframes: the 200 Hz IMU preintegrated on the
  manifold (Forster et al., TRO 2017) with the biases' random walk (GTSAM's combined form);
- ``GenericProjectionFactor`` from every keyframe to every landmark it sees, on the undistorted
  feature position in pixels of the ideal pinhole, under a Huber loss, through the camera
  mounting ``T_B_C``; with ``estimate_camera_mounting``, the mounting is a variable of the
  window (``MOUNTING``, gtsam_unstable's ``ProjectionFactorPPP``), its rotation held by a prior
  of ``mounting_rotation_sigma_deg`` at the configured one (after a rebuild or a
  re-initialisation, at its last estimate) and its position where configured;
  it is restamped at every keyframe, so never marginalised, and eliminated last with the newest
  keyframe, as VINS-Mono and OKVIS estimate it online;
- priors on the first keyframe (from static initialisation) or, after a rebuild, on the last
  good estimate;
- with ``hold_gauge`` (the default), the gauge hold: a prior on one keyframe inside the window
  at its estimate, tight in world yaw and position only, moved to a newer keyframe as the
  window slides (below);
- on a keyframe taken standing still, a prior ``V(k) = 0`` (``zero_velocity_sigma``;
  :mod:`autonomy.vins.stillness`);
- with ``drag_coefficient`` above 0 (off by default: docs/vins.md), on every keyframe interval
  the estimator calls airborne, the rotor drag's reading of the speed
  (:mod:`autonomy.vins.drag`);
- with ``keyframe_prior_position_sigma`` above 0 (off by default: docs/vins.md, the resets,
  for what it costs), a loose prior on every new keyframe's pose at its IMU prediction.
  Position and yaw are unobservable: without the gauge hold, all the window knows of them is
  the marginal of the first prior, whose information fades as the flight goes on, while the
  IMU factors between close keyframes hold their poses to about 1e-5 of that. A window with no
  landmark at all knows its biases only from their priors too, and meets iSAM2's
  "indeterminate linear system" within 10 s; the priors keep it from fading. In flight the
  window is sound, and the smoother eliminates the newest keyframe's variables last so that
  GTSAM's Cholesky does not call it indeterminate as the gauge fades
  (:mod:`autonomy.vins.fixed_lag`).

The fixed-lag smoother (:class:`FixedLagSmoother`, iSAM2 underneath) marginalises every variable
whose time stamp falls more than ``smoother_lag_s`` behind the newest keyframe; a landmark's
stamp is the time of the last keyframe that saw it. Landmarks enter only through the gate of
:mod:`autonomy.vins.landmarks`. An update that throws, or that leaves a state no vehicle can be
in (speed, bias magnitudes), is thrown away: the smoother cannot be copied, so a new one is
built from the last good keyframe's estimate, the keyframe is added again with its IMU factor
only, and the event counts as a reset. The rebuilt window holds that keyframe's position and yaw
nearly fixed (they are unobservable: nothing in it could move them), so the uncertainty they had
is carried by a :class:`GaugeAnchor` and added to every covariance reported after it.

The gauge hold holds the window's position and yaw at a keyframe ``g`` inside it, so that a
window whose gauge has faded cannot slide whole (every keyframe a metre away in one update, at
the sewer's pipe mouth: docs/vins.md, "The gauge hold"). When the update marginalises ``g``
the hold moves to the oldest keyframe the update keeps: the old prior is removed in the same
update, so it never enters a marginal, and the window's absolute information stays what it
was, the first prior's, fading, plus the hold's alone. The hold changes the covariance the
window computes, not the one it reports: :meth:`SlidingWindowSmoother.pose_covariance` takes
the hold's prior out again (a rank update, :func:`released_covariance`), so the covariance
still measures from the first prior, through every correlation of the pose with the velocity
and the biases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import gtsam
import gtsam_unstable
import numpy as np
from gtsam.symbol_shorthand import B, L, V, X

from autonomy.geometry import GRAVITY, PinholeCamera, invert_pose
from autonomy.vins.barometer import BarometerChain
from autonomy.vins.drag import MAX_INTERVAL_S, drag_factor
from autonomy.vins.fixed_lag import FixedLagSmoother, UpdateListener
from autonomy.vins.landmarks import (
    Gate, depth_sigma, gate_candidates, observation_limit_px, spread_choice, widest_ray_angle,
)
from autonomy.vins.options import VinsOptions
from autonomy.vins.preintegration import ImuNoise, about_vertical, gyro_axes_density
from autonomy.vins.track_precision import checked_noise_scale

#: Floors under the IMU densities, so a noiseless recording still gives a well-posed problem.
#: The bias walks' are 1.9 and 30 times under EuRoC's (1.9e-5, 3e-3), the presets' figures; a
#: configured figure below a floor is raised to it. At 1e-7 and 1e-6 a bias chain that stiff
#: left GTSAM finding the window indeterminate at a bias key and rebuilding it at nearly every
#: keyframe (``eval vio`` of a 40 s noiseless recording: 450 rebuilds).
_DENSITY_FLOOR = {"gyro": 1e-5, "accel": 1e-4, "gyro_walk": 1e-5, "accel_walk": 1e-4}


#: Prior widths on the last good keyframe when the smoother is rebuilt: its pose is kept nearly
#: fixed (position and yaw are unobservable, so the rebuilt window must not move them), its
#: tilt and velocity may be corrected by what follows.
REBUILD_ROTATION_SIGMAS = (0.02, 0.02, 0.005)
REBUILD_POSITION_SIGMA = 0.01
REBUILD_VELOCITY_SIGMA = 0.1

#: The gauge hold's prior: the hold needs only to be far stronger than the faded gauge (a
#: window a metre uncertain holds it with information about 1 m^-2), and a weaker hold keeps
#: what the rest of the window knows of the held keyframe within the precision of its
#: marginal, which :func:`released_covariance` takes back out.
HOLD_YAW_SIGMA = 0.005
HOLD_POSITION_SIGMA = 0.01
#: The hold's height where the barometer holds it (its offset's chain runs through the held
#: keyframe): negligible against the window's barometer samples, which a hold of
#: ``HOLD_POSITION_SIGMA`` would overrule, keeping the height each move found.
HOLD_BAROMETER_HEIGHT_SIGMA = 1.0

#: Below this fraction of the hold's prior covariance, what the rest of the window knows of
#: the held keyframe is lost in the marginal's rounding, and the covariance is unknown.
RELEASE_PRECISION = 1e-6

#: Columns and rows of the image grid over which new landmarks are spread.
LANDMARK_GRID = (4, 4)

#: GTSAM keys (``gtsam.Symbol``) hold the character in the top byte and the index below it.
_SYMBOL_INDEX_BITS = 56


@dataclass(frozen=True)
class KeyframeState:
    """The estimate of one keyframe: pose ``T_W_B`` (4x4), velocity, gyro and accel biases."""

    index: int
    t: float
    T_W_B: np.ndarray
    velocity: np.ndarray
    bias_g: np.ndarray
    bias_a: np.ndarray


@dataclass(frozen=True)
class PriorSigmas:
    """One-sigma priors for a (re)start: rotation ``(roll, pitch, yaw)`` about the body axes
    (radians), position (m), velocity (m/s), biases (rad/s, m/s^2)."""

    rotation: tuple[float, float, float]
    position: float
    velocity: float
    gyro_bias: float
    accel_bias: float

    @classmethod
    def with_bias_priors(cls, options: VinsOptions, rotation: tuple[float, float, float],
                         position: float, velocity: float) -> "PriorSigmas":
        """Priors whose bias widths are the options' static-initialisation ones."""
        return cls(rotation, position, velocity, options.prior_gyro_bias_sigma,
                   options.prior_accel_bias_sigma)


@dataclass(frozen=True)
class Landmarks:
    """The window's landmarks: track ``ids`` (N,), world ``points_W`` (N, 3), the depth
    uncertainty geometry ``parallax_rad`` (N,) and ``observations`` (N,) keyframe counts."""

    ids: np.ndarray
    points_W: np.ndarray
    parallax_rad: np.ndarray
    observations: np.ndarray

    @classmethod
    def empty(cls) -> "Landmarks":
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


@dataclass(frozen=True)
class GaugeAnchor:
    """The position and yaw a rebuilt smoother starts from, with the uncertainty they had.

    A rebuild pins the last good keyframe ``g`` (position ``p_g``) with tight priors, so the
    new window's estimates are relative to it: any error of ``g`` in yaw ``dpsi`` (about the
    world's z) and position ``dp`` (world) moves every later keyframe rigidly about ``p_g``,
    ``p -> p_g + Rz(dpsi) (p - p_g) + dp``, ``R -> Rz(dpsi) R``, ``v -> Rz(dpsi) v``. To first
    order a keyframe at ``(R, p)`` is then off by ``J (dpsi, dp)`` in the body-frame tangent
    (rotation, then position; GTSAM's ``Pose3`` order),
    ``J = [[R^T e_z, 0], [R^T (e_z x (p - p_g)), R^T]]``, and its covariance grows by
    ``J C J^T``, with ``C`` (4x4) the covariance of ``(dpsi, dp)`` taken from ``g``'s reported
    one. Roll, pitch and velocity are observable (gravity, the IMU) and the new window
    estimates them again from wide priors, so they are not carried.
    """

    position_W: np.ndarray
    covariance: np.ndarray

    @classmethod
    def at(cls, T_W_B: np.ndarray, pose_covariance: np.ndarray) -> "GaugeAnchor":
        """The anchor at the pose ``T_W_B`` whose covariance (6x6, body tangent) is given:
        ``dpsi = e_z^T R dtheta_B`` and ``dp = R dp_B``."""
        R = T_W_B[:3, :3]
        to_world = np.zeros((4, 6))
        to_world[0, :3] = R[2]
        to_world[1:, 3:] = R
        return cls(np.array(T_W_B[:3, 3]), to_world @ pose_covariance @ to_world.T)

    def pose_covariance(self, T_W_B: np.ndarray) -> np.ndarray:
        """What the anchor adds to the covariance of the pose ``T_W_B`` (class docstring)."""
        R, up = T_W_B[:3, :3], np.array([0.0, 0.0, 1.0])
        J = np.zeros((6, 4))
        J[:3, 0] = R.T @ up
        J[3:, 0] = R.T @ np.cross(up, T_W_B[:3, 3] - self.position_W)
        J[3:, 1:] = R.T
        return J @ self.covariance @ J.T

    def velocity_covariance(self, velocity_W: np.ndarray) -> np.ndarray:
        """What the anchor's yaw adds to the covariance of ``velocity_W`` (world frame)."""
        turned = np.cross([0.0, 0.0, 1.0], velocity_W)
        return self.covariance[0, 0] * np.outer(turned, turned)


def released_covariance(joint: np.ndarray, prior_covariance: np.ndarray) -> np.ndarray:
    """The covariance of ``x`` once a prior on ``y`` is taken out of the problem.

    ``joint`` is the covariance of ``(x, y)`` with the prior, ``[[S_xx, S_xy], [S_yx, S_yy]]``,
    and ``prior_covariance`` (``W^-1``) the prior's, in ``y``'s tangent. The information
    without the prior is ``L - P^T W P`` (``P`` picks ``y``), so by Woodbury's identity
    ``S'_xx = S_xx + S_xy (W^-1 - S_yy)^-1 S_yx``. ``W^-1 - S_yy`` is what the rest of the
    problem knows of ``y`` beside the prior; singular (nothing else holds ``y``), the
    covariance is unbounded; known only to within ``RELEASE_PRECISION`` of the prior's, it
    is unknown: NaN either way.
    """
    n = len(joint) - len(prior_covariance)
    S_xx, S_xy, S_yy = joint[:n, :n], joint[:n, n:], joint[n:, n:]
    # in the prior's whitened coordinates, where its covariance is the identity
    whiten = np.linalg.inv(np.linalg.cholesky(prior_covariance))
    rest = np.eye(len(prior_covariance)) - whiten @ S_yy @ whiten.T
    if not np.isfinite(rest).all() or np.linalg.eigvalsh(rest)[0] <= RELEASE_PRECISION:
        return np.full((n, n), np.nan)
    lever = S_xy @ whiten.T
    return S_xx + lever @ np.linalg.solve(rest, lever.T)


@dataclass(frozen=True)
class _GaugeHold:
    """The keyframe that holds the window's gauge, its prior's covariance (pose tangent) and
    iSAM2 slot; both None for the start prior, which also holds the tilt and stays."""

    index: int
    covariance: np.ndarray | None = None
    slot: int | None = None

    @property
    def moved(self) -> bool:
        """Whether this is a moved hold's prior, which the covariance takes out (its slot
        comes with the update that adds it), not the start prior."""
        return self.covariance is not None


class BackendError(RuntimeError):
    """The smoother could not take a keyframe even after a rebuild."""


@dataclass(frozen=True)
class _Keyframe:
    """A keyframe's observations, ``ids`` sorted, ``normalised`` undistorted and
    ``noise_scale`` (each one's noise as a share of ``pixel_sigma``) in the same order;
    the iSAM2 slots of the factors made of the IMU since the keyframe before it
    (``interval_slots``: the preintegrated factor, the drag's), and whether it flew then."""

    index: int
    t: float
    ids: np.ndarray
    normalised: np.ndarray
    noise_scale: np.ndarray
    interval_slots: tuple[int, ...] = ()
    airborne: bool = False
    pressure_pa: float | None = None  # the barometer's sample matched to it, if any


def imu_params(noise: ImuNoise, white_scale: float, walk_scale: float,
               gyro_scale: float = 1.0,
               gyro_extra=np.zeros((3, 3))) -> gtsam.PreintegrationCombinedParams:
    """GTSAM preintegration parameters for a z-up world from continuous noise densities: the
    white noise's times ``white_scale`` (the gyro's times ``gyro_scale`` too, plus the squared
    density matrix ``gyro_extra``: :func:`gyro_axes_density`), the bias random walk's times
    ``walk_scale``."""
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY)
    eye = np.eye(3)
    params.setGyroscopeCovariance((white_scale * gyro_scale * max(
        noise.gyro_noise_density, _DENSITY_FLOOR["gyro"])) ** 2 * eye + gyro_extra)
    params.setAccelerometerCovariance(
        (white_scale * max(noise.accel_noise_density, _DENSITY_FLOOR["accel"])) ** 2 * eye)
    params.setIntegrationCovariance(1e-8 * eye)
    params.setBiasOmegaCovariance(
        (walk_scale * max(noise.gyro_random_walk, _DENSITY_FLOOR["gyro_walk"])) ** 2 * eye)
    params.setBiasAccCovariance(
        (walk_scale * max(noise.accel_random_walk, _DENSITY_FLOOR["accel_walk"])) ** 2 * eye)
    return params


def _symbol_keys(keys: np.ndarray, char: str) -> np.ndarray:
    """The ``char`` symbols among GTSAM ``keys`` (uint64), in their order."""
    return keys[keys >> np.uint64(_SYMBOL_INDEX_BITS) == ord(char)]


def covariance_due(age_s: float, max_age_s: float) -> bool:
    """Whether a covariance ``age_s`` old in keyframe time is refreshed by an asker that keeps
    one for ``max_age_s`` (:meth:`SlidingWindowSmoother.pose_covariance`; the odometry's
    ``covariance_period_s``)."""
    return age_s >= max_age_s - 1e-9


def _is_landmark(key: int) -> bool:
    """Whether a GTSAM key is a landmark's, ``L(track)``: the smoother eliminates those first
    (:mod:`autonomy.vins.fixed_lag`)."""
    return key >> _SYMBOL_INDEX_BITS == ord("l")


def _symbol_indices(keys: np.ndarray, char: str) -> np.ndarray:
    """The sorted indices of the ``char`` symbols among GTSAM ``keys`` (uint64, sorted)."""
    index_mask = np.uint64((1 << _SYMBOL_INDEX_BITS) - 1)
    return (_symbol_keys(keys, char) & index_mask).astype(np.int64)


def _in_sorted(values: np.ndarray, sorted_ids: np.ndarray) -> np.ndarray:
    """``np.isin(values, sorted_ids)`` by binary search in the sorted ``sorted_ids``: the
    window's id sets are kept sorted, which ``np.isin`` would sort again."""
    if len(sorted_ids) == 0:
        return np.zeros(len(values), bool)
    rows = np.minimum(np.searchsorted(sorted_ids, values), len(sorted_ids) - 1)
    return sorted_ids[rows] == values


#: Tangent dimensions of the variables whose covariances are asked for: pose, velocity.
_DIMENSIONS = {"x": 6, "v": 3}


def _dimension(key: int) -> int:
    return _DIMENSIONS[chr(gtsam.Symbol(key).chr())]


#: The camera's mounting ``T_B_C``, a variable of the window with ``estimate_camera_mounting``.
MOUNTING = gtsam.symbol("c", 0)
#: Its position's prior, metres: held where configured. A few millimetres of it move the
#: projections less than the pixels' noise over the window's baselines, so the estimate only
#: wanders (docs/vins.md, "The camera's mounting, estimated").
MOUNTING_POSITION_SIGMA_M = 1e-5


def _bias(bias_g: np.ndarray, bias_a: np.ndarray) -> gtsam.imuBias.ConstantBias:
    return gtsam.imuBias.ConstantBias(np.asarray(bias_a, float), np.asarray(bias_g, float))


class SlidingWindowSmoother:
    """Keyframes and landmarks in a fixed-lag smoother on iSAM2 (module docstring)."""

    def __init__(self, camera: PinholeCamera, T_B_C: np.ndarray, noise: ImuNoise,
                 options: VinsOptions):
        self.options = options
        self.camera = camera
        self._noise = noise
        self.params = self._imu_params()
        self._T_B_C = np.asarray(T_B_C, dtype=float)
        self._body_P_camera = gtsam.Pose3(self._T_B_C)
        self._mounting_prior = gtsam.noiseModel.Diagonal.Sigmas(np.r_[
            [math.radians(options.mounting_rotation_sigma_deg)] * 3,
            [MOUNTING_POSITION_SIGMA_M] * 3])
        self._K = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
        self._pixel_noises = {1.0: self._robust_pixel_noise(1.0)}
        self._keyframe_prior = None if options.keyframe_prior_position_sigma == 0.0 else \
            gtsam.noiseModel.Diagonal.Sigmas(np.r_[[options.keyframe_prior_rotation_sigma] * 3,
                                                   [options.keyframe_prior_position_sigma] * 3])
        self._zero_velocity = gtsam.noiseModel.Isotropic.Sigma(3, options.zero_velocity_sigma)
        self._barometer = (BarometerChain(options.barometer_sigma_m,
                                          options.barometer_drift_m_per_sqrt_s)
                           if options.barometer_sigma_m > 0.0 else None)
        focal = math.sqrt(camera.fx * camera.fy)
        self.gate = Gate(options.min_observations, math.radians(options.min_parallax_deg),
                         options.min_depth, options.max_depth, options.max_reprojection_px, focal)
        self.resets = 0
        self.last_failure = ""
        #: given to every smoother it starts (``fixed_lag.UpdateListener``): an evaluation listens
        self.update_listener: UpdateListener | None = None
        self._smoother: FixedLagSmoother | None = None
        self._latest: KeyframeState | None = None
        self._window: list[_Keyframe] = []
        self._poses: dict[int, np.ndarray] = {}
        self._retired = np.zeros(0, np.int64)
        self._pose_covariance: tuple[int, float, np.ndarray] | None = None
        self._covariances: tuple[int, np.ndarray, np.ndarray] | None = None
        self._anchor: GaugeAnchor | None = None
        self._hold: _GaugeHold | None = None
        self._kept_from: float | None = None
        self._known_pose_covariance = np.full((6, 6), np.nan)
        self._landmarks = Landmarks.empty()

    # ------------------------------------------------------------------ public

    @property
    def started(self) -> bool:
        return self._latest is not None

    @property
    def latest(self) -> KeyframeState:
        if self._latest is None:
            raise RuntimeError("the smoother has not been started")
        return self._latest

    @property
    def gauge_hold_slot(self) -> int | None:
        """The iSAM2 slot of the gauge hold's prior, None while none holds the window."""
        return None if self._hold is None else self._hold.slot

    @property
    def gauge_keyframe(self) -> int | None:
        """The keyframe whose prior holds the window's position and yaw (module docstring),
        None while none does."""
        return None if self._hold is None else self._hold.index

    @property
    def landmarks(self) -> Landmarks:
        return self._landmarks

    @property
    def barometer_steps(self) -> int:
        """Barometer samples taken as steps of pressure, not climbs, since this smoother was
        made (:mod:`autonomy.vins.barometer`); 0 without the barometer."""
        return 0 if self._barometer is None else self._barometer.steps

    @property
    def camera_mounting(self) -> np.ndarray:
        """``T_B_C``: the configured mounting, or with ``estimate_camera_mounting`` its latest
        estimate."""
        return self._T_B_C

    def _imu_params(self, gyro_extra=np.zeros((3, 3))) -> gtsam.PreintegrationCombinedParams:
        """The options' preintegration parameters, the gyro's covariance plus ``gyro_extra``."""
        o = self.options
        return imu_params(self._noise, o.imu_noise_scale, o.imu_bias_walk_scale,
                          o.gyro_noise_scale, gyro_extra)

    def preintegration(self, gyro=None, dt=None) -> gtsam.PreintegratedCombinedMeasurements:
        """An empty preintegration at the latest keyframe's biases. With ``gyro_axes_noise``,
        for the interval whose gyro samples ``gyro`` (N, 3, rad/s) are held over ``dt`` (N,
        seconds), its gyro weighed less by the axes' errors over the interval's turn, the
        samples less the bias integrated (:func:`gyro_axes_density`), about the body's three
        axes or, with ``gyro_axes_noise_axes = "vertical"``, about the vertical at the latest
        keyframe (:func:`about_vertical`)."""
        s = self.latest
        params = self.params
        o = self.options
        if o.gyro_axes_noise and gyro is not None:
            dt = np.asarray(dt, dtype=float)
            rotation = (np.asarray(gyro, dtype=float) - s.bias_g).T @ dt
            density = gyro_axes_density(rotation, float(dt.sum()), o.gyro_scale_sigma,
                                        o.gyro_cross_axis_sigma)
            params = self._imu_params(
                about_vertical(density, np.asarray(s.T_W_B, float)[2, :3])
                if o.gyro_axes_noise_axes == "vertical" else np.diag(density))
        return gtsam.PreintegratedCombinedMeasurements(params, _bias(s.bias_g, s.bias_a))

    def start(self, state: KeyframeState, sigmas: PriorSigmas, ids=(), normalised=None,
              anchor: GaugeAnchor | None = None, pressure_pa: float | None = None,
              noise_scale=None) -> None:
        """Begin a new smoother at ``state`` with priors ``sigmas``; ``ids``/``normalised`` are
        that keyframe's observations (kept for later triangulation), ``noise_scale`` their
        noise as a share of ``pixel_sigma`` (None: each 1); ``anchor``, what a
        rebuild carries over of the old smoother's uncertainty (:class:`GaugeAnchor`);
        ``pressure_pa``, the barometer's sample at it (:mod:`autonomy.vins.barometer`)."""
        self._smoother = self._new_smoother()
        self._pose_covariance = self._covariances = None
        self._known_pose_covariance = np.full((6, 6), np.nan)
        self._anchor = anchor
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        k = state.index
        pose = gtsam.Pose3(state.T_W_B)
        values.insert(X(k), pose)
        values.insert(V(k), np.asarray(state.velocity, float))
        values.insert(B(k), _bias(state.bias_g, state.bias_a))
        pose_sigmas = np.r_[sigmas.rotation, [sigmas.position] * 3]
        graph.add(gtsam.PriorFactorPose3(X(k), pose, gtsam.noiseModel.Diagonal.Sigmas(pose_sigmas)))
        graph.add(gtsam.PriorFactorVector(V(k), np.asarray(state.velocity, float),
                                          gtsam.noiseModel.Isotropic.Sigma(3, sigmas.velocity)))
        bias_sigmas = np.r_[[sigmas.accel_bias] * 3, [sigmas.gyro_bias] * 3]
        graph.add(gtsam.PriorFactorConstantBias(B(k), _bias(state.bias_g, state.bias_a),
                                                gtsam.noiseModel.Diagonal.Sigmas(bias_sigmas)))
        if self._barometer is not None:
            self._barometer.restart()
            self._barometer.add(k, state.t, float(state.T_W_B[2, 3]), pressure_pa, graph,
                                values)
        stamps = dict.fromkeys(self._keys(k), state.t)
        if self.options.estimate_camera_mounting:
            mounting = gtsam.Pose3(self._T_B_C)
            values.insert(MOUNTING, mounting)
            graph.add(gtsam.PriorFactorPose3(MOUNTING, mounting, self._mounting_prior))
            stamps[MOUNTING] = state.t
        self._smoother.update(graph, values, stamps,
                              eliminate_last=self._eliminated_last(k))
        self._latest = state
        self._hold = _GaugeHold(k)
        self._window = [self._keyframe(k, state.t, ids, normalised, noise_scale,
                                       pressure_pa=pressure_pa)]
        self._poses = {k: np.asarray(state.T_W_B, float)}
        self._landmarks = Landmarks.empty()

    def add_keyframe(self, t: float, pim: gtsam.PreintegratedCombinedMeasurements, ids,
                     normalised, still: bool = False, airborne: bool = False,
                     pressure_pa: float | None = None, noise_scale=None) -> bool:
        """Add a keyframe at ``t`` with the IMU preintegrated since the last one and the
        features it sees (``noise_scale``: their noise as a share of ``pixel_sigma``, None
        for each 1); ``still``: it stands still, and gets a zero-velocity prior
        (:mod:`autonomy.vins.stillness`); ``airborne``: it flies, and the interval gets the
        rotor drag's factor (with ``drag_coefficient``; :mod:`autonomy.vins.drag`);
        ``pressure_pa``: the barometer's sample at it (with ``barometer_sigma_m``;
        :mod:`autonomy.vins.barometer`). Returns
        True when the update was used, False when it failed and the smoother was rebuilt (a
        reset; ``last_failure`` says why). Raises :class:`BackendError` when even the rebuilt
        smoother refuses the keyframe."""
        good, good_keyframe = self.latest, self._window[-1]
        # the last covariance asked for (the odometry's, at most covariance_period_s old),
        # taken before the update, which may leave the smoother unusable; not computed here
        # for callers that never read covariances
        good_covariance = self._known_pose_covariance
        keyframe = self._keyframe(good.index + 1, t, ids, normalised, noise_scale,
                                  airborne and not still, pressure_pa)
        try:
            self._update_with_vision(keyframe, pim, still)
            self._check_sane(self.latest)
            return True
        except (RuntimeError, ValueError) as error:
            self.resets += 1
            self.last_failure = f"keyframe {keyframe.index} at t={keyframe.t:.3f}: {error}"
            self._rebuild(good, good_keyframe, GaugeAnchor.at(good.T_W_B, good_covariance),
                          keyframe, pim, still)
            return False

    def _rebuild(self, good: KeyframeState, good_keyframe: _Keyframe, anchor: GaugeAnchor,
                 keyframe: _Keyframe, pim: gtsam.PreintegratedCombinedMeasurements,
                 still: bool) -> None:
        """Start over from ``good`` with its uncertainty widened (its position and yaw carried
        by ``anchor``), then add ``keyframe`` with its IMU factor only (the observations of
        both are kept for later landmarks)."""
        try:
            self._start_over(good, good_keyframe, anchor)
            graph, values, stamps, interval = self._imu_step(keyframe, pim, still)
            slots = self._smoother.update(graph, values, stamps,
                                          eliminate_last=self._eliminated_last(keyframe.index))
            keyframe = replace(keyframe, interval_slots=tuple(slots[:interval]))
            self._read_estimate(keyframe, self._window + [keyframe])
        except (RuntimeError, ValueError) as error:
            raise BackendError(f"the rebuilt smoother refused keyframe {keyframe.index} at "
                               f"t={keyframe.t:.3f}: {error}") from error

    @property
    def kept_from(self) -> float | None:
        """The time the window is kept open from (:meth:`keep_window_from`), None when not."""
        return self._kept_from

    def keep_window_from(self, t: float | None) -> None:
        """Keep every keyframe and landmark stamped at or after ``t`` in the window, however
        old, from the next update on; None lets them go (:mod:`autonomy.vins.fixed_lag`).
        A smoother started again keeps the same."""
        self._kept_from = None if t is None else float(t)
        if self._smoother is not None:
            self._smoother.kept_from = self._kept_from

    @property
    def window_keyframes(self) -> list[tuple[int, float]]:
        """The window's keyframes, oldest first: index and time."""
        return [(keyframe.index, keyframe.t) for keyframe in self._window]

    def retime(self, times, pims) -> bool:
        """Move the window's keyframes to ``times`` (one per keyframe, oldest first, increasing)
        and replace the factors of the IMU between them by ``pims``, preintegrated over the new
        intervals (one per pair of consecutive keyframes), then solve. For a camera time offset
        that has moved since the keyframes were added: their images were exposed at other
        times than they were filed at. The oldest keyframe's own interval went into the
        marginal with the keyframe before it and stays as it was; the landmarks' factors do
        not depend on time. Returns True when the update was used, False when it failed and
        the smoother was started again from the newest keyframe, moved (a reset, as in
        :meth:`add_keyframe`)."""
        window = self._window
        if len(times) != len(window) or len(pims) != len(window) - 1:
            raise ValueError(f"retiming a window of {len(window)} keyframes needs as many times "
                             f"and one IMU interval fewer, got {len(times)} and {len(pims)}")
        if np.any(np.diff(times) <= 0.0):
            raise ValueError("retimed keyframes must stay in increasing time order")
        good = replace(self.latest, t=float(times[-1]))
        good_covariance = self._known_pose_covariance
        moved = [replace(keyframe, t=float(t)) for keyframe, t in zip(window, times)]
        graph, stamps, removed, counts = gtsam.NonlinearFactorGraph(), {}, [], []
        for before, keyframe, pim in zip(moved, moved[1:], pims):
            factors = self._interval_factors(before.index, keyframe.index, pim,
                                             keyframe.airborne)
            for factor in factors:
                graph.add(factor)
            counts.append(len(factors))
            removed.extend(keyframe.interval_slots)
        for keyframe in moved:
            stamps.update(dict.fromkeys(self._keys(keyframe.index), keyframe.t))
        try:
            # the retime moves the window, it does not slide it: keyframes moved earlier than
            # the lag (or a kept window's start) leave with the next keyframe, the gauge hold
            # moved off them first (_gauge_move), not in this update
            slots = self._smoother.update(graph, gtsam.Values(), stamps, remove=removed,
                                          slide=False)
            ends = np.cumsum(counts)
            moved[1:] = [replace(keyframe, interval_slots=tuple(slots[end - count:end]))
                         for keyframe, count, end in zip(moved[1:], counts, ends)]
            self._pose_covariance = self._covariances = None
            self._read_estimate(moved[-1], moved)
            self._check_sane(self.latest)
            return True
        except (RuntimeError, ValueError) as error:
            self.resets += 1
            self.last_failure = f"retiming keyframes {moved[0].index}-{moved[-1].index}: {error}"
            self._start_over(good, moved[-1], GaugeAnchor.at(good.T_W_B, good_covariance))
            return False

    def _start_over(self, state: KeyframeState, keyframe: _Keyframe,
                    anchor: GaugeAnchor) -> None:
        """A new smoother at ``state`` with its uncertainty widened (its position and yaw
        carried by ``anchor``), ``keyframe``'s observations kept for later landmarks."""
        sigmas = PriorSigmas.with_bias_priors(self.options, REBUILD_ROTATION_SIGMAS,
                                              REBUILD_POSITION_SIGMA, REBUILD_VELOCITY_SIGMA)
        self.start(state, sigmas, keyframe.ids, keyframe.normalised, anchor,
                   keyframe.pressure_pa, keyframe.noise_scale)

    def pose_covariance(self, max_age_s: float = 0.0) -> np.ndarray:
        """The latest keyframe pose's covariance (6x6, rotation then position, body frame):
        its marginal in the smoother, plus what a rebuild's :class:`GaugeAnchor` carries; NaN
        where GTSAM cannot compute it (:meth:`_joint_marginal`). Computed once per keyframe,
        or, with ``max_age_s``, kept for later keyframes until it is that old in keyframe time
        (never across a (re)start). The odometry asks every ``covariance_period_s``: the
        marginal took twice the smoother's update until the landmarks were eliminated first, and
        about 0.3 ms since its own keys are eliminated last too, about a thirtieth of a
        keyframe's back-end median (:mod:`autonomy.vins.fixed_lag`; docs/benchmarks.md)."""
        state, cached = self.latest, self._pose_covariance
        if cached is None or (cached[0] != state.index and
                              covariance_due(state.t - cached[1], max_age_s)):
            covariance = self._newest_covariances()[0]
            self._pose_covariance = cached = (state.index, state.t, covariance)
            if np.isfinite(covariance).all():
                self._known_pose_covariance = covariance
        return cached[2]

    def velocity_covariance(self) -> np.ndarray:
        """The latest keyframe velocity's covariance (3x3, world frame), as
        :meth:`pose_covariance` (computed with the pose's, at no extra cost)."""
        return self._newest_covariances()[1]

    def _newest_covariances(self) -> tuple[np.ndarray, np.ndarray]:
        """The latest keyframe's pose and velocity covariances (:meth:`pose_covariance`,
        :meth:`velocity_covariance`), from one joint marginal, kept for that keyframe: iSAM2's
        joint marginal of the pose, the velocity and the gauge hold's pose costs about what
        the pose's alone does (docs/benchmarks.md), so the velocity's comes nearly free."""
        state = self.latest
        if self._covariances is None or self._covariances[0] != state.index:
            joint = self._released_marginal([X(state.index), V(state.index)])
            pose, velocity = joint[:6, :6], joint[6:, 6:]
            if self._anchor is not None:
                pose = pose + self._anchor.pose_covariance(state.T_W_B)
                velocity = velocity + self._anchor.velocity_covariance(state.velocity)
            self._covariances = (state.index, pose, velocity)
        return self._covariances[1], self._covariances[2]

    def _released_marginal(self, keys: list[int]) -> np.ndarray:
        """The joint marginal covariance of the newest keyframe's ``keys`` with the gauge
        hold's prior taken out (:func:`released_covariance`; the hold is never on the newest
        keyframe); the start prior stays."""
        hold = self._hold
        if hold is None or not hold.moved:
            return self._joint_marginal(keys)
        hold_key = X(hold.index)
        return released_covariance(self._joint_marginal([*keys, hold_key]), hold.covariance)

    def _joint_marginal(self, keys: list[int]) -> np.ndarray:
        """The joint covariance of ``keys`` (blocks in their order). iSAM2 can meet an
        indeterminate linear system computing it on a window whose update went through (the
        same ill-conditioning that rebuilds the smoother, docs/vins.md): the covariance is
        then unknown, NaN, which the odometry sends as MAVLink's "unknown" and the evaluation
        does not score."""
        try:
            joint = self._smoother.jointMarginalCovariance(keys)
        except RuntimeError:
            size = sum(_dimension(key) for key in keys)
            return np.full((size, size), np.nan)
        return np.block([[joint.at(row, column) for column in keys] for row in keys])

    def depth_sigma(self, depths: np.ndarray) -> np.ndarray:
        """One-sigma depth uncertainty of the landmarks at ``depths`` (same order)."""
        return depth_sigma(depths, self._landmarks.parallax_rad, self.options.pixel_sigma,
                           self.gate.focal_px)

    # ------------------------------------------------------------------ internals

    def _new_smoother(self) -> FixedLagSmoother:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.options.relinearize_threshold)
        params.relinearizeSkip = 1
        params.findUnusedFactorSlots = True
        params.setFactorization(self.options.factorization.upper())
        smoother = FixedLagSmoother(self.options.smoother_lag_s, params, self.update_listener,
                                    eliminated_early=_is_landmark)
        smoother.kept_from = self._kept_from
        return smoother

    @staticmethod
    def _keyframe(index: int, t: float, ids, normalised, noise_scale=None,
                  airborne: bool = False, pressure_pa: float | None = None) -> _Keyframe:
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        normalised = (np.zeros((0, 2)) if normalised is None
                      else np.asarray(normalised, dtype=float).reshape(-1, 2))
        noise_scale = (np.ones(len(ids)) if noise_scale is None
                       else checked_noise_scale(noise_scale, len(ids)))
        order = np.argsort(ids)
        return _Keyframe(index, float(t), ids[order], normalised[order], noise_scale[order],
                         airborne=airborne, pressure_pa=pressure_pa)

    def _keys(self, k: int) -> tuple[int, ...]:
        """Keyframe ``k``'s keys: pose, velocity, biases and, where it has one, the
        barometer's offset."""
        keys = (X(k), V(k), B(k))
        return keys if self._barometer is None else keys + self._barometer.keys(k)

    def _imu_step(self, keyframe: _Keyframe, pim, still: bool):
        """The new keyframe's variables at the IMU's prediction, its interval's factors first
        in the graph (their number is returned last), then its priors."""
        good = self.latest
        k = keyframe.index
        predicted = pim.predict(gtsam.NavState(gtsam.Pose3(good.T_W_B), good.velocity),
                                _bias(good.bias_g, good.bias_a))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        values.insert(X(k), predicted.pose())
        values.insert(V(k), predicted.velocity())
        values.insert(B(k), _bias(good.bias_g, good.bias_a))
        interval = self._interval_factors(good.index, k, pim, keyframe.airborne and not still)
        for factor in interval:
            graph.add(factor)
        if self._keyframe_prior is not None:
            graph.add(gtsam.PriorFactorPose3(X(k), predicted.pose(), self._keyframe_prior))
        if still:
            graph.add(gtsam.PriorFactorVector(V(k), np.zeros(3), self._zero_velocity))
        if self._barometer is not None:
            self._barometer.add(k, keyframe.t, float(predicted.pose().z()),
                                keyframe.pressure_pa, graph, values)
        self._poses[k] = predicted.pose().matrix()
        stamps = dict.fromkeys(self._keys(k), keyframe.t)
        if self.options.estimate_camera_mounting:
            stamps[MOUNTING] = keyframe.t  # never older than the lag: never marginalised
        return graph, values, stamps, len(interval)

    def _interval_factors(self, i: int, k: int, pim, airborne: bool) -> list:
        """The factors the IMU's interval from keyframe ``i`` to ``k`` makes: the preintegrated
        one, and in free flight with ``drag_coefficient`` the rotor drag's."""
        factors = [gtsam.CombinedImuFactor(X(i), V(i), X(k), V(k), B(i), B(k), pim)]
        if airborne and self.options.drag_coefficient > 0.0 and pim.deltaTij() <= MAX_INTERVAL_S:
            factors.append(drag_factor((X(i), V(i), V(k), B(i)), pim,
                                       self.options.drag_coefficient, self.options.drag_noise,
                                       self.options.huber_k))
        return factors

    def _eliminated_last(self, k: int, hold: _GaugeHold | None = None) -> tuple[int, ...]:
        """The keys the smoother eliminates last (:mod:`autonomy.vins.fixed_lag`): keyframe
        ``k``'s, the mounting, which every landmark's factors share, and the pose of a moved
        gauge ``hold``: with it the Bayes tree's root holds every key of the odometry's
        covariance (:meth:`_released_marginal`), which is then read from the root alone. The
        start hold is never named: the covariance does not take its prior out, and with
        ``hold_gauge`` false it outlives its keyframe, which the smoother would refuse to
        eliminate last."""
        last = self._keys(k)
        if self.options.estimate_camera_mounting:
            last = (*last, MOUNTING)
        if hold is not None and hold.moved:
            last = (*last, X(hold.index))
        return last

    def _update_with_vision(self, keyframe: _Keyframe, pim, still: bool) -> None:
        graph, values, stamps, interval = self._imu_step(keyframe, pim, still)
        window = self._window + [keyframe]
        seen = _in_sorted(keyframe.ids, self._landmarks.ids)
        tracks, xy, scales = self._consistent_observations(keyframe, seen)
        observed_pixels = self._pixels(xy)
        for track, pixel, scale in zip(tracks, observed_pixels, scales):
            graph.add(self._projection(keyframe.index, int(track), pixel, scale))
            stamps[L(int(track))] = keyframe.t
        fresh = ~seen & ~_in_sorted(keyframe.ids, self._retired)
        self._add_new_landmarks(window, keyframe.ids[fresh], observed_pixels, graph, values,
                                stamps)
        removed, hold = self._gauge_move(keyframe.t, graph)
        slots = self._smoother.update(graph, values, stamps,
                                      eliminate_last=self._eliminated_last(keyframe.index,
                                                                           hold),
                                      remove=removed)
        if hold is not self._hold:
            self._hold = None if hold is None else replace(hold, slot=slots[-1])
        window[-1] = keyframe = replace(keyframe, interval_slots=tuple(slots[:interval]))
        for _ in range(self.options.extra_iterations):
            self._smoother.update()
        self._read_estimate(keyframe, window)

    def _gauge_move(self, newest_t: float, graph: gtsam.NonlinearFactorGraph
                    ) -> tuple[list[int], _GaugeHold | None]:
        """The hold's move in the update that adds a keyframe at ``newest_t`` (module
        docstring): the iSAM2 slots of the priors this update removes, and the hold after it,
        a new one's prior added to ``graph`` last. The hold stays until this update
        marginalises its keyframe, then moves to the oldest keyframe that this update keeps:
        the most settled estimate of the window, which the marginalisation is about to freeze
        in any case. Where the update keeps none (a keyframe gap longer than the lag), it is
        let go, and taken up again at the next update."""
        hold = self._hold
        if not self.options.hold_gauge:
            return [], hold
        kept = [kf for kf in self._window if kf.t >= self._smoother.cutoff(newest_t)]
        if hold is not None and any(kf.index == hold.index for kf in kept):
            return [], hold
        removed = [] if hold is None or hold.slot is None else [hold.slot]
        if not kept:
            return removed, None
        prior, covariance = self._gauge_prior(kept[0].index, self._barometer_holds(kept))
        graph.add(prior)
        return removed, _GaugeHold(kept[0].index, covariance)

    def _barometer_holds(self, kept: list[_Keyframe]) -> bool:
        """Whether the barometer holds the height of the window's ``kept`` keyframes: its
        offset runs through the oldest, and a sample came with one of them."""
        return (self._barometer is not None and bool(self._barometer.keys(kept[0].index))
                and any(keyframe.pressure_pa is not None for keyframe in kept))

    def _gauge_prior(self, index: int, barometer_holds: bool
                     ) -> tuple[gtsam.PriorFactorPose3, np.ndarray]:
        """The prior holding keyframe ``index`` at its estimate in world yaw and position
        (``HOLD_YAW_SIGMA``, ``HOLD_POSITION_SIGMA``), and its covariance. Pose3's tangent
        is the body's: world yaw is the rotation about ``u = R^T e_z``, information
        ``u u^T / sigma^2``; roll and pitch, which gravity observes, get a negligible one
        (1 rad). Where ``barometer_holds`` the height, the height (along ``u`` too) gets
        ``HOLD_BAROMETER_HEIGHT_SIGMA``."""
        T_W_B = self._poses[index]
        up = np.outer(T_W_B[2, :3], T_W_B[2, :3])
        information = np.zeros((6, 6))
        information[:3, :3] = up / HOLD_YAW_SIGMA ** 2 + np.eye(3) - up
        information[3:, 3:] = np.eye(3) / HOLD_POSITION_SIGMA ** 2
        if barometer_holds:  # apart, so that without it the matrix keeps its bits (and a
            # flight its digits)
            information[3:, 3:] += up * (HOLD_BAROMETER_HEIGHT_SIGMA ** -2
                                         - HOLD_POSITION_SIGMA ** -2)
        prior = gtsam.PriorFactorPose3(X(index), gtsam.Pose3(T_W_B),
                                       gtsam.noiseModel.Gaussian.Information(information))
        return prior, np.linalg.inv(information)

    def _consistent_observations(self, keyframe: _Keyframe, seen: np.ndarray):
        """The observations of known landmarks that reproject near their landmark at the
        IMU-predicted pose, within :func:`observation_limit_px` of ``max_observation_px``:
        their ``tracks`` (N,), ``xy`` (N, 2) and noise scales (N,). A landmark seen further
        away (a track that slid off its point, or onto another surface) takes no observation
        from this keyframe, and is retired: once marginalised, no track of its id becomes a
        landmark again."""
        tracks, xy = keyframe.ids[seen], keyframe.normalised[seen]
        scales = keyframe.noise_scale[seen]
        rows = np.searchsorted(self._landmarks.ids, tracks)
        T_C_W = invert_pose(self._poses[keyframe.index] @ self._T_B_C)
        p_C = self._landmarks.points_W[rows] @ T_C_W[:3, :3].T + T_C_W[:3, 3]
        in_front = p_C[:, 2] > self.options.min_depth
        with np.errstate(invalid="ignore", divide="ignore"):
            error_px = self.gate.focal_px * np.linalg.norm(p_C[:, :2] / p_C[:, 2:] - xy, axis=1)
        limit = observation_limit_px(error_px[in_front], self.options.max_observation_px)
        good = in_front & (error_px <= limit)
        self._retire(tracks[~good])
        return tracks[good], xy[good], scales[good]

    def _retire(self, tracks: np.ndarray) -> None:
        """No track of these ids becomes a landmark again (``_retired`` stays sorted)."""
        if len(tracks):
            self._retired = np.union1d(self._retired, tracks)

    def _projection(self, index: int, track: int, pixel: np.ndarray, scale: float):
        """The factor of keyframe ``index`` seeing landmark ``track`` at ideal-pinhole
        ``pixel`` with a noise of ``scale`` times ``pixel_sigma``: through the mounting's
        estimate with ``estimate_camera_mounting``."""
        noise = self._pixel_noise(scale)
        if self.options.estimate_camera_mounting:
            return gtsam_unstable.ProjectionFactorPPPCal3_S2(pixel, noise, X(index),
                                                             MOUNTING, L(track), self._K)
        return gtsam.GenericProjectionFactorCal3_S2(pixel, noise, X(index),
                                                    L(track), self._K, False, False,
                                                    self._body_P_camera)

    #: Noise scales are rounded to this step, so that observations share their noise models.
    NOISE_SCALE_STEP = 0.01

    def _pixel_noise(self, scale: float):
        """The observations' noise model at ``scale`` times ``pixel_sigma`` (rounded to
        :data:`NOISE_SCALE_STEP`, at least one step), made once."""
        step = self.NOISE_SCALE_STEP
        key = max(round(float(scale) / step) * step, step)
        if key not in self._pixel_noises:
            self._pixel_noises[key] = self._robust_pixel_noise(key)
        return self._pixel_noises[key]

    def _robust_pixel_noise(self, scale: float):
        """Huber's loss (``huber_k`` in whitened units) on an isotropic pixel noise of
        ``scale`` times ``pixel_sigma``."""
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(self.options.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, scale * self.options.pixel_sigma))

    @staticmethod
    def _observed(window: list[_Keyframe], tracks: np.ndarray):
        """Which keyframes of the window observe each of ``tracks`` (``mask``, (M, K) bool), and
        for each observation the row of its track, the column of its keyframe and its place
        among the window's observations in keyframe order (``picked``)."""
        all_ids = np.concatenate([kf.ids for kf in window])
        column = np.repeat(np.arange(len(window)), [len(kf.ids) for kf in window])
        order = np.argsort(all_ids, kind="stable")
        sorted_ids = all_ids[order]
        first = np.searchsorted(sorted_ids, tracks, side="left")
        counts = np.searchsorted(sorted_ids, tracks, side="right") - first
        # each track's run first .. first + count - 1 in sorted_ids, all runs back to back
        row = np.repeat(np.arange(len(tracks)), counts)
        run_start = np.repeat(first - (np.cumsum(counts) - counts), counts)
        picked = order[run_start + np.arange(len(row))]
        mask = np.zeros((len(tracks), len(window)), bool)
        mask[row, column[picked]] = True
        return mask, row, column[picked], picked

    @classmethod
    def _observations(cls, window: list[_Keyframe], tracks: np.ndarray):
        """The window's observations of ``tracks``: ``mask`` (M, K), ``normalised``
        (M, K, 2) and their noise scales (M, K)."""
        mask, row, column, picked = cls._observed(window, tracks)
        normalised = np.zeros((len(tracks), len(window), 2))
        normalised[row, column] = np.concatenate([kf.normalised for kf in window])[picked]
        scales = np.ones((len(tracks), len(window)))
        scales[row, column] = np.concatenate([kf.noise_scale for kf in window])[picked]
        return mask, normalised, scales

    def _cameras(self, window: list[_Keyframe], count: int):
        """The window's cameras ``R_W_C`` (count, K, 3, 3) and centres (count, K, 3): the same
        for each of ``count`` tracks (broadcast views)."""
        T_W_C = np.stack([self._poses[kf.index] @ self._T_B_C for kf in window])
        K = len(window)
        return (np.broadcast_to(T_W_C[:, :3, :3], (count, K, 3, 3)),
                np.broadcast_to(T_W_C[:, :3, 3], (count, K, 3)))

    def _add_new_landmarks(self, window, candidates, observed_pixels, graph, values,
                           stamps) -> None:
        """Gate the candidates seen in enough keyframes and spend what is left of the landmark
        budget on the accepted ones, emptiest image cells first (:func:`spread_choice`).

        The budget counts every landmark in the window, in view or not: each costs the update
        until it is marginalised with the last keyframe that saw it. (Marginalising landmarks
        sooner, while keyframes that saw them stay, meets the weak spot of GTSAM's fixed-lag
        marginalisation: measured, it made updates fail and the smoother reset.)
        ``observed_pixels`` are the landmarks seen in the newest keyframe: the cells they
        occupy; how many they are sets the room (:meth:`_landmark_room`).
        """
        room = self._landmark_room(len(observed_pixels))
        if room <= 0 or len(candidates) == 0:
            return
        mask, normalised, scales = self._observations(window, candidates)
        ready = mask.sum(axis=1) >= self.gate.min_observations
        if not ready.any():
            return
        candidates, mask, normalised = candidates[ready], mask[ready], normalised[ready]
        scales = scales[ready]
        R_W_C, centres = self._cameras(window, len(candidates))
        result = gate_candidates(R_W_C, centres, normalised, mask, self.gate)
        accepted = np.flatnonzero(result.accepted)
        newest = window[-1]
        chosen = accepted[spread_choice(
            self._pixels(normalised[accepted, -1]), result.parallax_rad[accepted],
            observed_pixels, (self.camera.width, self.camera.height), LANDMARK_GRID,
            room)]
        pixels = self._pixels(normalised[chosen])
        for m, track_pixels in zip(chosen, pixels):
            track = int(candidates[m])
            values.insert(L(track), result.points[m])
            stamps[L(track)] = newest.t
            for j in np.flatnonzero(mask[m]):
                graph.add(self._projection(window[j].index, track, track_pixels[j],
                                           scales[m, j]))

    def _landmark_room(self, observed: int) -> int:
        """New landmarks this keyframe may add: what is left of the budget ``n``; with
        ``landmark_top_up``, while fewer than ``n / 2`` are in view, enough to bring the view
        back to ``n / 2`` with at most ``1.5 n`` held.

        The landmarks out of view still count until their keyframes leave the window, so after
        the front-end loses most of its tracks (a blurred frame, a fast turn) a full budget
        leaves the view with a handful for as long as the window lasts: too few for the depth
        stage's rescaling, which needs anchors in the frame. The top-up costs the update at
        most half the budget again, and only then (docs/vins.md, the landmark budget).
        """
        budget, held = self.options.max_landmarks, len(self._landmarks.ids)
        if not self.options.landmark_top_up:
            return budget - held
        top_up = min(budget // 2 - observed, budget + budget // 2 - held)
        return max(budget - held, top_up)

    def _pixels(self, normalised: np.ndarray) -> np.ndarray:
        """Ideal-pinhole pixels (..., 2) of undistorted normalised points (..., 2)."""
        c = self.camera
        return normalised * (c.fx, c.fy) + (c.cx, c.cy)

    def _read_estimate(self, keyframe: _Keyframe, window: list[_Keyframe]) -> None:
        estimate = self._smoother.calculateEstimate()
        k = keyframe.index
        self._latest = KeyframeState(
            k, keyframe.t, estimate.atPose3(X(k)).matrix(), np.asarray(estimate.atVector(V(k))),
            np.asarray(estimate.atConstantBias(B(k)).gyroscope()),
            np.asarray(estimate.atConstantBias(B(k)).accelerometer()))
        if self.options.estimate_camera_mounting:
            self._T_B_C = estimate.atPose3(MOUNTING).matrix()
        if self._barometer is not None:
            self._barometer.read(k, estimate)
        keys = np.array(estimate.keys(), dtype=np.uint64)
        kept = set(_symbol_indices(keys, "x").tolist())
        self._window = [kf for kf in window if kf.index in kept]
        self._poses = {kf.index: estimate.atPose3(X(kf.index)).matrix() for kf in self._window}
        alive = _symbol_indices(keys, "l")
        self._retire(self._landmarks.ids[~_in_sorted(self._landmarks.ids, alive)])
        points = np.array([estimate.atPoint3(key) for key in _symbol_keys(keys, "l").tolist()]
                          ).reshape(-1, 3)
        mask, *_ = self._observed(self._window, alive)
        _, centres = self._cameras(self._window, len(alive))
        rays = points[:, None, :] - centres
        rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
        self._landmarks = Landmarks(alive, points, widest_ray_angle(rays, mask), mask.sum(axis=1))

    def _check_sane(self, state: KeyframeState) -> None:
        o = self.options
        problems = []
        if not (np.isfinite(state.T_W_B).all() and np.isfinite(state.velocity).all()):
            problems.append("non-finite state")
        if np.linalg.norm(state.velocity) > o.max_speed:
            problems.append(f"speed {np.linalg.norm(state.velocity):.1f} m/s")
        if np.linalg.norm(state.bias_g) > o.max_gyro_bias:
            problems.append(f"gyro bias {np.linalg.norm(state.bias_g):.3f} rad/s")
        if np.linalg.norm(state.bias_a) > o.max_accel_bias:
            problems.append(f"accel bias {np.linalg.norm(state.bias_a):.2f} m/s^2")
        if problems:
            raise ValueError("diverged: " + ", ".join(problems))
