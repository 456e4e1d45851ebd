"""Degenerate and bad anchors give a clear no-fit, never an exception or a wrong curve."""

import numpy as np
import pytest

from autonomy.depth.rescale import METHODS, NoFitReason, fit
from autonomy.options import OptionError


def good_anchors(count=40, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.2, 2.0, count)
    return x, 1.0 / (0.3 * x + 0.05)


@pytest.mark.parametrize("method", METHODS)
def test_fewer_than_ten_anchors_is_no_fit(method):
    x, z = good_anchors(9)
    result = fit(x, z, method)
    assert not result.ok
    assert result.reason is NoFitReason.TOO_FEW_ANCHORS
    assert "9 valid anchors, need 10" in result.detail


@pytest.mark.parametrize("method", METHODS)
def test_empty_anchors_are_no_fit(method):
    result = fit([], [], method)
    assert not result.ok and result.reason is NoFitReason.TOO_FEW_ANCHORS
    assert result.anchors.given == 0


@pytest.mark.parametrize("method", METHODS)
def test_all_equal_relative_disparity_is_no_fit(method):
    result = fit(np.full(30, 0.7), np.linspace(1.0, 5.0, 30), method)
    assert not result.ok
    assert result.reason is NoFitReason.DEGENERATE_DISPARITY
    assert "same relative disparity" in result.detail


def test_invalid_anchors_are_dropped_and_counted():
    x, z = good_anchors(20)
    x[:3] = [np.nan, np.inf, -0.5]
    x[3] = 0.0
    z[4:7] = [np.nan, 0.01, 100.0]  # unknown, nearer than 5 cm, farther than 65 m
    z[7] = -2.0
    model = fit(x, z)
    assert model.ok
    assert (model.anchors.given, model.anchors.bad_disparity, model.anchors.bad_depth) == (20, 4, 4)
    assert model.anchors.used == 12


def test_too_many_invalid_anchors_say_what_was_wrong():
    x, z = good_anchors(12)
    x[:2] = np.nan
    z[2:5] = np.inf
    result = fit(x, z)
    assert result.reason is NoFitReason.TOO_FEW_ANCHORS
    assert "7 valid anchors, need 10" in result.detail
    assert "2 with non-finite or non-positive relative disparity" in result.detail
    assert "3 with depth outside [0.05, 65] m" in result.detail


@pytest.mark.parametrize("method", METHODS)
def test_anchors_whose_depth_grows_with_disparity_are_no_fit(method):
    x = np.linspace(0.2, 2.0, 40)
    z = 1.0 / (1.0 - 0.4 * x)  # metric disparity falls as relative disparity rises
    result = fit(x, z, method)
    assert not result.ok
    assert result.reason is NoFitReason.NOT_INCREASING


def test_spline_with_few_distinct_disparities_reduces_its_segments():
    x = np.repeat(np.linspace(0.3, 1.5, 6), 3)  # 18 anchors at 6 distinct disparities
    model = fit(x, 1.0 / (0.3 * x + 0.05), "monotone_spline")
    assert model.ok and model.method == "monotone_spline"
    assert any("segments reduced from 10 to 3" in note for note in model.notes)


@pytest.mark.parametrize("method", ["poly5", "smoothing_spline", "monotone_spline"])
def test_too_few_distinct_disparities_fall_back_to_poly1_and_say_so(method):
    x = np.repeat([0.4, 0.9, 1.6], 5)
    model = fit(x, 1.0 / (0.3 * x + 0.05), method)
    assert model.ok and model.method == "poly1"
    assert any("fell back to poly1" in note for note in model.notes)
    np.testing.assert_allclose(model.metric_disparity([1.0]), [0.35], rtol=1e-9)


def test_mismatched_arrays_are_a_programming_error():
    with pytest.raises(ValueError, match="equal length"):
        fit(np.ones(12), np.ones(11))
    with pytest.raises(ValueError, match="1-D"):
        fit(np.ones((4, 4)), np.ones((4, 4)))


def test_bad_options_name_the_option():
    x, z = good_anchors()
    with pytest.raises(OptionError, match="method: must be one of"):
        fit(x, z, "cubic")
    with pytest.raises(OptionError, match="kappa: must be >= 0"):
        fit(x, z, kappa=-1.0)
    with pytest.raises(TypeError):
        fit(x, z, kapa=1.0)
