"""Plain numbers for evaluation reports: JSON has no NaN, so a missing value is None."""

from __future__ import annotations

import math

import numpy as np


def finite_or_none(value) -> float | None:
    """A plain float, or None for NaN or infinity."""
    value = float(value)
    return value if math.isfinite(value) else None


def median_or_none(values) -> float | None:
    """The median, or None for no values."""
    return finite_or_none(np.median(values)) if len(values) else None


def mean_or_none(values) -> float | None:
    """The mean of the finite values, or None when there is none."""
    finite = [v for v in values if math.isfinite(v)]
    return finite_or_none(np.mean(finite)) if finite else None


def show(value: float | None, spec: str, unit: str = "") -> str:
    """``value`` formatted with ``spec`` and ``unit`` for a report line; "n/a" for None."""
    return "n/a" if value is None else f"{value:{spec}}{unit}"


def format_split(split: dict | None) -> str:
    """A position error's split over the path flown (``autonomy.trajectory.DisplacementSplit``
    as a dict) for a report line, in parentheses after a space; nothing for None."""
    if split is None:
        return ""
    return (f" (path scale {split['scale']:.4f}: {split['along_m']:+.2f} m along; bearing "
            f"{split['bearing_deg']:+.2f}°: {split['across_m']:+.2f} m across; height "
            f"{split['height_m']:+.2f} m)")
