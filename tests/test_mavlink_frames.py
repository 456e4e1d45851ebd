"""ENU/FLU <-> NED/FRD: the one place PX4's frames meet ours."""

import math

import numpy as np

from autonomy.geometry import quat_to_rot, rot_to_quat, rot_z, so3_exp
from drivers.mavlink.frames import (
    enu_to_ned, flu_to_frd, quat_enu_flu_to_ned_frd, quat_ned_frd_to_enu_flu,
)


def test_north_east_down_from_east_north_up():
    assert np.allclose(enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    assert np.allclose(flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])


def test_facing_east_is_px4_heading_ninety_degrees():
    q_ned = quat_enu_flu_to_ned_frd(rot_to_quat(rot_z(0.0)))
    R = quat_to_rot(q_ned)
    assert math.isclose(math.degrees(math.atan2(R[1, 0], R[0, 0])), 90.0, abs_tol=1e-9)


def test_attitude_conversion_maps_vectors_consistently_and_inverts():
    q_W_B = rot_to_quat(so3_exp(np.array([0.2, -0.4, 1.3])))
    q_NED_FRD = quat_enu_flu_to_ned_frd(q_W_B)
    v_B = np.array([0.3, -1.0, 2.0])
    # Rotating in our frames then converting equals converting then rotating in PX4's.
    assert np.allclose(enu_to_ned(quat_to_rot(q_W_B) @ v_B), quat_to_rot(q_NED_FRD) @ flu_to_frd(v_B))
    assert np.allclose(quat_ned_frd_to_enu_flu(q_NED_FRD), q_W_B)
