"""Curve families that map relative disparity x to metric disparity y = 1/z.

Each family is a small immutable object whose ``__call__(x)`` evaluates it, with a fitter
that makes one from anchors sorted by x. A fitter raises :class:`FitFailure` with a reason
when the anchors cannot support it; it never returns a silently wrong curve. The families are those compared in Section III-B of Yang, Tian, Goel,
Tabib, "Zero-Shot Metric Depth Estimation via Monocular Visual-Inertial Rescaling for
Autonomous Aerial Navigation", plus RANSAC on an affine map (Marsal et al. 2024).

:class:`GuardedCurve` wraps any family with the two guards that make it safe to apply to a
whole image: straight tails outside the anchor range and straight bridges across gaps.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import splev, splrep

from autonomy.depth.options import RescaleOptions


class FitFailure(Exception):
    """The anchors cannot support this family; ``reason`` is a NoFitReason value."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


# --------------------------------------------------------------------------------------------
# Families


@dataclass(frozen=True)
class Affine:
    """y = a·x + b."""

    a: float
    b: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.a * np.asarray(x, dtype=float) + self.b


@dataclass(frozen=True)
class Polynomial:
    """y = Σ c_k u^k with u = (x − shift) / scale, which keeps the Vandermonde well conditioned."""

    coef: np.ndarray
    shift: float
    scale: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        u = (np.asarray(x, dtype=float) - self.shift) / self.scale
        return np.polynomial.polynomial.polyval(u, self.coef)


@dataclass(frozen=True)
class Exponential:
    """y = a·e^(b·x)."""

    a: float
    b: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.a * np.exp(self.b * np.asarray(x, dtype=float))


@dataclass(frozen=True)
class Spline:
    """A cubic spline from FITPACK, knots and coefficients as ``splrep`` returns them."""

    tck: tuple

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return splev(np.asarray(x, dtype=float), self.tck)


@dataclass(frozen=True)
class PiecewiseLinear:
    """Straight segments through (grid_i, values_i); used to carry a curve across frames."""

    grid: np.ndarray
    values: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(x, dtype=float), self.grid, self.values)


# --------------------------------------------------------------------------------------------
# Fitters: x sorted ascending, y = 1/z, both float64 1-D.


def fit_affine_least_squares(x: np.ndarray, y: np.ndarray) -> Affine:
    """Ordinary least squares y ≈ a·x + b: a = cov(x, y) / var(x), b = ȳ − a·x̄."""
    x_mean, y_mean = x.mean(), y.mean()
    dx = x - x_mean
    a = float(dx @ (y - y_mean) / (dx @ dx))
    return Affine(a, float(y_mean - a * x_mean))


def count_distinct(x_sorted: np.ndarray) -> int:
    """How many distinct values a sorted array holds."""
    return 1 + int(np.count_nonzero(np.diff(x_sorted))) if len(x_sorted) else 0


def fit_polynomial(x: np.ndarray, y: np.ndarray, degree: int) -> Polynomial:
    """Least squares on the Vandermonde matrix of u = (x − centre)/half-range, degree 1…5."""
    shift = 0.5 * (x[0] + x[-1])
    scale = 0.5 * (x[-1] - x[0])
    vandermonde = np.vander((x - shift) / scale, degree + 1, increasing=True)
    coef, *_ = np.linalg.lstsq(vandermonde, y, rcond=None)
    return Polynomial(coef, float(shift), float(scale))


def fit_exponential(x: np.ndarray, y: np.ndarray) -> Exponential:
    """a·e^(b·x) by least squares on ln y = ln a + b·x (log-linear, as in the paper)."""
    log_line = fit_affine_least_squares(x, np.log(y))
    b, log_a = log_line.a, log_line.b
    if b <= 0:
        raise FitFailure("not_increasing", f"exponential fit has b = {b:.3g} <= 0: metric "
                         "disparity does not grow with relative disparity")
    return Exponential(float(np.exp(log_a)), float(b))


