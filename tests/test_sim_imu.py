"""The IMU model: noise of the datasheet's density at the sampling rate, biases that random-walk
at the configured rate, exact truth when switched off, and repeatable from a seed; in the
realistic profile, rotor vibration that aliases as PX4's integrate-then-sample pipeline makes it,
a per-run scale-and-misalignment matrix, and a turn-on bias that warms up exponentially."""

import dataclasses
import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY
from autonomy.options import OptionError
from drivers.sim.imu import ImuModel, ImuOptions, px4_accel_scales
from drivers.sim.quadrotor import ImuTruth

TRUTH = ImuTruth(angular_velocity=np.array([0.1, -0.2, 0.3]),
                 specific_force=np.array([0.5, -0.4, GRAVITY]))
#: Level hover: the specific force's magnitude is exactly g, so vibration runs at its hover
#: frequency and amplitude.
HOVER = ImuTruth(angular_velocity=np.zeros(3), specific_force=np.array([0.0, 0.0, GRAVITY]))
IDEAL = ImuOptions().for_profile("ideal")
#: No white noise and no random walk: only the effect under test is left.
QUIET = dataclasses.replace(IDEAL, gyro_noise_density=0.0, accel_noise_density=0.0,
                            gyro_bias_random_walk=0.0, accel_bias_random_walk=0.0)


def samples(model, count, dt, truth=TRUTH, **kwargs):
    """(count, 6) measurements minus truth: gyro then accel."""
    out = np.empty((count, 6))
    for k in range(count):
        gyro, accel = model.measure(truth, dt, **kwargs)
        out[k, :3] = gyro - truth.angular_velocity
        out[k, 3:] = accel - truth.specific_force
    return out


def test_defaults_are_the_icm42688p_datasheet_densities():
    options = ImuOptions()
    assert options.rate_hz == 200.0
    assert options.gyro_noise_density == pytest.approx(0.0028 * math.pi / 180.0)
    assert options.accel_noise_density == pytest.approx(70e-6 * GRAVITY)
    assert options.period == pytest.approx(0.005)


def test_realistic_defaults_are_the_cited_figures():
    options = ImuOptions()
    # PX4-gazebo-models x500: hover rotor speed sqrt(m g / (4 k)), m = 2.0 kg + 4 rotors.
    hover = math.sqrt((2.0 + 4 * 0.016076923076923075) * GRAVITY / (4 * 8.54858e-06))
    assert options.vibration_frequency_hz == pytest.approx(hover / (2 * math.pi), abs=0.1)
    assert options.vibration_cutoff_hz == 0.0  # PX4's IMU_*_CUTOFF filter only the controllers
    assert options.accel_vibration_amplitude == pytest.approx(GRAVITY / 2)
    # ICM-42688-P (DS-000347): sensitivity tolerance 0.5 %, cross-axis 1.25 % / 1 %.
    assert (options.gyro_scale_error, options.gyro_cross_axis) == (0.005, 0.0125)
    assert (options.accel_scale_error, options.accel_cross_axis) == (0.005, 0.01)
    assert options.accel_calibrated and options.accel_calibration_tilt_deg == 3.0  # assumed
    # PX4's calibration dead bands (0.01 rad/s, 0.05 m/s^2, vector norms) over three axes.
    assert options.gyro_turn_on_bias * math.sqrt(3) == pytest.approx(0.01)
    assert options.accel_turn_on_bias * math.sqrt(3) == pytest.approx(0.05)
    # Datasheet temperature coefficients (0.005 dps/degC, 0.15 mg/degC) over 20 degC.
    assert options.gyro_warmup_drift == pytest.approx(math.radians(0.1))
    assert options.accel_warmup_drift == pytest.approx(3e-3 * GRAVITY)


