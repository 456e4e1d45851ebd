"""The IMU model: what PX4's HIGHRES_IMU carries to the companion, body frame FLU, SI units.

Per axis, for the sample that closes the window ``[t - dt, t]`` (``t`` is the model's own
clock: the sum of every ``dt`` given to :meth:`ImuModel.measure` since power-on, ``t = 0`` when
the model is made)::

    gyro  = M_g (w + v_g(t)) + b_g(t) + n_g        accel = M_a (f + v_a(t)) + b_a(t) + n_a

1. White noise and bias random walk (the Kalibr / EuRoC model, Kalibr's "IMU noise model" wiki):
   ``n`` has standard deviation ``sigma / sqrt(dt)`` (density ``sigma``, unit/sqrt(Hz)), and a
   random-walk part of the bias moves by ``sigma_b sqrt(dt) N(0, 1)`` every sample. White-noise
   densities are the TDK InvenSense ICM-42688-P's (the IMU of the Pixhawk 6C / 6X): datasheet
   DS-000347 rev. 1.7, front-page features list, "Gyroscope Noise: 2.8 mdps/sqrt(Hz) &
   Accelerometer Noise: 70 ug/sqrt(Hz)". Datasheets give no bias random walk; the defaults are the
   EuRoC MAV dataset's (ADIS16448, ``mav0/imu0/sensor.yaml``: 1.9393e-05 rad/s^2/sqrt(Hz),
   3.0e-3 m/s^3/sqrt(Hz)), a stated stand-in, not a measurement of an ICM-42688-P.

2. Motor vibration ``v``: each rotor's imbalance shakes the airframe at the rotor frequency. It
   is a sinusoid per axis, ``v = s A sin(theta(t) + psi_axis)``, with one rotor angle ``theta``
   for all axes (advancing at ``2 pi f`` plus a slow phase random walk of
   ``vibration_phase_walk`` rad/sqrt(s)) and fixed per-axis phases ``psi`` drawn once per run.
   With ``s = thrust / g`` the amplitude scales with thrust and ``f = f_hover sqrt(s)`` with rotor
   speed (thrust ~ omega^2, and an imbalance force ~ omega^2 too). ``thrust`` is the collective
   specific thrust passed to :meth:`ImuModel.measure`; when the caller does not know it, the
   magnitude of the true specific force stands in, at most 2 g (right in flight; on the ground
   it reads g, so a model not told ``thrust=0`` vibrates on the ground as if hovering).

   What reaches the sample stream follows PX4's sensor pipeline (PX4-Autopilot source):
   the ICM-42688-P is read at an 8 kHz ODR (``src/drivers/imu/invensense/icm42688p/ICM42688P
   .hpp``: ``GYRO_RATE{8000}``, ``ACCEL_RATE{8000}``); ``VehicleIMU`` integrates the raw samples
   into delta angle / delta velocity over each ``IMU_INTEG_RATE`` window (``src/modules/sensors/
   vehicle_imu/VehicleIMU.cpp``: ``_accel_integrator.put(accel_raw, dt)``; default 200 Hz,
   ``imu_parameters.yaml``); and the HIGHRES_IMU the companion reads is that delta divided by its
   interval (``src/modules/mavlink/streams/HIGHRES_IMU.hpp``: ``delta_velocity * accel_dt_inv``).
   So the vibration is averaged over the sample's window ``dt`` -- a boxcar, gain
   ``sinc(f dt) exp(-i pi f dt)`` -- and then point-sampled at ``1 / dt``, where what is left of
   it aliases to ``|f - k / dt|``. PX4's low-pass filters ``IMU_GYRO_CUTOFF`` (default 40 Hz,
   ``vehicle_angular_velocity/imu_gyro_parameters.yaml``) and ``IMU_ACCEL_CUTOFF`` (30 Hz,
   ``vehicle_acceleration/imu_accel_parameters.yaml``), second-order Butterworth, filter only
   the controllers' topics ("Controllers only, not estimators"), not HIGHRES_IMU, so the
   default ``vibration_cutoff_hz = 0`` adds none; a cutoff above zero multiplies the response by
   that Butterworth's, ``1 / (1 - r^2 + i sqrt(2) r)`` with ``r = f / cutoff`` (a pipeline that
   low-passes before it samples). The response is the steady-state one of a sinusoid, exact
   while the frequency and phase walk are slow against ``1 / dt``.

   Defaults: rotor frequency 122.5 Hz, the hover rotor speed of PX4's own X500 model
   (PX4-gazebo-models ``models/x500/model.sdf``: motorConstant 8.54858e-06 N/(rad/s)^2, four
   rotors; ``models/x500_base/model.sdf``: 2.0 kg body + 4 x 0.0161 kg rotors, so
   ``omega = sqrt(m g / (4 k)) = 769 rad/s``). Accelerometer amplitude g/2 = 4.90 m/s^2 before
   the integration: a per-axis RMS of 3.5 m/s^2, inside ArduPilot's "Measuring Vibration" guide's
   "normal" (< 15 m/s/s, the standard deviation of the raw accelerometer; acceptable < 30), and
   at 200 Hz a 2.4 m/s^2 alias, a peak-to-peak of half of g on each axis -- half of what PX4's
   Flight Review guide calls too high ("if the z-axis graph is touching the x/y-axis graph during
   hover", ``docs/en/log/flight_review.md``, "Raw Acceleration"). Gyroscope amplitude 0.145 rad/s:
   derived, not measured -- the rigid-body angular rate a force ``m A`` at the X500's arm
   (0.246 m) drives at ``f`` against its inertia (Ixx 0.0217 kg m^2): ``m A L / (I 2 pi f)``.

3. Scale factor and axis misalignment ``M = I + S + A``, fixed per run: ``S`` diagonal with
   per-axis sensitivity errors, ``A`` the off-diagonal cross-axis sensitivities, each drawn
   ``N(0, sigma^2)`` with sigma the ICM-42688-P datasheet's tolerance (DS-000347, section 3,
   gyroscope and accelerometer specification tables): sensitivity scale factor tolerance +-0.5 %
   (both), cross-axis sensitivity +-1.25 % (gyro) and +-1 % (accel); the datasheet's +- figure
   is used as one standard deviation. ``M`` acts before the bias is added, and vibration is
   real motion, so it passes through ``M`` too.

   The accelerometer's ``M_a`` is then what PX4's six-orientation calibration leaves of it
   (``accel_calibrated``): ``diag(s) M_a``, with ``s`` the per-axis scales that PX4 fits and
   stores (``src/modules/commander/accelerometer_calibration.cpp``, ``do_accel_calibration``:
   the offset from each axis's pair of opposite orientations, ``A`` the rows of the tail-down,
   left and upside-down readings less it, ``T = A^-1 g``, ``set_scale(T.diag())``; applied as
   ``(raw - offset) * scale`` in ``src/lib/sensor_calibration/Accelerometer.hpp``, ``Correct``).
   The model runs that fit on the six still, noise-free readings of this vehicle, each
   orientation placed with a tilt about each horizontal axis drawn ``N(0, tilt^2)``: level
   placements give ``s = diag(M_a^-1)``, which takes the sensitivity errors out to second
   order and leaves the cross-axis ones (PX4 keeps only the diagonal); a tilt ``d`` reads
   ``g cos d`` on its axis, so each scale comes out ``1 / cos d`` too large, about ``tilt^2``
   on average. PX4 accepts any orientation within 5 m/s^2 of its axis (``src/modules/
   commander/calibration_routines.cpp``, ``detect_orientation``, ``accel_err_thr``), so the
   tilt is the person's placement: ``accel_calibration_tilt_deg = 3`` is ASSUMED (a vehicle
   set on its sides by hand). The gyroscope gets no such correction: PX4's
   ``Gyroscope::Correct`` applies offsets and the board rotation only.

4. Turn-on bias and warm-up: ``b(t) = b_walk(t) + b_final + (b_0 - b_final) exp(-t / tau)``
   with ``b_0 ~ N(0, sigma_on^2)`` and ``b_final - b_0 ~ N(0, sigma_warm^2)`` per axis, both
   drawn once per run, and ``b_walk`` the random walk of (1), from zero. ``sigma_on`` is what
   PX4's calibration leaves, not the datasheet's uncalibrated tolerance (gyro +-0.5 dps initial
   ZRO, accel +-20 mg initial zero-g): PX4's online gyro calibration does not apply an offset
   change under 0.01 rad/s (``src/lib/sensor_calibration/Gyroscope.cpp``, ``set_offset``,
   ``MIN_OFFSET_CHANGE = 0.01f``, a vector norm) and its learned accelerometer calibration none
   under 0.05 m/s^2 (``VehicleIMU::AccelCalibrationUpdate``, ``bias_estimate.longerThan
   (0.05f)``); those dead bands spread over three axes give sigma_on = 0.01 / sqrt(3) rad/s and
   0.05 / sqrt(3) m/s^2. ``sigma_warm`` is the datasheet's temperature coefficient over an
   ASSUMED 20 degC self-heating rise: 0.005 dps/degC (ZRO variation) and 0.15 mg/degC (zero-g
   change), so 0.1 dps and 3 mg. ``tau = 300 s`` is an ASSUMED board warm-up time constant (a
   few minutes); no source for it was found.

The model is deterministic from its ``rng``, and each error source draws from a stream of its
own, so switching one source off leaves every other source's numbers as they were and an
ablation changes one thing only. ``rng`` itself draws the white noise and walk (12 normals a
sample); three children spawned from its seed sequence (``Generator.spawn``, which leaves the
parent's stream untouched) draw the matrices ``M_g`` and ``M_a`` (always both, 18 normals,
then the calibration's 12 tilts), the biases ``b_0`` and ``b_final`` (12 normals) and the
vibration's phases and phase walk. With
every new effect off (:meth:`ImuOptions.for_profile` ``"ideal"``) the output is bit for bit
that of the white-noise-and-walk model alone.
"""