def _merge_duplicates(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct x of sorted x, the mean y at each, and how many anchors each stands for."""
    starts = np.flatnonzero(np.concatenate(([True], np.diff(x) != 0)))
    counts = np.diff(np.append(starts, len(x)))
    return x[starts], np.add.reduceat(y, starts) / counts, counts


def median(values: np.ndarray) -> float:
    """The median of a short 1-D array (a sort: np.median's overhead dominates at 150 anchors)."""
    ordered = np.sort(values)
    middle = len(ordered) // 2
    return float(ordered[middle] if len(ordered) % 2 else 0.5 * (ordered[middle - 1] + ordered[middle]))


def robust_sigma(residuals: np.ndarray) -> float:
    """1.4826 × median absolute deviation: the standard deviation of Gaussian noise, robustly."""
    return 1.4826 * median(np.abs(residuals - median(residuals)))


def local_noise_sigma(x: np.ndarray, y: np.ndarray) -> float:
    """Noise level of y from pseudo-residuals (Gasser, Sroka & Jennen-Steinmetz 1986).

    Each interior point is compared with the straight line through its two neighbours:
    e_i = (a_i·y_{i−1} + b_i·y_{i+1} − y_i) / √(a_i² + b_i² + 1) with a_i = (x_{i+1} − x_i) /
    (x_{i+1} − x_{i−1}), b_i = 1 − a_i. Where the curve is locally straight e_i has the noise's
    standard deviation whatever the curve's slope, so σ̂ = robust_sigma(e) does not mistake
    the curve's shape for noise, as a sigma from a parametric fit's residuals does.
    """
    a = (x[2:] - x[1:-1]) / (x[2:] - x[:-2])
    b = 1.0 - a
    pseudo_residuals = (a * y[:-2] + b * y[2:] - y[1:-1]) / np.sqrt(a * a + b * b + 1.0)
    return robust_sigma(pseudo_residuals)


def fit_smoothing_spline(x: np.ndarray, y: np.ndarray, options: RescaleOptions) -> Spline:
    """Cubic smoothing spline by FITPACK (Dierckx ``curfit`` through scipy's ``splrep``).

    FITPACK finds the smoothest spline with Σ (w_i r_i)² ≤ s. With weights w_i = 1/σ it
    recommends s = m, the number of points, so s = smoothing_factor · m and the factor is
    unit-free; ``python benchmarks/smoothing_factor.py`` compares factors on random smooth
    maps (docs/benchmarks.md). σ̂ comes from :func:`local_noise_sigma`, free of the curve's
    shape. When FITPACK reports s too small for its knot budget (ier 1–3: it
    would return a near-interpolating spline) s is doubled and the fit retried. Duplicate x
    are merged, their weights scaled by √count.

    FITPACK places knots where the residuals are largest and may put two knots on anchors a
    fraction of the noise apart; the cubic between them is then fixed by continuity alone
    and can swing far from the data (500 σ between two anchors near the end of the range).
    Knots that leave an interval with fewer than ``_ANCHORS_PER_KNOT_INTERVAL`` distinct
    anchors are dropped and the weighted least-squares spline refitted on the rest.
    """
    xu, yu, counts = _merge_duplicates(x, y)
    sigma = max(local_noise_sigma(xu, yu), 1e-6 * float(np.max(np.abs(yu))))
    weights = np.sqrt(counts) / sigma
    smoothing = options.smoothing_factor * len(xu)
    for _ in range(_SMOOTHING_RETRIES):
        tck, _, ier, message = splrep(xu, yu, w=weights, k=3, s=smoothing, full_output=True)
        if ier <= 0:
            return _with_supported_knots(tck, xu, yu, weights)
        if ier > 3:  # 10: invalid input
            break
        smoothing = 2.0 * smoothing if smoothing > 0 else float(len(xu))
    raise FitFailure("fit_failed", f"FITPACK curfit found no smoothing spline (ier={ier}): "
                     f"{message.strip()}")


def _with_supported_knots(tck: tuple, x: np.ndarray, y: np.ndarray,
                          weights: np.ndarray) -> Spline:
    """The spline refitted by weighted least squares on those of its interior knots that
    leave every knot interval at least ``_ANCHORS_PER_KNOT_INTERVAL`` distinct anchors."""
    interior = tck[0][4:-4]
    kept, left = [], 0
    for knot in interior:
        index = int(np.searchsorted(x, knot))
        if min(index - left, len(x) - index) >= _ANCHORS_PER_KNOT_INTERVAL:
            kept.append(knot)
            left = index
    if len(kept) == len(interior):
        return Spline(tck)
    return Spline(splrep(x, y, w=weights, k=3, task=-1, t=np.array(kept)))


#: Three anchors per knot interval: a cubic piece then answers to data inside it
#: (benchmarks/smoothing_factor.py, docs/benchmarks.md).
_ANCHORS_PER_KNOT_INTERVAL = 3
_SMOOTHING_RETRIES = 4


def pspline_knots(x_min: float, x_max: float, segments: int) -> np.ndarray:
    """The paper's knot vector: linspace(x_min − 4Δ, x_max + 4Δ, segments + 7), Δ = range/segments.

    For 10 segments that is 17 knots and 13 cubic bases, the released code's values.
    """
    delta = (x_max - x_min) / segments
    return np.linspace(x_min - 4 * delta, x_max + 4 * delta, segments + 7)


def _uniform_cubic_pieces(x: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """For each x, the index of its first non-zero basis and the four non-zero basis values.

    On uniform knots the four cubic B-splines that are non-zero at x are fixed polynomials of
    the position u ∈ [0, 1) within its knot interval: (1−u)³/6, (3u³ − 6u² + 4)/6,
    (−3u³ + 3u² + 3u + 1)/6 and u³/6 (de Boor, "A Practical Guide to Splines"). x outside the
    valid span [t₃, t₋₄] is evaluated on the first or last polynomial piece.
    """
    n_bases = len(knots) - 4
    position = (x - knots[0]) / (knots[1] - knots[0])
    # np.minimum/np.maximum, not np.clip: np.clip's Python-level checks cost more than the
    # arithmetic at these sizes, and this runs several times per fit.
    interval = np.minimum(np.maximum(np.floor(position).astype(np.intp), 3), n_bases - 1)
    u = position - interval
    v = 1.0 - u
    u2 = u * u
    u3 = u2 * u
    weights = [v * v * v / 6.0, (3 * u3 - 6 * u2 + 4) / 6.0, (-3 * u3 + 3 * u2 + 3 * u + 1) / 6.0,
               u3 / 6.0]
    return interval - 3, weights


def uniform_cubic_basis(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Dense design matrix B[i, j] = B_j(x_i) of cubic B-splines on uniform knots.

    Equal to scipy's ``BSpline.design_matrix`` at a fraction of its cost, which matters
    inside a per-frame fit.
    """
    first, weights = _uniform_cubic_pieces(x, knots)
    n_bases = len(knots) - 4
    design = np.zeros(len(x) * n_bases)
    flat_first = np.arange(len(x)) * n_bases + first
    for k, weight in enumerate(weights):
        design[flat_first + k] = weight
    return design.reshape(len(x), n_bases)


@dataclass(frozen=True)
class UniformSpline:
    """A cubic B-spline on uniform knots, y = Σ α_j B_j(x), evaluated in closed form.

    Twice as fast as scipy's general BSpline on the lookup-table grid.
    """

    knots: np.ndarray
    coef: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        first, weights = _uniform_cubic_pieces(np.asarray(x, dtype=float), self.knots)
        return sum(self.coef[first + k] * weight for k, weight in enumerate(weights))


@functools.lru_cache(maxsize=8)
def _difference_penalties(n_bases: int) -> tuple[np.ndarray, np.ndarray]:
    """First-difference matrix Δ and third-difference penalty D₃ᵀD₃ for ``n_bases`` bases."""
    identity = np.eye(n_bases)
    third = np.diff(identity, n=3, axis=0)
    return np.diff(identity, axis=0), third.T @ third


def fit_monotone_pspline(x: np.ndarray, y: np.ndarray, options: RescaleOptions,
                         smoothing_lambda: float) -> tuple[UniformSpline, int]:
    """Monotone P-spline (Eilers 2005), returning the spline and the segments used.

    Minimises  |y − Bα|² + λ|D₃α|² + κ Σ_j v_j (Δα_j)² + ε|α|²  where D₃ is the third
    difference, Δ the first, v_j = 1 where Δα_j < 0 (the asymmetric penalty) and ε a ridge
    that keeps the system regular where no anchor constrains a basis. v is recomputed from
    the solution until it stops changing, at most ``max_iterations`` times. A finite κ leaves
    dips of order 1/κ; a final running maximum of α removes them, so the spline — whose
    derivative is a spline with coefficients ∝ Δα — is non-decreasing exactly, not nearly.
    With fewer distinct anchors than bases the segments are reduced so bases ≤ anchors.
    """
    segments = min(options.segments, count_distinct(x) - 3)
    knots = pspline_knots(x[0], x[-1], segments)
    design = uniform_cubic_basis(x, knots)
    first_difference, third_difference_penalty = _difference_penalties(design.shape[1])
    fixed = design.T @ design + smoothing_lambda * third_difference_penalty \
        + options.ridge * np.eye(design.shape[1])
    rhs = design.T @ y
    decreasing = np.zeros(design.shape[1] - 1)
    for _ in range(options.max_iterations):
        penalty = options.kappa * (first_difference.T * decreasing) @ first_difference
        coef = np.linalg.solve(fixed + penalty, rhs)
        now_decreasing = (np.diff(coef) < 0).astype(float)
        if np.array_equal(now_decreasing, decreasing):
            break
        decreasing = now_decreasing
    coef = np.maximum.accumulate(coef)
    return UniformSpline(knots, coef), segments


def fit_ransac_affine(x: np.ndarray, y: np.ndarray, options: RescaleOptions) -> tuple[Affine, np.ndarray]:
    """RANSAC on y = a·x + b (Marsal et al. 2024), returning the model and its inlier mask.

    Hypotheses come from random anchor pairs; one with a ≤ 0 (disparity falling as the
    network's rises) is discarded. An anchor is an inlier when |a·x + b − y| ≤ τ·y, i.e. its
    depth is within about τ of the hypothesis'. The largest consensus is refitted by least
    squares and recounted until it settles (three rounds at most); the model returned is the
    least-squares fit to exactly the inliers returned. The sampler is seeded: the same
    anchors always give the same fit.
    """
    rng = np.random.default_rng(options.seed)
    first = rng.integers(0, len(x), options.ransac_iterations)
    second = rng.integers(0, len(x), options.ransac_iterations)
    dx = x[second] - x[first]
    usable = dx != 0
    with np.errstate(divide="ignore", invalid="ignore"):
        slopes = (y[second] - y[first]) / dx
    usable &= slopes > 0
    if not usable.any():
        raise FitFailure("not_increasing", "no anchor pair gives a rising affine map")
    slopes, first = slopes[usable], first[usable]
    offsets = y[first] - slopes * x[first]
    predicted = slopes[:, None] * x[None, :] + offsets[:, None]
    inlier_counts = (np.abs(predicted - y) <= options.ransac_threshold * y).sum(axis=1)
    best = int(np.argmax(inlier_counts))
    inliers = np.abs(predicted[best] - y) <= options.ransac_threshold * y
    for _ in range(3):  # refit on the consensus and recount until the inliers settle
        if count_distinct(x[inliers]) < 2:
            raise FitFailure("too_few_inliers", "RANSAC consensus has fewer than two distinct "
                             "relative disparities")
        recounted = np.abs(fit_affine_least_squares(x[inliers], y[inliers])(x) - y) \
            <= options.ransac_threshold * y
        if np.array_equal(recounted, inliers) or count_distinct(x[recounted]) < 2:
            break
        inliers = recounted
    return fit_affine_least_squares(x[inliers], y[inliers]), inliers


# --------------------------------------------------------------------------------------------
# The guarded curve


@dataclass(frozen=True)
class Bridge:
    """The straight line across an anchor-free gap (a, b), from g(a) to g(b)."""

    a: float
    b: float
    y_a: float
    y_b: float


@dataclass(frozen=True)
class GuardedCurve:
    """A fitted family made safe to apply to every pixel of an image.

    Inside the anchor range [x_lo, x_hi] it is the family's curve g, except across gaps —
    anchor-free stretches (a_k, b_k) — where it is the straight bridge from g(a_k) to g(b_k)
    (gap guard). Outside the range it continues as straight tails of one slope s,
    y = g(x_hi) + s·(x − x_hi) on the near side (larger disparity) and
    y = g(x_lo) + s·(x − x_lo) on the far side. :func:`guard` sets s to the anchors'
    least-squares affine slope, which is > 0, so a pixel nearer than the nearest anchor is
    never pushed farther away (near-side guard). Clamping instead (s = 0, the reference
    port's behaviour) gives every nearer pixel the nearest anchor's depth.
    """

    family: object
    x_lo: float
    x_hi: float
    tail_slope: float
    bridges: tuple[Bridge, ...] = ()

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Metric disparity y at relative disparity x (float64, any shape)."""
        x = np.asarray(x, dtype=float)
        inside = np.minimum(np.maximum(x, self.x_lo), self.x_hi)
        y = self.family(inside)
        for bridge in self.bridges:
            in_gap = (inside > bridge.a) & (inside < bridge.b)
            y[in_gap] = bridge.y_a + (inside[in_gap] - bridge.a) \
                * (bridge.y_b - bridge.y_a) / (bridge.b - bridge.a)
        return y + self.tail_slope * (x - inside)

    @property
    def affine(self) -> Affine | None:
        """The curve as one affine map when it is one everywhere, else None."""
        if isinstance(self.family, Affine) and self.tail_slope == self.family.a:
            return self.family
        return None


def gap_starts(x_sorted: np.ndarray, gap_fraction: float) -> np.ndarray:
    """Indices ``i`` of the sorted anchors followed by a gap: ``x[i + 1] - x[i]`` wider than
    ``gap_fraction`` of the anchor range."""
    return np.flatnonzero(np.diff(x_sorted) > gap_fraction * (x_sorted[-1] - x_sorted[0]))


def find_gaps(family, x_sorted: np.ndarray, gap_fraction: float) -> tuple[Bridge, ...]:
    """Bridges over the anchor-free stretches wider than ``gap_fraction`` of the anchor range."""
    starts = gap_starts(x_sorted, gap_fraction)
    if len(starts) == 0:
        return ()
    ends = family(np.concatenate([x_sorted[starts], x_sorted[starts + 1]]))
    return tuple(Bridge(float(x_sorted[i]), float(x_sorted[i + 1]), float(y_a), float(y_b))
                 for i, y_a, y_b in zip(starts, ends[:len(starts)], ends[len(starts):]))


def guard(family, x_sorted: np.ndarray, reference_slope: float,
          options: RescaleOptions) -> GuardedCurve:
    """Wrap a fitted family with tails and bridges as ``options`` ask.

    The tails take ``reference_slope``, the least-squares affine slope of the anchors used,
    not the family's own slope at the range's ends: a relative-disparity network is ideally
    affine in true disparity, and an end derivative rests on the few anchors near the end.
    An affine family needs no bridges; it stays one affine map when its tails share its slope.
    """
    x_lo, x_hi = float(x_sorted[0]), float(x_sorted[-1])
    slope = reference_slope if options.extrapolation == "linear" else 0.0
    if isinstance(family, Affine) or not options.bridge_gaps:
        return GuardedCurve(family, x_lo, x_hi, slope)
    return GuardedCurve(family, x_lo, x_hi, slope, find_gaps(family, x_sorted, options.gap_fraction))
