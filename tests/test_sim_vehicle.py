"""The simulated quadrotor: PX4-like tracking and limits, ground contact, collisions, and the
IMU consistency contract (integrating its IMU truth reproduces its ground truth)."""

import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY, quat_to_rot, rot_to_quat, so3_exp, yaw_of
from autonomy.options import OptionError
from drivers.sim.quadrotor import (
    MAX_STEP,
    ControlTarget,
    ImuTruth,
    Quadrotor,
    VehicleOptions,
)

DT = 0.005  # the 200 Hz step the simulator runs at


def fly(vehicle, seconds, dt=DT):
    """Step for ``seconds``; the state after each step and the IMU truth of each step."""
    states, imus = [], []
    for _ in range(round(seconds / dt)):
        imus.append(vehicle.step(dt))
        states.append(vehicle.state)
    return states, imus


def airborne(position=(0.0, 0.0, 1.5), options=None, clearance=None, yaw=0.0):
    """Armed and holding ``position`` (it starts there at rest)."""
    vehicle = Quadrotor(options, clearance, position=position, yaw=yaw)
    vehicle.arm()
    return vehicle


def tilt(state):
    """Angle between body z and world z."""
    return math.acos(min(1.0, quat_to_rot(state.q_W_B)[2, 2]))


def integrate_imu(state, imus, dt=DT):
    """Dead-reckon from a true state with the contract's scheme."""
    R, p, v = quat_to_rot(state.q_W_B), state.position.copy(), state.velocity.copy()
    gravity = np.array([0.0, 0.0, -GRAVITY])
    for imu in imus:
        a = R @ imu.specific_force + gravity
        p = p + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        R = R @ so3_exp(imu.angular_velocity * dt)
    return R, p, v


def assert_contract(start, states, imus, dt=DT):
    R, p, v = integrate_imu(start, imus, dt)
    end = states[-1]
    assert np.abs(p - end.position).max() < 1e-3
    assert np.abs(v - end.velocity).max() < 1e-3
    assert np.abs(R - quat_to_rot(end.q_W_B)).max() < 1e-6


def wall_at(x_wall, thickness=0.1):
    """Clearance of a slab x in [x_wall, x_wall + thickness] (no floor), like World's."""
    def clearance(points):
        x = np.asarray(points)[:, 0]
        return np.maximum(x_wall - x, x - (x_wall + thickness))
    return clearance


# --- tracking -------------------------------------------------------------------------------


def test_hover_holds_its_position():
    vehicle = airborne()
    states, imus = fly(vehicle, 5.0)
    positions = np.array([s.position for s in states])
    assert np.abs(positions - [0.0, 0.0, 1.5]).max() < 1e-6
    assert not vehicle.landed and not states[-1].on_ground
    np.testing.assert_allclose(imus[-1].specific_force, [0.0, 0.0, GRAVITY], atol=1e-9)


def test_position_target_is_reached_with_yaw():
    vehicle = airborne()
    vehicle.set_target(ControlTarget(position=[4.0, -2.0, 2.5], yaw=1.0))
    states, _ = fly(vehicle, 12.0)
    np.testing.assert_allclose(states[-1].position, [4.0, -2.0, 2.5], atol=0.02)
    assert abs(yaw_of(quat_to_rot(states[-1].q_W_B)) - 1.0) < 1e-3


def test_velocity_step_respects_acceleration_and_tilt_limits_and_converges():
    options = VehicleOptions()
    vehicle = airborne(options=options)
    vehicle.set_target(ControlTarget(velocity=[6.0, 0.0, 0.0]))
    # The integral takes out the drag with PX4's time constant MPC_XY_VEL_P/I_ACC = 4.5 s.
    states, _ = fly(vehicle, 20.0)
    horizontal = np.array([np.hypot(*s.acceleration_W[:2]) for s in states])
    assert horizontal.max() <= options.acc_hor_max * (1 + 1e-9)
    assert horizontal.max() > 0.8 * options.acc_hor_max  # the limit is what shaped the step
    assert max(tilt(s) for s in states) <= math.radians(options.tilt_max_deg)
    np.testing.assert_allclose(states[-1].velocity, [6.0, 0.0, 0.0], atol=0.05)
    assert abs(states[-1].position[2] - 1.5) < 0.05


