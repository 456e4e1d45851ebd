"""Anchor sampling for the rescaler: the network's relative disparity at each VINS feature.

A feature projects to a fractional pixel ``(u, v)`` (u = column, v = row; integer coordinates
are pixel centres, the OpenCV convention). Following the paper (Yang, Tian, Goel, Tabib), its
relative disparity is not interpolated but taken from the nearest surface among the four
surrounding pixels: the largest relative disparity of

    d[v0, u0], d[v0, u1], d[v1, u0], d[v1, u1],   u0 = floor(u), u1 = min(u0 + 1, W - 1),
                                                  v0 = floor(v), v1 = min(v0 + 1, H - 1).

At a depth edge, interpolating would blend foreground and background into a surface that does
not exist; taking the maximum (larger disparity = nearer) keeps the obstacle.
"""

from __future__ import annotations

import numpy as np


def _check_inputs(disparity: np.ndarray, pixels: np.ndarray) -> None:
    if disparity.ndim != 2:
        raise ValueError(f"disparity must be a 2-D (H, W) image, got shape {disparity.shape}")
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must be an (N, 2) array of (u, v) coordinates, "
                         f"got shape {pixels.shape}")


def _inside_image(u: np.ndarray, v: np.ndarray, height: int, width: int) -> np.ndarray:
    """True where ``(u, v)`` is finite and within ``[0, W-1] x [0, H-1]``."""
    return (np.isfinite(u) & np.isfinite(v)
            & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1))


def sample_nearest_surface(disparity: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """The largest relative disparity of the four pixels around each point.

    Parameters
    ----------
    disparity : (H, W) array
        Relative disparity from the depth network; larger is nearer.
    pixels : (N, 2) array
        Point coordinates ``(u, v)``: u the column, v the row, integers at pixel centres.

    Returns
    -------
    (N,) float64 array
        ``max`` over ``d[v0|v1, u0|u1]`` with ``u0 = floor(u)``, ``u1 = min(u0 + 1, W - 1)``
        and likewise for v. Non-finite neighbours are ignored; the result is NaN when all four
        are non-finite, or when the point is non-finite or outside ``[0, W-1] x [0, H-1]``.

    Raises
    ------
    ValueError
        If ``disparity`` is not 2-D or ``pixels`` is not (N, 2).
    """
    disparity = np.asarray(disparity)  # gathered as it is, then cast: no whole-image copy
    pixels = np.asarray(pixels, dtype=np.float64)
    _check_inputs(disparity, pixels)
    height, width = disparity.shape
    u, v = pixels[:, 0], pixels[:, 1]
    inside = _inside_image(u, v, height, width)
    u0 = np.floor(u[inside]).astype(np.intp)
    v0 = np.floor(v[inside]).astype(np.intp)
    u1 = np.minimum(u0 + 1, width - 1)
    v1 = np.minimum(v0 + 1, height - 1)
    neighbours = disparity[np.stack([v0, v0, v1, v1]), np.stack([u0, u1, u0, u1])]
    neighbours = neighbours.astype(np.float64)
    neighbours[~np.isfinite(neighbours)] = np.nan
    sampled = np.full(len(pixels), np.nan)
    sampled[inside] = np.fmax.reduce(neighbours, axis=0)
    return sampled
