"""Nearest-surface anchor sampling: the largest disparity of the four surrounding pixels."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.ndimage import map_coordinates

from autonomy.depth.anchors import sample_nearest_surface

# Row v, column u. Around (u, v) = (0.5, 0.5) the four are 1, 9, 3, 2: bilinear gives 3.75.
DISPARITY = np.array(
    [
        [1.0, 9.0, 4.0],
        [3.0, 2.0, 5.0],
    ],
    dtype=np.float32,
)


def test_largest_of_the_four_neighbours_wins_not_the_interpolation():
    result = sample_nearest_surface(DISPARITY, np.array([[0.5, 0.5], [1.9, 0.1]]))
    np.testing.assert_array_equal(result, [9.0, 9.0])


def test_u_is_the_column_and_v_the_row():
    # (u=1.2, v=0) touches columns 1, 2 of rows 0, 1: max(2, 3, 5, 6); read as (row, column)
    # it would lie outside the 2-row image. (u=0, v=0.3): columns 0, 1 of rows 0, 1.
    image = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    result = sample_nearest_surface(image, np.array([[1.2, 0.0], [0.0, 0.3]]))
    np.testing.assert_array_equal(result, [6.0, 5.0])


def test_integer_coordinates_look_right_and_down():
    # Pixel centre (1, 0): neighbours d[0,1], d[0,2], d[1,1], d[1,2] = 9, 4, 2, 5
    assert sample_nearest_surface(DISPARITY, np.array([[1.0, 0.0]]))[0] == 9.0
    # Pixel centre (0, 1) on the last row: only d[1,0], d[1,1] = 3, 2
    assert sample_nearest_surface(DISPARITY, np.array([[0.0, 1.0]]))[0] == 3.0


def test_last_row_and_column_use_themselves():
    result = sample_nearest_surface(DISPARITY, np.array([[2.0, 1.0], [2.0, 0.5], [1.5, 1.0]]))
    np.testing.assert_array_equal(result, [5.0, 5.0, 5.0])


@pytest.mark.parametrize(
    "point",
    [(-0.01, 0.0), (0.0, -0.01), (2.01, 0.0), (0.0, 1.01), (np.nan, 0.5), (0.5, np.nan),
     (np.inf, 0.5), (0.5, -np.inf)],
)
def test_points_outside_the_image_or_not_finite_are_nan(point):
    result = sample_nearest_surface(DISPARITY, np.array([point, (0.5, 0.5)]))
    assert math.isnan(result[0])
    assert result[1] == 9.0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_neighbours_are_ignored(bad):
    image = DISPARITY.copy()
    image[0, 1] = bad
    assert sample_nearest_surface(image, np.array([[0.5, 0.5]]))[0] == 3.0


def test_all_four_neighbours_non_finite_gives_nan():
    image = np.full((2, 2), np.nan)
    assert math.isnan(sample_nearest_surface(image, np.array([[0.5, 0.5]]))[0])


def test_result_is_float64_of_length_n():
    result = sample_nearest_surface(DISPARITY, np.array([[0, 0], [1, 1]], dtype=np.int32))
    assert result.dtype == np.float64
    assert result.shape == (2,)


def test_empty_points_give_empty_float_array():
    result = sample_nearest_surface(DISPARITY, np.zeros((0, 2)))
    assert result.dtype == np.float64
    assert result.shape == (0,)


@pytest.mark.parametrize("shape", [(3,), (2, 3, 1)])
def test_disparity_must_be_2d(shape):
    with pytest.raises(ValueError, match="disparity must be a 2-D"):
        sample_nearest_surface(np.ones(shape), np.zeros((1, 2)))


@pytest.mark.parametrize("shape", [(2,), (0,), (3, 3), (1, 2, 1)])
def test_pixels_must_be_n_by_2(shape):
    with pytest.raises(ValueError, match=r"pixels must be an \(N, 2\)"):
        sample_nearest_surface(DISPARITY, np.zeros(shape))


def _four_neighbours(image: np.ndarray, u: float, v: float) -> list[float]:
    height, width = image.shape
    u0, v0 = int(math.floor(u)), int(math.floor(v))
    u1, v1 = min(u0 + 1, width - 1), min(v0 + 1, height - 1)
    return [image[v0, u0], image[v0, u1], image[v1, u0], image[v1, u1]]


@st.composite
def images_and_points(draw):
    image = draw(arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6)),
                        elements=st.floats(0.0, 100.0)))
    height, width = image.shape
    points = draw(arrays(np.float64, st.tuples(st.integers(1, 8), st.just(2)),
                         elements=st.floats(0.0, 1.0)))
    return image, points * [width - 1, height - 1]


@given(images_and_points())
def test_sample_is_a_neighbour_at_least_the_bilinear_value(case):
    image, points = case
    sampled = sample_nearest_surface(image, points)
    bilinear = map_coordinates(image, [points[:, 1], points[:, 0]], order=1, mode="nearest")
    assert np.all(sampled >= bilinear - 1e-9 * (1.0 + np.abs(bilinear)))
    for value, (u, v) in zip(sampled, points):
        assert value in _four_neighbours(image, u, v)
