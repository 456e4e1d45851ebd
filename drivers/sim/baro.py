"""The barometer model: the static pressure PX4 publishes as ``vehicle_air_data``, which its
HIGHRES_IMU carries to the companion (``abs_pressure``, ``pressure_alt``, ``temperature``).

A sample is taken every ``1 / rate_hz`` of simulated time (PX4 publishes air data at most at
``SENS_BARO_RATE``, 20 Hz by default: ``src/modules/sensors/vehicle_air_data/params.c``; PX4's
own SITL barometer runs at 20 Hz, ``src/modules/simulation/sensor_baro_sim/SensorBaroSim.cpp``,
``ScheduleOnInterval(50_ms)``). Its pressure, Pa::

    p = p_ISA(h_AMSL) + n + d(t) + C q,    q = rho |v_horizontal|^2 / 2

1. ``p_ISA``: the International Standard Atmosphere's troposphere, as PX4's SITL barometer
   computes it (``SensorBaroSim.cpp``): ``T = 288 - 0.0065 h`` K, ``p = 101325 / (288 / T) ^
   5.256``; ``h`` is the vehicle's height above the world's origin plus the home altitude.
2. ``n``: white noise, ``noise_pa`` per sample. PX4 SITL draws 1 Pa RMS; the default is
   ASSUMED twice that, for the rotors' wash on a real airframe (no measurement of it found).
3. ``d``: a random-walk drift, ``drift_pa_per_sqrt_s``. PX4 SITL's is a constant rate, zero by
   default; the default here, 0.2 Pa/sqrt(s) (about 1.7 cm/sqrt(s)), is ASSUMED: the sensor's
   temperature settling and the room's air moving, a few centimetres over a short flight.
4. ``C q``: the static-pressure error of moving through the air, the error PX4's EKF2 corrects
   with ``EKF2_PCOEF_XP`` and its siblings ("the ratio of static pressure error to dynamic
   pressure", ``src/modules/ekf2/params_*.yaml``); one coefficient for every horizontal
   direction, ``dynamic_pressure_coefficient``, ASSUMED 0.2 (PX4 allows -0.5 to 0.5): at
   2 m/s about half a pascal, 4 cm of height read low. The air is still (no wind indoors).

Not modelled: the ground effect under the rotors at take-off (PX4's ``EKF2_GND_EFF_DZ``), the
sensor's quantisation, and a temperature that changes.

:func:`pressure_altitude` is the height PX4 reads from a pressure
(``VehicleAirData::PressureToAltitude``, the ISA with the sea-level pressure ``SENS_BARO_QNH``).
The model draws only from its own ``rng``, so turning it on or off changes nothing else of a
flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from autonomy.geometry import GRAVITY
from autonomy.options import option, validate

#: ISA sea-level pressure (Pa) and temperature (K), and the troposphere's lapse rate (K/m),
#: PX4 SITL's (``SensorBaroSim.cpp``).
SEA_LEVEL_PRESSURE_PA = 101325.0
SEA_LEVEL_TEMPERATURE_K = 288.0
LAPSE_RATE_K_PER_M = 0.0065
#: ``g / (R L)`` of the ISA troposphere, PX4 SITL's rounding.
PRESSURE_EXPONENT = 5.256
#: The specific gas constant of dry air, J/(kg K).
AIR_GAS_CONSTANT = 287.1
#: PX4's default SENS_BARO_QNH, hPa.
DEFAULT_QNH_HPA = 1013.25


def isa_pressure(altitude_m: float) -> float:
    """The ISA troposphere's pressure at ``altitude_m`` above mean sea level, Pa."""
    return SEA_LEVEL_PRESSURE_PA / (SEA_LEVEL_TEMPERATURE_K / isa_temperature(altitude_m)) \
        ** PRESSURE_EXPONENT


def isa_temperature(altitude_m: float) -> float:
    """The ISA troposphere's temperature at ``altitude_m``, K."""
    return SEA_LEVEL_TEMPERATURE_K - LAPSE_RATE_K_PER_M * altitude_m


def pressure_altitude(pressure_pa: float, qnh_hpa: float = DEFAULT_QNH_HPA) -> float:
    """The altitude PX4 reads from ``pressure_pa`` with the sea-level pressure ``qnh_hpa``
    (``VehicleAirData::PressureToAltitude``: ``((p / p1) ^ (-a R / g) T1 - T1) / a``, ``T1``
    288.15 K, ``a`` -6.5 K/km), metres."""
    t1, a = 288.15, -0.0065
    return ((pressure_pa / (qnh_hpa * 100.0)) ** (-a * AIR_GAS_CONSTANT / GRAVITY) * t1 - t1) / a


