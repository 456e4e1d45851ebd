"""The IMU model: white noise and bias random walk on the gyroscope and the accelerometer.

Continuous-time model per axis, body frame FLU (the Kalibr / EuRoC model)::

    measured(t) = true(t) + b(t) + n(t),   n white with density sigma   (unit/sqrt(Hz))
    db/dt = n_b(t),                        n_b white with density sigma_b (unit/s/sqrt(Hz))

Discretised for a sample taken after an interval ``dt`` (Kalibr's "IMU noise model" wiki)::

    b_k = b_{k-1} + sigma_b sqrt(dt) N(0, 1)
    measured_k = true_k + b_k + (sigma / sqrt(dt)) N(0, 1)

so at ``rate = 1 / dt`` the white noise has standard deviation ``sigma sqrt(rate)`` and the bias
drifts by ``sigma_b sqrt(T)`` (one standard deviation) over a time ``T``.

Default white-noise densities are those of the TDK InvenSense ICM-42688-P, the IMU of the
Pixhawk 6C / 6X: datasheet DS-000347 rev. 1.7, front-page features list, "Gyroscope Noise:
2.8 mdps/sqrt(Hz) & Accelerometer Noise: 70 ug/sqrt(Hz)". Datasheets do not give a bias random
walk; the defaults for it are the values the EuRoC MAV dataset publishes for its MEMS IMU
(ADIS16448, ``mav0/imu0/sensor.yaml``: gyroscope_random_walk 1.9393e-05 rad/s^2/sqrt(Hz),
accelerometer_random_walk 3.0e-3 m/s^3/sqrt(Hz)), the figures VIO pipelines are most often tuned
with. They are a stand-in, not a measurement of an ICM-42688-P.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.options import option, validate
from autonomy.vins.preintegration import (ICM42688P_ACCEL_NOISE_DENSITY,
                                          ICM42688P_GYRO_NOISE_DENSITY)
from drivers.sim.quadrotor import ImuTruth

@dataclass(frozen=True)
class ImuOptions:
    """Rate and noise of the simulated IMU (SI units; see the module docstring for sources)."""

    rate_hz: float = option(
        200.0, ge=20.0, le=2000.0,
        doc="samples per second (at least 20: the vehicle steps at most vehicle.MAX_STEP = 50 ms)",
    )
    gyro_noise_density: float = option(
        ICM42688P_GYRO_NOISE_DENSITY, ge=0.0, le=1.0,
        doc="gyroscope white noise, rad/s/sqrt(Hz) (ICM-42688-P: 0.0028 deg/s/sqrt(Hz))",
    )
    accel_noise_density: float = option(
        ICM42688P_ACCEL_NOISE_DENSITY, ge=0.0, le=10.0,
        doc="accelerometer white noise, m/s^2/sqrt(Hz) (ICM-42688-P: 70 ug/sqrt(Hz))",
    )
    gyro_bias_random_walk: float = option(
        1.9393e-05, ge=0.0, le=1.0,
        doc="gyroscope bias random walk, rad/s^2/sqrt(Hz) (EuRoC imu0 sensor.yaml)",
    )
    accel_bias_random_walk: float = option(
        3.0e-3, ge=0.0, le=10.0,
        doc="accelerometer bias random walk, m/s^3/sqrt(Hz) (EuRoC imu0 sensor.yaml)",
    )
    enabled: bool = option(True, doc="add noise and bias; false gives the exact truth")

    def __post_init__(self) -> None:
        validate(self)

    @property
    def period(self) -> float:
        """Seconds between samples."""
        return 1.0 / self.rate_hz


class ImuModel:
    """Turns IMU truth into measurements, with biases that wander as random walks from zero.

    The same ``rng`` state gives the same noise, so a seeded generator makes a run repeatable.
    """

    def __init__(self, options: ImuOptions | None = None, rng: np.random.Generator | None = None):
        self.options = options if options is not None else ImuOptions()
        if not isinstance(self.options, ImuOptions):
            raise TypeError(f"options must be ImuOptions, got {type(options).__name__}")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(
                f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {rng!r}"
            )
        self._rng = rng
        self._gyro_bias = np.zeros(3)
        self._accel_bias = np.zeros(3)
        o = self.options
        self._densities = np.array(
            [o.gyro_noise_density] * 3 + [o.accel_noise_density] * 3, dtype=float
        )
        self._walks = np.array(
            [o.gyro_bias_random_walk] * 3 + [o.accel_bias_random_walk] * 3, dtype=float
        )

    @property
    def gyro_bias(self) -> np.ndarray:
        """The true current gyroscope bias, rad/s (body FLU), for ground-truth files."""
        return self._gyro_bias.copy()

    @property
    def accel_bias(self) -> np.ndarray:
        """The true current accelerometer bias, m/s^2 (body FLU), for ground-truth files."""
        return self._accel_bias.copy()

    def measure(self, truth: ImuTruth, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(gyro rad/s, accel m/s^2), body FLU, of a sample taken ``dt`` seconds after the last.

        The biases first walk over ``dt``, then the sample is ``truth + bias + white noise`` with
        the white noise's standard deviation ``density / sqrt(dt)``.
        """
        dt = float(dt)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(
                f"IMU sample interval dt must be a positive number of seconds, got {dt!r}"
            )
        gyro = np.array(truth.angular_velocity, dtype=float)
        accel = np.array(truth.specific_force, dtype=float)
        if not self.options.enabled:
            return gyro, accel
        draws = self._rng.standard_normal(12)
        steps = self._walks * math.sqrt(dt) * draws[:6]
        self._gyro_bias += steps[:3]
        self._accel_bias += steps[3:]
        noise = self._densities / math.sqrt(dt) * draws[6:]
        return gyro + self._gyro_bias + noise[:3], accel + self._accel_bias + noise[3:]
