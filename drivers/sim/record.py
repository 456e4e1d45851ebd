"""Fly a smooth path through a world and record it as a EuRoC/ASL dataset.

The flight is the one a careful pilot would give a visual-inertial estimator: a few seconds standing
still on the ground (for a static initialisation), a vertical take-off to cruise height, then the
route's collision-free path, facing along it, back and forth until the duration is spent, at a
constant speed or, with a speed wave (the application's ``[planner] speed_swing``), swinging about
it as the application's flights do, and with a height wave (``[planner] height_swing``) swung up and
down about the cruise height as they are (``PathFollower``). The vehicle is the simulated quadrotor
with its PX4-like controller, so the motion is smooth and dynamically feasible; the IMU is sampled
from the same dynamics, so a noiseless recording integrates back onto its own ground truth.
``along`` replaces the route with the true path of another flight (a navigation flight's recording:
``companion sim record --along``), so that the estimator can be scored open loop on the very places
and the speed a flight met; ``timed`` flies that flight's own motion again in time instead
(``TimedFollower``: its changes of speed, stops and turns, as the planner flew them), so that a
steady cruise and the planner's way of flying can be told apart on one path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from autonomy.planning.height_wave import HeightWave, Offset
from autonomy.planning.speed_wave import SpeedWave
from drivers.camera.options import CameraOptions
from drivers.dataset.euroc import EurocWriter
from drivers.sim.camera import CameraHead
from drivers.sim.imu import ImuModel, ImuOptions, flight_generators
from drivers.sim.options import SimOptions
from drivers.sim.render import Renderer
from drivers.sim.sensor import SensorOptions
from drivers.sim.quadrotor import ControlTarget, Quadrotor, VehicleOptions
from drivers.sim.world import ROBOT_RADIUS, Route, World, build_world

SPEED = 1.0
"""Default cruise speed along the path, m/s: gentle enough that consecutive 20 Hz frames overlap.
The application's flights cruise faster (its planner's fastest tier is 2 m/s), and the VINS's
scale walks faster with them (docs/vins.md, "The scale at the planner's speed"): ``speed``
records at theirs."""

STATIC_SECONDS = 2.0
"""Time standing still on the ground before take-off, for static initialisation."""

CLIMB_SECONDS_PER_METRE = 1.0
SETTLE_SECONDS = 2.0
"""The climb over the start is given ``cruise_height * CLIMB_SECONDS_PER_METRE +
SETTLE_SECONDS`` (the controller climbs at about 1 m/s from rest and settles) before the path
begins."""


class RecordError(RuntimeError):
    """A recording that could not be made or was cut short, with the reason."""


@dataclass(frozen=True)
class RecordSummary:
    """What a recording holds."""

    world: str
    route: str
    duration: float
    imu_samples: int
    frames: int
    path_length: float


class Sink(Protocol):
    """Where the flight's samples go: a :class:`EurocWriter`, or nowhere when benchmarking.
    Each frame comes with its stamp and the middle of its exposure (the IMU tick it was
    rendered at), and the camera's true mounting once: the truth the stamps and the
    configured mounting hide (``drivers.dataset.euroc.CameraTruth``)."""

    def add_imu(self, t_ns: int, gyro: np.ndarray, accel: np.ndarray) -> None: ...
    def add_groundtruth(self, t_ns: int, position, q_W_B, velocity, gyro_bias, accel_bias) -> None: ...
    def add_frame(self, t_ns: int, rgb: np.ndarray, depth_m: np.ndarray,
                  exposed_ns: int) -> None: ...
    def add_camera_truth(self, T_B_C: np.ndarray) -> None: ...


#: Least clearance, metres, that a rounded corner of a recorded path keeps: the vehicle's
#: 0.3 m collision radius and 0.1 m for the follower's tracking error at the corner.
PATH_CLEARANCE = 0.4


def smooth_path(polyline: np.ndarray, spacing: float = 0.1, passes: int = 4,
                clearance: Callable[[np.ndarray], np.ndarray] | None = None,
                least: float = PATH_CLEARANCE) -> np.ndarray:
    """A polyline resampled every ``spacing`` metres with its corners rounded.

    Chaikin's corner cutting (each pass replaces every segment ``PQ`` by the points at 1/4 and
    3/4 of it) converges to a quadratic B-spline. Each corner's cut stays inside the triangle
    of the corner and its neighbours, but in free space that is not convex (a door, a tunnel's
    bend) that triangle can hold a wall: the 4-pass path of the sewer's seed-1 route cut the
    hallway's entrance with 0.22 m of clearance, and the recording flew into it. With
    ``clearance`` (``(N, 2)`` points to ``(N,)`` metres), a pass keeps a corner whose cut
    would pass closer than ``least`` to an obstacle; the next passes round it more tightly.
    """
    points = np.asarray(polyline, dtype=float)
    for _ in range(passes):
        if len(points) < 3:
            break
        inner = np.empty((2 * (len(points) - 1), points.shape[1]))
        inner[0::2] = 0.75 * points[:-1] + 0.25 * points[1:]
        inner[1::2] = 0.25 * points[:-1] + 0.75 * points[1:]
        if clearance is not None:
            # corner i is cut by the chord inner[2i - 1] -> inner[2i]; a kept one goes between
            corners = np.arange(1, len(points) - 1)
            kept = corners[_chords_too_close(inner[2 * corners - 1], inner[2 * corners],
                                             clearance, least)]
            inner = np.insert(inner, 2 * kept, points[kept], axis=0)
        points = np.vstack([points[:1], inner, points[-1:]])
    return resample(points, spacing)


def _chords_too_close(starts: np.ndarray, ends: np.ndarray,
                      clearance: Callable[[np.ndarray], np.ndarray], least: float,
                      step: float = 0.05) -> np.ndarray:
    """Whether each chord ``starts[i] -> ends[i]``, sampled every ``step`` metres or closer,
    passes within ``least`` of an obstacle."""
    longest = float(np.max(np.linalg.norm(ends - starts, axis=1), initial=0.0))
    along = np.linspace(0.0, 1.0, max(2, int(math.ceil(longest / step)) + 1))
    samples = starts[:, None, :] + along[None, :, None] * (ends - starts)[:, None, :]
    distances = clearance(samples.reshape(-1, starts.shape[1])).reshape(len(starts), -1)
    return distances.min(axis=1, initial=np.inf) < least


def resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points along the polyline every ``spacing`` metres of arc length, ends included."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    samples = np.linspace(0.0, arc[-1], max(2, int(math.ceil(arc[-1] / spacing)) + 1))
    return np.stack([np.interp(samples, arc, points[:, k]) for k in range(points.shape[1])], axis=1)


class PathFollower:
    """Targets that move along a path, back and forth, facing the way ahead.

    At time ``t`` the target is the point at arc length ``s(t) = speed * t`` folded onto
    ``[0, L]`` (a triangle wave, so the vehicle turns round at each end), with the path's
    tangent times the speed as velocity feed-forward and the tangent's heading as yaw. With a
    speed ``wave`` the speed swings about ``speed`` by half the wave's swing either way,
    ``speed (m(t) + share / 2)`` (speed_wave.py), so that the path flown in a given time, and
    a recording's length, are those of the constant speed. With a ``height_wave`` the target
    swings about the cruise height by ``h(t) = A sin(w t)`` (height_wave.py, its motion share
    1 throughout: the recorder's cruise never brakes), ``h'`` and ``h''`` its vertical
    velocity and acceleration feed-forward.
    """

    takes_off = False
    standing_s = STATIC_SECONDS

    def __init__(self, path_xy: np.ndarray, height: float, speed: float,
                 wave: SpeedWave | None = None, height_wave: HeightWave | None = None):
        self.points = np.asarray(path_xy, dtype=float)
        steps = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(steps)])
        self.length = float(self.arc[-1])
        self.height = height
        self.speed = speed
        self.wave = wave
        self.height_wave = height_wave
        if self.length <= 0.0:
            raise RecordError("the route's path has no length")
        if wave is not None and wave.swing >= 2.0 * speed:
            raise RecordError(f"a speed swing of {wave.swing:g} m/s would stop a vehicle "
                              f"cruising at {speed:g} m/s: it must be less than {2 * speed:g}")

    @property
    def start_yaw(self) -> float:
        """The heading the vehicle stands at before take-off: along the path's first half metre."""
        return _heading(self.points)

    def _speed_and_travel(self, t: float) -> tuple[float, float]:
        """The speed at ``t`` and the arc length travelled by then."""
        if self.wave is None:
            return self.speed, self.speed * t
        share = self.wave.swing / self.speed
        return (self.speed * (self.wave.factor(t, share) + share / 2.0),
                self.speed * (self.wave.progress(0.0, t, share) + share / 2.0 * t))

    def target(self, t: float) -> ControlTarget:
        speed, travelled = self._speed_and_travel(max(t, 0.0))
        lap, s = divmod(travelled, self.length)
        backwards = int(lap) % 2 == 1
        if backwards:
            s = self.length - s
        x, y = (np.interp(s, self.arc, self.points[:, k]) for k in range(2))
        i = min(int(np.searchsorted(self.arc, s, side="right")), len(self.points) - 1)
        tangent = self.points[i] - self.points[i - 1]
        tangent /= np.linalg.norm(tangent)
        if backwards:
            tangent = -tangent
        swing = (self.height_wave.offset(max(t, 0.0), 1.0) if self.height_wave is not None
                 else Offset(0.0, 0.0, 0.0))
        return ControlTarget(
            position=np.array([x, y, self.height + swing.height]),
            velocity=np.array([tangent[0] * speed, tangent[1] * speed, swing.velocity]),
            acceleration=np.array([0.0, 0.0, swing.acceleration]),
            yaw=math.atan2(tangent[1], tangent[0]),
        )


@dataclass(frozen=True)
class FlownMotion:
    """A recorded simulated flight: its ``world`` of ``seed`` as its ``profile`` built it (a
    realistic world has thin poles an ideal one lacks), and where it truly had the vehicle:
    ``times`` (N,) seconds, increasing, ``positions`` (N, 3) metres and ``yaws`` (N,) radians
    from east, world ENU."""

    world: str
    seed: int
    profile: str
    times: np.ndarray
    positions: np.ndarray
    yaws: np.ndarray


#: Seconds over which a replayed flight's acceleration is averaged before it is fed forward
#: (``TimedFollower``).
ACCELERATION_WINDOW_S = 0.2
#: Height above where it stood, metres, at which a flight counts as lifted off: the timed
#: replay begins on the floor at the sample before.
LIFT_OFF_M = 0.02


class TimedFollower:
    """Targets that fly a recorded flight's own motion again, in time, take-off included.

    Time 0 is the flight's last sample on the floor before it lifted off (rose ``LIFT_OFF_M``
    above where it stood), ``standing_s`` after its first sample (at least
    ``STATIC_SECONDS``); the target at ``t`` is the flight's true position and yaw ``t``
    seconds later, linearly interpolated, with their central differences (``np.gradient``:
    velocity and yaw rate) as feed-forward, and the velocity's difference averaged over
    ``ACCELERATION_WINDOW_S`` as acceleration, until its last airborne point (over
    ``AIRBORNE_M``, before it touched down); after that, a hover there. The average is
    needed: the truth is the pose at each frame's exposure under the frame's stamp, which a
    realistic camera jitters (1 ms at 2 m/s is 2 mm), and the raw second difference, fed to
    the controller as attitude, rocked the vehicle in pitch at the frame rate (measured once,
    docs/simulator.md: 15 deg/s rms on sewer 0 seed 3's cruise, where the flight's own is
    5.7; averaged, 5.8; none fed forward, 1.7 and a lag of up to 0.8 m).
    """

    takes_off = True

    def __init__(self, flown: FlownMotion):
        times, positions = np.asarray(flown.times, float), np.asarray(flown.positions, float)
        if not len(times) == len(positions) == len(flown.yaws):
            raise RecordError("a flown motion needs one time, position and yaw per sample")
        lifted = np.flatnonzero(positions[:, 2] > positions[0, 2] + LIFT_OFF_M)
        airborne = np.flatnonzero(positions[:, 2] > AIRBORNE_M)
        if len(airborne) == 0:
            raise RecordError("the flight never flew: no motion to fly again")
        # a recording that began in the air never lifts off in it: flown from its first sample
        span = slice(max(lifted[0] - 1, 0) if len(lifted) else 0, airborne[-1] + 1)
        self.standing_s = max(float(times[span.start] - times[0]), STATIC_SECONDS)
        self.times = times[span] - times[span.start]
        if np.any(np.diff(self.times) <= 0.0):
            raise RecordError("the flown motion's times must increase")
        self.positions = positions[span]
        self.yaws = np.unwrap(np.asarray(flown.yaws, float)[span])
        self.velocities = np.gradient(self.positions, self.times, axis=0)
        self._grid, self._accelerations = _averaged_acceleration(self.times, self.velocities)
        self.yaw_rates = np.gradient(self.yaws, self.times)
        self.length = float(np.sum(np.linalg.norm(np.diff(self.positions[:, :2], axis=0),
                                                  axis=1)))

    @property
    def span(self) -> float:
        """Seconds of the flight's motion flown again."""
        return float(self.times[-1])

    @property
    def start_yaw(self) -> float:
        """The heading the flight stood at before it lifted off."""
        return float(self.yaws[0])

    def target(self, t: float) -> ControlTarget:
        if t >= self.span:
            return ControlTarget(position=self.positions[-1], velocity=np.zeros(3),
                                 acceleration=np.zeros(3), yaw=float(self.yaws[-1]),
                                 yaw_rate=0.0)
        t = max(t, 0.0)

        def at(values: np.ndarray, grid: np.ndarray = self.times) -> np.ndarray:
            return np.array([np.interp(t, grid, column) for column in values.T])

        return ControlTarget(position=at(self.positions), velocity=at(self.velocities),
                             acceleration=at(self._accelerations, self._grid),
                             yaw=float(np.interp(t, self.times, self.yaws)),
                             yaw_rate=float(np.interp(t, self.times, self.yaw_rates)))


def _averaged_acceleration(times: np.ndarray, velocities: np.ndarray,
                           step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """The derivative of ``velocities`` (N, 3) at ``times``, on a grid of ``step`` seconds,
    averaged over a centred window of ``ACCELERATION_WINDOW_S``: the grid and (M, 3)."""
    grid = np.arange(times[0], times[-1] + step / 2, step)
    resampled = np.column_stack([np.interp(grid, times, column) for column in velocities.T])
    raw = np.gradient(resampled, step, axis=0) if len(grid) > 1 else np.zeros_like(resampled)
    width = max(1, int(round(ACCELERATION_WINDOW_S / step)))
    kernel = np.ones(width) / width
    return grid, np.column_stack([np.convolve(column, kernel, mode="same") for column in raw.T])


class Follower(Protocol):
    """What the recorded vehicle flies after standing still for ``standing_s``: a
    :class:`PathFollower` after the recorder's climb, or a :class:`TimedFollower`, which
    ``takes_off`` itself."""

    length: float
    takes_off: bool
    standing_s: float

    @property
    def start_yaw(self) -> float: ...
    def target(self, t: float) -> ControlTarget: ...


#: Least true height, metres, of the points of a flown path that the recorder follows: the rest
#: are the flight on the ground, taking off and landing.
AIRBORNE_M = 0.3
#: Least step, metres, between kept points of a flown path: a hover or a turn in place adds none.
ALONG_STEP_M = 0.02


def route_along(world: World, positions: np.ndarray) -> tuple[Route, np.ndarray]:
    """The route and smoothed path (:func:`smooth_path`, with the route's clearance) that
    follow a flight's true ``positions`` ((N, 3), world ENU, in time order): from the
    flight's start on the floor, at the median height it flew, along its airborne points.
    RecordError when it never flew (fewer than two airborne points a step apart)."""
    positions = np.asarray(positions, dtype=float)
    airborne = positions[positions[:, 2] > AIRBORNE_M]
    if len(airborne) < 2:
        raise RecordError("the flight never flew: no path to follow")
    kept = [airborne[0, :2]]
    for point in airborne[1:, :2]:
        if np.linalg.norm(point - kept[-1]) > ALONG_STEP_M:
            kept.append(point)
    points = np.array(kept)
    if len(points) < 2:
        raise RecordError("the flight never moved horizontally: no path to follow")
    height = float(np.median(airborne[:, 2]))
    route = Route("along a flight", np.array([*positions[0, :2], 0.0]),
                  np.array([*points[-1], height]), height)
    return route, smooth_path(resample(points, 0.1), clearance=_clearance_at(world, height))


def _clearance_at(world: World, height: float) -> Callable[[np.ndarray], np.ndarray]:
    """The clearance of horizontal points (M, 2) at ``height`` in ``world``."""
    return lambda xy: world.obstacle_clearance(np.column_stack([xy, np.full(len(xy), height)]))


def route_path(world: World, route: Route) -> np.ndarray:
    """The smoothed collision-free path of ``route`` in the horizontal plane, (M, 2)."""
    polyline = world.find_path(route.start[:2], route.goal[:2], ROBOT_RADIUS)
    if polyline is None:
        raise RecordError(f"{world.name}: no path with {ROBOT_RADIUS} m clearance "
                          f"for route {route.name}")
    return smooth_path(polyline, clearance=_clearance_at(world, world.cruise_height))


def fly(world: World, route: Route, sink: Sink, *, duration: float, seed: int,
        camera: CameraOptions, vehicle: VehicleOptions, imu: ImuOptions,
        sensor: SensorOptions | None = None, renderer: Renderer | None = None,
        vehicle_seed: int | None = None, wave: SpeedWave | None = None,
        height_wave: HeightWave | None = None, speed: float = SPEED,
        path: np.ndarray | None = None,
        follower: Follower | None = None, as_flight: bool = False) -> RecordSummary:
    """Fly ``route`` for ``duration`` simulated seconds at ``speed`` m/s, sending every sample to
    ``sink``. ``seed`` draws the sensors' noise, ``vehicle_seed`` (default ``seed``) the errors the
    vehicle keeps from flight to flight (:attr:`SimOptions.vehicle_seed`); ``wave`` swings the
    cruise's speed, ``height_wave`` its height (:class:`PathFollower`); ``path`` (M, 2), the path to
    follow instead of the route's own (:func:`route_along`); ``follower``, what to fly after the
    climb instead of the path at ``speed`` (a :class:`TimedFollower`); ``as_flight``: the IMU drawn
    as a simulated flight of these seeds draws it (``imu.flight_generators``: its vehicle's
    matrices, its turn-on biases), not as the recorder's own routes do.

    Physics and IMU tick at ``imu.rate_hz``; a frame is exposed around the first tick at or
    after each multiple of the camera period: with an ideal camera (``sensor`` None) stamped
    with that tick's time, else as the realistic ``sensor`` stamps it (late, with jitter;
    lost frames are not written). ``renderer`` must draw the camera head's render camera.
    """
    dt = 1.0 / imu.rate_hz
    if follower is None:
        path = route_path(world, route) if path is None else path
        follower = PathFollower(path, route.cruise_height, speed, wave, height_wave)
    quad = Quadrotor(vehicle, world.obstacle_clearance,
                     position=np.array([route.start[0], route.start[1], 0.0]),
                     yaw=follower.start_yaw)
    unit = seed if vehicle_seed is None else vehicle_seed
    imu_model = ImuModel(imu, *(flight_generators(seed, unit) if as_flight else
                                (np.random.default_rng([seed, 1]),
                                 np.random.default_rng([unit, 1]))))
    head = CameraHead(camera.pinhole(), camera.rate_hz, camera.T_B_C(), sensor, world.name,
                      np.random.default_rng([seed, 3]), np.random.default_rng([unit, 3]))
    sink.add_camera_truth(head.T_B_C)
    owned = renderer is None
    renderer = renderer or Renderer(world, head.render_camera)
    climb_seconds = 0.0 if follower.takes_off else \
        route.cruise_height * CLIMB_SECONDS_PER_METRE + SETTLE_SECONDS
    ticks = int(round(duration * imu.rate_hz))
    next_frame, frames = 0.0, 0
    try:
        for k in range(ticks + 1):
            t = k * dt
            t_ns = int(round(t * 1e9))
            state = quad.state
            if t >= next_frame - 1e-9:
                capture = head.shoot(renderer, t, state)
                if capture.stamp is not None:
                    sink.add_frame(int(round(capture.stamp * 1e9)), capture.image,
                                   capture.depth, t_ns)
                    frames += 1
                next_frame += 1.0 / camera.rate_hz
            _command(quad, follower, t, climb_seconds)
            truth = quad.step(dt)
            gyro, accel = imu_model.measure(truth, dt, thrust=quad.thrust)
            # The sample describes [t, t + dt); ground truth is the state at t.
            sink.add_groundtruth(t_ns, state.position, state.q_W_B, state.velocity,
                                 imu_model.gyro_bias, imu_model.accel_bias)
            sink.add_imu(t_ns, gyro, accel)
            if quad.collision is not None:
                c = quad.collision
                raise RecordError(f"{world.name}: collided at t={c.time:.2f} s at "
                                  f"{np.round(c.position, 2).tolist()} (clearance {c.clearance:.2f} m)")
    finally:
        if owned:
            renderer.close()
    return RecordSummary(world.name, route.name, duration, ticks + 1, frames, follower.length)


def _command(quad: Quadrotor, follower: Follower, t: float, climb_seconds: float) -> None:
    """Stand still, then climb over the start for ``climb_seconds``, then follow."""
    standing = follower.standing_s
    if t < standing:
        return
    if not quad.armed:
        quad.arm()
    if t < standing + climb_seconds:
        start = follower.target(0.0)
        quad.set_target(ControlTarget(position=start.position, yaw=start.yaw))
    else:
        quad.set_target(follower.target(t - standing - climb_seconds))


def _heading(path: np.ndarray) -> float:
    step = path[min(5, len(path) - 1)] - path[0]
    return math.atan2(step[1], step[0])


def record_dataset(out: Path, sim: SimOptions, camera: CameraOptions, vehicle: VehicleOptions,
                   imu: ImuOptions, *, duration: float | None,
                   sim_camera: SensorOptions | None = None,
                   wave: SpeedWave | None = None, height_wave: HeightWave | None = None,
                   speed: float = SPEED, along: FlownMotion | None = None,
                   timed: bool = False) -> RecordSummary:
    """Record ``duration`` seconds of ``sim.world`` (built from ``sim.seed``) into ``out``,
    in ``sim.profile``: realistic, through the camera sensor ``sim_camera`` (default
    ``[sim_camera]``'s defaults; its lens is written into ``sensor.yaml``, and the mounting
    written is the configured one, not the camera's true one; none when it is switched off),
    or ideal.

    The seed also picks the route and seeds the sensors' noise, so one seed gives one dataset;
    ``sim.vehicle_seed`` flies another seed's vehicle (its IMU matrices and camera mounting),
    ``sim.noise_seed`` the same flight with another draw of the sensors' noise. ``speed`` is
    the cruise's, m/s (at most the vehicle's ``xy_vel_max``); ``wave`` swings it and
    ``height_wave`` its height (:class:`PathFollower`). ``along``: another flight, in whose
    world and seed (its world as it flew it, the sensors of ``sim.profile``, its IMU drawn as
    the flight drew it) its path is followed at ``speed`` instead of the seed's route
    (:func:`route_along`), or, ``timed``, its motion flown again in time, take-off included,
    after standing as long as it stood (:class:`TimedFollower`; no wave of either kind);
    there a ``duration`` of None records all of it and a second of hover.
    """
    if timed and (along is None or wave is not None or height_wave is not None):
        raise RecordError("a timed recording flies a flight's own motion again: it needs the "
                          "flight and takes no speed or height wave")
    follower = TimedFollower(along) if timed else None
    if duration is None and follower is not None:
        duration = follower.standing_s + follower.span + 1.0
    if not (duration is not None and math.isfinite(duration) and duration > 0.0):
        raise RecordError(f"duration must be a positive number of seconds, got {duration}")
    fastest = speed + (wave.swing / 2.0 if wave is not None else 0.0)  # PathFollower's peak
    if not (math.isfinite(speed) and speed > 0.0 and fastest <= vehicle.xy_vel_max):
        raise RecordError(f"the cruise speed must be positive and, with half the speed wave's "
                          f"swing, at most the vehicle's xy_vel_max ({vehicle.xy_vel_max:g} "
                          f"m/s), got {speed} m/s")
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise RecordError(f"{out}: exists and is not empty; choose a new folder")
    if along is None:
        world = build_world(sim.world, sim.seed, sim.profile)
        route, path = world.routes[sim.seed % len(world.routes)], None
    else:
        sim = replace(sim, world=along.world, seed=along.seed)
        world = build_world(along.world, along.seed, along.profile)
        route, path = route_along(world, along.positions)
    sensor = (sim_camera or SensorOptions()).for_profile(sim.profile)
    imu = imu.for_profile(sim.profile)
    distortion = tuple(sensor.distortion) if sensor and sensor.distortion else (0.0,) * 4
    with EurocWriter(out, camera.pinhole(), camera.T_B_C(), camera.rate_hz,
                     _euroc_noise(imu), distortion=distortion) as writer:
        return fly(world, route, writer, duration=duration, seed=sim.noise_for(sim.seed),
                   camera=camera, vehicle=vehicle, imu=imu, sensor=sensor,
                   vehicle_seed=sim.vehicle_for(sim.seed), wave=wave,
                   height_wave=height_wave, speed=speed, path=path, follower=follower,
                   as_flight=along is not None)


def _euroc_noise(imu: ImuOptions) -> dict[str, float]:
    """The IMU's noise model under the names of EuRoC's ``imu0/sensor.yaml`` (zero when the
    recording is noiseless, so estimators read what the data holds)."""
    scale = 1.0 if imu.enabled else 0.0
    return {
        "rate_hz": imu.rate_hz,
        "gyroscope_noise_density": scale * imu.gyro_noise_density,
        "gyroscope_random_walk": scale * imu.gyro_bias_random_walk,
        "accelerometer_noise_density": scale * imu.accel_noise_density,
        "accelerometer_random_walk": scale * imu.accel_bias_random_walk,
    }