from __future__ import annotations

import cmath
import math
from dataclasses import dataclass, replace

import numpy as np

from autonomy.geometry import GRAVITY, so3_exp
from autonomy.options import option, validate
from autonomy.vins.preintegration import (ICM42688P_ACCEL_NOISE_DENSITY,
                                          ICM42688P_GYRO_NOISE_DENSITY)
from drivers.mavlink.frames import R_FLU_FRD
from drivers.sim.quadrotor import ImuTruth

#: Hover rotor speed of PX4's X500 simulation model, Hz: sqrt(m g / (4 k)) / (2 pi) with
#: m = 2.0 + 4 x 0.016077 kg and k = 8.54858e-06 N/(rad/s)^2 (PX4-gazebo-models x500, x500_base).
X500_HOVER_ROTOR_HZ = 122.5
#: X500 model (x500_base/model.sdf): rotor arm (0.174 m, 0.174 m) from the centre, body mass
#: 2.0 kg, roll inertia 0.0217 kg m^2; used only to derive the gyroscope vibration default.
_X500_ARM_M = 0.174 * math.sqrt(2.0)
_X500_MASS_KG = 2.0
_X500_IXX = 0.02166666666666667
_ACCEL_VIBRATION = GRAVITY / 2.0
_GYRO_VIBRATION = round(_ACCEL_VIBRATION * _X500_MASS_KG * _X500_ARM_M
                        / (_X500_IXX * 2.0 * math.pi * X500_HOVER_ROTOR_HZ), 3)
