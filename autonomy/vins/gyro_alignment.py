"""The gyro's response to yaw, as the camera sees it, estimated online and corrected.

A MEMS gyro's axes respond to rotation about the others (cross-axis sensitivity: the
ICM-42688-P's datasheet gives +-1.25 %), and a camera's mounting is known only to a
calibration's accuracy (0.5 deg in the realistic profile). Both make the gyro's rotation
disagree with the camera's. At a 90 deg corner a 1.25 % response of the x and y axes to the
yaw rate integrates about 1 deg of false tilt; gravity through it is 0.17 m/s^2 of false
horizontal acceleration, which the smoother explains as an accelerometer bias, and a bias
the rotor-drag factor (:mod:`autonomy.vins.drag`) then reads as speed (docs/vins.md).

**The model.** Only the response to the body's z rate is estimated: corners are yaw turns,
and the pitch and roll rates of a cruise excite the other columns too little to estimate them
(on the simulated flights the full 3x3 fit was off by up to 0.03 in its roll column and made
the flights worse). With ``e`` that column, the gyro reads

    omega_m = (I + e z^T) omega + b + n,    z = (0, 0, 1),

in the body frame *as the camera's configured mounting defines it*: a mounting error ``d``
turns the camera's rotations by ``[d]x``, so ``e`` is the gyro's own cross-axis and scale
response plus the mounting's, which is the combination that has to go for the gyro to agree
with the camera. Told apart they are not needed: the accelerometer's frame, off by the same
small rotation, reads a thrust that stays along the body's z as a constant bias, which the
smoother estimates anyway.

**The measurement.** The time-offset estimator's frame pairs (:mod:`autonomy.vins.time_offset`)
give, over each pair, the camera's rotation ``theta_v`` (in the body frame, information
``Lambda``) and the gyro's ``R_g = Exp(theta_v + e theta_v,z)``; with
``Exp(a + d) ~ Exp(a) Exp(J_r(a) d)`` (``J_r`` the right Jacobian of SO(3)) the residual is

    r = Log(R_g^T R_v) = A e,    A = -theta_v,z J_r(theta_v)

(to first order in ``e``; taking ``A = -theta_v,z I`` instead turns the fitted x and y
responses by half the pair's yaw, which corners one way round do not average out). The
estimate is the least-squares fit over the pairs with a Gaussian prior
(:class:`GyroAlignment`):

    (P + sum_k w_k A_k^T W_k A_k) e = sum_k w_k A_k^T W_k r_k,

``P`` the prior's information (datasheet sigmas), ``w_k`` a Huber weight on the pair's
Mahalanobis residual (against the estimate when the pair arrives). The camera's rotation is the
regressor, not the gyro's: the gyro's carries the rotors' vibration, which the camera does not
see, and a regression on a noisy regressor is biased towards zero (errors in variables;
measured, docs/vins.md). ``W_k`` is the camera rotation's information with
:data:`GYRO_PAIR_SIGMA` added to its covariance for that vibration, counted once per stretch of
time as the pair's own information is (the time-offset estimator scales it by the pairs'
overlap). A pair is used only once the time offset is known (a pair made at a wrong offset
reads the offset's error in every change of the turn rate).

**The correction.** Every gyro sample is corrected before the VINS uses it:
``omega = (I + e z^T)^-1 omega_m``, i.e. ``omega_z = omega_m,z / (1 + e_z)`` and
``omega_xy = omega_m,xy - e_xy omega_z``, and the smoother estimates its bias on the corrected
samples. The time-offset estimator keeps the raw samples (and gets that bias as the raw gyro
reads it, ``(I + e z^T) b``), so that its pairs measure the whole ``e`` whatever the
correction in use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.vins.preintegration import exp_and_right_jacobian
from autonomy.vins.time_offset import PairRotations, log_so3

#: The gyro's own scatter over a frame pair, radians, added to the camera rotation's covariance:
#: the rotors' vibration, which the camera does not see, integrates to this order over a pair
#: (the realistic profile's 0.145 rad/s; docs/simulator.md). Set before the measurements, not
#: tuned on them.
GYRO_PAIR_SIGMA = 1e-3
#: Huber threshold on a pair's Mahalanobis residual.
HUBER_K = 3.0


@dataclass(frozen=True)
class GyroAlignmentEstimate:
    """The gyro's response to the body's z rate (``column``: x, y and z axes, fractions),
    its one-sigma (``sigma``) and the number of frame ``pairs`` it rests on."""

    column: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sigma: tuple[float, float, float] | None = None
    pairs: int = 0

    def as_dict(self) -> dict:
        """Plain lists and numbers, for JSON: ``column``, ``sigma``, ``pairs``."""
        return {"column": list(self.column),
                "sigma": None if self.sigma is None else list(self.sigma),
                "pairs": self.pairs}


class GyroAlignment:
    """Least-squares estimate of the gyro's z-rate response from frame pairs (module docstring).

    ``cross_axis_sigma`` is the prior's sigma of the x and y responses, ``scale_sigma`` of the z
    response (fractions); ``prior`` its mean (a calibration carried over from an earlier flight
    of the vehicle; default none), which is also the correction until the first pair.
    """

    def __init__(self, cross_axis_sigma: float, scale_sigma: float,
                 prior: tuple[float, float, float] = (0.0, 0.0, 0.0)):
        if not (cross_axis_sigma > 0.0 and scale_sigma > 0.0):
            raise ValueError("the prior's sigmas must be positive, got "
                             f"{cross_axis_sigma} and {scale_sigma}")
        prior = np.asarray(prior, dtype=float)
        if prior.shape != (3,) or not np.isfinite(prior).all() or prior[2] <= -1.0:
            raise ValueError(f"the prior's mean must be three finite responses with the z axis "
                             f"above -1, got {prior.tolist()}")
        self._normal = np.diag(1.0 / np.array([cross_axis_sigma, cross_axis_sigma,
                                               scale_sigma]) ** 2)  # the prior's information
        self._rhs = self._normal @ prior
        self._column = prior
        self._pairs = 0

    @property
    def column(self) -> np.ndarray:
        """The current estimate of ``e`` (a copy)."""
        return self._column.copy()

    @property
    def estimate(self) -> GyroAlignmentEstimate:
        """The estimate with its sigma (None before the first pair)."""
        sigma = None
        if self._pairs:
            sigma = tuple(float(s) for s in np.sqrt(np.diag(np.linalg.inv(self._normal))))
        return GyroAlignmentEstimate(tuple(float(c) for c in self._column), sigma, self._pairs)

    def add_pair(self, pair: PairRotations) -> None:
        """One frame pair, its gyro side from the raw gyro. A non-finite pair, or one whose
        overlap is not in (0, 1], is ignored."""
        if not (all(np.isfinite(m).all() for m in (pair.R_gyro, pair.R_camera, pair.information))
                and 0.0 < pair.overlap <= 1.0):
            return
        theta = log_so3(pair.R_camera)
        A = -theta[2] * exp_and_right_jacobian(theta[None])[1][0]
        residual = log_so3(pair.R_gyro.T @ pair.R_camera)
        # W = (Lambda^-1 + s^2 I)^-1 written so that a singular Lambda (no information) is 0
        spread = GYRO_PAIR_SIGMA ** 2 / pair.overlap
        W = np.linalg.solve(np.eye(3) + spread * pair.information, pair.information)
        left = residual - A @ self._column  # what the estimate leaves unexplained
        chi = math.sqrt(max(float(left @ W @ left), 0.0))
        weight = 1.0 if chi <= HUBER_K else HUBER_K / chi
        self._normal += weight * (A.T @ W @ A)
        self._rhs += weight * (A.T @ W @ residual)
        self._column = np.linalg.solve(self._normal, self._rhs)
        self._pairs += 1

    def correct(self, gyro: np.ndarray) -> np.ndarray:
        """``(I + e z^T)^-1 gyro``: a raw rate (or a raw rate less a bias) as the camera's
        body frame has it."""
        gyro = np.asarray(gyro, dtype=float)
        e = self._column
        z = gyro[2] / (1.0 + e[2])
        return np.array([gyro[0] - e[0] * z, gyro[1] - e[1] * z, z])

    def uncorrect(self, rate: np.ndarray) -> np.ndarray:
        """``(I + e z^T) rate``: a corrected rate (or bias) as the raw gyro reads it."""
        rate = np.asarray(rate, dtype=float)
        return rate + self._column * rate[2]

