"""Rotations, poses and the pinhole model that every frame conversion rests on."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from autonomy.geometry import (
    R_BODY_CAMERA, PinholeCamera, invert_pose, make_pose, quat_multiply, quat_to_rot,
    rot_to_quat, rot_z, so3_exp, so3_log, yaw_of,
)

rotation_vectors = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)


@given(rotation_vectors)
def test_exp_and_log_are_inverse_within_pi(phi):
    R = so3_exp(phi)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    if np.linalg.norm(phi) < math.pi - 1e-6:
        assert np.allclose(so3_log(R), phi, atol=1e-9)


@given(rotation_vectors, rotation_vectors)
def test_quaternion_product_composes_rotations(a, b):
    qa, qb = rot_to_quat(so3_exp(a)), rot_to_quat(so3_exp(b))
    assert np.allclose(quat_to_rot(quat_multiply(qa, qb)), so3_exp(a) @ so3_exp(b), atol=1e-12)
    assert np.allclose(quat_to_rot(qa), so3_exp(a), atol=1e-12)


def test_half_turn_survives_the_quaternion_round_trip():
    for axis in np.eye(3):
        R = so3_exp(math.pi * axis)
        assert np.allclose(quat_to_rot(rot_to_quat(R)), R, atol=1e-12)


def test_yaw_of_reads_back_rot_z():
    for yaw in (-3.0, -1.0, 0.0, 0.5, 3.1):
        assert math.isclose(yaw_of(rot_z(yaw)), yaw, abs_tol=1e-12)


def test_camera_looks_along_body_x_with_image_down_along_gravity():
    # A point 2 m ahead of the body is on the optical axis, 2 m deep.
    assert np.allclose(R_BODY_CAMERA @ np.array([0.0, 0.0, 2.0]), [2.0, 0.0, 0.0])
    # Image right is body right (-y); image down is body down (-z).
    assert np.allclose(R_BODY_CAMERA @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    assert np.allclose(R_BODY_CAMERA @ [0.0, 1.0, 0.0], [0.0, 0.0, -1.0])
    assert np.isclose(np.linalg.det(R_BODY_CAMERA), 1.0)


def test_pose_inverse_undoes_the_pose():
    T = make_pose(so3_exp(np.array([0.3, -0.2, 1.0])), np.array([1.0, 2.0, 3.0]))
    assert np.allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)


def test_pinhole_from_field_of_view_projects_the_edge_ray_to_the_edge():
    camera = PinholeCamera.from_hfov(640, 480, math.radians(90.0))
    assert math.isclose(camera.fx, 320.0)
    edge = camera.project(np.array([[1.0, 0.0, 1.0]]))[0]  # 45 degrees to the right
    assert math.isclose(edge[0], 639.5)  # the image's right border (pixel centres 0 .. 639)
    rays = camera.rays()
    pixels = camera.project(rays.reshape(-1, 3)).reshape(480, 640, 2)
    assert np.allclose(pixels[12, 34], [34.0, 12.0])


@pytest.mark.parametrize("kwargs, message", [
    ({"width": 0, "height": 480, "fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}, "size"),
    ({"width": 640, "height": 480, "fx": -1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0}, "focal"),
])
def test_pinhole_rejects_impossible_intrinsics(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PinholeCamera(**kwargs)


def test_field_of_view_outside_the_open_half_turn_is_rejected():
    with pytest.raises(ValueError, match="field of view"):
        PinholeCamera.from_hfov(640, 480, math.pi)


def test_undistortion_inverts_the_radial_tangential_model_and_matches_opencv():
    import cv2

    from autonomy.geometry import distort_points, undistort_points

    camera = PinholeCamera(752, 480, 458.654, 457.296, 367.215, 248.375)
    euroc = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    u, v = np.meshgrid(np.linspace(0, 751, 12), np.linspace(0, 479, 9))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    for distortion in (euroc, euroc + (0.01,), ()):
        xy = undistort_points(camera, distortion, pixels)
        assert np.allclose(distort_points(camera, distortion, xy), pixels, atol=1e-8)
        expected = cv2.undistortPoints(
            pixels.reshape(-1, 1, 2), camera.K, np.array(distortion, dtype=float), None, None,
            None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
        assert np.allclose(xy, expected, atol=1e-7)


def test_undistortion_rejects_bad_coefficients_and_shapes():
    from autonomy.geometry import undistort_points

    camera = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
    with pytest.raises(ValueError, match="coefficients"):
        undistort_points(camera, (0.1, 0.2), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="finite"):
        undistort_points(camera, (np.nan, 0.0, 0.0, 0.0), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="shape"):
        undistort_points(camera, (), np.zeros((3,)))
    assert undistort_points(camera, (-0.3, 0.1, 0.0, 0.0), np.zeros((0, 2))).shape == (0, 2)
