"""Triangulating tracks into landmarks, and the gate a landmark must pass to enter the smoother.

Each candidate track ``m`` has up to ``K`` observations: the camera centre ``c_mk`` and the unit
viewing ray ``d_mk`` in the world frame (``mask[m, k]`` says which exist). The point closest to
all rays in the least-squares sense (the midpoint method, Hartley & Sturm 1997) solves

    sum_k (I - d_mk d_mk^T) p = sum_k (I - d_mk d_mk^T) c_mk.

The gate (why: forward flight puts many features near the focus of expansion, where the rays
are nearly parallel and depth is unobservable; a smoother given such a point is pulled apart
by it) keeps a point only if

- it has at least ``min_observations`` observations,
- the widest angle between two of its rays is at least ``min_parallax`` (rotation is already
  compensated: the rays are in the world frame),
- it lies between ``min_depth`` and ``max_depth`` in front of every observing camera, and
- it reprojects within ``max_reprojection_px`` of every observation.

A landmark costs the smoother a variable and a factor per observation, and the update time grows
with their number, so the smoother holds a budget of them. :func:`spread_choice` spends what is
left of it on the gated candidates that fill the emptiest parts of the image first, so the map
covers the view (for the rescaler's fit and for the pose's conditioning) instead of clustering on
the most textured surface.

Once in the smoother, a landmark is observed again at each keyframe only where the track lands
near its projection at the IMU-predicted pose (:func:`observation_limit_px`): a track that has
slid off its point by more than a pixel or two would otherwise keep pulling on the landmark, and
in a cruise, where the IMU says little of the scale, on the scale (docs/vins.md, "The observation
gate at 1.5 px").

The depth uncertainty of a triangulated point follows from the observation geometry: an angular
error ``sigma_px / f`` on a ray, over a baseline that subtends ``parallax`` at the point, moves
it along the ray by about ``z * (sigma_px / f) / sin(parallax)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Gate:
    """The landmark gate's limits (see the module docstring)."""

    min_observations: int
    min_parallax_rad: float
    min_depth: float
    max_depth: float
    max_reprojection_px: float
    focal_px: float


@dataclass(frozen=True)
class Triangulated:
    """Gate results for ``M`` candidates: ``points`` (M, 3) world (NaN where unsolved),
    ``parallax_rad`` (M,), ``accepted`` (M,) bool."""

    points: np.ndarray
    parallax_rad: np.ndarray
    accepted: np.ndarray


