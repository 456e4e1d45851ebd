"""Rescaling relative disparity into metric depth (Yang et al., Section III-B).

A monocular network gives relative disparity x for every pixel; the VINS gives metric depth z
for a few features. Working in disparity, fit f: x ↦ y = 1/z on the features (the anchors)
and apply it to every pixel: depth = 1 / f(x).

    >>> model = fit(x_at_features, z_of_features, method="monotone_spline")
    >>> if model.ok:
    ...     depth = model.depth(relative_disparity_image)       # float32 metres, NaN invalid
    ...     trust = model.confidence(relative_disparity_image)  # float32 in [0, 1]
    ... else:
    ...     log.warning("no metric depth this frame: %s", model.detail)

Beyond the paper, every method is made safe to apply to a whole image (see
:class:`~autonomy.depth.curves.GuardedCurve`): residual-based outlier rejection, straight
tails outside the anchor range (never pushing a near pixel farther away), straight bridges
across anchor gaps, a per-pixel confidence, and optional temporal blending across frames.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import Enum
from typing import ClassVar, Union

import cv2
import numpy as np

from autonomy.depth import curves
from autonomy.depth.options import METHODS, MONOTONE_METHODS, RescaleOptions

__all__ = [
    "METHODS", "MONOTONE_METHODS", "AnchorSummary", "NoFit", "NoFitReason", "RescaleModel",
    "RescaleOptions", "RescaleResult", "TemporalBlend", "fit",
]


class NoFitReason(str, Enum):
    """Why a frame got no metric depth."""

    TOO_FEW_ANCHORS = "too_few_anchors"
    DEGENERATE_DISPARITY = "degenerate_disparity"
    TOO_FEW_INLIERS = "too_few_inliers"
    NOT_INCREASING = "not_increasing"
    FIT_FAILED = "fit_failed"


@dataclass(frozen=True)
class AnchorSummary:
    """What became of the anchors handed to :func:`fit`."""

    given: int
    bad_disparity: int = 0  #: relative disparity non-finite or ≤ 0
    bad_depth: int = 0  #: metric depth non-finite or outside [min_depth, max_depth]
    outliers: int = 0  #: valid, but rejected by outlier rejection or RANSAC
    used: int = 0  #: anchors the curve was finally fitted to

    @property
    def valid(self) -> int:
        return self.given - self.bad_disparity - self.bad_depth


@dataclass(frozen=True)
class NoFit:
    """No usable fit this frame, and why. ``ok`` is False; nothing here is a depth."""

    reason: NoFitReason
    detail: str
    method: str
    anchors: AnchorSummary
    ok: ClassVar[bool] = False


@dataclass(frozen=True, eq=False)
class RescaleModel:
    """A fitted map from relative disparity to metric depth. ``ok`` is True.

    ``method`` is the family actually fitted (``notes`` says when it differs from the one
    asked for). ``support`` holds the relative disparities of the anchors used, sorted.
    """

    method: str
    curve: curves.GuardedCurve
    anchors: AnchorSummary
    support: np.ndarray
    options: RescaleOptions
    residual_rms: float  #: RMS of metric-disparity residuals at the anchors used, 1/m
    notes: tuple[str, ...] = ()
    ok: ClassVar[bool] = True

    @property
    def anchor_range(self) -> tuple[float, float]:
        """Relative disparities of the farthest and nearest anchor used."""
        return self.curve.x_lo, self.curve.x_hi

    def metric_disparity(self, relative_disparity: np.ndarray) -> np.ndarray:
        """f(x) in 1/m, evaluated exactly (float64), guards included."""
        return self.curve(relative_disparity)

    def depth(self, relative_disparity: np.ndarray, *, exact: bool = False) -> np.ndarray:
        """Metric depth in metres (float32, the input's shape) for every pixel.

        depth = 1 / f(x), clipped to [min_depth, max_depth]; where f(x) ≤ 1/max_depth the
        pixel is at least max_depth away and reads max_depth. Non-finite or negative x reads
        NaN. The curve is evaluated once on a ``lut_size`` table over the image's disparity
        range and applied by indexing (nearest entry); an affine curve is applied directly,
        which is cheaper. ``exact=True`` evaluates f at every pixel instead: the reference
        the table is measured against.
        """
        image = _as_float32_image(relative_disparity)
        if exact:
            invalid = _invalid(image)
            y = self.curve(np.where(invalid, 0.0, image))
            return np.where(invalid, np.nan, self._depth_from_disparity(y)).astype(np.float32)
        affine = self.curve.affine
        if affine is not None:
            return _affine_depth(image, affine.a, affine.b, self.options)
        return _lookup(image, lambda grid: self._depth_from_disparity(self.curve(grid)),
                       self.options.lut_size, fills=(np.nan,))

    def confidence(self, relative_disparity: np.ndarray) -> np.ndarray:
        """Per-pixel trust in [0, 1] (float32): how densely anchors support this disparity.

        c(x) = min(1, n(x) / m), where n(x) counts anchors within ±h of x, h = anchor range /
        segments (one knot spacing) and m = ``confidence_neighbours``. It is 1 inside a densely
        anchored range, falls to 0 within h of the range's ends (extrapolated pixels) and in
        the middle of a bridged gap, and is 0 for invalid pixels.
        """
        image = _as_float32_image(relative_disparity)
        return _lookup(image, self._support_confidence, self.options.lut_size, fills=(0.0,))

    def depth_and_confidence(self, relative_disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(depth(x), confidence(x))``, equal to the two calls but gathered in one pass
        over the image (a two-channel table) where the curve is applied through a table."""
        image = _as_float32_image(relative_disparity)
        if self.curve.affine is not None:
            return self.depth(image), self.confidence(image)

        def tables(grid: np.ndarray) -> np.ndarray:
            return np.stack([self._depth_from_disparity(self.curve(grid)),
                             self._support_confidence(grid)])

        both = _lookup(image, tables, self.options.lut_size, fills=(np.nan, 0.0))
        return both[..., 0], both[..., 1]

    def _support_confidence(self, x: np.ndarray) -> np.ndarray:
        lo, hi = self.anchor_range
        half_width = (hi - lo) / self.options.segments
        count = np.searchsorted(self.support, x + half_width, side="right") \
            - np.searchsorted(self.support, x - half_width, side="left")
        return np.minimum(count / self.options.confidence_neighbours, 1.0)

    def _depth_from_disparity(self, y: np.ndarray) -> np.ndarray:
        near, far = self.options.min_depth, self.options.max_depth
        with np.errstate(divide="ignore"):
            depth = np.where(y > 1.0 / far, 1.0 / y, far)
        return np.maximum(depth, near)


RescaleResult = Union[RescaleModel, NoFit]


def _as_float32_image(relative_disparity: np.ndarray) -> np.ndarray:
    """The image as C-contiguous float32; a clear error for anything but real numbers."""
    image = np.asarray(relative_disparity)
    if not (np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)):
        raise TypeError(f"relative disparity must be a real-valued array, got dtype {image.dtype}")
    return np.ascontiguousarray(image, dtype=np.float32)