def test_ideal_profile_is_the_noise_and_walk_model_bit_for_bit():
    """The ideal profile reproduces, to the last bit, what the model gave before the realistic
    error sources existed (numbers recorded from that model, seed 7)."""
    model = ImuModel(IDEAL, np.random.default_rng(7))
    out = np.array([np.concatenate(model.measure(TRUTH, 0.005)) for _ in range(1000)])
    assert out[0].tolist() == [0.10004156784024938, -0.19907334730734622, 0.2996594527079413,
                               0.4937874518868769, -0.3953410204103683, 9.809904330552296]
    assert out[1].tolist() == [0.09868618245161065, -0.20089208531069927, 0.29872673302561614,
                               0.49767628758661436, -0.4126860834383328, 9.808976023358086]
    assert out[999].tolist() == [0.1012292182612372, -0.19987460887982184, 0.29993212995482177,
                                 0.511495359245413, -0.39440519915193584, 9.799756680103403]
    assert float(out.sum()) == 10099.652247060407
    assert np.concatenate([model.gyro_bias, model.accel_bias]).tolist() == [
        -2.3938555440684427e-05, -1.362599159708798e-05, 1.9042882957915013e-05,
        -0.004985674332513249, 0.0009101960389189178, -0.00015692211612258674]


def test_profiles_switch_only_the_new_effects():
    options = ImuOptions(rate_hz=400.0, gyro_noise_density=1e-4)
    assert options.for_profile("realistic") is options
    ideal = options.for_profile("ideal")
    kept = ("rate_hz", "gyro_noise_density", "accel_noise_density", "gyro_bias_random_walk",
            "accel_bias_random_walk", "enabled")
    assert all(getattr(ideal, name) == getattr(options, name) for name in kept)
    for name in ("accel_vibration_amplitude", "gyro_vibration_amplitude", "gyro_scale_error",
                 "gyro_cross_axis", "accel_scale_error", "accel_cross_axis",
                 "gyro_turn_on_bias", "accel_turn_on_bias", "gyro_warmup_drift",
                 "accel_warmup_drift"):
        assert getattr(ideal, name) == 0.0 < getattr(options, name), name
    model = ImuModel(ideal, np.random.default_rng(0))
    np.testing.assert_array_equal(model.gyro_matrix, np.eye(3))
    np.testing.assert_array_equal(model.accel_matrix, np.eye(3))
    with pytest.raises(ValueError, match="ideal, realistic; got 'perfect'"):
        options.for_profile("perfect")


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
    options = dataclasses.replace(IDEAL, gyro_bias_random_walk=0.0, accel_bias_random_walk=0.0)
    errors = samples(ImuModel(options, np.random.default_rng(1)), 40_000, 1.0 / rate_hz)
    expected = np.array([options.gyro_noise_density] * 3 + [options.accel_noise_density] * 3)
    expected *= math.sqrt(rate_hz)
    # The sample std of n normal draws has relative standard error 1/sqrt(2n) = 0.35 %;
    # 3 % is more than 8 of those, yet far below any discretisation mistake (sqrt(rate) or
    # a dt where 1/dt belongs is off by a factor of 14 or more).
    np.testing.assert_allclose(errors.std(axis=0), expected, rtol=0.03)
    np.testing.assert_allclose(errors.mean(axis=0), 0.0, atol=float(expected.max()) * 0.03)


def test_bias_random_walk_grows_as_root_time():
    options = dataclasses.replace(IDEAL, gyro_noise_density=0.0, accel_noise_density=0.0)
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
    options = dataclasses.replace(IDEAL, gyro_noise_density=0.0, accel_noise_density=0.0)
    model = ImuModel(options, np.random.default_rng(4))
    for _ in range(100):
        gyro, accel = model.measure(TRUTH, 0.005)
    np.testing.assert_allclose(gyro, TRUTH.angular_velocity + model.gyro_bias, atol=1e-15)
    np.testing.assert_allclose(accel, TRUTH.specific_force + model.accel_bias, atol=1e-15)
    assert np.all(model.gyro_bias != 0.0)


