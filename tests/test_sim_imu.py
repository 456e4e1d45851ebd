"""The IMU model: noise of the datasheet's density at the sampling rate, biases that random-walk
at the configured rate, exact truth when switched off, and repeatable from a seed."""

import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY
from autonomy.options import OptionError
from drivers.sim.imu import ImuModel, ImuOptions
from drivers.sim.quadrotor import ImuTruth

TRUTH = ImuTruth(angular_velocity=np.array([0.1, -0.2, 0.3]),
                 specific_force=np.array([0.5, -0.4, GRAVITY]))


def samples(model, count, dt):
    """(count, 6) measurements minus truth: gyro then accel."""
    out = np.empty((count, 6))
    for k in range(count):
        gyro, accel = model.measure(TRUTH, dt)
        out[k, :3] = gyro - TRUTH.angular_velocity
        out[k, 3:] = accel - TRUTH.specific_force
    return out


def test_defaults_are_the_icm42688p_datasheet_densities():
    options = ImuOptions()
    assert options.rate_hz == 200.0
    assert options.gyro_noise_density == pytest.approx(0.0028 * math.pi / 180.0)
    assert options.accel_noise_density == pytest.approx(70e-6 * GRAVITY)
    assert options.period == pytest.approx(0.005)


def test_disabled_noise_returns_the_truth_exactly():
    model = ImuModel(ImuOptions(enabled=False), np.random.default_rng(0))
    for _ in range(10):
        gyro, accel = model.measure(TRUTH, 0.005)
    np.testing.assert_array_equal(gyro, TRUTH.angular_velocity)
    np.testing.assert_array_equal(accel, TRUTH.specific_force)
    np.testing.assert_array_equal(model.gyro_bias, 0.0)
    np.testing.assert_array_equal(model.accel_bias, 0.0)


@pytest.mark.parametrize("rate_hz", [200.0, 1000.0])
def test_white_noise_std_is_density_times_root_rate(rate_hz):
    options = ImuOptions(gyro_bias_random_walk=0.0, accel_bias_random_walk=0.0)
    errors = samples(ImuModel(options, np.random.default_rng(1)), 40_000, 1.0 / rate_hz)
    expected = np.array([options.gyro_noise_density] * 3 + [options.accel_noise_density] * 3)
    expected *= math.sqrt(rate_hz)
    # The sample std of n normal draws has relative standard error 1/sqrt(2n) = 0.35 %;
    # 3 % is more than 8 of those, yet far below any discretisation mistake (sqrt(rate) or
    # a dt where 1/dt belongs is off by a factor of 14 or more).
    np.testing.assert_allclose(errors.std(axis=0), expected, rtol=0.03)
    np.testing.assert_allclose(errors.mean(axis=0), 0.0, atol=float(expected.max()) * 0.03)


def test_bias_random_walk_grows_as_root_time():
    options = ImuOptions(gyro_noise_density=0.0, accel_noise_density=0.0)
    model = ImuModel(options, np.random.default_rng(2))
    dt, window_s, windows = 0.005, 1.0, 400
    steps = round(window_s / dt)
    biases = np.empty((windows + 1, 6))
    biases[0] = 0.0
    for w in range(1, windows + 1):
        samples(model, steps, dt)
        biases[w] = np.concatenate([model.gyro_bias, model.accel_bias])
    walks = np.array([options.gyro_bias_random_walk] * 3 + [options.accel_bias_random_walk] * 3)
    # Increments over disjoint windows are independent, each N(0, rw^2 T): over 1 s windows
    # 1200 of them per sensor (relative standard error of the std 2 %), over 20 s windows 60
    # (9 %). Both give rw, so the spread grows as sqrt(T).
    for window in (1, 20):
        increments = np.diff(biases[::window], axis=0) / math.sqrt(window * window_s)
        for sensor in (slice(0, 3), slice(3, 6)):
            measured = np.sqrt(np.mean(increments[:, sensor] ** 2))
            assert measured == pytest.approx(walks[sensor][0], rel=0.1 if window == 1 else 0.3)


def test_measurements_include_the_current_bias():
    options = ImuOptions(gyro_noise_density=0.0, accel_noise_density=0.0)
    model = ImuModel(options, np.random.default_rng(4))
    for _ in range(100):
        gyro, accel = model.measure(TRUTH, 0.005)
    np.testing.assert_allclose(gyro, TRUTH.angular_velocity + model.gyro_bias, atol=1e-15)
    np.testing.assert_allclose(accel, TRUTH.specific_force + model.accel_bias, atol=1e-15)
    assert np.all(model.gyro_bias != 0.0)


def test_the_same_seed_gives_the_same_noise():
    a = samples(ImuModel(ImuOptions(), np.random.default_rng(7)), 50, 0.005)
    b = samples(ImuModel(ImuOptions(), np.random.default_rng(7)), 50, 0.005)
    c = samples(ImuModel(ImuOptions(), np.random.default_rng(8)), 50, 0.005)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_bad_inputs_are_rejected():
    model = ImuModel(ImuOptions(), np.random.default_rng(0))
    for dt in (0.0, -0.005, math.nan, math.inf):
        with pytest.raises(ValueError, match="dt must be a positive"):
            model.measure(TRUTH, dt)
    with pytest.raises(TypeError, match="numpy.random.Generator"):
        ImuModel(ImuOptions(), 42)
    with pytest.raises(OptionError, match="gyro_noise_density"):
        ImuOptions(gyro_noise_density=-1e-4)
    with pytest.raises(OptionError, match="rate_hz"):
        ImuOptions(rate_hz=0.0)
    with pytest.raises(OptionError, match="enabled"):
        ImuOptions(enabled="yes")
