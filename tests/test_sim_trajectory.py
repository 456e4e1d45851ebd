"""PX4's jerk-limited smoothing, as the mock's take-off flies it (drivers/sim/trajectory.py)."""

import math

import numpy as np
import pytest

from drivers.sim.trajectory import AxisState, VelocitySmoothing, max_speed_from_distance

DT = 0.005


def fly(smoothing: VelocitySmoothing, setpoint, seconds: float) -> np.ndarray:
    """(jerk, acceleration, velocity, position) every tick, re-planning every tick toward
    ``setpoint(state)`` as PositionSmoothing does."""
    states = []
    for _ in range(int(round(seconds / DT))):
        state = smoothing.update_traj(DT)
        smoothing.update_durations(setpoint(state))
        states.append((state.j, state.a, state.v, state.x))
    return np.array(states)


def test_a_velocity_change_is_an_s_curve_within_the_jerk_and_acceleration_limits():
    smoothing = VelocitySmoothing(max_jerk=4.0, max_accel=0.5, max_vel=1.5)
    states = fly(smoothing, lambda state: 1.5, 6.0)
    jerk, accel, velocity = states[:, 0], states[:, 1], states[:, 2]
    assert np.abs(jerk).max() == pytest.approx(4.0)
    assert accel.max() == pytest.approx(0.5, abs=1e-9)
    assert velocity[-1] == pytest.approx(1.5, abs=1e-6)
    # time-optimal: 1.5 m/s at 0.5 m/s² takes 3 s, plus a/j = 0.125 s of each ramp's half
    reached = np.argmax(velocity > 1.5 - 1e-6) * DT
    assert reached == pytest.approx(3.0 + 0.125, abs=0.02)


def test_the_speed_from_distance_stops_within_the_distance():
    jerk, accel, distance = 4.0, 0.5, 2.0
    speed = max_speed_from_distance(jerk, accel, distance)
    assert speed == pytest.approx(-2 * accel ** 2 / jerk + math.sqrt(
        (2 * accel ** 2 / jerk) ** 2 + 2 * accel * distance))
    assert max_speed_from_distance(jerk, accel, 0.0) == 0.0
    assert max_speed_from_distance(jerk, accel, 0.0, final_speed=0.3) == 0.3
    smoothing = VelocitySmoothing(jerk, accel, 10.0, AxisState(v=speed))
    states = fly(smoothing, lambda state: 0.0, 8.0)
    assert states[-1, 2] == pytest.approx(0.0, abs=1e-9)
    assert states[-1, 3] <= distance


def test_a_climb_to_a_height_stops_there_from_rest():
    """The take-off's loop: the fastest speed that still stops at the goal, smoothed."""
    smoothing = VelocitySmoothing(max_jerk=4.0, max_accel=0.5, max_vel=1.5)
    goal = 1.5
    states = fly(smoothing, lambda state: min(1.5, max_speed_from_distance(
        4.0, 0.5, max(goal - state.x, 0.0))), 8.0)
    assert states[-1, 3] == pytest.approx(goal, abs=0.05)
    assert states[-1, 2] == pytest.approx(0.0, abs=0.01)
    assert np.abs(states[:, 1]).max() <= 0.5 + 1e-9
    assert states[:, 2].max() < 1.0  # 1.5 m does not leave room to reach 1.5 m/s


@pytest.mark.parametrize("limits", [(0.0, 0.5, 1.5), (4.0, -1.0, 1.5), (4.0, 0.5, math.nan)])
def test_limits_that_are_not_positive_are_refused(limits):
    with pytest.raises(ValueError, match="must be positive"):
        VelocitySmoothing(*limits)