def test_tilt_limit_caps_a_hard_acceleration():
    options = VehicleOptions(acc_hor_max=15.0, tilt_max_deg=20.0)
    vehicle = airborne(options=options)
    vehicle.set_target(ControlTarget(velocity=[10.0, 0.0, 0.0]))
    states, _ = fly(vehicle, 3.0)
    tilts = [tilt(s) for s in states]
    assert max(tilts) <= math.radians(20.0) + 1e-9
    assert max(tilts) > math.radians(19.0)


def test_velocity_setpoints_are_clipped_to_px4_speed_limits():
    vehicle = airborne()
    vehicle.set_target(ControlTarget(velocity=[30.0, 0.0, 10.0]))
    states, _ = fly(vehicle, 25.0)
    o = vehicle.options
    assert np.hypot(*states[-1].velocity[:2]) == pytest.approx(o.xy_vel_max, abs=0.05)
    assert max(s.velocity[2] for s in states) <= o.z_vel_max_up + 0.05


def test_yaw_rate_is_tracked_and_limited():
    vehicle = airborne()
    vehicle.set_target(ControlTarget(velocity=[0.0, 0.0, 0.0], yaw_rate=0.8))
    _, imus = fly(vehicle, 3.0)
    assert imus[-1].angular_velocity[2] == pytest.approx(0.8, rel=1e-3)
    vehicle.set_target(ControlTarget(yaw_rate=20.0))
    _, imus = fly(vehicle, 1.0)
    assert imus[-1].angular_velocity[2] == pytest.approx(math.radians(200.0), rel=1e-3)


def test_yaw_only_target_holds_the_current_position():
    vehicle = airborne()
    vehicle.set_target(ControlTarget(velocity=[3.0, 0.0, 0.0]))
    fly(vehicle, 3.0)
    where = vehicle.state.position
    vehicle.set_target(ControlTarget(yaw=2.0))
    states, _ = fly(vehicle, 10.0)
    np.testing.assert_allclose(states[-1].position, where, atol=0.05)
    assert np.abs(states[-1].velocity).max() < 0.02
    assert yaw_of(quat_to_rot(states[-1].q_W_B)) == pytest.approx(2.0, abs=1e-3)


def test_acceleration_feed_forward_is_added():
    plain, fed = airborne(), airborne()
    fed.set_target(ControlTarget(acceleration=[2.0, 0.0, 0.0]))
    fly(plain, 0.5)
    fly(fed, 0.5)
    assert fed.state.velocity[0] > 0.3 and plain.state.velocity[0] == 0.0


# --- ground contact -------------------------------------------------------------------------


