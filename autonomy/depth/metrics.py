"""Depth evaluation metrics: predicted against ground-truth metric depth.

Depth images are float32 metres with NaN for unknown. A pixel is *valid* when both the
prediction and the ground truth are finite and strictly positive, and, when a boolean ``mask``
is given, the mask is true there. Every metric is taken over the valid pixels only; with no
valid pixel it is NaN (and its pixel count 0), never an error or a numpy warning.

With ``z`` the predicted and ``z*`` the ground-truth depth over the ``n`` valid pixels, the
standard monocular-depth metrics are

    AbsRel = (1/n) sum |z - z*| / z*
    delta1 = (1/n) #{ max(z / z*, z* / z) < 1.25 }
    RMSE   = sqrt((1/n) sum (z - z*)^2)

plus a safety metric, the overestimate rate: the share of near obstacles placed too far away.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

#: Accepted values of the ``denominator`` argument of :func:`abs_rel`.
DENOMINATORS = ("gt", "pred")
#: Ratio bound of :func:`delta1`, the usual delta < 1.25.
DELTA1_THRESHOLD = 1.25
#: Ground-truth depth in metres below which :func:`overestimate_rate` looks at a pixel.
NEAR_DEPTH = 5.0
#: Relative excess over the truth beyond which :func:`overestimate_rate` counts a pixel.
OVERESTIMATE_MARGIN = 0.25


@dataclass(frozen=True)
class DepthMetrics:
    """All metrics of one prediction against one ground truth."""

    abs_rel: float
    delta1: float
    rmse: float
    overestimate_rate: float
    valid_pixels: int
    near_pixels: int

    def as_dict(self) -> dict[str, float | int]:
        """The metrics by field name, e.g. for a report row."""
        return dataclasses.asdict(self)


def valid_pairs(pred, gt, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """The 1-D float64 predicted and true depths at the valid pixels.

    Valid: both finite and > 0, and ``mask`` true where given. Raises ValueError when the
    shapes of ``pred``, ``gt`` and ``mask`` differ.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt shapes differ: pred {pred.shape}, gt {gt.shape}")
    valid = np.isfinite(pred) & np.isfinite(gt) & (pred > 0) & (gt > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != gt.shape:
            raise ValueError(f"mask shape {mask.shape} differs from the depth shape {gt.shape}")
        valid &= mask
    return pred[valid], gt[valid]


def _mean_or_nan(values: np.ndarray) -> float:
    return float(np.mean(values)) if values.size else float("nan")


def _abs_rel(pred: np.ndarray, gt: np.ndarray, denominator: str) -> float:
    if denominator not in DENOMINATORS:
        raise ValueError(f"denominator must be one of {DENOMINATORS}, got {denominator!r}")
    reference = gt if denominator == "gt" else pred
    return _mean_or_nan(np.abs(pred - gt) / reference)


def _delta(pred: np.ndarray, gt: np.ndarray, threshold: float) -> float:
    if not threshold > 1.0:
        raise ValueError(f"threshold must be > 1 (the ratio is always >= 1), got {threshold}")
    ratio = np.maximum(pred / gt, gt / pred)
    return _mean_or_nan(ratio < threshold)


def _rmse(pred: np.ndarray, gt: np.ndarray) -> float:
    return float(np.sqrt(_mean_or_nan((pred - gt) ** 2)))


def _near_overestimates(pred: np.ndarray, gt: np.ndarray, near: float,
                        margin: float) -> tuple[float, int]:
    if not near > 0.0:
        raise ValueError(f"near must be > 0 metres, got {near}")
    if not margin >= 0.0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    is_near = gt < near
    too_far = pred[is_near] > (1.0 + margin) * gt[is_near]
    return _mean_or_nan(too_far), int(np.count_nonzero(is_near))


def abs_rel(pred, gt, *, mask=None, denominator: str = "gt") -> float:
    """Mean absolute relative error, ``(1/n) sum |z - z*| / z*``.

    ``denominator="gt"`` (default) is the standard definition above. ``denominator="pred"``
    divides by the prediction instead, ``(1/n) sum |z - z*| / z``, the formula as printed in
    the paper. NaN when no pixel is valid.
    """
    return _abs_rel(*valid_pairs(pred, gt, mask), denominator)


def delta1(pred, gt, *, mask=None, threshold: float = DELTA1_THRESHOLD) -> float:
    """Share of valid pixels with ``max(z / z*, z* / z) < threshold``; NaN if none is valid."""
    return _delta(*valid_pairs(pred, gt, mask), threshold)


def rmse(pred, gt, *, mask=None) -> float:
    """Root mean square error in metres, ``sqrt((1/n) sum (z - z*)^2)``; NaN if none is valid."""
    return _rmse(*valid_pairs(pred, gt, mask))


def overestimate_rate(pred, gt, *, mask=None, near: float = NEAR_DEPTH,
                      margin: float = OVERESTIMATE_MARGIN) -> float:
    """Share of near obstacles predicted too far away: the safety metric.

    Among valid pixels with ``z* < near`` metres, the share with ``z > (1 + margin) z*``.
    A prediction exactly at ``(1 + margin) z*`` is not counted. NaN when no valid pixel is
    near.
    """
    rate, _ = _near_overestimates(*valid_pairs(pred, gt, mask), near, margin)
    return rate


def evaluate(pred, gt, *, mask=None, denominator: str = "gt") -> DepthMetrics:
    """All metrics at their default parameters, from one pass over the valid pixels."""
    pred_valid, gt_valid = valid_pairs(pred, gt, mask)
    rate, near_pixels = _near_overestimates(pred_valid, gt_valid, NEAR_DEPTH, OVERESTIMATE_MARGIN)
    return DepthMetrics(
        abs_rel=_abs_rel(pred_valid, gt_valid, denominator),
        delta1=_delta(pred_valid, gt_valid, DELTA1_THRESHOLD),
        rmse=_rmse(pred_valid, gt_valid),
        overestimate_rate=rate,
        valid_pixels=int(gt_valid.size),
        near_pixels=near_pixels,
    )
