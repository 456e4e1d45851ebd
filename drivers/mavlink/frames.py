"""PX4's frames against ours: local NED and body FRD versus world ENU (z up) and body FLU.

The simulator's world frame ``W`` is east-north-up, so PX4's local NED is ``x_N = y_W``,
``y_E = x_W``, ``z_D = -z_W``; body FRD is body FLU with y and z negated. Both maps are their
own inverses.
"""

from __future__ import annotations

import numpy as np

from autonomy.geometry import quat_multiply, rot_to_quat

#: R_NED_ENU: swaps x and y, negates z. Symmetric and its own inverse.
R_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: R_FLU_FRD: negates y and z. Symmetric and its own inverse.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])

_Q_NED_ENU = rot_to_quat(R_NED_ENU)
_Q_FLU_FRD = rot_to_quat(R_FLU_FRD)


def enu_to_ned(v) -> np.ndarray:
    """A world vector (position, velocity, acceleration) from ENU into NED, or back."""
    x, y, z = v
    return np.array([y, x, -z], dtype=float)


ned_to_enu = enu_to_ned


def flu_to_frd(v) -> np.ndarray:
    """A body vector (angular rate, specific force) from FLU into FRD, or back."""
    x, y, z = v
    return np.array([x, -y, -z], dtype=float)


frd_to_flu = flu_to_frd


def quat_enu_flu_to_ned_frd(q_ENU_FLU) -> np.ndarray:
    """Attitude ``q_W_B`` (ENU world, FLU body) as PX4's ``q_NED_FRD``, scalar first, ``w >= 0``."""
    q = quat_multiply(quat_multiply(_Q_NED_ENU, np.asarray(q_ENU_FLU, dtype=float)), _Q_FLU_FRD)
    return -q if q[0] < 0.0 else q


def quat_ned_frd_to_enu_flu(q_NED_FRD) -> np.ndarray:
    """PX4's attitude ``q_NED_FRD`` as ``q_W_B`` (ENU world, FLU body); the inverse map."""
    # R_NED_ENU and R_FLU_FRD are involutions, so the same sandwich inverts itself.
    return quat_enu_flu_to_ned_frd(q_NED_FRD)