def _valid_range(image: np.ndarray) -> tuple[float, float] | None:
    """Smallest and largest finite, non-negative value, or None when there is none."""
    if image.size == 0:
        return None
    lo, hi = float(np.fmin.reduce(image, axis=None)), float(np.fmax.reduce(image, axis=None))
    if lo >= 0 and np.isfinite(hi):  # NaN-ignoring reductions: the fast, common case
        return lo, hi
    valid = np.isfinite(image) & (image >= 0)  # rare: infinities or negatives present
    if not valid.any():
        return None
    return float(np.min(image, where=valid, initial=np.inf)), \
        float(np.max(image, where=valid, initial=-np.inf))


def _invalid(image: np.ndarray) -> np.ndarray:
    """Pixels that carry no relative disparity: NaN, ±∞ or negative."""
    invalid = ~np.isfinite(image)
    invalid |= image < 0
    return invalid


def _affine_depth(image: np.ndarray, a: float, b: float, options: RescaleOptions) -> np.ndarray:
    """depth = 1 / max(a·x + b, 1/max_depth), at least min_depth, in place on one buffer."""
    depth = np.multiply(image, np.float32(a))
    depth += np.float32(b)
    np.maximum(depth, np.float32(1.0 / options.max_depth), out=depth)
    np.reciprocal(depth, out=depth)
    np.maximum(depth, np.float32(options.min_depth), out=depth)
    np.copyto(depth, np.float32(np.nan), where=_invalid(image))
    return depth


