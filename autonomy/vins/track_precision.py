"""How precisely each track can be found, from its patch's texture: its observations' weights.

A patch found by least squares in a frame with white noise of standard deviation ``s_n`` (grey
levels) finds its translation with covariance ``2 s_n^2 S^-1`` to first order, ``S = sum
g g^T`` being the patch's structure tensor over its window (``g`` the image's gradient at each
pixel) and the 2 counting the noise of both patches compared. This is the matrix whose least
eigenvalue Shi and Tomasi rank corners by ("Good Features to Track", CVPR 1994, section 2);
along its weakest direction a track errs by ``s_n sqrt(2 / lambda_min)`` pixels. A strong
corner is found to a few hundredths of a pixel, a faint one in a dark, noisy image to a few
tenths, and the VINS weighed both alike (``[vins] pixel_sigma``).

A track's error is mostly what it inherits from its first frames (its anchor is cut at the
second) and carries on as its patch grows, so it is the texture a track was born on that
predicts its error: on the realistic mine's seed-0 recording (anchored tracks under a
homography, through the camera's truth) the median error rises 0.15 → 0.37 px over the fifths
of the birth texture's prediction (rank correlation 0.36), where the texture the track has in
the frame predicts it hardly at all past 20 frames (docs/vins.md, "Observations weighed by
their texture").

:func:`relative_noise` gives each track its standard deviation relative to the frame's median
track, ``sqrt(median lambda_min / lambda_min)``, within :data:`SCALE_RANGE`: the frame's median
track keeps ``pixel_sigma``. The noise ``s_n`` is the same for every track of a frame and
cancels. The isotropic bound (the weakest direction's) is kept rather than the whole matrix so
that the smoother's noise models can be shared between observations.
"""

from __future__ import annotations

import numpy as np

#: The least and largest standard deviation given a track, as a share of ``pixel_sigma``: at
#: most four times the weight of the frame's typical track (no single corner carries a
#: frame), at least a ninth (a flat patch is still an observation the gate has judged).
SCALE_RANGE = (0.5, 3.0)


def checked_noise_scale(scale, count: int) -> np.ndarray:
    """``scale`` as one positive, finite noise scale (a share of ``pixel_sigma``) for each of
    ``count`` features, float; ValueError naming what it got otherwise."""
    checked = np.asarray(scale, dtype=float)
    if checked.shape != (count,) or not np.all(np.isfinite(checked) & (checked > 0.0)):
        raise ValueError(f"noise_scale must be one positive noise scale for each of the "
                         f"{count} features, got {scale}")
    return checked


def least_eigenvalues(gray: np.ndarray, pixels: np.ndarray, half: int) -> np.ndarray:
    """The least eigenvalue of the structure tensor ``sum g g^T`` over the ``2 half + 1``
    square window round each of ``pixels`` (N, 2; rounded to whole pixels, the image's edge
    replicated where a window passes it), ``g`` the central difference of ``gray`` (grey
    levels per pixel). (N,). In float64: the least eigenvalue of an edge-like patch is a
    small difference of large sums."""
    gray = np.asarray(gray, np.float64)
    h, w = gray.shape
    centres = np.rint(np.asarray(pixels, float).reshape(-1, 2)).astype(np.int64)
    offsets = np.arange(-half - 1, half + 2)
    columns = np.clip(centres[:, :1] + offsets, 0, w - 1)  # (N, side)
    rows = np.clip(centres[:, 1:] + offsets, 0, h - 1)
    patch = gray[rows[:, :, None], columns[:, None, :]]  # (N, side, side): [row, column]
    gx = 0.5 * (patch[:, 1:-1, 2:] - patch[:, 1:-1, :-2])
    gy = 0.5 * (patch[:, 2:, 1:-1] - patch[:, :-2, 1:-1])
    a, b, c = ((u * v).sum(axis=(1, 2)) for u, v in ((gx, gx), (gx, gy), (gy, gy)))
    return 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)


def relative_noise(eigenvalues: np.ndarray, clip: bool = True) -> np.ndarray:
    """``sqrt(median lambda_min / lambda_min)`` of each of ``eigenvalues`` (module docstring),
    within :data:`SCALE_RANGE` with ``clip``; ones where there is no texture to compare. A NaN
    eigenvalue (unknown) is left out of the median and gives NaN."""
    eigenvalues = np.asarray(eigenvalues, float)
    known = eigenvalues[~np.isnan(eigenvalues)]
    median = float(np.median(known)) if len(known) else 0.0
    if median <= 0.0:
        return np.where(np.isnan(eigenvalues), np.nan, 1.0)
    with np.errstate(divide="ignore"):
        scales = np.sqrt(median / np.maximum(eigenvalues, 0.0))
    return np.clip(scales, *SCALE_RANGE) if clip else scales


class BirthTextures:
    """Each track's least eigenvalue in the frame it was born in, kept for its life: a track's
    error is mostly what it inherits from its first frames (its anchor is cut at the second),
    carried into later frames as the patch grows, so the texture it was found on predicts its
    error at every age and the texture it has now does not past twenty frames (docs/vins.md,
    "Observations weighed by their texture"). ``strict``: every track not born in a frame was
    given in the frame before (the tracker's, which sees every frame), else ValueError; not
    strict, such a track's texture is unknown, NaN (an evaluation that skips frames)."""

    def __init__(self, half: int, strict: bool = True):
        self.half, self.strict = half, strict
        self._ids = np.zeros(0, np.int64)
        self._eigenvalues = np.zeros(0)

    def update(self, gray: np.ndarray, ids: np.ndarray, pixels: np.ndarray,
               born: np.ndarray) -> np.ndarray:
        """The eigenvalues of the tracks ``ids`` (in any order: a restarted track takes a new
        id where it stands), those ``born`` in this frame ``gray`` measured at their
        ``pixels``, the others as kept."""
        eigenvalues = np.full(len(ids), np.nan)
        old = np.flatnonzero(~born)
        kept = np.zeros(len(old), bool)
        if len(self._ids):  # the kept ids are sorted, for the lookup
            rows = np.minimum(np.searchsorted(self._ids, ids[old]), len(self._ids) - 1)
            kept = self._ids[rows] == ids[old]
            eigenvalues[old[kept]] = self._eigenvalues[rows[kept]]
        if self.strict and not kept.all():
            raise ValueError("tracks not born in this frame must have been given in the frame "
                             "before")
        eigenvalues[born] = least_eigenvalues(gray, pixels[born], self.half)
        order = np.argsort(ids, kind="stable")
        self._ids, self._eigenvalues = ids[order], eigenvalues[order]
        return eigenvalues
