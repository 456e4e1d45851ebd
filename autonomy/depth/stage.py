"""The metric depth stage: one camera frame's relative disparity made metric with the VINS map.

For the frame taken at ``t`` (Yang et al., Section III-B):

1. check the network's output (:func:`check_relative_disparity`): an image with NaN, ±∞ or
   negative values, or a constant one, is rejected with its reason and counted;
2. take the VINS sparse map of the same frame (the one whose time is nearest ``t``, within
   ``max_map_offset_s``), keep the landmarks the front-end saw in this frame (all landmarks
   in view with ``tracked_only`` off), and sample the relative disparity at each one's pixel,
   the nearest surface of the four pixels around it
   (:func:`~autonomy.depth.anchors.sample_nearest_surface`);
3. fit the configured map from relative to metric disparity on those anchors
   (:func:`~autonomy.depth.rescale.fit`, optionally blended over frames) and apply it to every
   pixel: a metric depth image with its per-pixel confidence and the fit's diagnostics.

A frame whose fit fails (too few anchors, say) is given the last good fit while it is at most
``hold_s`` old, marked ``held``; after that, and for a rejected network output, the result is
"no depth", which the planner treats as stop.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from enum import Enum

import numpy as np

from autonomy.depth.anchors import sample_nearest_surface
from autonomy.depth.rescale import RescaleModel, RescaleOptions, TemporalBlend, fit
from autonomy.messages import DepthDiagnostics, MetricDepth, RelativeDepth, SparseMap
from autonomy.options import option, validate


@dataclass(frozen=True)
class DepthStageOptions:
    """How the stage pairs frames with sparse maps and bridges frames without a fit."""

    hold_s: float = option(0.5, ge=0.0, le=5.0, doc="how long the last good fit is applied to "
                           "frames that get none, seconds; after that there is no depth")
    tracked_only: bool = option(True, doc="anchors only from landmarks seen in this very frame "
                                "(a landmark merely projected into view may be occluded)")
    max_map_offset_s: float = option(0.002, ge=0.0, le=0.1, doc="largest difference between "
                                     "a frame's time and its sparse map's time, seconds")
    map_history: int = option(32, ge=1, le=1000, doc="sparse maps kept to pair with frames "
                              "whose network output arrives later")

    def __post_init__(self) -> None:
        validate(self)


#: The :attr:`MetricDepthStage.no_fit` key of frames that had no sparse map to pair with.
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


class MetricDepthStage:
    """Relative disparity + VINS sparse maps → :class:`MetricDepth`, one frame at a time.

    Feed every sparse map the VINS produces with :meth:`add_sparse_map` and each network
    output with :meth:`process`, in time order. ``rejected`` counts rejected network outputs
    by :class:`Rejection` value; ``no_fit`` counts frames without a fresh fit by reason.
    """

    def __init__(self, rescale: RescaleOptions | None = None,
                 options: DepthStageOptions | None = None):
        self.rescale = rescale or RescaleOptions()
        self.options = options or DepthStageOptions()
        self.rejected: Counter[str] = Counter()
        self.no_fit: Counter[str] = Counter()
        self._maps: deque[SparseMap] = deque(maxlen=self.options.map_history)
        self._blend = TemporalBlend(self.rescale.temporal_blend)
        self._last_good: _GoodFit | None = None

    def add_sparse_map(self, sparse_map: SparseMap) -> None:
        """Keep the VINS map of one frame for pairing with that frame's network output."""
        self._maps.append(sparse_map)

    def map_at(self, t: float) -> SparseMap | None:
        """The kept sparse map nearest ``t``, if within ``max_map_offset_s`` of it."""
        if not self._maps:
            return None
        nearest = min(self._maps, key=lambda m: abs(m.t - t))
        return nearest if abs(nearest.t - t) <= self.options.max_map_offset_s else None

    def process(self, relative: RelativeDepth) -> MetricDepth:
        """The metric depth of one frame (module docstring)."""
        t = relative.t
        problem = check_relative_disparity(relative.disparity)
        if problem is not None:
            reason, detail = problem
            self.rejected[reason.value] += 1
            self._blend = TemporalBlend(self.rescale.temporal_blend)  # no curve across a gap
            return _no_depth(t, f"network output rejected ({reason.value}): {detail}")
        disparity = np.asarray(relative.disparity, dtype=np.float32)
        sparse_map = self.map_at(t)
        if sparse_map is None:
            self.no_fit[NO_SPARSE_MAP] += 1
            return self._hold(t, disparity, 0, "no VINS sparse map for this frame")
        x, z = self.anchors(sparse_map, disparity)
        result = self._blend.update(fit(x, z, options=self.rescale))
        if not result.ok:
            self.no_fit[result.reason.value] += 1
            return self._hold(t, disparity, len(x),
                              f"no fit ({result.reason.value}): {result.detail}")
        self._last_good = _GoodFit(t, result)
        return _apply(t, disparity, result, len(x), fit_age_s=0.0, reason="")

    def _hold(self, t: float, disparity: np.ndarray, anchors: int, reason: str) -> MetricDepth:
        """The last good fit applied to this frame while it is at most ``hold_s`` old, else
        no depth."""
        held = self._last_good
        if held is None or not 0.0 <= t - held.t <= self.options.hold_s:
            return _no_depth(t, reason, anchors)
        return _apply(t, disparity, held.model, anchors, fit_age_s=t - held.t, reason=reason)

    def anchors(self, sparse_map: SparseMap,
                disparity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(relative disparity, metric depth)`` of the landmarks of ``sparse_map`` that fall
        on the image (only those tracked in this frame with ``tracked_only``)."""
        use = np.asarray(sparse_map.tracked, dtype=bool) if self.options.tracked_only \
            else np.ones(len(sparse_map), dtype=bool)
        pixels = np.asarray(sparse_map.pixels, dtype=float).reshape(-1, 2)[use]
        depth = np.asarray(sparse_map.points_C, dtype=float).reshape(-1, 3)[use, 2]
        x = sample_nearest_surface(disparity, pixels)
        on_image = np.isfinite(x)
        return x[on_image], depth[on_image]


def _apply(t: float, disparity: np.ndarray, model: RescaleModel, anchors: int, *,
           fit_age_s: float, reason: str) -> MetricDepth:
    """``model`` applied to the frame; a non-empty ``reason`` marks a held fit."""
    depth, confidence = model.depth_and_confidence(disparity)
    diagnostics = DepthDiagnostics(anchors, model.anchors.used, model.residual_rms,
                                   model.method, fit_age_s, reason)
    return MetricDepth(t, depth, confidence, held=bool(reason), diagnostics=diagnostics)


def _no_depth(t: float, reason: str, anchors: int = 0) -> MetricDepth:
    return MetricDepth(t, None, None, held=False,
                       diagnostics=DepthDiagnostics(anchors, 0, math.nan, "", math.nan, reason))