#: OpenCV's remap handles images and tables up to this many rows and columns.
_REMAP_LIMIT = 32767


def _lookup(image: np.ndarray, tables_of, size: int, fills: tuple[float, ...]) -> np.ndarray:
    """Apply functions of x to every pixel through tables over the image's valid range.

    ``tables_of(grid)`` returns one table row per function, evaluated once on ``size`` evenly
    spaced x from the smallest to the largest valid pixel; each pixel takes its nearest entry,
    half a step at most (range / (2·(size − 1))) from its own x, and invalid pixels take the
    function's entry of ``fills``. The result has the image's shape plus, for more than one
    function, a last axis with one channel per function: the gather is OpenCV's
    nearest-neighbour remap over a one-row table of that many channels, which rounds as it
    reads, runs on every core and fetches all functions in one pass; 1.5 times faster than
    numpy's take at 640x480 (benchmarks/lookup_gather.py, docs/benchmarks.md).
    """
    channels = len(fills)
    bounds = _valid_range(image)
    if bounds is None:
        filled = np.empty(image.shape + (channels,), dtype=np.float32)
        filled[...] = fills
        return filled[..., 0] if channels == 1 else filled
    lo, hi = bounds
    table = np.empty((1, size + 1, channels), dtype=np.float32)
    table[0, :size] = np.reshape(tables_of(np.linspace(lo, hi, size)), (channels, size)).T
    table[0, size] = fills
    steps = np.float32((size - 1) / (hi - lo) if hi > lo else 0.0)
    # Column of each pixel's entry. Subtracting lo first keeps the smallest pixel at exactly
    # 0; +∞ is capped to the fill column, NaN and negative pixels (−∞ too) sent there
    # explicitly, so no NaN ever reaches OpenCV's float-to-int rounding, which differs
    # between CPUs.
    columns = np.subtract(image, np.float32(lo), dtype=np.float32)
    columns *= steps
    np.minimum(columns, np.float32(size), out=columns)
    no_disparity = image >= 0
    np.logical_not(no_disparity, out=no_disparity)
    np.copyto(columns, np.float32(size), where=no_disparity)
    looked_up = _remap_nearest(table[..., 0] if channels == 1 else table, columns)
    return looked_up.reshape(image.shape + ((channels,) if channels > 1 else ()))