#: Most collective specific thrust the |specific force| stand-in for ``thrust`` may claim, m/s^2:
#: 2 g, PX4's default thrust range (MPC_THR_HOVER 0.5, MPC_THR_MAX 1; drivers/sim/quadrotor.py),
#: so a touchdown's contact spike does not read as a rotor 20 times faster.
_STAND_IN_THRUST_MAX = 2.0 * GRAVITY
#: Self-heating rise assumed for the warm-up drift, degC (an assumption; see the module doc).
_WARMUP_RISE_C = 20.0


@dataclass(frozen=True)
class ImuOptions:
    """Rate, noise and error sources of the simulated IMU (SI units; sources in the module
    docstring). The defaults are the realistic profile; :meth:`for_profile` gives the ideal."""

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
    enabled: bool = option(
        True, doc="add noise and every error source; false gives the exact truth")
    accel_vibration_amplitude: float = option(
        _ACCEL_VIBRATION, ge=0.0, le=160.0,
        doc="rotor vibration on each accelerometer axis at hover thrust, amplitude before PX4's "
            "integration, m/s^2 (g/2: RMS 3.5, ArduPilot's 'normal' is < 15; PX4 Flight Review)",
    )
    gyro_vibration_amplitude: float = option(
        _GYRO_VIBRATION, ge=0.0, le=35.0,
        doc="rotor vibration on each gyroscope axis at hover thrust, amplitude before PX4's "
            "integration, rad/s (derived: X500 rigid body driven by the accelerometer's)",
    )
    vibration_frequency_hz: float = option(
        X500_HOVER_ROTOR_HZ, gt=0.0, le=4000.0,
        doc="rotor frequency at hover thrust, Hz (PX4's X500 model: 769 rad/s); scales with "
            "sqrt(thrust / g)",
    )
    vibration_cutoff_hz: float = option(
        0.0, ge=0.0, le=4000.0,
        doc="second-order Butterworth low-pass on the vibration before sampling, Hz; 0: none, "
            "as in PX4's HIGHRES_IMU (IMU_GYRO_CUTOFF 40 / IMU_ACCEL_CUTOFF 30 filter only the "
            "controllers' topics)",
    )
    vibration_phase_walk: float = option(
        1.0, ge=0.0, le=100.0,
        doc="random walk of the rotor phase, rad/sqrt(s) (a modelling choice: a line "
            "broadened by about 0.16 Hz)",
    )
    gyro_scale_error: float = option(
        0.005, ge=0.0, le=0.1,
        doc="std of each gyroscope sensitivity error, fraction (ICM-42688-P: +-0.5 %)",
    )
    gyro_cross_axis: float = option(
        0.0125, ge=0.0, le=0.1,
        doc="std of each gyroscope cross-axis sensitivity, fraction (ICM-42688-P: +-1.25 %)",
    )
    accel_scale_error: float = option(
        0.005, ge=0.0, le=0.1,
        doc="std of each accelerometer sensitivity error, fraction (ICM-42688-P: +-0.5 %)",
    )
    accel_cross_axis: float = option(
        0.01, ge=0.0, le=0.1,
        doc="std of each accelerometer cross-axis sensitivity, fraction (ICM-42688-P: +-1 %)",
    )
    accel_calibrated: bool = option(
        True, doc="the accelerometer as PX4's six-orientation calibration leaves it: per-axis "
                  "scales fitted and divided out (accelerometer_calibration.cpp); false: the "
                  "chip's raw sensitivity errors",
    )
    accel_calibration_tilt_deg: float = option(
        3.0, ge=0.0, le=20.0,
        doc="std of each calibration orientation's tilt about each horizontal axis, degrees "
            "(assumed: placed by hand; PX4 accepts up to 5 m/s^2 off the axis)",
    )
    gyro_turn_on_bias: float = option(
        0.01 / math.sqrt(3.0), ge=0.0, le=1.0,
        doc="std of each gyroscope bias at power-on, rad/s (PX4's gyro calibration dead band, "
            "0.01 rad/s, over three axes)",
    )
    accel_turn_on_bias: float = option(
        0.05 / math.sqrt(3.0), ge=0.0, le=10.0,
        doc="std of each accelerometer bias at power-on, m/s^2 (PX4's learned accel "
            "calibration dead band, 0.05 m/s^2, over three axes)",
    )
    gyro_warmup_drift: float = option(
        math.radians(0.005 * _WARMUP_RISE_C), ge=0.0, le=1.0,
        doc="std of each gyroscope bias change over the warm-up, rad/s (ICM-42688-P "
            "0.005 dps/degC over an assumed 20 degC rise)",
    )
    accel_warmup_drift: float = option(
        0.15e-3 * _WARMUP_RISE_C * GRAVITY, ge=0.0, le=10.0,
        doc="std of each accelerometer bias change over the warm-up, m/s^2 (ICM-42688-P "
            "0.15 mg/degC over an assumed 20 degC rise)",
    )
    warmup_time_constant_s: float = option(
        300.0, gt=0.0, le=86400.0,
        doc="time constant of the warm-up bias change, seconds (assumed: a few minutes)",
    )

    def __post_init__(self) -> None:
        validate(self)

    @property
    def period(self) -> float:
        """Seconds between samples."""
        return 1.0 / self.rate_hz

    def for_profile(self, profile: str) -> "ImuOptions":
        """These options in the simulator's ``profile``: ``realistic`` as they are; ``ideal``
        with vibration, scale and misalignment, turn-on bias and warm-up off, leaving white
        noise and bias random walk exactly as they are. ``ValueError`` for any other name."""
        from drivers.sim.options import PROFILES  # drivers.sim.options imports this module

        if profile == "realistic":
            return self
        if profile == "ideal":
            return replace(self, accel_vibration_amplitude=0.0, gyro_vibration_amplitude=0.0,
                           gyro_scale_error=0.0, gyro_cross_axis=0.0, accel_scale_error=0.0,
                           accel_cross_axis=0.0, gyro_turn_on_bias=0.0, accel_turn_on_bias=0.0,
                           gyro_warmup_drift=0.0, accel_warmup_drift=0.0)
        raise ValueError(f"profile must be one of {', '.join(PROFILES)}; got {profile!r}")


