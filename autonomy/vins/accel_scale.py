"""The accelerometer's vertical sensitivity, read from its specific force at rest.

A multicopter's specific force lies along its thrust, the body's z axis: the horizontal
accelerations that show the path's metric scale are read on that axis, tilted, as is the height
wave's vertical one. An accelerometer whose z axis reads ``1 + e`` of the truth therefore makes
every path ``e`` long, times about 0.6-0.8 (docs/vins.md, "The accelerometer as PX4 calibrates
it" and "Seeds 0-9 ... with the height wave"), and nothing in flight tells ``e`` from a bias:
the thrust's variation, the only thing that would, is a few per cent of ``g``.

On the ground, level or tilted, the accelerometer reads ``|f| = g (1 + e) + b_z`` to first
order. Started with a zero bias, the smoother takes the whole excess ``r = |f| / g - 1`` as the
bias (``b = g r``) and keeps ``e`` in the scale. With ``e`` and ``b_z / g`` independent, zero
mean and of spreads ``s_e`` and ``s_b``, the least-squares split of the excess is

    e_hat = k r,    k = s_e^2 / (s_e^2 + s_b^2),

and ``e - e_hat`` has the variance ``s_e^2 s_b^2 / (s_e^2 + s_b^2)``: a share ``1 - k`` of the
scale's variance, at the price of the bias's share ``k`` read as scale. ``k`` is
``[vins] rest_accel_scale_share`` (0, the default: all bias, as before). For a vehicle PX4
calibrated by hand, ``s_e`` is its six-orientation fit's scale error, 0.465 % at 3 degree
placements (``drivers/sim/imu.py``, ``_px4_calibrated``, over 2,000 of its vehicles; ASSUMED
placements), and ``s_b`` the bias its learned calibration leaves, 0.05 / sqrt(3) m/s^2 of
``g``, 0.294 % (``VehicleIMU::AccelCalibrationUpdate``'s dead band): ``k = 0.71``. A vehicle
calibrated on a level jig has ``s_e`` near 0.06 %: ``k`` near 0.04, so 0.

``g`` is the smoother's gravity (:data:`autonomy.geometry.GRAVITY`), so that the corrected
reading at rest is the one the smoother expects but for the bias's share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autonomy.geometry import GRAVITY


@dataclass(frozen=True)
class RestAccelScale:
    """The accelerometer's z axis read as ``1 + error`` of the truth (module docstring);
    :meth:`correct` divides it out."""

    error: float

    @classmethod
    def from_rest(cls, accel_norm: float, share: float) -> "RestAccelScale":
        """``share`` of the mean specific force's excess over gravity at rest, ``accel_norm``
        (m/s^2), taken as the z axis's sensitivity error."""
        if not (math.isfinite(accel_norm) and accel_norm > 0.0):
            raise ValueError(f"accel_norm must be a positive number of m/s^2, got {accel_norm}")
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"share must be in [0, 1], got {share}")
        return cls(share * (accel_norm / GRAVITY - 1.0))

    def correct(self, accel) -> np.ndarray:
        """The specific force ``accel`` (body, m/s^2; one ``(3,)`` or rows ``(N, 3)``) with its
        z divided by ``1 + error``."""
        corrected = np.array(accel, dtype=float)
        corrected[..., 2] /= 1.0 + self.error
        return corrected