def test_the_reported_bias_is_exactly_what_a_realistic_sample_adds_after_the_matrix():
    """Ground-truth files get the whole bias (turn-on, warm-up, walk) and nothing else: no
    vibration, no scale error."""
    options = ImuOptions(gyro_noise_density=0.0, accel_noise_density=0.0,
                         accel_vibration_amplitude=0.0, gyro_vibration_amplitude=0.0)
    model = ImuModel(options, np.random.default_rng(5))
    for _ in range(200):
        gyro, accel = model.measure(TRUTH, 0.005)
    np.testing.assert_allclose(gyro, model.gyro_matrix @ TRUTH.angular_velocity
                               + model.gyro_bias, atol=1e-14)
    np.testing.assert_allclose(accel, model.accel_matrix @ TRUTH.specific_force
                               + model.accel_bias, atol=1e-13)
    # Larger than the walk alone could have grown in one second: the turn-on bias is in it.
    assert np.linalg.norm(model.accel_bias) > 5 * options.accel_bias_random_walk


def test_the_same_seed_gives_the_same_noise():
    a = samples(ImuModel(ImuOptions(), np.random.default_rng(7)), 50, 0.005)
    b = samples(ImuModel(ImuOptions(), np.random.default_rng(7)), 50, 0.005)
    c = samples(ImuModel(ImuOptions(), np.random.default_rng(8)), 50, 0.005)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_a_vehicle_keeps_its_matrices_from_flight_to_flight():
    """A vehicle generator seeded as the flight's changes nothing; another flight of the same
    vehicle has its matrices and a noise of its own."""
    alone = ImuModel(ImuOptions(), np.random.default_rng([7, 1]))
    same = ImuModel(ImuOptions(), np.random.default_rng([7, 1]), np.random.default_rng([7, 1]))
    np.testing.assert_array_equal(samples(alone, 50, 0.005), samples(same, 50, 0.005))
    other_flight = ImuModel(ImuOptions(), np.random.default_rng([8, 1]),
                            np.random.default_rng([7, 1]))
    np.testing.assert_array_equal(other_flight.gyro_matrix, alone.gyro_matrix)
    np.testing.assert_array_equal(other_flight.accel_matrix, alone.accel_matrix)
    other_vehicle = ImuModel(ImuOptions(), np.random.default_rng([8, 1]))
    assert not np.array_equal(other_vehicle.gyro_matrix, alone.gyro_matrix)
    # the turn-on bias comes with the power-up, so with the flight
    np.testing.assert_array_equal(other_flight.gyro_bias, other_vehicle.gyro_bias)
    assert not np.array_equal(other_flight.gyro_bias, alone.gyro_bias)


def run_of(options, count=400, thrust=None):
    """Per sample of seed 9 at TRUTH: the output, and the bias it carried (gyro then accel)."""
    model = ImuModel(options, np.random.default_rng(9))
    outputs, biases = [], []
    for _ in range(count):
        outputs.append(np.concatenate(model.measure(TRUTH, 0.005, thrust=thrust)))
        biases.append(np.concatenate([model.gyro_bias, model.accel_bias]))
    return model, np.array(outputs), np.array(biases)


def test_switching_one_error_source_off_leaves_the_others_draws_as_they_were():
    """An ablation changes one thing: each source has a stream of its own."""
    realistic = ImuOptions()
    base, _, base_biases = run_of(realistic)
    no_matrices = dataclasses.replace(realistic, gyro_scale_error=0.0, gyro_cross_axis=0.0,
                                      accel_scale_error=0.0, accel_cross_axis=0.0)
    no_biases = dataclasses.replace(realistic, gyro_turn_on_bias=0.0, accel_turn_on_bias=0.0,
                                    gyro_warmup_drift=0.0, accel_warmup_drift=0.0)
    no_vibration = dataclasses.replace(realistic, accel_vibration_amplitude=0.0,
                                       gyro_vibration_amplitude=0.0)
    # Without the matrices, the biases (turn-on, warm-up and walk) are the same numbers.
    np.testing.assert_array_equal(run_of(no_matrices)[2], base_biases)
    # Without the turn-on and warm-up biases, the matrices are the same, and so is the walk.
    model, _, walk_only = run_of(no_biases)
    np.testing.assert_array_equal(model.accel_matrix, base.accel_matrix)
    np.testing.assert_array_equal(model.gyro_matrix, base.gyro_matrix)
    np.testing.assert_array_equal(run_of(IDEAL)[2], walk_only)
    # Without vibration, every sample is what the realistic model gives with its rotors
    # stopped (thrust 0: no vibration, though its phase walk still draws).
    np.testing.assert_array_equal(run_of(no_vibration)[1], run_of(realistic, thrust=0.0)[1])
    assert not np.array_equal(run_of(no_vibration)[1], run_of(realistic)[1])


