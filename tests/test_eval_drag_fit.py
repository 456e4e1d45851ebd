"""The rotor drag coefficient fitted from a flight's keyframes and accelerometer
(companion/tools/eval/drag_fit.py)."""

import numpy as np
import pytest

from autonomy.geometry import rot_z
from companion.tools.eval.drag_fit import fit_drag


def flight(seconds=30.0, drag=0.3, offset=(0.05, -0.1), noise=0.05, speed=1.5, seed=0):
    """Keyframes every 0.1 s of a body turning slowly while its speed along its own axes
    varies, and a 200 Hz accelerometer reading ``-drag v_xy + offset`` (plus noise) on its
    horizontal axes."""
    rng = np.random.default_rng(seed)
    imu_t = np.arange(0.0, seconds, 0.005)
    velocity_B = np.column_stack([speed * (1 + np.sin(0.4 * imu_t)) / 2,
                                  0.5 * speed * np.sin(0.23 * imu_t), 0.0 * imu_t])
    accel = np.column_stack([-drag * velocity_B[:, :2] + offset,
                             np.full(len(imu_t), 9.81)])
    accel[:, :2] += rng.normal(0.0, noise, (len(imu_t), 2))
    keyframe_t = np.arange(0.0, seconds, 0.1)
    index = np.searchsorted(imu_t, keyframe_t)
    R_W_B = np.array([rot_z(0.05 * t) for t in keyframe_t])
    velocity_W = np.einsum("kij,kj->ki", R_W_B, velocity_B[index])
    return keyframe_t, R_W_B, velocity_W, imu_t, accel


def test_the_coefficient_and_offsets_are_recovered():
    fit = fit_drag(*flight())
    assert fit.coefficient == pytest.approx(0.3, rel=0.02)
    assert np.allclose(fit.offset_xy, (0.05, -0.1), atol=0.005)
    assert fit.intervals > 200 and fit.speed_spread > 0.3


def test_a_hover_gives_no_fit():
    """Below the least speed the body may stand on the ground: nothing to fit."""
    assert fit_drag(*flight(speed=0.1)) is None


def test_too_short_a_flight_gives_no_fit():
    assert fit_drag(*flight(seconds=1.0)) is None


def test_a_cruise_at_one_speed_gives_no_fit():
    """At one speed along x and none sideways, ``k`` and the offsets cannot be told apart."""
    keyframe_t, R_W_B, velocity_W, imu_t, accel = flight()
    velocity_W[:] = [1.5, 0.0, 0.0]
    assert fit_drag(keyframe_t, np.broadcast_to(np.eye(3), R_W_B.shape), velocity_W, imu_t,
                    accel) is None


def test_a_sample_that_is_not_finite_costs_its_interval_only():
    keyframe_t, R_W_B, velocity_W, imu_t, accel = flight()
    accel[1000] = np.nan
    fit = fit_drag(keyframe_t, R_W_B, velocity_W, imu_t, accel)
    assert fit.coefficient == pytest.approx(0.3, rel=0.02)
    assert fit.intervals == fit_drag(*flight()).intervals - 1
