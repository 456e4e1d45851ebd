"""A quadrotor flown by a PX4-like cascaded controller, with ground contact and collisions.

World ``W`` is ENU (z up), body ``B`` is FLU; SI units, radians. One :meth:`Quadrotor.step`
advances the vehicle by ``dt`` and returns the noiseless IMU truth of that step.

The controller follows PX4's multicopter position controller (``mc_pos_control``,
``PositionControl.cpp``), with PX4's parameter names and default values
(``src/modules/mc_pos_control/*_params.yaml``, ``src/modules/mc_att_control/*``):

1. position P loop: ``v_sp = K_p (p_sp - p) + v_ff`` with ``K_p`` = ``MPC_XY_P`` horizontally and
   ``MPC_Z_P`` vertically; ``v_sp`` clipped to ``MPC_XY_VEL_MAX`` (horizontal norm) and
   ``[-MPC_Z_VEL_MAX_DN, MPC_Z_VEL_MAX_UP]`` (vertical);
2. velocity PID: ``a_sp = K_v (v_sp - v) + K_i int(v_sp - v) - K_d dv/dt + a_ff`` with the
   ``MPC_{XY,Z}_VEL_{P,I,D}_ACC`` gains and dv/dt low-passed at ``MPC_VELD_LP``; ``a_sp`` clipped
   to ``MPC_ACC_HOR_MAX`` (horizontal norm) and ``[-MPC_ACC_DOWN_MAX, MPC_ACC_UP_MAX]``
   (vertical). PX4 applies these acceleration limits in its setpoint generators; here they bound
   the controller output directly, a simplification;
3. thrust vector ``t = a_sp + (0, 0, g)``: its direction, tilted at most ``MPC_TILTMAX_AIR``
   from vertical, is the desired body z; the collective specific thrust keeps the vertical
   acceleration (``|t_z| / b_z``, PX4's vertical priority) within ``[MPC_THR_MIN, MPC_THR_MAX]``
   scaled by ``g / MPC_THR_HOVER`` (a linear thrust curve: hover at ``MPC_THR_HOVER``);
4. desired attitude from body z and the yaw setpoint (PX4's ``bodyzToAttitude``); the attitude
   follows it to first order: body rates ``w = P * log(R^T R_sp)`` with ``P`` = ``MC_ROLL_P``
   / ``MC_PITCH_P`` on the tilt axes and ``MC_YAW_P`` on yaw (so time constants ``1/P``), plus
   the yaw-rate feed-forward, clipped per axis to ``MC_ROLLRATE_MAX``, ``MC_PITCHRATE_MAX``,
   ``MC_YAWRATE_MAX``.

Dynamics: ``a = R (0, 0, T) - k_d v + (0, 0, -g)`` (collective thrust along the actual body z,
linear drag ``k_d``), body rates as commanded (a perfect rate loop). Every step integrates
exactly as the IMU consistency contract states, so integrating the returned IMU truth from a
true state reproduces the ground truth::

    R' = R Exp(w dt);  a = R f + (0, 0, -g);  v' = v + a dt;  p' = p + v dt + a dt^2 / 2.

Contact with the floor (z = 0) and with obstacles is written as a constrained acceleration
held over the step, so the contract holds through contact too (see :meth:`Quadrotor.step`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from autonomy.geometry import GRAVITY, hamilton_product, quat_exp, quat_from_axes, quat_log
from autonomy.options import OptionError, option, validate

#: ``obstacle_clearance(points (N, 3)) -> (N,)`` metres to the nearest solid surface other than
#: the floor, <= 0 inside solid (``World.obstacle_clearance``).
ClearanceFn = Callable[[np.ndarray], np.ndarray]

#: Longest step accepted: the explicit integration of the attitude and velocity loops and the
#: two-step contact model assume steps far shorter than the attitude time constant (~0.15 s).
MAX_STEP = 0.05


@dataclass(frozen=True)
class VehicleOptions:
    """The quadrotor's PX4 flight-controller limits and gains, and its physical model.

    Defaults are PX4's parameter defaults (PX4-Autopilot ``src/modules/mc_pos_control/
    multicopter_position_control_{gain,limits}_params.yaml``, ``multicopter_position_mode_params
    .yaml`` for ``MPC_ACC_HOR_MAX``, ``multicopter_altitude_mode_params.yaml`` for
    ``MPC_ACC_UP_MAX``/``MPC_ACC_DOWN_MAX``, ``multicopter_position_control_params.yaml`` for
    ``MPC_THR_HOVER``/``MPC_VELD_LP``, ``src/modules/mc_att_control/mc_att_control_params``).
    """

    xy_p: float = option(0.95, ge=0.0, le=2.0, doc="MPC_XY_P: horizontal position gain, 1/s")
    z_p: float = option(1.0, ge=0.1, le=1.5, doc="MPC_Z_P: vertical position gain, 1/s")
    xy_vel_p: float = option(
        1.8, ge=1.2, le=5.0, doc="MPC_XY_VEL_P_ACC: horizontal velocity P gain, 1/s"
    )
    xy_vel_i: float = option(
        0.4, ge=0.0, le=60.0, doc="MPC_XY_VEL_I_ACC: horizontal velocity I gain, 1/s^2"
    )
    xy_vel_d: float = option(
        0.2, ge=0.0, le=2.0, doc="MPC_XY_VEL_D_ACC: horizontal velocity D gain"
    )
    z_vel_p: float = option(
        4.0, ge=2.0, le=15.0, doc="MPC_Z_VEL_P_ACC: vertical velocity P gain, 1/s"
    )
    z_vel_i: float = option(
        2.0, ge=0.0, le=3.0, doc="MPC_Z_VEL_I_ACC: vertical velocity I gain, 1/s^2"
    )
    z_vel_d: float = option(0.0, ge=0.0, le=2.0, doc="MPC_Z_VEL_D_ACC: vertical velocity D gain")
    vel_deriv_lp_hz: float = option(
        5.0, gt=0.0, le=50.0, doc="MPC_VELD_LP: low-pass cutoff of the velocity derivative, Hz"
    )
    xy_vel_max: float = option(
        12.0, gt=0.0, le=20.0, doc="MPC_XY_VEL_MAX: horizontal speed limit, m/s"
    )
    z_vel_max_up: float = option(
        3.0, ge=0.5, le=8.0, doc="MPC_Z_VEL_MAX_UP: climb rate limit, m/s"
    )
    z_vel_max_dn: float = option(
        1.5, ge=0.5, le=4.0, doc="MPC_Z_VEL_MAX_DN: descent rate limit, m/s"
    )
    acc_hor_max: float = option(
        5.0, ge=2.0, le=15.0, doc="MPC_ACC_HOR_MAX: horizontal acceleration limit, m/s^2"
    )
    acc_up_max: float = option(
        4.0, ge=2.0, le=15.0, doc="MPC_ACC_UP_MAX: upward acceleration limit, m/s^2"
    )
    acc_down_max: float = option(
        3.0, ge=2.0, le=15.0, doc="MPC_ACC_DOWN_MAX: downward acceleration limit, m/s^2"
    )
    tilt_max_deg: float = option(
        45.0, ge=20.0, le=89.0, doc="MPC_TILTMAX_AIR: tilt limit, degrees"
    )
    thrust_hover: float = option(
        0.5, ge=0.1, le=0.8,
        doc="MPC_THR_HOVER: normalised thrust that hovers (so maximum thrust is g / it)",
    )
    thrust_min: float = option(
        0.12, ge=0.0, le=0.5, doc="MPC_THR_MIN: normalised minimum thrust in flight"
    )
    thrust_max: float = option(1.0, gt=0.0, le=1.0, doc="MPC_THR_MAX: normalised maximum thrust")
    attitude_p: float = option(
        6.5, gt=0.0, le=12.0,
        doc="MC_ROLL_P / MC_PITCH_P: tilt rate per tilt error, 1/s (time constant 1/P); "
        "PX4 default 6.5 (4.0 in some newer trees)",
    )
    yaw_p: float = option(2.8, gt=0.0, le=5.0, doc="MC_YAW_P: yaw rate per yaw error, 1/s")
    roll_rate_max_deg: float = option(
        220.0, gt=0.0, le=1800.0, doc="MC_ROLLRATE_MAX: roll rate limit, deg/s"
    )
    pitch_rate_max_deg: float = option(
        220.0, gt=0.0, le=1800.0, doc="MC_PITCHRATE_MAX: pitch rate limit, deg/s"
    )
    yaw_rate_max_deg: float = option(
        200.0, gt=0.0, le=1800.0, doc="MC_YAWRATE_MAX: yaw rate limit, deg/s"
    )
    drag: float = option(
        0.3, ge=0.0, le=5.0,
        doc="linear drag per unit mass, 1/s (a_drag = -drag * v); the order of magnitude of "
        "small quadrotors' rotor drag",
    )
    collision_radius: float = option(
        0.3, gt=0.0, le=5.0,
        doc="radius of the sphere around the body origin that must stay free of obstacles, m",
    )

    def __post_init__(self) -> None:
        validate(self)
        if self.thrust_min >= self.thrust_hover:
            raise OptionError("thrust_min", f"must be below thrust_hover ({self.thrust_hover}), "
                                            f"got {self.thrust_min}")
        if self.thrust_max <= self.thrust_hover:
            raise OptionError("thrust_max", f"must exceed thrust_hover ({self.thrust_hover}), or "
                                            f"the vehicle cannot climb; got {self.thrust_max}")


def _vector_or_none(name: str, value) -> np.ndarray | None:
    if value is None:
        return None
    v = np.array(value, dtype=float).reshape(-1)
    if v.shape != (3,):
        raise ValueError(
            f"ControlTarget.{name} must be a 3-vector, got shape {np.shape(value)}"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError(f"ControlTarget.{name} must be finite, got {v.tolist()}")
    v.flags.writeable = False
    return v


def _scalar_or_none(name: str, value) -> float | None:
    if value is None:
        return None
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"ControlTarget.{name} must be finite, got {value!r}")
    return v


@dataclass(frozen=True)
class ControlTarget:
    """What the flight controller tracks, world frame ENU, SI units.

    ``position`` given: position loop, ``velocity`` (if given) is its feed-forward. Only
    ``velocity``: velocity loop. Neither: hold the position the vehicle had when the target was
    set. ``acceleration`` is always a feed-forward. ``yaw`` (rad, from east, counter-clockwise)
    with ``yaw_rate`` (rad/s) as its feed-forward; only ``yaw_rate``: turn at that rate; neither:
    hold the heading. Every given value must be finite (``ValueError`` otherwise).
    """

    position: np.ndarray | None = None
    velocity: np.ndarray | None = None
    acceleration: np.ndarray | None = None
    yaw: float | None = None
    yaw_rate: float | None = None

    def __post_init__(self) -> None:
        for name in ("position", "velocity", "acceleration"):
            object.__setattr__(self, name, _vector_or_none(name, getattr(self, name)))
        for name in ("yaw", "yaw_rate"):
            object.__setattr__(self, name, _scalar_or_none(name, getattr(self, name)))


@dataclass(frozen=True)
class ImuTruth:
    """Noiseless IMU of one step, held constant over it: body FLU rad/s and m/s^2.

    ``specific_force = R^T (a - (0, 0, -g))``: at rest it reads ``(0, 0, +g)`` when level.
    """

    angular_velocity: np.ndarray
    specific_force: np.ndarray


@dataclass(frozen=True)
class VehicleState:
    """Ground truth at ``time``: ENU position/velocity/acceleration, attitude ``q_W_B``
    (w, x, y, z) and body rates over the last step."""

    time: float
    position: np.ndarray
    velocity: np.ndarray
    q_W_B: np.ndarray
    angular_velocity_B: np.ndarray
    acceleration_W: np.ndarray
    on_ground: bool


@dataclass(frozen=True)
class Collision:
    """The first point of the flown path closer than the collision radius to an obstacle."""

    time: float
    position: np.ndarray
    clearance: float


# --- plain-float 3-vector and quaternion helpers (a step must cost microseconds) ---------------


def _rotate(q, v):
    """``R(q) v`` for a unit quaternion ``q = (w, x, y, z)``."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 (q_v x v); v' = v + w t + q_v x t
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