# --- motor vibration ---------------------------------------------------------------------------

def vibration_options(**changes):
    """Only vibration, with its realistic amplitudes; a steady phase unless changed."""
    realistic = ImuOptions()
    changes = {"accel_vibration_amplitude": realistic.accel_vibration_amplitude,
               "gyro_vibration_amplitude": realistic.gyro_vibration_amplitude,
               "vibration_phase_walk": 0.0, **changes}
    return dataclasses.replace(QUIET, **changes)


def peak_frequency(signal, rate_hz):
    """Frequency of the largest line of ``signal`` (Hann window, zero-padded 8 times)."""
    n = len(signal)
    spectrum = np.abs(np.fft.rfft((signal - signal.mean()) * np.hanning(n), n=8 * n))
    return float(np.fft.rfftfreq(8 * n, 1.0 / rate_hz)[spectrum.argmax()])


def passband(frequency, dt, cutoff=0.0):
    """|gain| of PX4's path: a Butterworth of ``cutoff`` (0: none), then the average over the
    sample's window of ``dt`` (VehicleIMU's integrator, HIGHRES_IMU = delta / dt)."""
    gain = abs(math.sin(math.pi * frequency * dt) / (math.pi * frequency * dt))
    if cutoff:
        gain /= math.sqrt(1.0 + (frequency / cutoff) ** 4)
    return gain


@pytest.mark.parametrize("rate_hz, rotor_hz, cutoff_hz, alias_hz", [
    (200.0, 122.5, 0.0, 77.5),     # the default: |122.5 - 200|
    (200.0, 330.0, 0.0, 70.0),     # |330 - 2 x 200|
    (200.0, 122.5, 30.0, 77.5),    # a controller-style 30 Hz Butterworth ahead of sampling
    (1000.0, 122.5, 0.0, 122.5),   # below Nyquist: no alias
])
def test_vibration_appears_at_its_alias_with_the_pipelines_attenuation(
        rate_hz, rotor_hz, cutoff_hz, alias_hz):
    options = vibration_options(rate_hz=rate_hz, vibration_frequency_hz=rotor_hz,
                                vibration_cutoff_hz=cutoff_hz)
    dt = 1.0 / rate_hz
    errors = samples(ImuModel(options, np.random.default_rng(11)), 16_384, dt, truth=HOVER)
    gain = passband(rotor_hz, dt, cutoff_hz)
    for axis in range(6):
        # 16384 samples: a bin of 0.012 Hz at 200 Hz, 0.06 Hz at 1 kHz.
        assert peak_frequency(errors[:, axis], rate_hz) == pytest.approx(alias_hz, abs=0.05)
    # A sinusoid of amplitude a has RMS a / sqrt(2); 16384 samples hold 6000+ cycles.
    rms = np.sqrt(np.mean(errors ** 2, axis=0))
    np.testing.assert_allclose(rms[:3], options.gyro_vibration_amplitude * gain / math.sqrt(2),
                               rtol=0.01)
    np.testing.assert_allclose(rms[3:], options.accel_vibration_amplitude * gain / math.sqrt(2),
                               rtol=0.01)


def test_the_wandering_rotor_phase_keeps_the_line_at_its_alias():
    options = vibration_options(vibration_phase_walk=ImuOptions().vibration_phase_walk)
    errors = samples(ImuModel(options, np.random.default_rng(12)), 16_384, 0.005, truth=HOVER)
    assert peak_frequency(errors[:, 5], 200.0) == pytest.approx(77.5, abs=0.5)
    gain = passband(options.vibration_frequency_hz, 0.005)
    assert np.sqrt(np.mean(errors[:, 5] ** 2)) == pytest.approx(
        options.accel_vibration_amplitude * gain / math.sqrt(2), rel=0.02)


