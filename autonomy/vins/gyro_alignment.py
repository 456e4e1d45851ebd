"""The gyro's misalignment, as the camera sees it, estimated online and corrected.

A MEMS gyro's axes respond to rotation about the others (cross-axis sensitivity: the
ICM-42688-P's datasheet gives +-1.25 %), and a camera's mounting is known only to a
calibration's accuracy (0.5 deg in the realistic profile). Both make the gyro's rotation
disagree with the camera's. At a 90 deg corner a 1.25 % response of the x and y axes to the
yaw rate integrates about 1 deg of false tilt; gravity through it is 0.17 m/s^2 of false
horizontal acceleration, which the smoother explains as an accelerometer bias, and a bias
the rotor-drag factor (:mod:`autonomy.vins.drag`) then reads as speed (docs/vins.md). The
responses to the roll and pitch rates do the same whenever the vehicle pitches to speed up
or slow down: a 2 % response of the roll axis to the pitch rate rolls the gyro's attitude by
0.1 deg for each 5 deg of pitch, and the flight's bearing turns by up to 1.7 deg
(docs/vins.md, "The gyro's whole misalignment in navigation").

**The model.** With ``E`` the misalignment, the gyro reads

    omega_m = (I + E) omega + b + n

in the body frame *as the camera's configured mounting defines it*: a mounting error ``d``
turns the camera's rotations by ``[d]x``, so ``E`` is the gyro's own cross-axis and scale
response plus the mounting's, which is the combination that has to go for the gyro to agree
with the camera. Told apart they are not needed: the accelerometer's frame, off by the same
small rotation, reads a thrust that stays along the body's z as a constant bias, which the
smoother estimates anyway. ``rates`` chooses the columns of ``E`` estimated: the response to
the yaw rate alone (``e = E z``, three numbers: corners are yaw turns, and it is learned in
the first), or all three (nine numbers: the roll and pitch columns need the tilts of many
starts and stops, so they are learned later in a flight). The others stay at the prior's
mean, and what they explain is taken out of each pair's residual before the fit.

**The measurement.** The time-offset estimator's frame pairs (:mod:`autonomy.vins.time_offset`)
give, over each pair, the camera's rotation ``theta_v`` (in the body frame, information
``Lambda``) and the gyro's ``R_g = Exp(theta_v + E theta_v)``; with
``Exp(a + d) ~ Exp(a) Exp(J_r(a) d)`` (``J_r`` the right Jacobian of SO(3)) and
``E theta = (theta^T kron I) vec(E)`` (``vec`` stacking the columns) the residual is

    r = Log(R_g^T R_v) = A vec(E),    A = -J_r(theta_v) (theta_v^T kron I),

(to first order in ``E``; for the yaw column alone ``A = -theta_v,z J_r(theta_v)``; taking
``J_r = I`` instead turns the fitted x and y responses by half the pair's yaw, which corners
one way round do not average out). The estimate is the least-squares fit of the estimated
elements over the pairs with a Gaussian prior (:class:`GyroAlignment`):

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

**The correction.** Every gyro sample is corrected before the VINS uses it,
``omega = (I + E)^-1 omega_m``, and the smoother estimates its bias on the corrected
samples. The time-offset estimator keeps the raw samples (and gets that bias as the raw gyro
reads it, ``(I + E) b``), so that its pairs measure the whole ``E`` whatever the
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
#: The columns of ``E`` each choice of ``rates`` estimates.
RATE_COLUMNS = {"yaw": (2,), "all": (0, 1, 2)}


@dataclass(frozen=True)
class GyroAlignmentEstimate:
    """The gyro's response to the body's z rate (``column``: x, y and z axes, fractions),
    its one-sigma (``sigma``) and the number of frame ``pairs`` it rests on; ``matrix``, the
    whole ``E`` by rows when more than its yaw column is corrected (None otherwise), and
    ``matrix_sigma``, its one-sigma by rows (0 where not estimated; None before the first
    pair)."""

    column: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sigma: tuple[float, float, float] | None = None
    pairs: int = 0
    matrix: tuple[tuple[float, ...], ...] | None = None
    matrix_sigma: tuple[tuple[float, ...], ...] | None = None

    def as_dict(self) -> dict:
        """Plain lists and numbers, for JSON: ``column``, ``sigma``, ``pairs``, ``matrix``,
        ``matrix_sigma``."""
        def rows(m):
            return None if m is None else [list(r) for r in m]
        return {"column": list(self.column),
                "sigma": None if self.sigma is None else list(self.sigma),
                "pairs": self.pairs, "matrix": rows(self.matrix),
                "matrix_sigma": rows(self.matrix_sigma)}


class GyroAlignment:
    """Least-squares estimate of the gyro's misalignment ``E`` from frame pairs (module
    docstring).

    ``cross_axis_sigma`` is the prior's sigma of each axis' response to another's rate,
    ``scale_sigma`` of its response to its own (fractions); ``prior`` its mean, a calibration
    carried over from an earlier flight of the vehicle (three numbers: the yaw column; nine:
    the whole ``E`` by rows; default none), which is also the correction until the first
    pair. ``rates``: the rates whose responses are estimated, ``"yaw"`` or ``"all"``
    (:data:`RATE_COLUMNS`).
    """

    def __init__(self, cross_axis_sigma: float, scale_sigma: float,
                 prior: tuple[float, ...] = (0.0, 0.0, 0.0), rates: str = "yaw"):
        if not (cross_axis_sigma > 0.0 and scale_sigma > 0.0):
            raise ValueError("the prior's sigmas must be positive, got "
                             f"{cross_axis_sigma} and {scale_sigma}")
        if rates not in RATE_COLUMNS:
            raise ValueError(f"rates must be one of {sorted(RATE_COLUMNS)}, got {rates!r}")
        self._E = _prior_matrix(prior)
        self._whole = rates == "all" or bool(np.any(self._E[:, :2]))
        #: the estimated elements of vec(E) (column-major)
        self._index = np.array([3 * c + r for c in RATE_COLUMNS[rates] for r in range(3)])
        self._held = np.setdiff1d(np.arange(9), self._index)
        sigmas = np.array([scale_sigma if k % 4 == 0 else cross_axis_sigma
                           for k in self._index])  # k % 4 == 0: the diagonal of vec(E)
        self._normal = np.diag(1.0 / sigmas ** 2)  # the prior's information
        self._rhs = self._normal @ self._vec[self._index]
        self._pairs = 0

    @property
    def _vec(self) -> np.ndarray:
        return self._E.reshape(9, order="F")

    @property
    def matrix(self) -> np.ndarray:
        """The current estimate of ``E`` (a copy)."""
        return self._E.copy()

    @property
    def column(self) -> np.ndarray:
        """The current estimate of ``e``, its yaw column (a copy)."""
        return self._E[:, 2].copy()

    @property
    def estimate(self) -> GyroAlignmentEstimate:
        """The estimate with its sigmas (None before the first pair)."""
        sigma = matrix_sigma = None
        if self._pairs:
            variance = np.zeros(9)
            variance[self._index] = np.diag(np.linalg.inv(self._normal))
            deviation = np.sqrt(variance).reshape(3, 3, order="F")
            sigma = tuple(float(s) for s in deviation[:, 2])
            matrix_sigma = _rows(deviation) if self._whole else None
        return GyroAlignmentEstimate(tuple(float(c) for c in self._E[:, 2]), sigma, self._pairs,
                                     _rows(self._E) if self._whole else None, matrix_sigma)

    def add_pair(self, pair: PairRotations) -> None:
        """One frame pair, its gyro side from the raw gyro. A non-finite pair, or one whose
        overlap is not in (0, 1], is ignored."""
        if not (all(np.isfinite(m).all() for m in (pair.R_gyro, pair.R_camera, pair.information))
                and 0.0 < pair.overlap <= 1.0):
            return
        theta = log_so3(pair.R_camera)
        A_all = -exp_and_right_jacobian(theta[None])[1][0] @ np.kron(theta, np.eye(3))
        A = A_all[:, self._index]
        # the residual less what the elements held at the prior's mean explain
        residual = log_so3(pair.R_gyro.T @ pair.R_camera) - A_all[:, self._held] @ \
            self._vec[self._held]
        # W = (Lambda^-1 + s^2 I)^-1 written so that a singular Lambda (no information) is 0
        spread = GYRO_PAIR_SIGMA ** 2 / pair.overlap
        W = np.linalg.solve(np.eye(3) + spread * pair.information, pair.information)
        left = residual - A @ self._vec[self._index]  # what the estimate leaves unexplained
        chi = math.sqrt(max(float(left @ W @ left), 0.0))
        weight = 1.0 if chi <= HUBER_K else HUBER_K / chi
        self._normal += weight * (A.T @ W @ A)
        self._rhs += weight * (A.T @ W @ residual)
        vec = self._vec.copy()
        vec[self._index] = np.linalg.solve(self._normal, self._rhs)
        self._E = vec.reshape(3, 3, order="F")
        self._pairs += 1

    def correct(self, gyro: np.ndarray) -> np.ndarray:
        """``(I + E)^-1 gyro``: a raw rate (or a raw rate less a bias) as the camera's
        body frame has it."""
        return np.linalg.solve(np.eye(3) + self._E, np.asarray(gyro, dtype=float))

    def uncorrect(self, rate: np.ndarray) -> np.ndarray:
        """``(I + E) rate``: a corrected rate (or bias) as the raw gyro reads it."""
        return (np.eye(3) + self._E) @ np.asarray(rate, dtype=float)


def _prior_matrix(prior) -> np.ndarray:
    """``E`` from a prior's mean: three numbers (the yaw column) or nine (``E`` by rows);
    ValueError unless finite with every axis' own response above -1."""
    values = np.asarray(prior, dtype=float).reshape(-1)
    if values.shape == (3,):
        E = np.zeros((3, 3))
        E[:, 2] = values
    elif values.shape == (9,):
        E = values.reshape(3, 3)
    else:
        E = None
    if E is None or not np.isfinite(E).all() or np.any(np.diag(E) <= -1.0):
        raise ValueError(f"the prior's mean must be three finite responses to the yaw rate or "
                         f"nine (the whole matrix by rows), each axis' own above -1, got "
                         f"{values.tolist()}")
    return E


def _rows(matrix: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in matrix)
