"""The fast paths equal the reference implementations they replace."""

import numpy as np
import pytest
from scipy.interpolate import BSpline

from autonomy.depth import curves
from autonomy.depth.rescale import fit


def test_uniform_cubic_basis_equals_scipys_design_matrix():
    x = np.sort(np.random.default_rng(0).uniform(0.3, 2.7, 200))
    knots = curves.pspline_knots(x[0], x[-1], 10)
    expected = BSpline.design_matrix(x, knots, 3).toarray()
    np.testing.assert_allclose(curves.uniform_cubic_basis(x, knots), expected, atol=1e-12)


def test_uniform_spline_equals_scipys_bspline():
    knots = curves.pspline_knots(0.5, 3.0, 10)
    coef = np.cumsum(np.random.default_rng(1).uniform(0, 1, len(knots) - 4))
    x = np.linspace(0.5, 3.0, 1000)
    np.testing.assert_allclose(curves.UniformSpline(knots, coef)(x),
                               BSpline(knots, coef, 3)(x), atol=1e-12)


def test_paper_knot_layout_gives_thirteen_bases_for_ten_segments():
    knots = curves.pspline_knots(1.0, 2.0, 10)
    assert len(knots) == 17 and len(knots) - 4 == 13
    np.testing.assert_allclose([knots[0], knots[-1]], [1.0 - 0.4, 2.0 + 0.4])


@pytest.mark.parametrize("shape", [(7,), (40000,), (3, 4, 5), (2, 40000)])
def test_lookup_works_for_any_array_shape(shape):
    rng = np.random.default_rng(2)
    x = rng.uniform(0.2, 2.0, 60)
    model = fit(x, 1.0 / (0.3 * x + 0.05), "monotone_spline")
    image = rng.uniform(0.0, 2.5, shape).astype(np.float32)
    image.reshape(-1)[::11] = np.nan
    depth = model.depth(image)
    assert depth.shape == shape
    np.testing.assert_array_equal(np.isnan(depth), np.isnan(image))
    np.testing.assert_allclose(depth, model.depth(image, exact=True), rtol=0.01)


def test_median_of_short_arrays():
    assert curves.median(np.array([3.0, 1.0, 2.0])) == 2.0
    assert curves.median(np.array([4.0, 1.0, 2.0, 3.0])) == 2.5