def test_vibration_follows_the_rotor_thrust():
    options = vibration_options()
    still = samples(ImuModel(options, np.random.default_rng(13)), 100, 0.005, truth=HOVER,
                    thrust=0.0)
    np.testing.assert_array_equal(still, 0.0)  # motors off: nothing shakes
    # A quarter of hover thrust: rotors at half speed (61.25 Hz, below Nyquist), a quarter of the
    # imbalance force.
    quarter = samples(ImuModel(options, np.random.default_rng(13)), 16_384, 0.005, truth=HOVER,
                      thrust=GRAVITY / 4)
    assert peak_frequency(quarter[:, 3], 200.0) == pytest.approx(61.25, abs=0.05)
    expected = options.accel_vibration_amplitude / 4 * passband(61.25, 0.005) / math.sqrt(2)
    assert np.sqrt(np.mean(quarter[:, 3] ** 2)) == pytest.approx(expected, rel=0.01)


# --- scale factor and misalignment -------------------------------------------------------------

def test_a_constant_truth_reads_as_the_runs_matrix_times_it():
    options = dataclasses.replace(QUIET, gyro_scale_error=0.005, gyro_cross_axis=0.0125,
                                  accel_scale_error=0.005, accel_cross_axis=0.01)
    model = ImuModel(options, np.random.default_rng(21))
    gyro_matrix, accel_matrix = model.gyro_matrix, model.accel_matrix
    assert not np.allclose(gyro_matrix, np.eye(3)) and not np.allclose(accel_matrix, np.eye(3))
    for truth in (TRUTH, HOVER, ImuTruth(np.array([2.0, 0.0, -1.0]), np.array([0.0, 9.0, 3.0]))):
        for _ in range(50):  # fixed for the whole run
            gyro, accel = model.measure(truth, 0.005)
            np.testing.assert_allclose(gyro, gyro_matrix @ truth.angular_velocity, atol=1e-15)
            np.testing.assert_allclose(accel, accel_matrix @ truth.specific_force, atol=1e-14)
    np.testing.assert_array_equal(model.gyro_matrix, gyro_matrix)


def test_the_matrices_spread_as_the_datasheet_tolerances_from_run_to_run():
    options = dataclasses.replace(ImuOptions(), accel_calibrated=False)  # the chip's own
    diagonal = np.eye(3, dtype=bool)
    gyro, accel = [], []
    for seed in range(1000):
        model = ImuModel(options, np.random.default_rng(seed))
        gyro.append(model.gyro_matrix - np.eye(3))
        accel.append(model.accel_matrix - np.eye(3))
    gyro, accel = np.array(gyro), np.array(accel)
    # 3000 diagonal and 6000 off-diagonal draws: relative standard errors of the std 1.3 %
    # and 0.9 %; 6 % is over four of those.
    for errors, scale, cross in ((gyro, options.gyro_scale_error, options.gyro_cross_axis),
                                 (accel, options.accel_scale_error, options.accel_cross_axis)):
        assert errors[:, diagonal].std() == pytest.approx(scale, rel=0.06)
        assert errors[:, ~diagonal].std() == pytest.approx(cross, rel=0.06)
        assert abs(errors[:, ~diagonal].mean()) < 0.1 * cross


# --- PX4's six-orientation accelerometer calibration -----------------------------------------

#: PX4's orientations (accelerometer_calibration.cpp), FRD: tail down, nose down, left, right,
#: upside down, right side up.
PX4_REFERENCES = GRAVITY * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1],
                                     [0, 0, -1]], dtype=float)


def test_px4_scales_take_a_sensitivity_error_out_whatever_the_offset():
    sensitivity = np.array([1.004, 0.995, 1.003])
    offset = np.array([0.03, -0.02, 0.05])
    scales = px4_accel_scales(PX4_REFERENCES * sensitivity + offset)
    np.testing.assert_allclose(scales, 1.0 / sensitivity, rtol=1e-14)