def test_disarmed_vehicle_rests_on_the_ground():
    vehicle = Quadrotor(position=(1.0, 2.0, 0.0), yaw=0.5)
    states, imus = fly(vehicle, 1.0)
    assert vehicle.landed and states[-1].on_ground
    np.testing.assert_array_equal(states[-1].position, [1.0, 2.0, 0.0])
    np.testing.assert_array_equal(states[-1].velocity, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(imus[-1].specific_force, [0.0, 0.0, GRAVITY], atol=1e-12)
    np.testing.assert_array_equal(imus[-1].angular_velocity, [0.0, 0.0, 0.0])


def test_take_off_and_land_again():
    vehicle = Quadrotor()
    vehicle.arm()
    fly(vehicle, 0.5)  # armed, holding the ground position: stays down
    assert vehicle.landed and vehicle.state.position[2] == 0.0

    vehicle.set_target(ControlTarget(position=[0.0, 0.0, 1.5]))
    start = vehicle.state
    states, imus = fly(vehicle, 6.0)
    assert not vehicle.landed and not states[-1].on_ground
    assert states[-1].position[2] == pytest.approx(1.5, abs=0.02)
    assert max(s.velocity[2] for s in states) <= vehicle.options.z_vel_max_up + 1e-6

    vehicle.set_target(ControlTarget(velocity=[0.0, 0.0, -1.0]))
    more_states, more_imus = fly(vehicle, 4.0)
    end = more_states[-1]
    assert vehicle.landed and end.on_ground
    assert abs(end.position[2]) < 1e-9 and np.abs(end.velocity).max() < 1e-9
    assert min(s.position[2] for s in more_states) > -0.01  # no sinking into the floor
    assert_contract(start, states + more_states, imus + more_imus)


def test_commanded_upward_on_the_ground_is_not_landed():
    vehicle = Quadrotor()
    vehicle.arm()
    vehicle.set_target(ControlTarget(velocity=[0.0, 0.0, 1.0]))
    vehicle.step(DT)
    assert not vehicle.landed
    assert vehicle.state.position[2] > 0.0


def test_disarming_in_the_air_falls_to_the_ground():
    vehicle = airborne(position=(0.0, 0.0, 3.0))
    fly(vehicle, 0.5)
    vehicle.disarm()
    start = vehicle.state
    states, imus = fly(vehicle, 0.3)
    drop = 3.0 - states[-1].position[2]
    assert drop == pytest.approx(0.5 * GRAVITY * 0.3**2, rel=0.05)
    # Free fall: the accelerometer feels the drag only.
    drag = -vehicle.options.drag * states[-1].velocity
    np.testing.assert_allclose(imus[-1].specific_force, drag, atol=0.05)
    more_states, more_imus = fly(vehicle, 1.0)
    assert vehicle.landed and abs(more_states[-1].position[2]) < 1e-9
    assert_contract(start, states + more_states, imus + more_imus)


# --- collisions -----------------------------------------------------------------------------


def test_flying_into_a_wall_records_a_collision_and_freezes():
    vehicle = airborne(clearance=wall_at(5.0))
    vehicle.set_target(ControlTarget(velocity=[3.0, 0.0, 0.0]))
    start = vehicle.state
    states, imus = fly(vehicle, 4.0)
    hit = vehicle.collision
    assert hit is not None
    assert hit.clearance < vehicle.options.collision_radius
    assert hit.position[0] == pytest.approx(5.0 - vehicle.options.collision_radius, abs=0.02)
    assert 0.0 < hit.time < states[-1].time
    assert max(s.position[0] for s in states) < 5.0
    frozen = [s for s in states if s.time > hit.time + DT]
    assert frozen and all(np.array_equal(s.position, frozen[0].position) for s in frozen)
    assert all(np.array_equal(s.velocity, [0.0, 0.0, 0.0]) for s in frozen)
    np.testing.assert_array_equal(imus[-1].angular_velocity, [0.0, 0.0, 0.0])
    f_rest = quat_to_rot(states[-1].q_W_B).T @ [0.0, 0.0, GRAVITY]
    np.testing.assert_allclose(imus[-1].specific_force, f_rest, atol=1e-12)
    assert_contract(start, states, imus)


def test_fast_flight_does_not_tunnel_through_a_thin_wall():
    options = VehicleOptions(collision_radius=0.05)
    vehicle = airborne(options=options, clearance=wall_at(5.0, thickness=0.01))
    vehicle.set_target(ControlTarget(velocity=[12.0, 0.0, 0.0]))
    # 50 ms steps at up to 12 m/s move 0.6 m: far more than the wall and the radius.
    states, _ = fly(vehicle, 3.0, dt=MAX_STEP)
    hit = vehicle.collision
    assert hit is not None and hit.position[0] < 5.0
    # The impact stops the vehicle within its step: at most half a step's travel further.
    speed = max(np.linalg.norm(s.velocity) for s in states)
    assert vehicle.state.position[0] < hit.position[0] + speed * MAX_STEP / 2


def test_skipped_clearance_queries_still_stop_the_vehicle_before_the_wall():
    # Sphere tracing skips queries only inside the ball the last clearance proved free.
    calls = []

    def clearance(points):
        calls.append(len(points))
        return wall_at(5.0)(points)

    vehicle = airborne(clearance=clearance)
    vehicle.set_target(ControlTarget(velocity=[2.0, 0.0, 0.0]))
    states, _ = fly(vehicle, 5.0)
    assert vehicle.collision is not None
    assert max(s.position[0] for s in states) < 5.0 - 0.25
    assert len(calls) < len(states)


def test_clear_flight_records_no_collision():
    vehicle = airborne(clearance=wall_at(50.0))
    vehicle.set_target(ControlTarget(velocity=[3.0, 0.0, 0.0]))
    fly(vehicle, 2.0)
    assert vehicle.collision is None


# --- the IMU contract -----------------------------------------------------------------------


def test_integrating_imu_truth_of_an_aggressive_manoeuvre_reproduces_the_state():
    vehicle = airborne(options=VehicleOptions(acc_hor_max=12.0, tilt_max_deg=60.0))
    vehicle.set_target(ControlTarget(velocity=[-3.0, 2.0, 1.0], yaw_rate=2.0))
    fly(vehicle, 1.0)
    vehicle.set_target(
        ControlTarget(position=[8.0, 6.0, 4.0], acceleration=[3.0, -4.0, 2.0], yaw=-2.5)
    )
    start = vehicle.state
    states, imus = fly(vehicle, 1.0)
    assert max(np.linalg.norm(s.acceleration_W) for s in states) > 8.0
    assert max(np.abs(i.angular_velocity).max() for i in imus) > 2.0
    assert_contract(start, states, imus)


def test_variable_steps_keep_the_contract():
    vehicle = airborne()
    vehicle.set_target(ControlTarget(velocity=[2.0, 1.0, 0.5], yaw_rate=1.0))
    start = vehicle.state
    R, p, v = quat_to_rot(start.q_W_B), start.position, start.velocity
    rng = np.random.default_rng(3)
    for dt in rng.uniform(0.001, MAX_STEP, 100):
        imu = vehicle.step(dt)
        R, p, v = integrate_imu(ImuState(R, p, v), [imu], dt)
    end = vehicle.state
    assert np.abs(p - end.position).max() < 1e-9
    assert np.abs(R - quat_to_rot(end.q_W_B)).max() < 1e-9


class ImuState:
    """A state in the form integrate_imu reads, from a rotation matrix."""

    def __init__(self, R, p, v):
        self.q_W_B, self.position, self.velocity = rot_to_quat(R), p, v


# --- determinism and bad input --------------------------------------------------------------


def test_the_same_commands_give_the_same_flight():
    def run():
        vehicle = Quadrotor(position=(1.0, 1.0, 0.0))
        vehicle.arm()
        vehicle.set_target(ControlTarget(position=[3.0, 2.0, 2.0], yaw_rate=0.3))
        return fly(vehicle, 2.0)[0][-1]

    a, b = run(), run()
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.q_W_B, b.q_W_B)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"position": [np.nan, 0.0, 0.0]}, "position must be finite"),
        ({"velocity": [1.0, np.inf, 0.0]}, "velocity must be finite"),
        ({"acceleration": [1.0, 2.0]}, "acceleration must be a 3-vector"),
        ({"yaw": np.nan}, "yaw must be finite"),
        ({"yaw_rate": -np.inf}, "yaw_rate must be finite"),
    ],
)
def test_bad_targets_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ControlTarget(**kwargs)


