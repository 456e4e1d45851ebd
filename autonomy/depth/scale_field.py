"""A smooth scale field over the image: the part of a network's depth error that one curve
cannot remove.

The rescaling curve (Yang et al., Section III-B) maps relative to metric disparity the same
way at every pixel. A monocular network's error is not the same everywhere: the same relative
disparity reads nearer on one side of the image than on the other (the synthetic network's
``field_sigma``, docs/synthetic_depth.md; VI-Depth, Wofk et al. 2023, align globally and then
learn a dense scale map from the sparse points' residuals for this reason). The anchors
measure that error where they are: after the curve ``f``, anchor ``i`` at pixel ``p_i`` with
relative disparity ``r_i`` and VINS depth ``z_i`` leaves the log residual

    e_i = log(1 / z_i) - log f(r_i)

and the field ``F`` is the smooth function of the pixel that best explains them:

    metric disparity(p) = f(r(p)) · exp(F(p)),   depth(p) = depth_curve(p) · exp(-F(p)).

``F`` is bilinear between the nodes of an ``n x n`` grid laid over the image as OpenCV's
``resize`` lays an ``n x n`` image's pixel centres (so the whole-image field is one
``cv2.resize`` of the node values, exactly the function fitted), constant beyond the outer
nodes. The node values ``w`` are the Gaussian posterior mean (MAP) of

    e_i = B(p_i) w + noise (sigma_e),   w_k ~ N(0, sigma²),   w_k - w_l ~ N(0, sigma²)

for neighbouring nodes ``k, l``: a node without anchors near it leans toward its neighbours
and toward no correction, so the field corrects only where anchors say so, and by no more
than they support. ``sigma_e`` is the robust spread (1.4826 MAD) of the residuals about the
field, floored at :data:`MIN_RESIDUAL_SIGMA`: the VINS depth's own noise and the network's
pixel-scale error, which the field must not chase. It is fitted twice: first with the spread
of the residuals themselves (which holds the field's own variation, so that fit leans on the
prior), then with the spread about that first field and without the residuals farther than
:data:`OUTLIER_SIGMAS` ``sigma_e`` from it (a wrong landmark).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: The smallest residual spread the field is fitted with (log disparity): 2 %.
MIN_RESIDUAL_SIGMA = 0.02

#: Residuals farther than this many ``sigma_e`` from the first field are left out of the
#: second (the curve's own outlier rule, ``[rescale] outlier_threshold``, is the same 3).
OUTLIER_SIGMAS = 3.0


@dataclass(frozen=True)
class ScaleField:
    """The fitted field: ``nodes`` (n, n) log-disparity corrections, row-major from the
    image's top-left."""

    nodes: np.ndarray

    def depth_factor(self, shape: tuple[int, int]) -> np.ndarray:
        """``exp(-F)`` at every pixel of an image of ``shape`` (H, W), float32: what the
        curve's depth is multiplied by."""
        height, width = shape
        field = cv2.resize(self.nodes.astype(np.float32), (width, height),
                           interpolation=cv2.INTER_LINEAR)
        return np.exp(-field)


def node_weights(pixels: np.ndarray, shape: tuple[int, int], n: int) -> np.ndarray:
    """(N, n²) bilinear weights of the grid's nodes at ``pixels`` (N, 2) ``(u, v)``: node
    ``(i, j)`` stands at ``u = (j + 0.5) W / n - 0.5``, ``v = (i + 0.5) H / n - 0.5`` (where
    ``cv2.resize`` puts an n x n image's pixel centres), clamped beyond the outer nodes."""
    height, width = shape
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    weights = np.zeros((len(pixels), n * n))
    rows = np.arange(len(pixels))
    (j0, fu), (i0, fv) = (_cell(pixels[:, 0], width, n), _cell(pixels[:, 1], height, n))
    for di, wv in ((0, 1.0 - fv), (1, fv)):
        for dj, wu in ((0, 1.0 - fu), (1, fu)):
            i, j = np.minimum(i0 + di, n - 1), np.minimum(j0 + dj, n - 1)
            np.add.at(weights, (rows, i * n + j), wv * wu)
    return weights


def _cell(coordinate: np.ndarray, size: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index of the node at or before ``coordinate`` along one axis, and the fraction of the
    way to the next one (0 beyond the outer nodes)."""
    position = np.clip((coordinate + 0.5) * n / size - 0.5, 0.0, n - 1.0)
    index = np.minimum(np.floor(position).astype(int), n - 2) if n > 1 else \
        np.zeros(len(position), int)
    return index, position - index


def fit_scale_field(pixels: np.ndarray, log_residuals: np.ndarray, shape: tuple[int, int],
                    n: int, sigma: float) -> ScaleField:
    """The MAP field (module docstring) of the anchors at ``pixels`` (N, 2) with
    ``log_residuals`` (N,) = log(VINS disparity / the curve's), on an image of ``shape``,
    ``n`` nodes a side, prior spread ``sigma``."""
    residuals = np.asarray(log_residuals, dtype=float)
    if len(residuals) == 0:
        return ScaleField(np.zeros((n, n)))
    B = node_weights(pixels, shape, n)
    prior = (np.eye(n * n) + _difference_gram(n)) / sigma**2
    first = _solve(B, residuals, _spread(residuals), prior)
    misfit = residuals - B @ first
    noise = _spread(misfit)
    inliers = np.abs(misfit) <= OUTLIER_SIGMAS * noise
    nodes = _solve(B[inliers], residuals[inliers], noise, prior)
    return ScaleField(nodes.reshape(n, n))


def _spread(values: np.ndarray) -> float:
    """Robust standard deviation (1.4826 MAD), at least :data:`MIN_RESIDUAL_SIGMA`."""
    mad = float(np.median(np.abs(values - np.median(values))))
    return max(1.4826 * mad, MIN_RESIDUAL_SIGMA)


def _solve(B: np.ndarray, residuals: np.ndarray, noise: float, prior: np.ndarray) -> np.ndarray:
    """The MAP node values of ``residuals = B w + N(0, noise²)`` under the prior precision."""
    return np.linalg.solve(B.T @ B / noise**2 + prior, B.T @ residuals / noise**2)


def _difference_gram(n: int) -> np.ndarray:
    """``D^T D`` of the differences between horizontally and vertically neighbouring nodes."""
    index = np.arange(n * n).reshape(n, n)
    pairs = np.concatenate([np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], 1),
                            np.stack([index[:-1, :].ravel(), index[1:, :].ravel()], 1)])
    D = np.zeros((len(pairs), n * n))
    D[np.arange(len(pairs)), pairs[:, 0]] = 1.0
    D[np.arange(len(pairs)), pairs[:, 1]] = -1.0
    return D.T @ D
