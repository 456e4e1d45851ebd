"""The metric depth stage: one camera frame's relative disparity made metric with the VINS map.

For the frame taken at ``t`` (Yang et al., Section III-B):

1. check the network's output (:func:`check_relative_disparity`): an image with NaN, ±∞ or
   negative values, or a constant one, is rejected with its reason and counted;
2. take the VINS sparse map of the same frame (given with it; one whose time is more than
   ``max_map_offset_s`` from ``t`` belongs to another frame and is refused), keep the
   landmarks the front-end saw in this frame (all landmarks in view with ``tracked_only``
   off), and sample the relative disparity at each one's pixel,
   the nearest surface of the four pixels around it
   (:func:`~autonomy.depth.anchors.sample_nearest_surface`);
3. fit the configured map from relative to metric disparity on those anchors
   (:func:`~autonomy.depth.rescale.fit`, optionally blended over frames) and apply it to every
   pixel: a metric depth image with its per-pixel confidence and the fit's diagnostics.

A frame whose fit fails (too few anchors, say) is given the last good fit while it is at most
``hold_s`` old, marked ``held``. After that, a frame with at least ``fallback_min_anchors``
anchors gets the affine map of relative to metric disparity fitted to them
(:func:`affine_fallback`): the ambiguity a relative-depth network is trained to leave (Depth
Anything's affine-invariant disparity loss; Yang et al., Section III-B), two parameters where
the configured curve wants ``[rescale] min_anchors``. Otherwise, and for a rejected network
output, the result is "no depth", which the planner treats as stop.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import dataclass
from enum import Enum

import numpy as np

from autonomy.depth.anchors import sample_nearest_surface
from autonomy.depth.rescale import RescaleModel, RescaleOptions, TemporalBlend, fit
from autonomy.depth.scale_field import ScaleField, fit_scale_field
from autonomy.messages import (DepthDiagnostics, FitSamples, MetricDepth, RelativeDepth,
                               SparseMap)
from autonomy.options import OptionError, option, validate


@dataclass(frozen=True)
class DepthStageOptions:
    """Which anchors the stage takes from a frame's sparse map, and how it bridges frames
    without a fit."""

    hold_s: float = option(0.5, ge=0.0, le=5.0, doc="how long the last good fit is applied to "
                           "frames that get none, seconds; after that there is no depth")
    tracked_only: bool = option(True, doc="anchors only from landmarks seen in this very frame "
                                "(a landmark merely projected into view may be occluded)")
    max_map_offset_s: float = option(0.002, ge=0.0, le=0.1, doc="largest difference between "
                                     "a frame's time and its sparse map's time, seconds")
    scale_field_nodes: int = option(0, ge=0, le=16, doc="nodes a side of the smooth scale "
                                    "field fitted to the anchors' residuals after the curve "
                                    "(scale_field.py); 0: none, the curve alone (the paper)")
    scale_field_sigma: float = option(0.1, gt=0.0, le=1.0, doc="prior spread of the scale "
                                      "field's nodes and of their neighbours' differences, log "
                                      "disparity")
    fallback_min_anchors: int = option(5, ge=0, doc="a frame the configured curve cannot "
                                       "be fitted to (too few anchors, say), with no held fit "
                                       "left, gets an affine map (poly1) fitted to its anchors "
                                       "when at least this many remain, instead of no depth; "
                                       "0: never")

    def __post_init__(self) -> None:
        validate(self)
        if self.scale_field_nodes == 1:
            raise OptionError("scale_field_nodes", "must be 0 (no field) or at least 2, got 1")
        if 0 < self.fallback_min_anchors < 4:
            raise OptionError("fallback_min_anchors", "must be 0 (no fallback) or at least 4 "
                              "(two parameters and two anchors to judge them by), got "
                              f"{self.fallback_min_anchors}")


#: The :attr:`MetricDepthStage.no_fit` key of frames that came without their sparse map.
NO_SPARSE_MAP = "no_sparse_map"


class Rejection(str, Enum):
    """Why a network output is not used."""

    NON_FINITE = "non_finite"
    NEGATIVE = "negative"
    CONSTANT = "constant"
    NOT_AN_IMAGE = "not_an_image"


def check_relative_disparity(disparity: np.ndarray) -> tuple[Rejection, str] | None:
    """None for a usable relative-disparity image, else ``(reason, detail)``.

    Usable: a 2-D array of real numbers, all finite and non-negative, not constant. A
    healthy network never emits NaN or ∞ (one means numerical trouble, e.g. an fp16
    overflow) nor negative disparity (Depth Anything and MiDaS end in a ReLU); a constant
    image carries no depth at all (a covered lens, a model that has broken down). Costs two
    reductions over the image: min and max propagate NaN, so they find everything.
    """
    image = np.asarray(disparity)
    if image.ndim != 2 or image.size == 0 or not (
            np.issubdtype(image.dtype, np.floating) or np.issubdtype(image.dtype, np.integer)):
        return Rejection.NOT_AN_IMAGE, f"expected a 2-D real image, got {image.dtype} " \
                                       f"with shape {image.shape}"
    lo, hi = float(image.min()), float(image.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):
        bad = int(np.count_nonzero(~np.isfinite(image)))
        return Rejection.NON_FINITE, f"{bad} pixels are NaN or infinite"
    if lo < 0.0:
        return Rejection.NEGATIVE, f"{int(np.count_nonzero(image < 0))} pixels are negative " \
                                   f"(smallest {lo:.3g})"
    if hi - lo <= 1e-6 * hi or hi == 0.0:
        return Rejection.CONSTANT, f"every pixel is {lo:.6g}"
    return None


@dataclass(frozen=True)
class _GoodFit:
    t: float
    model: RescaleModel
    field: ScaleField | None


class MetricDepthStage:
    """Relative disparity + VINS sparse maps → :class:`MetricDepth`, one frame at a time.

    Feed each network output with the VINS sparse map of the same frame to :meth:`process`,
    in time order. ``rejected`` counts rejected network outputs by :class:`Rejection` value;
    ``no_fit`` counts frames without a fresh fit of the configured method by reason,
    ``fallbacks`` those of them given the affine fallback.
    """

    def __init__(self, rescale: RescaleOptions | None = None,
                 options: DepthStageOptions | None = None):
        self.rescale = rescale or RescaleOptions()
        self.options = options or DepthStageOptions()
        self.rejected: Counter[str] = Counter()
        self.no_fit: Counter[str] = Counter()
        self.fallbacks = 0
        self._blend = TemporalBlend(self.rescale.temporal_blend)
        self._last_good: _GoodFit | None = None

    def process(self, relative: RelativeDepth, sparse_map: SparseMap | None) -> MetricDepth:
        """The metric depth of one frame, from its network output and the VINS sparse map of
        the same frame (None when the VINS had none; module docstring)."""
        t = relative.t
        problem = check_relative_disparity(relative.disparity)
        if problem is not None:
            reason, detail = problem
            self.rejected[reason.value] += 1
            self._blend = TemporalBlend(self.rescale.temporal_blend)  # no curve across a gap
            return _no_depth(t, f"network output rejected ({reason.value}): {detail}", None)
        disparity = np.asarray(relative.disparity, dtype=np.float32)
        if sparse_map is not None and abs(sparse_map.t - t) > self.options.max_map_offset_s:
            sparse_map = None  # another frame's map: its landmarks are not at these pixels
        if sparse_map is None:
            self.no_fit[NO_SPARSE_MAP] += 1
            return self._bridge(t, disparity, 0, "no VINS sparse map for this frame")
        x, z, pixels = self._anchor_samples(sparse_map, disparity)
        result = self._blend.update(fit(x, z, options=self.rescale))
        if not result.ok:
            self.no_fit[result.reason.value] += 1
            return self._bridge(t, disparity, len(x),
                              f"no fit ({result.reason.value}): {result.detail}",
                              fallback_anchors=(x, z))
        field = self._scale_field(result, x, z, pixels, disparity.shape)
        self._last_good = _GoodFit(t, result, field)
        return _apply(t, disparity, result, (x, z), field, fit_age_s=0.0, reason="")

    def _scale_field(self, model: RescaleModel, x: np.ndarray, z: np.ndarray,
                     pixels: np.ndarray, shape: tuple[int, int]) -> ScaleField | None:
        """The field of the curve's residuals at the anchors (scale_field.py), None when
        ``scale_field_nodes`` is 0."""
        n = self.options.scale_field_nodes
        if n == 0:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            residuals = np.log(1.0 / (z * model.metric_disparity(x)))
        usable = np.isfinite(residuals)
        return fit_scale_field(pixels[usable], residuals[usable], shape, n,
                               self.options.scale_field_sigma)

    def _bridge(self, t: float, disparity: np.ndarray, anchors: int, reason: str,
              fallback_anchors: tuple[np.ndarray, np.ndarray] | None = None) -> MetricDepth:
        """A frame without a fresh fit of the configured method: the last good fit applied
        to it while that is at most ``hold_s`` old, else the affine fallback on
        ``fallback_anchors`` (this frame's), else no depth."""
        held = self._last_good
        if held is None or not 0.0 <= t - held.t <= self.options.hold_s:
            fallback = None if fallback_anchors is None else affine_fallback(
                *fallback_anchors, self.rescale, self.options.fallback_min_anchors)
            if fallback is None:
                return _no_depth(t, reason, disparity, anchors)
            self.fallbacks += 1
            return _apply(t, disparity, fallback, fallback_anchors, None, fit_age_s=0.0,
                          reason=f"affine fallback after {reason}", fallback=True)
        empty = np.empty(0)
        return _apply(t, disparity, held.model, (empty, empty), held.field,
                      fit_age_s=t - held.t, reason=reason, held=True, sampled=anchors)

    def anchors(self, sparse_map: SparseMap,
                disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(relative disparity, metric depth)`` of the landmarks of ``sparse_map`` that fall
        on the image (only those tracked in this frame with ``tracked_only``)."""
        x, z, _ = self._anchor_samples(sparse_map, disparity)
        return x, z

    def _anchor_samples(self, sparse_map: SparseMap, disparity: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`anchors` with their pixels (N, 2)."""
        use = np.asarray(sparse_map.tracked, dtype=bool) if self.options.tracked_only \
            else np.ones(len(sparse_map), dtype=bool)
        pixels = np.asarray(sparse_map.pixels, dtype=float).reshape(-1, 2)[use]
        depth = np.asarray(sparse_map.points_C, dtype=float).reshape(-1, 3)[use, 2]
        x = sample_nearest_surface(disparity, pixels)
        on_image = np.isfinite(x)
        return x[on_image], depth[on_image], pixels[on_image]


def affine_fallback(x: np.ndarray, z: np.ndarray, rescale: RescaleOptions,
                    min_anchors: int) -> RescaleModel | None:
    """The affine map 1/z = a x + b (a > 0) fitted to a frame's anchors ``x`` (relative
    disparity) and ``z`` (metric depth), for a frame the configured curve could not be fitted
    to: at least ``min_anchors`` of them valid and inliers (0: never), with the configured
    outlier rejection and guards. None when they are fewer or no such map fits (a slope that
    does not rise, say).

    A relative-depth network's disparity is metric disparity up to an unknown scale and
    shift (Depth Anything's affine-invariant loss), so two parameters are what few anchors
    can pin; the curve's flexibility, which corrects the network's non-affine error, needs
    more (the paper's monotone spline). The map's per-pixel confidence counts anchors near
    each disparity (:meth:`RescaleModel.confidence`), so with few of them most pixels stay
    below the planner's ``min_confidence``."""
    if min_anchors == 0:
        return None
    model = fit(x, z, options=dataclasses.replace(rescale, method="poly1",
                                                  min_anchors=min_anchors))
    return model if model.ok else None


#: Points the curve is sampled at for :class:`~autonomy.messages.FitSamples`.
CURVE_SAMPLES = 32


def _apply(t: float, disparity: np.ndarray, model: RescaleModel,
           anchors: tuple[np.ndarray, np.ndarray], field: ScaleField | None, *,
           fit_age_s: float, reason: str, held: bool = False, fallback: bool = False,
           sampled: int | None = None) -> MetricDepth:
    """``model`` applied to the frame, then ``field`` if any; ``reason``: why the configured
    fit was not made on this frame (empty when it was), ``held``: ``model`` is an earlier
    frame's, ``fallback``: it is :func:`affine_fallback`'s. ``anchors``: the (relative, depth)
    pairs of this frame's fit; ``sampled``: how many anchors the frame had, when not those (a
    held fit)."""
    depth, confidence = model.depth_and_confidence(disparity)
    if field is not None:
        depth = depth * field.depth_factor(depth.shape)
    count = len(anchors[0]) if sampled is None else sampled
    diagnostics = DepthDiagnostics(count, model.anchors.used, model.residual_rms,
                                   model.method, fit_age_s, reason, fallback)
    curve_x = np.linspace(*model.anchor_range, CURVE_SAMPLES)
    fit = FitSamples(anchors[0], anchors[1], curve_x, model.metric_disparity(curve_x))
    return MetricDepth(t, depth, confidence, held=held, diagnostics=diagnostics,
                       relative=disparity, fit=fit)


def _no_depth(t: float, reason: str, disparity: np.ndarray | None,
              anchors: int = 0) -> MetricDepth:
    return MetricDepth(t, None, None, held=False,
                       diagnostics=DepthDiagnostics(anchors, 0, math.nan, "", math.nan, reason),
                       relative=disparity)
