"""The simulated barometer (drivers/sim/baro.py): PX4's air data, its rate and its errors."""

import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY
from drivers.sim.baro import (
    AIR_GAS_CONSTANT, Barometer, BaroOptions, baro_generator, isa_pressure, isa_temperature,
    pressure_altitude,
)

HOME = 488.0  # PX4 SITL's home altitude, metres (drivers.sim.mock_px4.HOME_ALTITUDE_M)
STILL = np.zeros(3)


def samples(options: BaroOptions, seconds: float, height=0.0, velocity=STILL, seed=0,
            dt=0.005) -> list:
    """What the barometer gives, called every ``dt`` as the physics ticks, in ``seconds``."""
    barometer = Barometer(options, np.random.default_rng(seed), HOME)
    taken = [barometer.sample(k * dt, height, velocity) for k in range(int(seconds / dt))]
    return [sample for sample in taken if sample is not None]


def density_at_home() -> float:
    return isa_pressure(HOME) / (AIR_GAS_CONSTANT * isa_temperature(HOME))


EXACT = BaroOptions(noise_pa=0.0, drift_pa_per_sqrt_s=0.0, dynamic_pressure_coefficient=0.0)


def test_the_isa_pressure_reads_back_as_its_altitude_a_metre_per_metre():
    """PX4 SITL's ISA (288 K, exponent 5.256) and PX4's reading of it (288.15 K, the
    hypsometric equation) differ by under 0.4 m and 0.1 % of the altitude; their slopes agree
    to 0.2 %."""
    assert isa_pressure(0.0) == pytest.approx(101325.0)
    for altitude in (0.0, HOME, 2000.0):
        assert pressure_altitude(isa_pressure(altitude)) == pytest.approx(
            altitude, abs=0.4 + 1e-3 * altitude)
        climb = pressure_altitude(isa_pressure(altitude + 1.0)) - pressure_altitude(
            isa_pressure(altitude))
        assert climb == pytest.approx(1.0, abs=0.002)
    # a higher sea-level pressure (QNH) reads the same pressure as higher
    assert pressure_altitude(95000.0, qnh_hpa=1020.0) > pressure_altitude(95000.0) + 50.0


def test_samples_come_at_the_rate_whatever_the_tick():
    """20 Hz on 200 Hz ticks, and on 50 Hz or 33 Hz ticks, which do not divide its period."""
    for dt in (0.005, 0.02, 0.03):
        assert len(samples(EXACT, 2.0, dt=dt)) == 40


def test_a_still_vehicle_reads_its_height_with_the_white_noise_in_metres():
    """2 Pa at 488 m is 2 / (rho g) = 0.17 m; the exact barometer reads the ISA itself."""
    exact = samples(EXACT, 1.0, height=3.0)
    assert exact[0].pressure_pa == pytest.approx(isa_pressure(HOME + 3.0))
    assert exact[0].temperature_c == pytest.approx(isa_temperature(HOME + 3.0) - 273.15)
    noisy = samples(BaroOptions().for_profile("ideal"), 100.0, height=3.0)
    heights = np.array([sample.altitude_m for sample in noisy])
    assert np.std(heights) == pytest.approx(2.0 / (density_at_home() * GRAVITY), rel=0.1)
    assert np.mean(heights) == pytest.approx(exact[0].altitude_m, abs=0.02)


def test_the_drift_walks_as_its_density_says():
    """Over 100 s a walk of 0.2 Pa/sqrt(s) spreads to 2 Pa over independent vehicles."""
    drifting = BaroOptions(noise_pa=0.0, dynamic_pressure_coefficient=0.0)
    ends = [samples(drifting, 100.0, seed=seed, dt=0.05)[-1].pressure_pa
            for seed in range(60)]
    assert np.std(ends) == pytest.approx(0.2 * math.sqrt(100.0), rel=0.3)
    assert samples(drifting.for_profile("ideal"), 10.0)[-1].pressure_pa == pytest.approx(
        isa_pressure(HOME))


def test_flying_forward_raises_the_static_pressure_by_its_share_of_the_dynamic():
    """C q at 2 m/s: 0.2 x rho v^2 / 2, about half a pascal, 4 cm read low; climbing does not
    count (the coefficient is the horizontal flight's)."""
    options = BaroOptions(noise_pa=0.0, drift_pa_per_sqrt_s=0.0)
    hover = samples(options, 0.1)[0]
    cruise = samples(options, 0.1, velocity=np.array([0.0, 2.0, 0.0]))[0]
    climb = samples(options, 0.1, velocity=np.array([0.0, 0.0, 2.0]))[0]
    expected = 0.2 * 0.5 * density_at_home() * 4.0
    assert cruise.pressure_pa - hover.pressure_pa == pytest.approx(expected, rel=1e-6)
    assert hover.altitude_m - cruise.altitude_m == pytest.approx(0.04, abs=0.005)
    assert climb.pressure_pa == hover.pressure_pa
    assert samples(options.for_profile("ideal"), 0.1, velocity=np.array([2.0, 0.0, 0.0])
                   )[0].pressure_pa == pytest.approx(isa_pressure(HOME))


def test_a_flight_controller_without_a_barometer_gives_none():
    assert samples(BaroOptions(enabled=False), 1.0) == []


def test_a_seed_gives_the_same_samples_and_its_own_stream():
    first = samples(BaroOptions(), 1.0, seed=3)
    assert first == samples(BaroOptions(), 1.0, seed=3)
    assert first != samples(BaroOptions(), 1.0, seed=4)
    # the flight's other generators (drivers.sim.serve, drivers.sim.imu) are children 0-2
    drawn = baro_generator(5).standard_normal(3)
    for child in np.random.SeedSequence(5).spawn(3):
        assert not np.allclose(np.random.default_rng(child).standard_normal(3), drawn)


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="rate_hz"):
        BaroOptions(rate_hz=0.0)
    with pytest.raises(ValueError, match="noise_pa"):
        BaroOptions(noise_pa=-1.0)
    with pytest.raises(ValueError, match="profile"):
        BaroOptions().for_profile("perfect")