def test_px4_scales_read_a_tilted_placement_as_too_little_sensitivity():
    """Tail down tilted by d about y reads g (cos d, 0, -sin d): the x offset is -c with
    c = g (1 - cos d) / 2, so A = [[a, 0, b], [c, g, 0], [c, 0, g]] with a = g (1 + cos d) / 2
    and b = -g sin d; det A = g (a g - b c), and the scales are g diag(A^-1) = g (g^2, a g - b c,
    a g) / det A: x too large by about d^2 / 4, z too small by far less (-b c / g^2)."""
    tilt = math.radians(4.0)
    readings = PX4_REFERENCES.copy()
    readings[0] = GRAVITY * np.array([math.cos(tilt), 0.0, -math.sin(tilt)])
    g, a, b, c = (GRAVITY, GRAVITY * (1 + math.cos(tilt)) / 2, -GRAVITY * math.sin(tilt),
                  GRAVITY * (1 - math.cos(tilt)) / 2)
    determinant = g * (a * g - b * c)
    np.testing.assert_allclose(px4_accel_scales(readings),
                               g * np.array([g * g, a * g - b * c, a * g]) / determinant,
                               rtol=1e-14)


def test_calibration_divides_the_accelerometer_rows_and_leaves_the_gyro_alone():
    raw = dataclasses.replace(ImuOptions(), accel_calibrated=False)
    for seed in range(20):
        calibrated = ImuModel(ImuOptions(), np.random.default_rng(seed))
        chip = ImuModel(raw, np.random.default_rng(seed))
        scales = np.diag(calibrated.accel_matrix) / np.diag(chip.accel_matrix)
        np.testing.assert_allclose(calibrated.accel_matrix, np.diag(scales) @ chip.accel_matrix,
                                   rtol=1e-12)
        np.testing.assert_array_equal(calibrated.gyro_matrix, chip.gyro_matrix)
        assert np.abs(scales - 1.0).max() < 0.05


def test_level_placements_leave_only_second_order_sensitivity_and_the_cross_axis_terms():
    level = dataclasses.replace(ImuOptions(), accel_calibration_tilt_deg=0.0)
    raw = dataclasses.replace(ImuOptions(), accel_calibrated=False)
    off_diagonal = ~np.eye(3, dtype=bool)
    for seed in range(200):
        calibrated = ImuModel(level, np.random.default_rng(seed)).accel_matrix
        chip = ImuModel(raw, np.random.default_rng(seed)).accel_matrix
        # (M^-1)_ii M_ii - 1 is a product of two errors of 1 %: far under the chip's 0.5 %.
        assert np.abs(np.diag(calibrated) - 1.0).max() < 1e-3
        np.testing.assert_allclose(calibrated[off_diagonal], chip[off_diagonal], atol=5e-4)


def test_a_placements_tilt_leaves_scales_too_large_by_about_its_square():
    """Each scale is 2 / (cos d+ + cos d-) to leading order, d+- the two placements' tilts
    (two components of N(0, t^2) each): on average 1 + t^2."""
    tilt = math.radians(3.0)
    options = ImuOptions()
    diagonals = np.array([np.diag(ImuModel(options, np.random.default_rng(seed)).accel_matrix)
                          for seed in range(1000)])
    # 3000 axes of a spread about 1.7 t^2: the mean's standard error is about 3 % of t^2.
    assert diagonals.mean() - 1.0 == pytest.approx(tilt**2, rel=0.15)
    assert (diagonals > 1.0).mean() > 0.6


# --- turn-on bias and warm-up ------------------------------------------------------------------

def warmup_options(**changes):
    realistic = ImuOptions()
    return dataclasses.replace(
        QUIET, gyro_turn_on_bias=realistic.gyro_turn_on_bias,
        accel_turn_on_bias=realistic.accel_turn_on_bias,
        gyro_warmup_drift=realistic.gyro_warmup_drift,
        accel_warmup_drift=realistic.accel_warmup_drift, **changes)


