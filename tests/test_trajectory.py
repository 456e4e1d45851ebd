"""Trajectory alignment and error: a known transform is recovered, and a wrong scale shows;
the NEES of errors drawn from a covariance averages their dimension."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from autonomy.geometry import make_pose, quat_to_rot, rot_to_quat, so3_exp, so3_log
from autonomy.trajectory import (
    align_umeyama, ate_rmse, interpolate_poses, nees, path_length, pose_error_body,
)

rotation_vectors = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3).map(np.array)
translations = st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3).map(np.array)
scales = st.floats(0.1, 10.0)
seeds = st.integers(0, 2**32 - 1)


def _cloud(seed: int, n: int = 30) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-5.0, 5.0, (n, 3))


@given(rotation_vectors, translations, scales, seeds)
def test_a_noise_free_similarity_is_recovered_exactly(phi, t, s, seed):
    source = _cloud(seed)
    R = so3_exp(phi)
    alignment = align_umeyama(source, s * source @ R.T + t, with_scale=True)
    assert np.allclose(alignment.R, R, atol=1e-9)
    assert alignment.s == pytest.approx(s, rel=1e-9)
    assert np.allclose(alignment.t, t, atol=1e-7)


@given(rotation_vectors, translations, seeds)
def test_a_noise_free_rigid_motion_is_recovered_exactly(phi, t, seed):
    source = _cloud(seed)
    R = so3_exp(phi)
    alignment = align_umeyama(source, source @ R.T + t, with_scale=False)
    assert np.allclose(alignment.R, R, atol=1e-9) and np.allclose(alignment.t, t, atol=1e-8)
    assert alignment.s == 1.0
    assert ate_rmse(source, source @ R.T + t) < 1e-9


@given(rotation_vectors, translations, scales, seeds)
def test_with_noise_the_transform_is_close_and_the_ate_is_the_noise(phi, t, s, seed):
    rng = np.random.default_rng(seed)
    source = rng.uniform(-5.0, 5.0, (2000, 3))
    R = so3_exp(phi)
    sigma = 0.01 * s  # 1 cm on the unscaled 10 m cloud
    target = s * source @ R.T + t + sigma * rng.standard_normal(source.shape)
    alignment = align_umeyama(source, target, with_scale=True)
    assert np.linalg.norm(so3_log(alignment.R.T @ R)) < 1e-3
    assert alignment.s == pytest.approx(s, rel=1e-3)
    # Each point's residual is 3-D Gaussian noise: its RMS norm is sigma * sqrt(3).
    assert ate_rmse(source, target, with_scale=True) == pytest.approx(sigma * math.sqrt(3), rel=0.1)


def test_a_scale_error_shows_in_the_ate_only_without_scale():
    truth = _cloud(1, 200)
    estimated = 0.8 * truth @ so3_exp(np.array([0.1, -0.4, 2.0])).T + [3.0, 1.0, -2.0]
    assert ate_rmse(estimated, truth, with_scale=True) < 1e-9
    assert ate_rmse(estimated, truth) > 0.1 * np.sqrt(np.mean(np.sum(
        (truth - truth.mean(axis=0)) ** 2, axis=1)))


def test_a_reflection_is_fitted_by_the_best_rotation_not_by_a_mirror():
    source = _cloud(2)
    alignment = align_umeyama(source, source * [1.0, 1.0, -1.0], with_scale=False)
    assert np.linalg.det(alignment.R) == pytest.approx(1.0)


@pytest.mark.parametrize("source, target, complaint", [
    (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3 points"),
    (np.zeros((4, 3)), np.zeros((5, 3)), "matching points"),
    (np.zeros((4, 2)), np.zeros((4, 2)), "matching points"),
    (np.full((4, 3), np.nan), np.zeros((4, 3)), "NaN"),
    (np.ones((4, 3)), np.ones((4, 3)), "coincide or are collinear"),
    (np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), np.outer(np.arange(5.0), [0.0, 0.0, 1.0]),
     "coincide or are collinear"),
])
def test_unusable_points_raise_a_clear_error(source, target, complaint):
    with pytest.raises(ValueError, match=complaint):
        align_umeyama(source, target, with_scale=True)


def test_path_length_sums_the_steps():
    assert path_length(np.array([[0.0, 0, 0], [3, 4, 0], [3, 4, 2]])) == pytest.approx(7.0)
    assert path_length(np.zeros((1, 3))) == 0.0


@given(rotation_vectors, rotation_vectors, st.floats(0.0, 1.0))
def test_interpolation_is_linear_in_position_and_slerps_the_rotation(a, b, alpha):
    q0, q1 = rot_to_quat(so3_exp(a)), -rot_to_quat(so3_exp(b))  # either sign of q1 is q1
    delta = so3_exp(a).T @ so3_exp(b)
    positions = np.array([[0.0, 0.0, 0.0], [2.0, -4.0, 6.0]])
    p, q = interpolate_poses([10.0 + alpha], np.array([10.0, 11.0]), positions, np.array([q0, q1]))
    assert np.allclose(p, alpha * positions[1])
    # Slerp turns at a constant rate about the fixed axis of the relative rotation.
    expected = so3_exp(a) @ so3_exp(alpha * so3_log(delta))
    assert np.allclose(quat_to_rot(q[0]), expected, atol=1e-9)


def test_interpolation_hits_the_samples_and_refuses_to_extrapolate():
    t = np.array([0.0, 0.5, 2.0])
    positions = np.arange(9.0).reshape(3, 3)
    quaternions = np.array([rot_to_quat(so3_exp(np.array([0.0, 0.0, k]))) for k in range(3)])
    p, q = interpolate_poses(t, t, positions, quaternions)
    assert np.allclose(p, positions) and np.allclose(q, quaternions)
    for outside in (-0.01, 2.01, np.nan):
        with pytest.raises(ValueError, match="outside the samples' span"):
            interpolate_poses([outside], t, positions, quaternions)
    with pytest.raises(ValueError, match="strictly increasing"):
        interpolate_poses([0.0], np.array([0.0, 0.0]), positions[:2], quaternions[:2])


@pytest.mark.parametrize("dimension", [3, 6])
def test_errors_drawn_from_the_covariance_average_their_dimension(dimension):
    rng = np.random.default_rng(dimension)
    root = rng.normal(size=(dimension, dimension))
    covariance = root @ root.T + 0.1 * np.eye(dimension)
    errors = rng.multivariate_normal(np.zeros(dimension), covariance, size=20000)
    mean = np.mean([nees(e, covariance) for e in errors])
    # the mean of 20000 chi-squared draws: sigma sqrt(2 d / 20000) < 0.025
    assert mean == pytest.approx(dimension, abs=0.1)
    assert np.mean([nees(e, covariance / 4.0) for e in errors]) == pytest.approx(4 * mean)


@pytest.mark.parametrize("covariance, complaint", [
    (np.zeros((3, 3)), "singular"),
    (np.full((3, 3), np.nan), "not finite"),
    (np.eye(2), "wrong shape"),
])
def test_an_unusable_covariance_is_refused(covariance, complaint):
    with pytest.raises(ValueError, match=complaint):
        nees(np.ones(3), covariance)


@given(rotation_vectors, translations)
def test_the_pose_error_is_the_body_frame_perturbation_that_makes_the_truth(phi, t):
    estimate = make_pose(so3_exp(phi), t)
    rotation, shift = np.array([0.01, -0.02, 0.005]), np.array([0.3, -0.1, 0.2])
    truth = make_pose(estimate[:3, :3] @ so3_exp(rotation), t + estimate[:3, :3] @ shift)
    assert np.allclose(pose_error_body(estimate, truth), np.r_[rotation, shift], atol=1e-9)