def _rotate_inverse(q, v):
    """``R(q)^T v``."""
    return _rotate((q[0], -q[1], -q[2], -q[3]), v)


def _normalised(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _attitude_from_body_z(bz, yaw):
    """PX4's ``bodyzToAttitude`` in ENU/FLU: body z along ``bz`` (unit), body x as close to the
    heading ``yaw`` as the tilt allows."""
    heading = (math.cos(yaw), math.sin(yaw), 0.0)
    # body y = bz x heading, normalised; body x = y x z
    yx = bz[1] * heading[2] - bz[2] * heading[1]
    yy = bz[2] * heading[0] - bz[0] * heading[2]
    yz = bz[0] * heading[1] - bz[1] * heading[0]
    n = math.sqrt(yx * yx + yy * yy + yz * yz)
    yx, yy, yz = yx / n, yy / n, yz / n
    x = (yy * bz[2] - yz * bz[1], yz * bz[0] - yx * bz[2], yx * bz[1] - yy * bz[0])
    return quat_from_axes(x, (yx, yy, yz), bz)


def _yaw_of(q):
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _wrap(angle):
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _clip(value, limit):
    return limit if value > limit else (-limit if value < -limit else value)


def _clip_horizontal(x, y, limit):
    norm = math.hypot(x, y)
    if norm > limit:
        return x * limit / norm, y * limit / norm
    return x, y


def _finite_vector(name, value):
    v = np.array(value, dtype=float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite 3-vector, got {value!r}")
    return tuple(float(c) for c in v)


def _as_tuple(v):
    return None if v is None else (float(v[0]), float(v[1]), float(v[2]))


@dataclass
class _Controller:
    """The flight controller's memory: setpoints (plain floats), velocity integral, filtered
    dv/dt."""

    position: tuple | None = None
    velocity: tuple | None = None
    acceleration: tuple = (0.0, 0.0, 0.0)
    yaw_rate: float | None = None
    yaw_is_set: bool = False
    hold_position: tuple = (0.0, 0.0, 0.0)
    yaw_setpoint: float = 0.0
    integral: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    accel_filtered: list = field(default_factory=lambda: [0.0, 0.0, 0.0])


class Quadrotor:
    """A PX4-controlled quadrotor over the floor z = 0, among a world's obstacles.

    ``obstacle_clearance`` is the world's ``World.obstacle_clearance`` (or None for open space).
    The vehicle starts disarmed, at rest on the ground if ``position`` has z = 0, holding its
    start position and heading. Raises ``ValueError`` for a start below the floor or inside the
    collision radius of an obstacle.
    """

    def __init__(
        self,
        options: VehicleOptions | None = None,
        obstacle_clearance: ClearanceFn | None = None,
        *,
        position=(0.0, 0.0, 0.0),
        yaw: float = 0.0,
        time: float = 0.0,
    ):
        self.options = options if options is not None else VehicleOptions()
        if not isinstance(self.options, VehicleOptions):
            raise TypeError(f"options must be VehicleOptions, got {type(options).__name__}")
        self._clearance_fn = obstacle_clearance
        p = _finite_vector("position", position)
        if p[2] < 0.0:
            raise ValueError(f"start position is below the floor (z = {p[2]} < 0)")
        yaw = _scalar_or_none("yaw", yaw)
        time = _scalar_or_none("time", time)
        self._derive_limits()
        self._time = time
        self._p = p
        self._v = (0.0, 0.0, 0.0)
        self._a = (0.0, 0.0, 0.0)
        self._q = quat_exp((0.0, 0.0, yaw))
        self._w = (0.0, 0.0, 0.0)
        self._on_ground = p[2] == 0.0
        self._thrust_lifts = False
        self.armed = False
        self.collision: Collision | None = None
        self._ctl = _Controller(hold_position=p, yaw_setpoint=yaw)
        self._free_ball = (p, 0.0)  # (centre, radius) of a ball known free for the body
        if self._clearance_fn is not None:
            clearance = self._clearance(np.array([p]))[0]
            self._free_ball = (p, float(clearance) - self.options.collision_radius)
            if clearance < self.options.collision_radius:
                raise ValueError(
                    f"start position {list(p)} is {clearance:.3f} m from an obstacle, inside the "
                    f"collision radius {self.options.collision_radius} m"
                )

    def _derive_limits(self) -> None:
        o = self.options
        self._tilt_max = math.radians(o.tilt_max_deg)
        self._thrust_lo = GRAVITY * o.thrust_min / o.thrust_hover
        self._thrust_hi = GRAVITY * o.thrust_max / o.thrust_hover
        limits_deg = (o.roll_rate_max_deg, o.pitch_rate_max_deg, o.yaw_rate_max_deg)
        self._rate_max = tuple(math.radians(d) for d in limits_deg)

    # --- public API ------------------------------------------------------------------------

    @property
    def state(self) -> VehicleState:
        return VehicleState(
            time=self._time,
            position=np.array(self._p),
            velocity=np.array(self._v),
            q_W_B=np.array(self._q),
            angular_velocity_B=np.array(self._w),
            acceleration_W=np.array(self._a),
            on_ground=self._on_ground,
        )

    #: The rotors' collective specific thrust over the last step, m/s^2 (0 with the motors
    #: off): what the airframe's vibration scales with (drivers.sim.imu).
    thrust: float = 0.0

    @property
    def landed(self) -> bool:
        """On the ground and not commanded upward (disarmed, or thrust below weight)."""
        return self._on_ground and not (self.armed and self._thrust_lifts)

    def arm(self) -> None:
        """Motors on: the controller flies the current target. Resets the velocity integral."""
        self.armed = True
        self._ctl.integral = [0.0, 0.0, 0.0]

    def disarm(self) -> None:
        """Motors off: no thrust; in the air the vehicle falls with its attitude held (a
        simplification: no tumbling), on the ground it rests."""
        self.armed = False

    def set_target(self, target: ControlTarget) -> None:
        """Track ``target`` from the next step on (see :class:`ControlTarget`)."""
        if not isinstance(target, ControlTarget):
            raise TypeError(f"target must be a ControlTarget, got {type(target).__name__}")
        ctl = self._ctl
        ctl.position = _as_tuple(target.position)
        ctl.velocity = _as_tuple(target.velocity)
        ctl.acceleration = _as_tuple(target.acceleration) or (0.0, 0.0, 0.0)
        ctl.yaw_rate = target.yaw_rate
        ctl.yaw_is_set = target.yaw is not None
        if target.position is None and target.velocity is None:
            ctl.hold_position = self._p
        if target.yaw is not None:
            ctl.yaw_setpoint = target.yaw
        elif target.yaw_rate is None:
            ctl.yaw_setpoint = _yaw_of(self._q)

    def step(self, dt: float) -> ImuTruth:
        """Advance by ``dt`` seconds (0 < dt <= MAX_STEP) and return the step's IMU truth.

        The acceleration ``a`` and body rate ``w`` are decided at the start of the step and held
        over it; the state is then integrated exactly as the IMU contract says. Constraints
        enter as a different ``a``, never as a correction after integration:

        - floor contact: when the free step would end below z = 0, or while resting on the
          ground with thrust not above weight, the vertical acceleration is the deadbeat
          landing law ``a_z = -(z / dt^2 + 1.5 v_z / dt)`` (both eigenvalues of the discrete
          (z, v_z) map are zero, so z and v_z reach 0 two equal steps after touchdown, after
          penetrating at most |v_z| dt / 4), and static friction stops horizontal motion,
          ``a_xy = -v_xy / dt``. The attitude levels at the current heading.
        - obstacle contact: if the step's path comes closer than ``collision_radius`` to an
          obstacle, the collision is recorded and the step is replaced by an impact that stops
          the vehicle within it (``a = -v / dt``, ``w = 0``, so it comes to rest half a step's
          travel on); every later step keeps it frozen at rest and returns the resting IMU
          truth. Clearance queries are skipped while the step stays inside the ball the last
          query proved free (see ``_first_contact``).
        """
        dt = float(dt)
        if not 0.0 < dt <= MAX_STEP:
            raise ValueError(f"step dt must be in (0, {MAX_STEP}] s, got {dt!r}")
        if self.collision is not None:
            return self._rest(dt)
        thrust, body_z_sp, yaw_rate_ff = self._control(dt)
        self.thrust = thrust
        free = self._free_acceleration(thrust)
        self._thrust_lifts = free[2] > 0.0
        end_z = self._p[2] + self._v[2] * dt + 0.5 * free[2] * dt * dt
        if end_z < 0.0 or (self._on_ground and not self._thrust_lifts):
            a = self._ground_acceleration(dt)
            level = _attitude_from_body_z((0.0, 0.0, 1.0), _yaw_of(self._q))
            w = self._rates_towards(level, 0.0)
            on_ground = True
        else:
            a = free
            w = self._rates_towards(
                _attitude_from_body_z(body_z_sp, self._ctl.yaw_setpoint), yaw_rate_ff
            ) if self.armed else (0.0, 0.0, 0.0)
            on_ground = False
        p_end = self._integrate_position(a, dt)
        hit = self._first_contact(self._p, p_end, dt)
        if hit is not None:
            self.collision = hit
            a = tuple(-v / dt for v in self._v)
            w = (0.0, 0.0, 0.0)
        return self._advance(a, w, dt, on_ground)

    # --- the controller ----------------------------------------------------------------------

    def _control(self, dt):
        """(collective specific thrust, desired body z, yaw-rate feed-forward) for this step."""
        if not self.armed:
            return 0.0, (0.0, 0.0, 1.0), 0.0
        acc = self._acceleration_setpoint(dt)
        return (*self._thrust(acc), self._yaw_rate_feedforward(dt))

    def _velocity_setpoint(self):
        o, t, p = self.options, self._ctl, self._p
        if t.position is not None or t.velocity is None:
            sp = t.position if t.position is not None else t.hold_position
            ff = t.velocity if t.velocity is not None else (0.0, 0.0, 0.0)
            v = (
                o.xy_p * (sp[0] - p[0]) + ff[0],
                o.xy_p * (sp[1] - p[1]) + ff[1],
                o.z_p * (sp[2] - p[2]) + ff[2],
            )
        else:
            v = t.velocity
        vx, vy = _clip_horizontal(v[0], v[1], o.xy_vel_max)
        return vx, vy, min(max(v[2], -o.z_vel_max_dn), o.z_vel_max_up)

    def _acceleration_setpoint(self, dt):
        """The velocity PID (PX4 ``PositionControl::_velocityControl``), limited.

        Anti-windup as PX4's: horizontally a tracking term feeds the saturation back into the
        integral (gain ``2 / MPC_XY_VEL_P_ACC``); vertically the integral stops growing in the
        direction the limit saturates. It is frozen on the ground, as PX4 does while landed.
        """
        o, ctl, v = self.options, self._ctl, self._v
        v_sp = self._velocity_setpoint()
        errors = (v_sp[0] - v[0], v_sp[1] - v[1], v_sp[2] - v[2])
        gains = ((o.xy_vel_p, o.xy_vel_d), (o.xy_vel_p, o.xy_vel_d), (o.z_vel_p, o.z_vel_d))
        ff, integral, dv = ctl.acceleration, ctl.integral, ctl.accel_filtered
        wanted = [
            kp * e + i - kd * d + f
            for (kp, kd), e, i, d, f in zip(gains, errors, integral, dv, ff)
        ]
        ax, ay = _clip_horizontal(wanted[0], wanted[1], o.acc_hor_max)
        az = min(max(wanted[2], -o.acc_down_max), o.acc_up_max)
        if not self._on_ground:
            tracking = 2.0 / o.xy_vel_p
            integral[0] += o.xy_vel_i * (errors[0] - (wanted[0] - ax) * tracking) * dt
            integral[1] += o.xy_vel_i * (errors[1] - (wanted[1] - ay) * tracking) * dt
            excess = wanted[2] - az
            if excess == 0.0 or (excess > 0.0) != (errors[2] > 0.0):
                integral[2] += o.z_vel_i * errors[2] * dt
        return ax, ay, az

    def _thrust(self, acc):
        """Collective specific thrust and desired body z for the acceleration ``acc``."""
        tx, ty, tz = acc[0], acc[1], acc[2] + GRAVITY
        horizontal = math.hypot(tx, ty)
        up = max(tz, 1e-6)  # a thrust vector pointing down still tilts no more than the limit
        if math.atan2(horizontal, up) > self._tilt_max:
            s = math.sin(self._tilt_max) / horizontal
            body_z = (tx * s, ty * s, math.cos(self._tilt_max))
        else:
            n = math.sqrt(horizontal * horizontal + up * up)
            body_z = (tx / n, ty / n, up / n)
        thrust = min(max(tz / body_z[2], self._thrust_lo), self._thrust_hi)
        return thrust, body_z

    def _yaw_rate_feedforward(self, dt):
        """Advance the yaw setpoint of a rate-only target; return the yaw-rate feed-forward."""
        ctl = self._ctl
        if ctl.yaw_rate is None:
            return 0.0
        rate = _clip(ctl.yaw_rate, self._rate_max[2])
        if not ctl.yaw_is_set:
            ctl.yaw_setpoint = _wrap(self._ctl.yaw_setpoint + rate * dt)
        return rate

    def _rates_towards(self, q_sp, yaw_rate_ff):
        """First-order attitude tracking: body rates ``P log(q^-1 q_sp)`` plus the feed-forward,
        clipped per axis (MC_*RATE_MAX)."""
        o = self.options
        e = quat_log(hamilton_product((self._q[0], -self._q[1], -self._q[2], -self._q[3]), q_sp))
        ff = _rotate_inverse(self._q, (0.0, 0.0, yaw_rate_ff))
        gains = (o.attitude_p, o.attitude_p, o.yaw_p)
        return tuple(_clip(gains[i] * e[i] + ff[i], self._rate_max[i]) for i in range(3))

    # --- the physics -------------------------------------------------------------------------

    def _free_acceleration(self, thrust):
        """World acceleration in free flight: thrust along body z, linear drag, gravity."""
        k = self.options.drag
        tx, ty, tz = _rotate(self._q, (0.0, 0.0, thrust))
        v = self._v
        return (tx - k * v[0], ty - k * v[1], tz - k * v[2] - GRAVITY)

    def _ground_acceleration(self, dt):
        """Floor contact: the deadbeat landing law vertically, static friction horizontally."""
        (vx, vy, vz), z = self._v, self._p[2]
        return (-vx / dt, -vy / dt, -(z / (dt * dt) + 1.5 * vz / dt))

    def _integrate_position(self, a, dt):
        p, v, h = self._p, self._v, 0.5 * dt * dt
        return (
            p[0] + v[0] * dt + a[0] * h,
            p[1] + v[1] * dt + a[1] * h,
            p[2] + v[2] * dt + a[2] * h,
        )

    def _first_contact(self, start, end, dt) -> Collision | None:
        """The first point of the segment start -> end within the collision radius of an
        obstacle, or None.

        The clearance is a distance, so the ball around the last queried point with radius
        ``clearance - collision_radius`` is free for the body: while the step ends inside it
        (and so, the ball being convex, the whole segment does) no query is needed. Otherwise
        the segment is sampled at most one radius apart, so a path through any solid
        (clearance <= 0 somewhere) has a sample within radius / 2 of it: no tunnelling.
        """
        if self._clearance_fn is None:
            return None
        radius = self.options.collision_radius
        free_centre, free_radius = self._free_ball
        ex, ey, ez = end[0] - free_centre[0], end[1] - free_centre[1], end[2] - free_centre[2]
        if ex * ex + ey * ey + ez * ez < free_radius * free_radius:
            return None
        dx, dy, dz = end[0] - start[0], end[1] - start[1], end[2] - start[2]
        count = max(1, math.ceil(math.sqrt(dx * dx + dy * dy + dz * dz) / radius))
        if count == 1:  # the usual case: one point, no array arithmetic
            points = np.array((end,))
        else:
            fractions = np.arange(1, count + 1)[:, None] / count
            points = np.array(start) + fractions * np.array((dx, dy, dz))
        clearance = self._clearance(points)
        for i in range(count):
            if clearance[i] < radius:
                return Collision(
                    time=self._time + (i + 1) / count * dt,
                    position=points[i],
                    clearance=float(clearance[i]),
                )
        self._free_ball = (end, float(clearance[-1]) - radius)
        return None

    def _clearance(self, points):
        clearance = self._clearance_fn(points)
        if getattr(clearance, "shape", None) != (len(points),) or not all(
            math.isfinite(c) for c in clearance
        ):
            raise ValueError(
                f"obstacle_clearance must return {len(points)} finite distances, got {clearance!r}"
            )
        return clearance

    def _advance(self, a, w, dt, on_ground) -> ImuTruth:
        """Integrate one step with the IMU contract's scheme and return its IMU truth."""
        q0 = self._q
        f = _rotate_inverse(q0, (a[0], a[1], a[2] + GRAVITY))
        self._p = self._integrate_position(a, dt)
        v = self._v
        self._v = (v[0] + a[0] * dt, v[1] + a[1] * dt, v[2] + a[2] * dt)
        self._q = _normalised(hamilton_product(q0, quat_exp((w[0] * dt, w[1] * dt, w[2] * dt))))
        self._w = w
        self._a = a
        self._on_ground = on_ground
        self._time += dt
        self._filter_acceleration(a, dt)
        return ImuTruth(angular_velocity=np.array(w), specific_force=np.array(f))

    def _filter_acceleration(self, a, dt):
        """dv/dt for the D term, first-order low-passed at MPC_VELD_LP."""
        alpha = dt / (dt + 1.0 / (2.0 * math.pi * self.options.vel_deriv_lp_hz))
        filtered = self._ctl.accel_filtered
        for i in range(3):
            filtered[i] += alpha * (a[i] - filtered[i])

    def _rest(self, dt) -> ImuTruth:
        """Frozen after a collision: at rest, so the IMU reads gravity's reaction only."""
        self._v = (0.0, 0.0, 0.0)
        return self._advance((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), dt, self._on_ground)
