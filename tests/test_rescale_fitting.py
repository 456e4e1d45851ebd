"""Each rescaling method recovers a mapping of its own family, and the monotone ones never fall.

Anchors are made the way the product meets them: relative disparity x from the network,
metric depth z from the VINS with noise in metric disparity 1/z (triangulation makes depth
error grow as z², so disparity error is about uniform).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from autonomy.depth.rescale import METHODS, MONOTONE_METHODS, fit

NOISE = 0.003  # metric-disparity noise of the anchors, 1/m


def anchors_from(mapping, rng, count=150, lo=0.2, hi=2.0, noise=NOISE):
    x = rng.uniform(lo, hi, count)
    y = mapping(x) + noise * rng.standard_normal(count)
    return x, 1.0 / y


def error_in_noise_units(model, mapping, lo, hi):
    grid = np.linspace(lo, hi, 400)
    return np.abs(model.metric_disparity(grid) - mapping(grid)) / NOISE


@pytest.mark.parametrize("degree", [1, 2, 3, 4, 5])
def test_polynomial_recovers_a_polynomial_of_its_degree(degree):
    rng = np.random.default_rng(degree)
    # Rising, positive polynomials on [0.2, 2]: a base line plus small higher terms.
    coef = np.concatenate([[0.05, 0.4], rng.uniform(0.0, 0.08, degree - 1)])
    mapping = np.polynomial.Polynomial(coef)
    x, z = anchors_from(mapping, rng)
    model = fit(x, z, f"poly{degree}")
    assert model.ok and model.method == f"poly{degree}"
    errors = error_in_noise_units(model, mapping, x.min(), x.max())
    assert np.sqrt(np.mean(errors ** 2)) < 1.0
    assert errors.max() < 3.0


def test_exponential_recovers_an_exponential():
    rng = np.random.default_rng(0)
    mapping = lambda x: 0.08 * np.exp(1.3 * x)  # noqa: E731
    x, z = anchors_from(mapping, rng)
    model = fit(x, z, "exponential")
    assert model.ok
    errors = error_in_noise_units(model, mapping, x.min(), x.max())
    assert errors.max() < 3.0


def test_ransac_affine_recovers_an_affine_map_through_40_percent_outliers():
    rng = np.random.default_rng(3)
    mapping = lambda x: 0.4 * x + 0.05  # noqa: E731
    x, z = anchors_from(mapping, rng)
    wrong = rng.random(len(z)) < 0.4
    z[wrong] *= rng.uniform(1.5, 3.0, wrong.sum())  # features triangulated far too far
    model = fit(x, z, "ransac_affine")
    assert model.ok
    assert model.anchors.used <= (~wrong).sum() + 3
    errors = error_in_noise_units(model, mapping, x.min(), x.max())
    assert errors.max() < 3.0


def sigmoid(t):
    return 1.0 / (1.0 + np.exp(-t))


@st.composite
def smooth_monotone_mappings(draw, min_width):
    """y = b + a·x + Σ w_k σ((x − c_k)/s_k): rising, smooth, with up to two soft steps."""
    a = draw(st.floats(0.1, 1.0))
    b = draw(st.floats(0.02, 0.2))
    steps = [(draw(st.floats(0.0, 0.3)), draw(st.floats(0.4, 1.8)), draw(st.floats(min_width, 0.6)))
             for _ in range(2)]
    seed = draw(st.integers(0, 2**31))
    return (lambda x: b + a * x + sum(w * sigmoid((x - c) / s) for w, c, s in steps)), seed


# RMS bounds in noise units: FITPACK's and the P-spline's own accuracy on 150 anchors, with
# room for the worst of several hundred random draws (measured: 1.7 and 0.5 at the worst).
@pytest.mark.parametrize("method, rms_bound, max_bound", [
    ("smoothing_spline", 2.0, None),
    ("monotone_spline", 1.0, 4.0),
])
@given(case=smooth_monotone_mappings(min_width=0.15))
@settings(max_examples=40, deadline=None)
def test_spline_methods_recover_smooth_monotone_mappings(method, rms_bound, max_bound, case):
    mapping, seed = case
    x, z = anchors_from(mapping, np.random.default_rng(seed))
    model = fit(x, z, method)
    assert model.ok
    errors = error_in_noise_units(model, mapping, x.min(), x.max())
    assert np.sqrt(np.mean(errors ** 2)) < rms_bound
    if max_bound is not None:
        assert errors.max() < max_bound



def test_smoothing_spline_stays_with_the_data_between_two_close_anchors():
    """Two anchors 3·10⁻⁴ apart in x and 3σ apart in y near the range's end: FITPACK may put a
    knot on each, and with all its knots the cubic between them swung 9σ off the line on one
    of these 40 draws (557σ on a curved map). The knots kept leave three anchors per interval."""
    line = lambda x: 0.1 + 0.5 * x  # noqa: E731
    worst = 0.0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        x = np.sort(rng.uniform(0.2, 2.0, 150))
        x[-3] = x[-4] + 3e-4
        y = line(x) + NOISE * rng.standard_normal(150)
        y[-3] = y[-4] + 3 * NOISE
        model = fit(x, 1.0 / y, "smoothing_spline")
        worst = max(worst, error_in_noise_units(model, line, x[0], x[-1]).max())
    assert worst < 4.0

@given(case=smooth_monotone_mappings(min_width=0.5))
@settings(max_examples=40, deadline=None)
def test_monotone_smoothing_spline_recovers_gently_curved_mappings(case):
    # λ = 1e5 (the paper's value) makes this variant stiff — nearly a monotone quadratic — so
    # its family is the gently curved maps, not steps (measured RMS over 300 random draws:
    # median 0.7, worst 1.8 noise units with steps at least 0.5 wide; steps 0.4 wide reach 3.3).
    mapping, seed = case
    x, z = anchors_from(mapping, np.random.default_rng(seed))
    model = fit(x, z, "monotone_smoothing_spline")
    assert model.ok
    errors = error_in_noise_units(model, mapping, x.min(), x.max())
    assert np.sqrt(np.mean(errors ** 2)) < 3.0


arbitrary_anchors = st.integers(10, 60).flatmap(lambda n: st.tuples(
    st.lists(st.floats(1e-3, 50.0), min_size=n, max_size=n),
    st.lists(st.floats(0.05, 65.0), min_size=n, max_size=n)))


@pytest.mark.parametrize("method", MONOTONE_METHODS)
@given(anchors=arbitrary_anchors)
@settings(max_examples=60, deadline=None)
def test_monotone_methods_never_fall_on_any_input(method, anchors):
    """Nearer in the network's eyes is never farther in metres: on the whole real line.

    Exactly, up to floating-point rounding of a flat stretch (1e-12 relative in metric
    disparity, float32's 1e-6 in depth).
    """
    x, z = map(np.asarray, anchors)
    model = fit(x, z, method)
    if not model.ok:
        return  # garbage anchors may rightly give no fit; a fit must still be monotone
    lo, hi = model.anchor_range
    grid = np.linspace(0.0, 2 * hi + 1.0, 5000)
    disparity = model.metric_disparity(grid)
    assert np.all(np.diff(disparity) >= -1e-12 * np.abs(disparity[1:]))
    depth = model.depth(grid.reshape(50, 100)).reshape(-1)
    assert np.all(np.isfinite(depth))
    assert np.all(np.diff(depth) <= 1e-6 * depth[1:])


def test_every_method_is_selectable_by_name_and_reports_it():
    rng = np.random.default_rng(11)
    x, z = anchors_from(lambda x: 0.3 * x + 0.05, rng)
    for method in METHODS:
        model = fit(x, z, method)
        assert model.ok, (method, getattr(model, "detail", ""))
        assert model.method == method
        assert model.anchors.used >= 10


def test_same_anchors_give_the_same_fit():
    rng = np.random.default_rng(12)
    x, z = anchors_from(lambda x: 0.3 * x + 0.05, rng)
    grid = np.linspace(0, 3, 50)
    for method in METHODS:
        first, second = fit(x, z, method), fit(x, z, method)
        np.testing.assert_array_equal(first.metric_disparity(grid), second.metric_disparity(grid))


AFFINE_MAP = lambda x: 0.4 * x + 0.05  # noqa: E731
EXPONENTIAL_MAP = lambda x: 0.08 * np.exp(1.3 * x)  # noqa: E731


@pytest.mark.parametrize("method", [m for m in METHODS if m != "ransac_affine"])
def test_outlier_rejection_keeps_gross_outliers_from_bending_the_curve(method):
    rng = np.random.default_rng(21)
    mapping = EXPONENTIAL_MAP if method == "exponential" else AFFINE_MAP
    x, z = anchors_from(mapping, rng)
    wrong = rng.random(len(z)) < 0.15
    z[wrong] *= 3.0  # VINS features whose depth is three times too large
    robust = fit(x, z, method)
    naive = fit(x, z, method, outlier_rejection=False)
    grid = np.linspace(0.3, 1.9, 200)
    robust_error = np.max(np.abs(robust.metric_disparity(grid) - mapping(grid)) / mapping(grid))
    naive_error = np.max(np.abs(naive.metric_disparity(grid) - mapping(grid)) / mapping(grid))
    assert naive_error > 0.08  # the failure: outliers drag the curve
    assert robust_error < 0.05
    assert wrong.sum() <= robust.anchors.outliers <= wrong.sum() + 5
