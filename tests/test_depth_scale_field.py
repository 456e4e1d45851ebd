"""The scale field: the smooth, image-varying correction fitted to the anchors' residuals
after the rescaling curve (autonomy/depth/scale_field.py)."""

import cv2
import numpy as np

from autonomy.depth.scale_field import fit_scale_field, node_weights

SHAPE = (480, 640)


def _field_image(nodes: np.ndarray) -> np.ndarray:
    """The log-disparity field of ``nodes`` at every pixel, as OpenCV resizes a node image."""
    return cv2.resize(nodes.astype(np.float32), SHAPE[::-1], interpolation=cv2.INTER_LINEAR)


def _anchors(count: int, seed: int, region=(0, 640, 0, 480)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u0, u1, v0, v1 = region
    return np.column_stack([rng.uniform(u0, u1, count), rng.uniform(v0, v1, count)])


def _at(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    return image[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]


def test_a_smooth_error_over_the_image_is_mostly_removed_with_forty_noisy_anchors():
    """A 4 x 4 error field of 9 % (the synthetic network's, docs/synthetic_depth.md), 40
    anchors at random pixels with 2 % noise: over ten draws the field leaves under half of the
    error in the median draw and under 70 % in the worst."""
    left = []
    for seed in range(10):
        rng = np.random.default_rng(100 + seed)
        true = _field_image(rng.normal(0.0, 0.09, (4, 4)))
        pixels = _anchors(40, seed)
        residuals = _at(true, pixels) + rng.normal(0.0, 0.02, len(pixels))
        field = fit_scale_field(pixels, residuals, SHAPE, 4, 0.1)
        corrected = true + np.log(field.depth_factor(SHAPE))  # F - F_hat
        left.append(np.sqrt(np.mean(corrected ** 2) / np.mean(true ** 2)))
    assert np.median(left) < 0.5 and max(left) < 0.7, np.round(left, 2)


def test_the_fitted_function_is_the_one_applied_to_the_image():
    """The nodes' bilinear weights at a pixel are OpenCV's resize there, so the field fitted at
    the anchors is the field applied to the whole image."""
    nodes = np.random.default_rng(3).normal(0.0, 0.1, (3, 3))
    pixels = np.floor(_anchors(200, 4))  # whole pixels, where the image is read
    np.testing.assert_allclose(node_weights(pixels, SHAPE, 3) @ nodes.ravel(),
                               _at(_field_image(nodes), pixels), atol=2e-3)
    field = fit_scale_field(pixels, _at(_field_image(nodes), pixels), SHAPE, 3, 0.1)
    np.testing.assert_allclose(node_weights(pixels, SHAPE, 3) @ field.nodes.ravel(),
                               -np.log(_at(field.depth_factor(SHAPE), pixels)), atol=2e-3)


def test_anchors_that_agree_with_the_curve_leave_the_depth_as_it_is():
    field = fit_scale_field(_anchors(30, 5), np.zeros(30), SHAPE, 4, 0.1)
    np.testing.assert_array_equal(field.depth_factor(SHAPE), 1.0)


def test_without_anchors_there_is_no_correction():
    field = fit_scale_field(np.empty((0, 2)), np.empty(0), SHAPE, 4, 0.1)
    np.testing.assert_array_equal(field.depth_factor(SHAPE), 1.0)


def test_where_no_anchor_lies_the_field_corrects_less_than_where_they_say_so():
    """Every anchor on the left reads 10 % near: the left is corrected by most of that, the
    far right, with no anchor, by less (its nodes lean toward no correction)."""
    pixels = _anchors(40, 6, region=(0, 200, 0, 480))
    field = fit_scale_field(pixels, np.full(40, 0.1), SHAPE, 4, 0.1)
    factor = field.depth_factor(SHAPE)
    left, right = -np.log(factor[:, :100]).mean(), -np.log(factor[:, -100:]).mean()
    assert left > 0.07 and 0.0 <= right < 0.5 * left, (left, right)


def test_one_wrong_landmark_moves_the_field_little():
    pixels = _anchors(40, 7)
    residuals = np.random.default_rng(8).normal(0.0, 0.02, 40)
    clean = fit_scale_field(pixels, residuals, SHAPE, 4, 0.1)
    residuals[0] = 1.0  # a landmark 2.7 times too near
    spoiled = fit_scale_field(pixels, residuals, SHAPE, 4, 0.1)
    change = np.abs(np.log(spoiled.depth_factor(SHAPE) / clean.depth_factor(SHAPE)))
    assert change.max() < 0.05, change.max()