def world_rays(R_W_C: np.ndarray, normalised: np.ndarray) -> np.ndarray:
    """Unit world-frame rays ``R_W_C [x, y, 1]`` for (..., 3, 3) rotations and (..., 2) points."""
    bearing = np.concatenate([normalised, np.ones(normalised.shape[:-1] + (1,))], axis=-1)
    rays = (R_W_C @ bearing[..., None])[..., 0]
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def widest_ray_angle(rays: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The largest angle between any two present rays of each candidate, radians (0 when fewer
    than two)."""
    cosines = rays @ np.swapaxes(rays, -1, -2)
    pair = mask[:, :, None] & mask[:, None, :]
    cosines = np.where(pair, cosines, 1.0)
    return np.arccos(np.clip(cosines.min(axis=(1, 2)), -1.0, 1.0))


def midpoint_triangulate(centres: np.ndarray, rays: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Least-squares closest points to each candidate's rays (module docstring), (M, 3); NaN
    for candidates whose rays are (numerically) parallel.

    With ``n`` present rays, ``sum_k (I - d d^T) = n I - sum_k d d^T`` and
    ``sum_k (I - d d^T) c = sum_k c - sum_k d (d . c)``.
    """
    weights = mask.astype(float)[..., None]
    weighted_rays = weights * rays
    A = (mask.sum(axis=1)[:, None, None] * np.eye(3)
         - np.swapaxes(weighted_rays, 1, 2) @ rays)
    along = (rays * centres).sum(axis=-1, keepdims=True)
    b = (weights * centres).sum(axis=1) - (weighted_rays * along).sum(axis=1)
    points = np.full((len(A), 3), np.nan)
    eigenvalues = np.linalg.eigvalsh(A)  # ascending; A is symmetric positive semi-definite
    solvable = eigenvalues[:, 0] > 1e-10 * eigenvalues[:, -1]
    if solvable.any():
        points[solvable] = np.linalg.solve(A[solvable], b[solvable][..., None])[..., 0]
    return points


def gate_candidates(R_W_C: np.ndarray, centres: np.ndarray, normalised: np.ndarray,
                    mask: np.ndarray, gate: Gate) -> Triangulated:
    """Triangulate and gate ``M`` candidates of up to ``K`` observations each.

    ``R_W_C`` (M, K, 3, 3) and ``centres`` (M, K, 3) are the observing cameras' orientations
    and positions in the world (broadcast views are fine), ``normalised`` (M, K, 2) the
    undistorted observations, ``mask`` (M, K) which exist.
    """
    rays = world_rays(R_W_C, normalised)
    parallax = widest_ray_angle(rays, mask)
    enough = (mask.sum(axis=1) >= gate.min_observations) & (parallax >= gate.min_parallax_rad)
    points = np.full((len(mask), 3), np.nan)
    if enough.any():
        points[enough] = midpoint_triangulate(centres[enough], rays[enough], mask[enough])
    p_C = (np.swapaxes(R_W_C, -1, -2) @ (points[:, None, :] - centres)[..., None])[..., 0]
    depth = p_C[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        error_px = gate.focal_px * np.linalg.norm(p_C[..., :2] / depth[..., None] - normalised,
                                                  axis=-1)
        good = (depth >= gate.min_depth) & (depth <= gate.max_depth) & (
            error_px <= gate.max_reprojection_px)
    accepted = enough & np.where(mask, good, True).all(axis=1)
    return Triangulated(points, parallax, accepted)


#: Fewest observations whose median error says how far the predicted pose is off.
MIN_OBSERVATIONS_FOR_MEDIAN = 10


def observation_limit_px(errors_px: np.ndarray, limit_px: float) -> float:
    """The farthest a keyframe's observation of a known landmark may lie from the landmark's
    projection at the IMU-predicted pose and still be used, pixels:
    ``hypot(limit_px, median(errors_px))``.

    An error the whole keyframe shares is the prediction's, not the tracks': a camera-IMU time
    offset not yet estimated turns the first pitch or yaw into a shift of every projection (5 px
    at the first pitch of a realistic mine flight, 15 ms late). The median of the keyframe's
    errors measures it and widens the limit, so such a keyframe keeps its observations instead
    of losing them all. With fewer than :data:`MIN_OBSERVATIONS_FOR_MEDIAN` finite errors the
    median says nothing and ``limit_px`` stands."""
    finite = np.asarray(errors_px, dtype=float)
    finite = finite[np.isfinite(finite)]
    if len(finite) < MIN_OBSERVATIONS_FOR_MEDIAN:
        return float(limit_px)
    return math.hypot(limit_px, float(np.median(finite)))


def depth_sigma(depth: np.ndarray, parallax_rad: np.ndarray, pixel_sigma: float,
                focal_px: float) -> np.ndarray:
    """One-sigma depth uncertainty from the observation geometry (module docstring)."""
    sin_parallax = np.maximum(np.sin(parallax_rad), math.sin(math.radians(0.1)))
    return depth * (pixel_sigma / focal_px) / sin_parallax


def spread_choice(pixels: np.ndarray, parallax_rad: np.ndarray, occupied_pixels: np.ndarray,
                  size: tuple[int, int], grid: tuple[int, int], count: int) -> np.ndarray:
    """Indices of at most ``count`` of the candidates at ``pixels`` (N, 2), chosen round-robin
    over a ``grid`` (columns, rows) of cells on an image of ``size`` (width, height).

    A candidate's turn is the number of landmarks already in its cell (``occupied_pixels``) plus
    its rank in the cell by descending ``parallax_rad`` (a wider angle gives a better-conditioned
    depth); the earliest turns win, and within a turn the wider parallax.
    """
    if count <= 0 or len(pixels) == 0:
        return np.zeros(0, np.int64)
    cells = _grid_cells(pixels, size, grid)
    occupancy = np.bincount(_grid_cells(occupied_pixels, size, grid), minlength=grid[0] * grid[1])
    by_cell = np.lexsort((-parallax_rad, cells))
    sorted_cells = cells[by_cell]
    first_in_cell = np.searchsorted(sorted_cells, sorted_cells)
    rank = np.empty(len(cells), np.int64)
    rank[by_cell] = np.arange(len(cells)) - first_in_cell
    turn = occupancy[cells] + rank
    return np.lexsort((-parallax_rad, turn))[:count]


def _grid_cells(pixels: np.ndarray, size: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """The flat grid cell of each pixel; pixels outside the image count in the nearest cell."""
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    column = np.clip((pixels[:, 0] * grid[0] / size[0]).astype(np.int64), 0, grid[0] - 1)
    row = np.clip((pixels[:, 1] * grid[1] / size[1]).astype(np.int64), 0, grid[1] - 1)
    return row * grid[0] + column