def _remap_nearest(table: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """table[0, round(columns)] for every element, through cv2.remap on a 2-D view; a table of
    shape (1, n, c) gives c values per element (last axis)."""
    if columns.ndim == 2 and max(columns.shape) < _REMAP_LIMIT:
        grid = columns
    else:  # any other shape: rows of 1024 columns, the last one padded with the fill column
        flat = columns.reshape(-1)
        grid = np.full((-(-flat.size // 1024), 1024), table.shape[1] - 1, dtype=np.float32)
        grid.reshape(-1)[:flat.size] = flat
    rows = np.zeros_like(grid)
    looked_up = cv2.remap(table, grid, rows, interpolation=cv2.INTER_NEAREST)
    channels = table.shape[2:]
    return looked_up.reshape((-1,) + channels)[:columns.size]


# --------------------------------------------------------------------------------------------
# Fitting

_DEFAULT_OPTIONS = RescaleOptions()


def fit(relative_disparity, metric_depth, method: str | None = None, *,
        options: RescaleOptions | None = None, **overrides) -> RescaleResult:
    """Fit the map from relative disparity to metric disparity on anchors.

    ``relative_disparity`` and ``metric_depth`` are 1-D and equally long: the network's
    value at each feature (see :func:`autonomy.depth.anchors.sample_nearest_surface`) and the
    feature's metric depth in metres. Anchors with non-finite or non-positive disparity, or
    depth outside [min_depth, max_depth], are dropped. ``method`` and ``overrides`` replace
    fields of ``options`` (defaults: :class:`RescaleOptions`).

    Returns a :class:`RescaleModel`, or a :class:`NoFit` saying why: fewer than
    ``min_anchors`` valid anchors, all disparities equal, a map that does not rise, too few
    inliers left by outlier rejection. Raises ValueError only for arrays of the wrong shape
    and :class:`~autonomy.options.OptionError` for a bad option.
    """
    opts = options or _DEFAULT_OPTIONS
    if method is not None:
        overrides["method"] = method
    if overrides:
        opts = dataclasses.replace(opts, **overrides)
    x, z = _as_anchor_arrays(relative_disparity, metric_depth)
    keep, summary = _select_anchors(x, z, opts)
    if summary.valid < opts.min_anchors:
        return NoFit(NoFitReason.TOO_FEW_ANCHORS, _too_few_detail(summary, opts), opts.method,
                     summary)
    order = np.argsort(x[keep], kind="stable")
    x, y = x[keep][order], 1.0 / z[keep][order]
    span = x[-1] - x[0]
    if span <= 1e-9 * abs(x[-1]):
        return NoFit(NoFitReason.DEGENERATE_DISPARITY, f"all {len(x)} anchors have the same "
                     f"relative disparity ({x[0]:.6g}); no map can be fitted", opts.method,
                     summary)
    try:
        return _fit_sorted(x, y, opts, summary)
    except curves.FitFailure as failure:
        return NoFit(NoFitReason(failure.reason), failure.detail, opts.method, summary)
    except np.linalg.LinAlgError as error:
        return NoFit(NoFitReason.FIT_FAILED, f"{opts.method}: linear algebra failed: {error}",
                     opts.method, summary)


def _as_anchor_arrays(relative_disparity, metric_depth) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(relative_disparity, dtype=float)
    z = np.asarray(metric_depth, dtype=float)
    if x.ndim != 1 or z.shape != x.shape:
        raise ValueError("relative_disparity and metric_depth must be 1-D arrays of equal "
                         f"length, got shapes {x.shape} and {z.shape}")
    return x, z


def _select_anchors(x: np.ndarray, z: np.ndarray, opts: RescaleOptions) -> tuple[np.ndarray, AnchorSummary]:
    good_disparity = np.isfinite(x) & (x > 0)
    good_depth = np.isfinite(z) & (z >= opts.min_depth) & (z <= opts.max_depth)
    summary = AnchorSummary(given=len(x), bad_disparity=int((~good_disparity).sum()),
                            bad_depth=int((good_disparity & ~good_depth).sum()))
    return good_disparity & good_depth, summary


def _too_few_detail(summary: AnchorSummary, opts: RescaleOptions) -> str:
    return (f"{summary.valid} valid anchors, need {opts.min_anchors} ({summary.given} given: "
            f"{summary.bad_disparity} with non-finite or non-positive relative disparity, "
            f"{summary.bad_depth} with depth outside [{opts.min_depth:g}, {opts.max_depth:g}] m)")


def _fit_sorted(x: np.ndarray, y: np.ndarray, opts: RescaleOptions,
                summary: AnchorSummary) -> RescaleResult:
    """Fit the family (with outlier rejection), check it rises, and guard it."""
    family, used, method, notes = _fit_robustly(x, y, opts)
    if used.sum() < opts.min_anchors:
        return NoFit(NoFitReason.TOO_FEW_INLIERS, f"{int(used.sum())} inliers after outlier "
                     f"rejection, need {opts.min_anchors}", opts.method, summary)
    x_used, y_used = x[used], y[used]
    reference = curves.fit_affine_least_squares(x_used, y_used)
    if reference.a <= 0:
        return NoFit(NoFitReason.NOT_INCREASING, "metric disparity does not rise with relative "
                     f"disparity (least-squares slope {reference.a:.3g}): the anchors or the "
                     "network output are wrong", opts.method, summary)
    curve = curves.guard(family, x_used, reference.a, opts)
    summary = dataclasses.replace(summary, outliers=int((~used).sum()), used=int(used.sum()))
    residual_rms = float(np.sqrt(np.mean((curve(x_used) - y_used) ** 2)))
    return RescaleModel(method, curve, summary, x_used, opts, residual_rms, notes)


def _fit_robustly(x, y, opts: RescaleOptions):
    """(family, used-anchor mask, method fitted, notes), after outlier rejection.

    The first judgement of the anchors is against a curve of fixed flexibility, the
    monotone P-spline: a flexible family fitted through outliers (FITPACK adds knots until
    it reaches them) makes every residual small and hides them. Then the method is fitted to the anchors kept, judges them
    itself, and is refitted until the kept set stops changing (at most
    ``_REJECTION_ROUNDS`` refits), so a curve dragged by outliers is corrected before it
    judges again.
    """
    if opts.method == "ransac_affine":
        family, inliers = curves.fit_ransac_affine(x, y, opts)
        return family, inliers, opts.method, ()
    if not opts.outlier_rejection:
        family, method, notes = _fit_family(x, y, opts)
        return family, np.ones(len(x), dtype=bool), method, notes
    used = _supported(x, y, _inliers(x, y, _screening_curve(x, y, opts),
                                     opts.outlier_threshold), opts)
    for round_ in range(_REJECTION_ROUNDS):
        if used.sum() < opts.min_anchors:
            return None, used, opts.method, ()
        family, method, notes = _fit_family(x[used], y[used], opts)
        judged = _supported(x, y, _inliers(x, y, family, opts.outlier_threshold), opts)
        if _settled(judged, used) or round_ == _REJECTION_ROUNDS - 1:
            return family, used, method, notes
        used = judged


def _settled(judged: np.ndarray, used: np.ndarray) -> bool:
    """The fit's own judgement differs from the anchors it was fitted to by at most 1 % of
    them (one at least): anchors on the residual limit flip in and out, and refitting for
    them would not move the curve."""
    return np.count_nonzero(judged != used) <= max(1, len(used) // 100)


_REJECTION_ROUNDS = 3


def _screening_curve(x, y, opts: RescaleOptions):
    if curves.count_distinct(x) < 4:
        return curves.fit_affine_least_squares(x, y)
    return curves.fit_monotone_pspline(x, y, opts, smoothing_lambda=0.0)[0]


#: An anchor beyond the near end's gap is unsupported when its metric disparity is less than
#: the others' affine map's by more than this factor (it claims a surface this much farther).
NEAR_END_FACTOR = 1.5


def _supported(x, y, used: np.ndarray, opts: RescaleOptions) -> np.ndarray:
    """``used`` less the anchors at the near end that the others do not support
    (``near_end_check``).

    The anchors of ``used`` beyond its last gap (a stretch of relative disparity wider than
    ``gap_fraction`` of their range with no anchor), when fewer than those below it, have no
    neighbour to contradict them: any flexible curve, the screening one too, bends to reach
    them, so their residuals say nothing. They are judged instead by the least-squares affine
    map of the anchors below the gap (the map a relative-disparity network ideally follows;
    a curve fitted to few anchors is no steadier a judge): one whose metric disparity is less
    than that map's by more than :data:`NEAR_END_FACTOR` is dropped. One-sided, because that is
    the harmful error: such an anchor sets the curve's near end farther than its neighbours
    say, and every nearer surface is read farther with it. Why: a landmark on a wall just
    beside a thin pole samples the pole's larger disparity (the nearest surface of its four
    pixels, anchors.py); alone beyond a gap, it set the near end at the wall's depth, and the
    pole 1.1 m away read 3.1 m (a realistic sewer flight, docs/rescaling.md). A network that
    reads near surfaces farther than affine (less relative disparity) is never judged wrong
    by it; one that reads them nearer (more) by more than the factor loses those anchors, and
    its near surfaces are then read by the curve's straight tail, nearer than they are: the
    safe side.
    """
    if not opts.near_end_check:
        return used
    index = np.flatnonzero(used)  # x is sorted, so these are too
    if len(index) < 2:
        return used
    gaps = curves.gap_starts(x[index], opts.gap_fraction)
    if len(gaps) == 0:
        return used
    below, beyond = index[:gaps[-1] + 1], index[gaps[-1] + 1:]
    if len(beyond) >= len(below) or curves.count_distinct(x[below]) < 4:
        return used
    extension = curves.fit_affine_least_squares(x[below], y[below])(x[beyond])
    result = used.copy()
    result[beyond[y[beyond] * NEAR_END_FACTOR < extension]] = False
    return result


def _inliers(x, y, family, threshold: float) -> np.ndarray:
    """Anchors whose residual lies within ``threshold`` robust sigmas of the median residual.

    Two noise models are both plausible for VINS depths: triangulation error grows as z², so
    metric-disparity noise is uniform (σ in 1/m); other errors are proportional to depth (σ
    relative to y). An anchor is rejected only when it is an outlier under both, so neither
    far nor near anchors are thrown out wholesale when the other model holds.
    Centring on the median residual keeps the inliers when outliers have shifted the whole
    curve. A residual under 1 % of the anchor's own disparity is never an outlier, so
    noise-free anchors are not split in half.
    """
    residuals = y - family(x)
    centred = np.abs(residuals - curves.median(residuals))
    uniform = curves.robust_sigma(residuals)
    relative = curves.robust_sigma(residuals / y) * np.abs(y)
    limit = np.maximum(threshold * np.maximum(uniform, relative), 0.01 * np.abs(y))
    return centred <= limit


#: Distinct anchors each family needs; with fewer it falls back to poly1.
_PARAMETERS = {"poly1": 2, "poly2": 3, "poly3": 4, "poly4": 5, "poly5": 6, "exponential": 2,
               "smoothing_spline": 4, "monotone_smoothing_spline": 4, "monotone_spline": 4}


def _fit_family(x, y, opts: RescaleOptions):
    """(family, method fitted, notes) for every method but RANSAC."""
    distinct = curves.count_distinct(x)
    if distinct < _PARAMETERS[opts.method]:
        note = (f"{opts.method} needs {_PARAMETERS[opts.method]} distinct relative "
                f"disparities, got {distinct}: fell back to poly1")
        return curves.fit_affine_least_squares(x, y), "poly1", (note,)
    if opts.method == "poly1":
        return curves.fit_affine_least_squares(x, y), "poly1", ()
    if opts.method.startswith("poly"):
        return curves.fit_polynomial(x, y, int(opts.method[4:])), opts.method, ()
    if opts.method == "exponential":
        return curves.fit_exponential(x, y), opts.method, ()
    if opts.method == "smoothing_spline":
        return curves.fit_smoothing_spline(x, y, opts), opts.method, ()
    smoothing = opts.smoothing_lambda if opts.method == "monotone_smoothing_spline" else 0.0
    family, segments = curves.fit_monotone_pspline(x, y, opts, smoothing)
    notes = () if segments == opts.segments else (
        f"{distinct} distinct anchors: segments reduced from {opts.segments} to {segments}",)
    return family, opts.method, notes


# --------------------------------------------------------------------------------------------
# Temporal smoothing


class TemporalBlend:
    """Blend each frame's curve with the previous frame's, for any method.

    y_t(x) = (1 − w)·f_t(x) + w·y_{t−1}(x), sampled at ``grid_points`` relative disparities
    evenly spread over the new fit's anchor range and carried as straight segments, with
    tails whose slopes blend the same way. Blending non-decreasing curves keeps them
    non-decreasing. Weight 0 passes every result through unchanged (the default: off). A
    frame without a fit passes its :class:`NoFit` through and forgets the history, so a stale
    curve is never carried over a gap in fits.
    """

    def __init__(self, weight: float, grid_points: int = 256):
        if not 0.0 <= weight < 1.0:
            raise ValueError(f"temporal blend weight must be in [0, 1), got {weight!r}")
        self.weight = weight
        self.grid_points = grid_points
        self._previous: RescaleModel | None = None

    def update(self, result: RescaleResult) -> RescaleResult:
        if not result.ok:
            self._previous = None
            return result
        if self.weight == 0.0 or self._previous is None:
            self._previous = result
            return result
        blended = self._blend(result, self._previous)
        self._previous = blended
        return blended

    def _blend(self, new: RescaleModel, old: RescaleModel) -> RescaleModel:
        w = self.weight
        lo, hi = new.anchor_range
        grid = np.linspace(lo, hi, self.grid_points)
        values = (1 - w) * new.metric_disparity(grid) + w * old.metric_disparity(grid)
        curve = curves.GuardedCurve(
            curves.PiecewiseLinear(grid, values), lo, hi,
            tail_slope=(1 - w) * new.curve.tail_slope + w * old.curve.tail_slope)
        note = f"blended with the previous frame's curve, weight {w:g}"
        return dataclasses.replace(new, curve=curve, notes=new.notes + (note,))
