"""Static initialisation: gravity direction and gyro bias from an IMU at rest."""

import math
from pathlib import Path

import numpy as np
import pytest

from autonomy.geometry import GRAVITY, quat_to_rot, so3_exp, yaw_of
from autonomy.options import OptionError
from autonomy.vins.static_init import (NotStill, StaticInit, StaticInitOptions,
                                       static_initialise)

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_v1_01"


def _static(R_W_B, n=400, rate=200.0, bias=(0.01, -0.02, 0.03), seed=0, vib=0.0):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    gyro = np.asarray(bias) + rng.normal(0, 2.4e-3 + vib, (n, 3))
    accel = (R_W_B.T @ [0, 0, GRAVITY]) + rng.normal(0, 0.03 + 10 * vib, (n, 3))
    return t, gyro, accel


def _angle(a, b):
    return math.degrees(math.acos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b),
                                          -1, 1)))


def test_tilted_static_body_gives_its_tilt_with_zero_yaw():
    R_true = so3_exp(np.array([0.3, -0.2, 1.2]))
    t, gyro, accel = _static(R_true, vib=0.03)   # with rotor-like vibration
    out = static_initialise(t, gyro, accel)
    assert isinstance(out, StaticInit), out
    assert _angle(out.R_W_B.T @ [0, 0, 1], R_true.T @ [0, 0, 1]) < 0.1
    assert abs(yaw_of(out.R_W_B)) < 1e-9
    np.testing.assert_allclose(out.R_W_B @ out.R_W_B.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(out.gyro_bias, [0.01, -0.02, 0.03], atol=8e-3)  # 4 sigma of the mean
    assert out.accel_norm == pytest.approx(GRAVITY, abs=0.05)
    assert out.t_end == t[-1] and out.t_end - out.t_start == pytest.approx(1.5, abs=0.01)
    # the tilt equals the true one up to a rotation about world z
    D = out.R_W_B @ R_true.T
    assert abs(D[2, 2] - 1) < 1e-4


def test_upside_down_and_level_bodies():
    for R in (np.eye(3), np.diag([1.0, -1.0, -1.0])):
        out = static_initialise(*_static(R))
        assert isinstance(out, StaticInit)
        np.testing.assert_allclose(out.R_W_B, R, atol=2e-2)


def test_rotating_window_is_rejected_with_a_reason():
    t, gyro, accel = _static(np.eye(3))
    gyro[200:260] += [0.0, 0.0, 0.5]           # a 0.3 s yaw turn inside the window
    out = static_initialise(t, gyro, accel)
    assert isinstance(out, NotStill) and "rotating" in out.reason


def test_accelerating_window_is_rejected_with_a_reason():
    t, gyro, accel = _static(np.eye(3))
    accel[250:300, 2] += 1.0                   # being lifted
    out = static_initialise(t, gyro, accel)
    assert isinstance(out, NotStill) and "accelerating" in out.reason


def test_short_history_and_wrong_gravity_wait():
    t, gyro, accel = _static(np.eye(3), n=100)
    out = static_initialise(t, gyro, accel)
    assert isinstance(out, NotStill) and "need" in out.reason
    t, gyro, accel = _static(np.eye(3))
    out = static_initialise(t, gyro, accel * 0.5)
    assert isinstance(out, NotStill) and "not gravity" in out.reason


def test_motion_before_the_window_does_not_matter():
    t, gyro, accel = _static(np.eye(3), n=800)
    gyro[:300] += 1.0
    assert isinstance(static_initialise(t, gyro, accel), StaticInit)


@pytest.mark.parametrize("mutate", [
    lambda t, g, a: (t, g[:, :2], a),
    lambda t, g, a: (t, g[:-1], a),
    lambda t, g, a: (t[:-1], g, a),
    lambda t, g, a: (t, np.where(np.arange(len(t))[:, None] == 5, np.nan, g), a),
    lambda t, g, a: (np.r_[t[:5], t[4], t[6:]], g, a),
    lambda t, g, a: (t[:1], g[:1], a[:1]),
])
def test_bad_inputs_raise(mutate):
    with pytest.raises(ValueError):
        static_initialise(*mutate(*_static(np.eye(3))))


def test_options_are_validated_and_derivable_from_noise():
    with pytest.raises(OptionError):
        StaticInitOptions(window_s=-1.0)
    o = StaticInitOptions.from_noise(1.6968e-4, 2.0e-3, factor=5.0)
    assert o.max_gyro_norm_std == pytest.approx(5 * 1.6968e-4 / math.sqrt(0.05))
    # a vibration-free IMU at its white-noise floor passes those tight thresholds
    rng = np.random.default_rng(3)
    t = np.arange(400) / 200.0
    gyro = 0.01 + rng.normal(0, 1.6968e-4 * math.sqrt(200), (400, 3))
    accel = np.array([0, 0, GRAVITY]) + rng.normal(0, 2e-3 * math.sqrt(200), (400, 3))
    assert isinstance(static_initialise(t, gyro, accel, o), StaticInit)


@pytest.mark.skipif(not EUROC.is_dir(), reason=f"EuRoC V1_01 not present at {EUROC}")
def test_real_euroc_static_start():
    from drivers.dataset.euroc import read_groundtruth, read_imu

    imu = read_imu(EUROC)
    gt = read_groundtruth(EUROC)
    t = (imu.t_ns - imu.t_ns[0]) * 1e-9
    m = t <= 4.0                                   # the vehicle sits on the ground (rotors on)
    for window in (1.0, 2.0, 4.0):
        out = static_initialise(t[m], imu.gyro[m], imu.accel[m],
                                StaticInitOptions(window_s=window))
        assert isinstance(out, StaticInit), out
        k = np.argmin(np.abs(gt.t_ns - imu.t_ns[m][-1]))
        up_true = quat_to_rot(gt.q_W_B[k]).T @ [0, 0, 1]
        assert _angle(out.gravity_B, up_true) < 1.0
        b = gt.gyro_bias[k]
        assert np.linalg.norm(out.gyro_bias - b) / np.linalg.norm(b) < 0.2
    # the flight itself is not still
    f = (t > 10) & (t < 20)
    assert isinstance(static_initialise(t[f], imu.gyro[f], imu.accel[f]), NotStill)