@dataclass(frozen=True)
class BaroOptions:
    """Rate and error sources of the simulated barometer (module docstring); the defaults are
    the realistic profile, :meth:`for_profile` gives the ideal."""

    enabled: bool = option(
        True, doc="publish air data in HIGHRES_IMU; false: a flight controller without a "
                  "barometer (the fields stay zero and never marked updated)")
    rate_hz: float = option(20.0, gt=0.0, le=200.0,
                            doc="samples per second [SENS_BARO_RATE]")
    noise_pa: float = option(
        2.0, ge=0.0, le=1000.0,
        doc="white noise per sample, Pa (PX4 SITL: 1; twice that ASSUMED for the rotors' wash)")
    drift_pa_per_sqrt_s: float = option(
        0.2, ge=0.0, le=100.0, doc="random-walk drift of the pressure, Pa/sqrt(s) (ASSUMED)")
    dynamic_pressure_coefficient: float = option(
        0.2, ge=-1.0, le=1.0,
        doc="static pressure error per dynamic pressure of horizontal flight (ASSUMED; PX4's "
            "EKF2_PCOEF_XP corrects it)")

    def __post_init__(self) -> None:
        validate(self)

    def for_profile(self, profile: str) -> "BaroOptions":
        """These options in the simulator's ``profile``: ``realistic`` as they are; ``ideal``
        with the drift and the dynamic pressure's error off, the white noise as it is
        (the IMU's ideal keeps its white noise too). ``ValueError`` for any other name."""
        from drivers.sim.options import PROFILES  # drivers.sim.options imports this module

        if profile == "realistic":
            return self
        if profile == "ideal":
            return replace(self, drift_pa_per_sqrt_s=0.0, dynamic_pressure_coefficient=0.0)
        raise ValueError(f"profile must be one of {', '.join(PROFILES)}; got {profile!r}")


@dataclass(frozen=True)
class AirData:
    """One barometer sample as PX4 publishes it: pressure (Pa), the altitude PX4 reads from it
    (m above mean sea level, :func:`pressure_altitude`) and the temperature (degC)."""

    pressure_pa: float
    altitude_m: float
    temperature_c: float


def baro_generator(seed: int) -> np.random.Generator:
    """The barometer's generator of a simulated flight of ``seed``: a child of the flight's
    seed sequence that no other part of the flight draws from (:func:`drivers.sim.imu.
    flight_generators` takes the first, ``SimulatedVehicle`` the next two)."""
    return np.random.default_rng(np.random.SeedSequence(seed).spawn(4)[3])


class Barometer:
    """Air data every ``1 / rate_hz`` from the vehicle's true height and velocity."""

    def __init__(self, options: BaroOptions, rng: np.random.Generator,
                 home_altitude_m: float):
        self.options = options
        self._rng = rng
        self._home_altitude = float(home_altitude_m)
        self._drift_pa = 0.0
        self._last_t: float | None = None
        self._due: float | None = None

    def sample(self, t: float, height_m: float, velocity_W) -> AirData | None:
        """The sample due at simulated time ``t`` (s) for a vehicle ``height_m`` above the
        world's origin moving at ``velocity_W`` (m/s, world frame, z up); None when no sample
        is due yet (or the barometer is off)."""
        o = self.options
        if not o.enabled or (self._due is not None and t < self._due - 1e-9):
            return None
        period = 1.0 / o.rate_hz
        # on the rate's own grid, so that a tick that does not divide the period keeps the
        # rate; after a gap longer than the period, a new grid from now
        on_grid = None if self._due is None else self._due + period
        self._due = on_grid if on_grid is not None and on_grid > t else t + period
        dt = 0.0 if self._last_t is None else t - self._last_t
        self._last_t = t
        self._drift_pa += o.drift_pa_per_sqrt_s * math.sqrt(dt) * self._rng.standard_normal()
        altitude = self._home_altitude + float(height_m)
        temperature = isa_temperature(altitude)
        pressure = isa_pressure(altitude)
        density = pressure / (AIR_GAS_CONSTANT * temperature)
        horizontal_speed2 = float(velocity_W[0]) ** 2 + float(velocity_W[1]) ** 2
        measured = (pressure + o.noise_pa * self._rng.standard_normal() + self._drift_pa
                    + o.dynamic_pressure_coefficient * 0.5 * density * horizontal_speed2)
        return AirData(measured, pressure_altitude(measured), temperature - 273.15)