@pytest.mark.parametrize("dt", [0.0, -0.005, np.nan, np.inf, MAX_STEP * 1.5])
def test_bad_steps_are_rejected(dt):
    with pytest.raises(ValueError, match="step dt"):
        Quadrotor().step(dt)


def test_bad_options_and_starts_are_rejected():
    with pytest.raises(OptionError, match="tilt_max_deg"):
        VehicleOptions(tilt_max_deg=5.0)
    with pytest.raises(OptionError, match="collision_radius"):
        VehicleOptions(collision_radius=0.0)
    with pytest.raises(ValueError, match="thrust_min"):
        VehicleOptions(thrust_min=0.5, thrust_hover=0.4)
    with pytest.raises(ValueError, match="below the floor"):
        Quadrotor(position=(0.0, 0.0, -0.1))
    with pytest.raises(ValueError, match="position must be a finite 3-vector"):
        Quadrotor(position=(0.0, np.nan, 1.0))
    with pytest.raises(ValueError, match="inside the collision radius"):
        Quadrotor(obstacle_clearance=wall_at(0.1), position=(0.0, 0.0, 1.0))
    with pytest.raises(TypeError, match="ControlTarget"):
        Quadrotor().set_target({"velocity": [1.0, 0.0, 0.0]})


@pytest.mark.parametrize("garbage", [np.array([np.nan]), np.array([1.0, 2.0]), 7.0])
def test_a_world_answering_garbage_is_an_error_not_a_pass(garbage):
    answers = iter([np.array([0.5])])
    vehicle = airborne(clearance=lambda points: next(answers, garbage))
    vehicle.set_target(ControlTarget(velocity=[3.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="finite distances"):
        fly(vehicle, 2.0)


def test_imu_truth_is_plain_arrays():
    imu = airborne().step(DT)
    assert isinstance(imu, ImuTruth)
    assert imu.angular_velocity.shape == (3,) and imu.specific_force.shape == (3,)