def _scale_misalignment(rng: np.random.Generator, scale: float, cross: float) -> np.ndarray:
    """``I + S + A``: diagonal errors N(0, scale^2), off-diagonal N(0, cross^2)."""
    spread = np.full((3, 3), cross)
    np.fill_diagonal(spread, scale)
    return np.eye(3) + spread * rng.standard_normal((3, 3))


def px4_accel_scales(readings: np.ndarray) -> np.ndarray:
    """The per-axis scales PX4's six-orientation accelerometer calibration stores, from the
    mean readings ``(6, 3)`` (FRD, m/s^2) of its orientations in the order tail down
    ``[g, 0, 0]``, nose down ``[-g, 0, 0]``, left ``[0, g, 0]``, right, upside down
    ``[0, 0, g]``, right side up (``accelerometer_calibration.cpp``, ``do_accel_calibration``,
    board rotation identity): ``offset_i`` the mean of axis ``i`` over its two orientations,
    ``A`` the rows tail down, left and upside down less the offset, ``scale = diag(A^-1 g)``.
    """
    readings = np.asarray(readings, dtype=float)
    offset = (0.5 * (readings[0::2] + readings[1::2])).diagonal()
    return np.diag(np.linalg.inv(readings[0::2] - offset) * GRAVITY).copy()