def test_the_bias_warms_up_exponentially_to_its_final_value_with_time_constant_tau():
    options = warmup_options()
    tau = options.warmup_time_constant_s
    model = ImuModel(options, np.random.default_rng(31))
    start_model = ImuModel(options, np.random.default_rng(31))
    start_model.measure(HOVER, 1e-9)
    start = np.concatenate([start_model.gyro_bias, start_model.accel_bias])
    times, biases = [], []
    for _ in range(3000):  # 10 tau in steps of 1 s
        errors = samples(model, 1, 1.0, truth=HOVER)[0]
        biases.append(np.concatenate([model.gyro_bias, model.accel_bias]))
        np.testing.assert_allclose(errors, biases[-1], atol=1e-14)  # what the sample carries
        times.append(model.time)
    times, biases = np.array(times), np.array(biases)
    final = biases[-1]
    assert np.all(np.abs(final - start) > 1e-6)
    # b(t) = b_final + (b_0 - b_final) exp(-t / tau), to the end of warm-up (exp(-10) left).
    expected = final + (start - final) * np.exp(-times / tau)[:, None]
    np.testing.assert_allclose(biases, expected, atol=1e-4 * np.abs(final - start).max())
    # After one time constant 1/e of the change is left, after three 5 %.
    at_tau = biases[np.searchsorted(times, tau)]
    np.testing.assert_allclose((at_tau - final) / (start - final), math.exp(-1.0), rtol=1e-3)


def test_turn_on_and_warm_up_biases_spread_as_configured_from_run_to_run():
    options = warmup_options()
    starts, changes = [], []
    for seed in range(1000):
        model = ImuModel(options, np.random.default_rng(seed))
        model.measure(HOVER, 1e-9)
        start = np.concatenate([model.gyro_bias, model.accel_bias])
        model.measure(HOVER, 100 * options.warmup_time_constant_s)
        starts.append(start)
        changes.append(np.concatenate([model.gyro_bias, model.accel_bias]) - start)
    starts, changes = np.array(starts), np.array(changes)
    # 3000 draws per sensor: relative standard error of the std 1.3 %.
    assert starts[:, :3].std() == pytest.approx(options.gyro_turn_on_bias, rel=0.06)
    assert starts[:, 3:].std() == pytest.approx(options.accel_turn_on_bias, rel=0.06)
    assert changes[:, :3].std() == pytest.approx(options.gyro_warmup_drift, rel=0.06)
    assert changes[:, 3:].std() == pytest.approx(options.accel_warmup_drift, rel=0.06)


def test_bad_inputs_are_rejected():
    model = ImuModel(ImuOptions(), np.random.default_rng(0))
    for dt in (0.0, -0.005, math.nan, math.inf):
        with pytest.raises(ValueError, match="dt must be a positive"):
            model.measure(TRUTH, dt)
    for thrust in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="thrust must be a finite number >= 0"):
            model.measure(TRUTH, 0.005, thrust=thrust)
    with pytest.raises(TypeError, match="numpy.random.Generator"):
        ImuModel(ImuOptions(), 42)
    with pytest.raises(OptionError, match="gyro_noise_density"):
        ImuOptions(gyro_noise_density=-1e-4)
    with pytest.raises(OptionError, match="rate_hz"):
        ImuOptions(rate_hz=0.0)
    with pytest.raises(OptionError, match="enabled"):
        ImuOptions(enabled="yes")
    for name, value in (("accel_vibration_amplitude", -1.0), ("gyro_vibration_amplitude", 50.0),
                        ("vibration_frequency_hz", 0.0), ("vibration_cutoff_hz", -30.0),
                        ("vibration_phase_walk", math.nan), ("gyro_scale_error", 0.5),
                        ("accel_cross_axis", -0.01), ("gyro_turn_on_bias", -1e-3),
                        ("accel_warmup_drift", math.inf), ("warmup_time_constant_s", 0.0),
                        ("accel_calibration_tilt_deg", -1.0), ("accel_calibrated", "yes")):
        with pytest.raises(OptionError, match=name):
            ImuOptions(**{name: value})
