"""Our odometry (frame L = PX4's local frame as ENU z-up, body FLU) as MAVLink ODOMETRY fields.

ODOMETRY is sent with ``frame_id = MAV_FRAME_LOCAL_NED`` (position, attitude ``q_NED_FRD``)
and ``child_frame_id = MAV_FRAME_BODY_FRD`` (velocity and angular rate in the body FRD frame),
the frames PX4's ``mavlink_receiver.cpp`` takes for external vision.

Pose covariance. Ours is 6x6 over the body-frame right perturbation ``ξ = (δφ_B, δρ_B)``,
rotation first: ``R' = R Exp(δφ_B)``, ``p' = p + R δρ_B`` (GTSAM's Pose3 tangent), body FLU.
MAVLink's is over ``η = (δx, δy, δz, δroll, δpitch, δyaw)``: position in local NED and the
ZYX Euler angles of ``q_NED_FRD``. To first order ``η = J ξ`` with

    δp_NED = R_NED_ENU R_L_B δρ_B
    δe     = E(roll, pitch)^-1 R_FRD_FLU δφ_B,     E^-1 = [[1, sφ tθ, cφ tθ],
                                                           [0, cφ,    -sφ   ],
                                                           [0, sφ/cθ, cφ/cθ]]

(``E^-1`` maps a body FRD rotation increment to Euler-angle increments, the Euler kinematic
equation), so ``Σ_MAVLink = J Σ J^T``, sent as its upper triangle row by row (21 numbers).
Near pitch ±90° the Euler angles are singular: the covariance is then sent as unknown (NaN in
the first element), as it is when none is given. PX4 (v1.14) reads only the diagonal.
"""

from __future__ import annotations

import math

import numpy as np

from autonomy.geometry import quat_to_rot
from drivers.mavlink.frames import (R_FLU_FRD, R_NED_ENU, enu_to_ned, flu_to_frd,
                                    quat_enu_flu_to_ned_frd)

#: |cos(pitch)| below this (pitch within about 0.6° of ±90°): Euler covariance unknown.
MIN_COS_PITCH = 0.01
#: The covariance MAVLink reads as "unknown".
UNKNOWN_COVARIANCE = [math.nan] + [0.0] * 20
_UPPER = np.triu_indices(6)


def _finite_vector(name: str, value, size: int) -> np.ndarray:
    array = np.asarray(value, dtype=float)
    if array.shape != (size,) or not np.isfinite(array).all():
        raise ValueError(f"{name} must be {size} finite numbers, got {value!r}")
    return array


def unit_quaternion(q) -> np.ndarray:
    """``q`` (w, x, y, z) normalised; ValueError when not finite or far from unit length."""
    q = _finite_vector("q_L_B", q, 4)
    norm = float(np.linalg.norm(q))
    if not 0.9 < norm < 1.1:
        raise ValueError(f"q_L_B must be a unit quaternion (w, x, y, z), its norm is {norm:.3g}")
    return q / norm


def euler_rate_matrix(R_NED_FRD: np.ndarray) -> np.ndarray | None:
    """``E^-1`` of the module docstring at the attitude's roll and pitch; None near ±90°."""
    roll = math.atan2(R_NED_FRD[2, 1], R_NED_FRD[2, 2])
    pitch = -math.asin(max(-1.0, min(1.0, R_NED_FRD[2, 0])))
    cr, sr, cp = math.cos(roll), math.sin(roll), math.cos(pitch)
    if abs(cp) < MIN_COS_PITCH:
        return None
    tp = math.tan(pitch)
    return np.array([[1.0, sr * tp, cr * tp], [0.0, cr, -sr], [0.0, sr / cp, cr / cp]])


def pose_covariance_to_mavlink(covariance, q_L_B) -> list[float]:
    """Our 6x6 pose covariance (rotation then position, body right perturbation) at attitude
    ``q_L_B`` as ODOMETRY.pose_covariance; unknown when ``covariance`` is None or its first
    element NaN. ValueError for any other non-finite or ill-shaped input."""
    if covariance is None:
        return list(UNKNOWN_COVARIANCE)
    sigma = np.asarray(covariance, dtype=float)
    if sigma.shape != (6, 6):
        raise ValueError(f"pose_covariance must be 6x6, got shape {sigma.shape}")
    if math.isnan(sigma[0, 0]):
        return list(UNKNOWN_COVARIANCE)
    if not np.isfinite(sigma).all() or (np.diag(sigma) < 0.0).any():
        raise ValueError("pose_covariance must be finite with a non-negative diagonal")
    R_L_B = quat_to_rot(q_L_B)
    E_inv = euler_rate_matrix(R_NED_ENU @ R_L_B @ R_FLU_FRD)
    if E_inv is None:
        return list(UNKNOWN_COVARIANCE)
    J = np.zeros((6, 6))
    J[0:3, 3:6] = R_NED_ENU @ R_L_B
    J[3:6, 0:3] = E_inv @ R_FLU_FRD
    converted = J @ (0.5 * (sigma + sigma.T)) @ J.T
    return [float(x) for x in converted[_UPPER]]


def odometry_fields(position_L, q_L_B, velocity_L, angular_velocity_B) -> dict:
    """Position (NED), ``q`` (NED/FRD), velocity (body FRD) and rates (FRD) for ODOMETRY,
    with ``q_L_B`` normalised.

    ``velocity_L`` and ``angular_velocity_B`` may be None (unknown: NaN on the wire, which PX4
    reads as "not provided"); position and attitude are required. ValueError when not finite.
    """
    position = _finite_vector("position_L", position_L, 3)
    q = unit_quaternion(q_L_B)
    velocity_B = np.full(3, math.nan)
    if velocity_L is not None:
        velocity_B = quat_to_rot(q).T @ _finite_vector("velocity_L", velocity_L, 3)
    rates = np.full(3, math.nan)
    if angular_velocity_B is not None:
        rates = _finite_vector("angular_velocity_B", angular_velocity_B, 3)
    return {"position": enu_to_ned(position), "q_L_B": q, "q": quat_enu_flu_to_ned_frd(q),
            "velocity": flu_to_frd(velocity_B), "rates": flu_to_frd(rates)}