def _px4_calibrated(matrix: np.ndarray, rng: np.random.Generator, tilt: float) -> np.ndarray:
    """``diag(s) matrix``: an accelerometer ``matrix`` (FLU) as PX4's calibration leaves it,
    ``s`` fitted on its still readings in the six orientations, each tilted about its two
    horizontal axes by ``N(0, tilt^2)`` radians (12 normals from ``rng``). The scales are the
    same in FLU and FRD: a diagonal is unchanged by the axes' signs."""
    matrix_frd = R_FLU_FRD @ matrix @ R_FLU_FRD  # FRD, PX4's sensor frame (its own inverse)
    readings = []
    for orientation, tilts in enumerate(rng.standard_normal((6, 2)) * tilt):
        axis, sign = divmod(orientation, 2)
        reference = np.zeros(3)
        reference[axis] = GRAVITY * (-1.0 if sign else 1.0)
        rotation = np.zeros(3)
        rotation[[a for a in range(3) if a != axis]] = tilts
        readings.append(matrix_frd @ so3_exp(rotation) @ reference)
    return np.diag(px4_accel_scales(np.array(readings))) @ matrix


def flight_generators(seed: int, vehicle_seed: int) -> tuple[np.random.Generator,
                                                             np.random.Generator]:
    """The generators of a simulated flight's IMU (``drivers.sim.serve.SimulatedVehicle``):
    its noise's from ``seed``, its vehicle's (the scale and misalignment matrices) from
    ``vehicle_seed``. ``sim record --along`` draws with them, so that it flies the flight's
    own IMU; the recorder's own routes keep theirs (``record.fly``), so that its recordings
    stay what the docs' tables measured."""
    return (np.random.default_rng(np.random.SeedSequence(seed).spawn(3)[0]),
            np.random.default_rng(np.random.SeedSequence(vehicle_seed).spawn(1)[0]))


