"""The rescaler's options: every default and allowed range in one place.

The config section ``[rescale]`` is exactly this class; the names follow the paper
(Yang et al., Section III-B) and Eilers (2005) where they have one.
"""

from __future__ import annotations

from dataclasses import dataclass

from autonomy.options import OptionError, option, validate

#: Fitting methods selectable by name, as compared in the paper plus robust RANSAC.
METHODS = (
    "poly1", "poly2", "poly3", "poly4", "poly5",
    "exponential",
    "smoothing_spline",
    "monotone_smoothing_spline",
    "monotone_spline",
    "ransac_affine",
)

#: Methods whose fitted map from relative to metric disparity is non-decreasing everywhere.
MONOTONE_METHODS = ("poly1", "exponential", "monotone_smoothing_spline", "monotone_spline",
                    "ransac_affine")


@dataclass(frozen=True)
class RescaleOptions:
    """How relative disparity is mapped to metric depth."""

    method: str = option("monotone_spline", choices=METHODS,
                         doc="fitting method: relative disparity -> metric disparity (1/z)")
    min_depth: float = option(0.05, gt=0.0, doc="nearest metric depth kept as an anchor and "
                              "output, metres")
    max_depth: float = option(65.0, gt=0.0, le=1000.0, doc="farthest metric depth kept as an anchor and "
                              "output, metres")
    min_anchors: int = option(10, ge=4, doc="fewest valid anchors a fit is made from")
    outlier_rejection: bool = option(True, doc="refit without anchors whose residual exceeds "
                                     "outlier_threshold robust sigmas (not for ransac_affine)")
    outlier_threshold: float = option(3.0, gt=0.0, doc="residual limit in robust sigmas "
                                      "(1.4826 x median absolute deviation)")
    near_end_check: bool = option(True, doc="with outlier rejection, judge the anchors beyond "
                                  "an anchor-free gap at the near end (the largest relative "
                                  "disparities) by the least-squares affine map of the others, "
                                  "dropping one that claims a surface 1.5x farther: a curve "
                                  "bends to reach an anchor no neighbour contradicts")
    segments: int = option(10, ge=1, le=100, doc="P-spline knot segments over the anchor range "
                           "(13 cubic bases for 10)")
    kappa: float = option(1e6, ge=0.0, doc="P-spline asymmetric penalty on decreasing "
                          "coefficient steps (Eilers 2005)")
    smoothing_lambda: float = option(1e5, ge=0.0, doc="third-difference penalty of "
                                     "monotone_smoothing_spline")
    ridge: float = option(1e-8, ge=0.0, doc="ridge penalty that keeps the P-spline system "
                          "regular where no anchor constrains a basis")
    max_iterations: int = option(30, ge=1, le=1000, doc="most re-weightings of the asymmetric "
                                 "penalty")
    smoothing_factor: float = option(1.0, ge=0.0, doc="smoothing_spline: FITPACK s = "
                                     "factor x anchors, with weights 1/noise")
    ransac_iterations: int = option(100, ge=1, le=100000, doc="hypotheses drawn by "
                                    "ransac_affine")
    ransac_threshold: float = option(0.1, gt=0.0, lt=1.0, doc="ransac_affine inlier limit on "
                                     "|predicted - measured| / measured metric disparity")
    seed: int = option(0, ge=0, doc="seed of the RANSAC sampler, for repeatable fits")
    extrapolation: str = option("linear", choices=("linear", "clamp"), doc="beyond the anchor "
                                "range: straight tails (near-side guard) or the reference "
                                "port's clamp")
    bridge_gaps: bool = option(True, doc="replace the curve across anchor-free gaps with a "
                               "straight bridge (gap guard)")
    gap_fraction: float = option(0.1, gt=0.0, le=1.0, doc="an anchor-free stretch wider than "
                                 "this share of the anchor range is a gap")
    confidence_neighbours: int = option(3, ge=1, doc="anchors within one knot spacing that "
                                        "give full confidence")
    lut_size: int = option(4096, ge=16, le=32766, doc="entries of the lookup table the "
                           "curve is applied through")
    temporal_blend: float = option(0.0, ge=0.0, lt=1.0, doc="weight of the previous frame's "
                                   "curve in a TemporalBlend; 0 turns smoothing off")

    def __post_init__(self) -> None:
        validate(self)
        if self.min_depth >= self.max_depth:
            raise OptionError("min_depth", f"must be < max_depth ({self.max_depth:g}), "
                              f"got {self.min_depth:g}")