class ImuModel:
    """Turns IMU truth into measurements with the error sources of :class:`ImuOptions`.

    The same ``rng`` state gives the same output, so a seeded generator makes a run repeatable.
    ``vehicle_rng`` (default ``rng``) draws what a vehicle keeps from flight to flight, the
    matrices ``M_g`` and ``M_a``, from the child ``rng`` would draw them from, so that a
    vehicle generator seeded as ``rng`` gives ``rng``'s. The model keeps its own clock, the sum
    of the ``dt`` it was given (:attr:`time`).
    """

    def __init__(self, options: ImuOptions | None = None, rng: np.random.Generator | None = None,
                 vehicle_rng: np.random.Generator | None = None):
        self.options = options if options is not None else ImuOptions().for_profile("ideal")
        if not isinstance(self.options, ImuOptions):
            raise TypeError(f"options must be ImuOptions, got {type(options).__name__}")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(
                f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {rng!r}"
            )
        self._rng = rng
        self._time = 0.0
        self._gyro_bias = np.zeros(3)  # the random-walk part
        self._accel_bias = np.zeros(3)
        o = self.options
        self._densities = np.array(
            [o.gyro_noise_density] * 3 + [o.accel_noise_density] * 3, dtype=float
        )
        self._walks = np.array(
            [o.gyro_bias_random_walk] * 3 + [o.accel_bias_random_walk] * 3, dtype=float
        )
        # One stream per error source (module docstring), each drawn only when it is on.
        matrix_rng, bias_rng, self._vibration_rng = rng.spawn(3)
        if vehicle_rng is not None:
            matrix_rng = vehicle_rng.spawn(1)[0]  # a fresh generator's first child, as rng's
        self._gyro_matrix: np.ndarray | None = None
        self._accel_matrix: np.ndarray | None = None
        if o.enabled and (o.gyro_scale_error or o.gyro_cross_axis
                          or o.accel_scale_error or o.accel_cross_axis):
            self._gyro_matrix = _scale_misalignment(matrix_rng, o.gyro_scale_error,
                                                    o.gyro_cross_axis)
            self._accel_matrix = _scale_misalignment(matrix_rng, o.accel_scale_error,
                                                     o.accel_cross_axis)
            if o.accel_calibrated:
                self._accel_matrix = _px4_calibrated(
                    self._accel_matrix, matrix_rng, math.radians(o.accel_calibration_tilt_deg))
        self._bias_start: np.ndarray | None = None  # b_0, gyro then accel
        self._bias_final: np.ndarray | None = None  # b_final
        if o.enabled and (o.gyro_turn_on_bias or o.accel_turn_on_bias
                          or o.gyro_warmup_drift or o.accel_warmup_drift):
            draws = bias_rng.standard_normal(12)
            self._bias_start = np.repeat([o.gyro_turn_on_bias, o.accel_turn_on_bias], 3) * draws[:6]
            self._bias_final = self._bias_start + np.repeat(
                [o.gyro_warmup_drift, o.accel_warmup_drift], 3) * draws[6:]
        self._vibrating = o.enabled and bool(o.accel_vibration_amplitude
                                              or o.gyro_vibration_amplitude)
        if self._vibrating:
            self._rotor_angle = float(self._vibration_rng.uniform(0.0, 2.0 * math.pi))
            self._axis_phases = self._vibration_rng.uniform(0.0, 2.0 * math.pi, 6)
            self._vibration_amplitudes = np.repeat(
                [o.gyro_vibration_amplitude, o.accel_vibration_amplitude], 3)

    @property
    def time(self) -> float:
        """Seconds since power-on: the sum of every ``dt`` given to :meth:`measure`."""
        return self._time

    def _systematic_bias(self) -> np.ndarray | None:
        """Turn-on bias plus warm-up at the current time, gyro then accel; None when off."""
        if self._bias_start is None:
            return None
        decay = math.exp(-self._time / self.options.warmup_time_constant_s)
        return self._bias_final + (self._bias_start - self._bias_final) * decay

    @property
    def gyro_bias(self) -> np.ndarray:
        """The true gyroscope bias at the last sample, rad/s (body FLU), for ground-truth files:
        turn-on bias, warm-up and random walk -- exactly what the sample adds after ``M``; not
        the vibration, the scale and misalignment, or the white noise."""
        systematic = self._systematic_bias()
        if systematic is None:
            return self._gyro_bias.copy()
        return self._gyro_bias + systematic[:3]

    @property
    def accel_bias(self) -> np.ndarray:
        """The true accelerometer bias at the last sample, m/s^2 (body FLU), for ground-truth
        files; as :attr:`gyro_bias`."""
        systematic = self._systematic_bias()
        if systematic is None:
            return self._accel_bias.copy()
        return self._accel_bias + systematic[3:]

    @property
    def gyro_matrix(self) -> np.ndarray:
        """This run's gyroscope scale-and-misalignment matrix ``M_g`` (identity when off)."""
        return np.eye(3) if self._gyro_matrix is None else self._gyro_matrix.copy()

    @property
    def accel_matrix(self) -> np.ndarray:
        """This run's accelerometer scale-and-misalignment matrix ``M_a`` (identity when off),
        as PX4's calibration leaves it when ``accel_calibrated``."""
        return np.eye(3) if self._accel_matrix is None else self._accel_matrix.copy()

    def _vibration_gain(self, frequency: float, dt: float) -> complex:
        """Complex gain of PX4's path from the airframe to a sample closing a ``dt`` window:
        the optional Butterworth, then the window's average (boxcar)."""
        gain = complex(np.sinc(frequency * dt)) * cmath.exp(-1j * math.pi * frequency * dt)
        cutoff = self.options.vibration_cutoff_hz
        if cutoff > 0.0:
            r = frequency / cutoff
            gain /= complex(1.0 - r * r, math.sqrt(2.0) * r)
        return gain

    def _vibration(self, thrust: float, dt: float) -> np.ndarray:
        """Gyro then accel vibration in the sample closing the current window; advances the
        rotor angle over the window (one normal drawn when the phase walk is on)."""
        o = self.options
        level = thrust / GRAVITY
        frequency = o.vibration_frequency_hz * math.sqrt(level)
        self._rotor_angle += 2.0 * math.pi * frequency * dt
        if o.vibration_phase_walk > 0.0:
            step = self._vibration_rng.standard_normal()
            self._rotor_angle += o.vibration_phase_walk * math.sqrt(dt) * step
        self._rotor_angle = math.fmod(self._rotor_angle, 2.0 * math.pi)
        gain = self._vibration_gain(frequency, dt)
        phasors = np.exp(1j * (self._rotor_angle + self._axis_phases))
        return level * self._vibration_amplitudes * np.imag(gain * phasors)

    def measure(self, truth: ImuTruth, dt: float, *,
                thrust: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(gyro rad/s, accel m/s^2), body FLU, of a sample taken ``dt`` seconds after the last.

        The model's clock advances by ``dt``; the random-walk bias steps over ``dt``; the sample
        is ``M (truth + vibration) + bias + white noise`` (module docstring), the white noise's
        standard deviation ``density / sqrt(dt)``. ``thrust``: the rotors' collective specific
        thrust, m/s^2 (0 with the motors off), that the vibration scales with; None: the
        magnitude of the true specific force stands in, at most 2 g.
        """
        dt = float(dt)
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(
                f"IMU sample interval dt must be a positive number of seconds, got {dt!r}"
            )
        if thrust is not None:
            thrust = float(thrust)
            if not (math.isfinite(thrust) and thrust >= 0.0):
                raise ValueError(f"thrust must be a finite number >= 0 (m/s^2), got {thrust!r}")
        gyro = np.array(truth.angular_velocity, dtype=float)
        accel = np.array(truth.specific_force, dtype=float)
        self._time += dt
        if not self.options.enabled:
            return gyro, accel
        draws = self._rng.standard_normal(12)
        steps = self._walks * math.sqrt(dt) * draws[:6]
        self._gyro_bias += steps[:3]
        self._accel_bias += steps[3:]
        noise = self._densities / math.sqrt(dt) * draws[6:]
        if self._vibrating:
            if thrust is None:  # the stand-in, no more than the rotors can give
                thrust = min(float(np.linalg.norm(accel)), _STAND_IN_THRUST_MAX)
            vibration = self._vibration(thrust, dt)
            gyro = gyro + vibration[:3]
            accel = accel + vibration[3:]
        if self._gyro_matrix is not None:
            gyro = self._gyro_matrix @ gyro
            accel = self._accel_matrix @ accel
        gyro_bias, accel_bias = self._gyro_bias, self._accel_bias
        systematic = self._systematic_bias()
        if systematic is not None:
            gyro_bias = gyro_bias + systematic[:3]
            accel_bias = accel_bias + systematic[3:]
        return gyro + gyro_bias + noise[:3], accel + accel_bias + noise[3:]
