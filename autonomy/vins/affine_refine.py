"""Each Lucas-Kanade track refined frame to frame under an affine warp of its patch.

Pyramidal Lucas-Kanade (OpenCV's) moves a window by a translation alone. Flying forward, a
feature's patch grows from one frame to the next by ``s = z / (z - dz)``, a few percent at
cruise speed, and a translation-only fit of a patch that scales follows the centroid of the
patch's gradients, not its centre: it errs by ``(s - 1) c`` for a centroid ``c`` pixels off
the centre, every frame, in the same direction. A track's error then grows linearly with its
age (measured on the simulator's sewer: a median of 0.09 px at 2–4 frames, 0.8 px at 20
frames and more; docs/vins.md, "Tracks refined under an affine warp").

The refinement fits the patch under ``u -> c + A u`` (``A`` 2x2, ``c`` the track's new
position), starting from Lucas-Kanade's position and ``A = I``, by inverse-compositional
Gauss-Newton (Baker and Matthews, "Lucas-Kanade 20 Years On", IJCV 2004, section 3.2): the
steepest-descent images and the Hessian are the template's, computed once, and each step
``dp = H^-1 sum SD^T e`` is composed inverted into the warp, ``W <- W o W(dp)^-1``. The
warped patch is normalised to the template's mean and contrast every step, so an exposure
change between frames is not read as motion. A step that raises the patch's residual is taken
back and halved (:func:`fit_warp`). The scale no longer biases the centre; what is left is the
frame's noise, which adds up as a random walk.

A refinement that does not converge, moves the track further than ``max_shift`` from
Lucas-Kanade's answer or deforms the patch by more than ``max_deformation`` keeps
Lucas-Kanade's position: the refinement only ever sharpens a track the tracker kept.

Its two halves, :func:`prepare_templates` (a patch made ready once) and :func:`fit_warp` (the
fit from a given warp), also serve ``anchored_tracks.py``, whose templates outlive a frame and
whose patches may be fitted under a homography as well: the warp is kept as a 3x3 matrix ``G``
from the patch's offsets, scaled to [-1, 1], to the image's pixels, the affine map being the
homography whose last row is ``(0, 0, 1)``.

Off by default (``FrontendOptions.affine_refinement``): on the simulator's flights it halves
the error of tracks 10 frames and older, but the trajectories scored with it are better on
some seeds and worse on others, it moves the realistic profile's mean scale from 0.999 to
1.007 for a reason not found, and it doubles the front-end's time (docs/vins.md,
docs/benchmarks.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Sobel's 3x3 derivative is a central difference (twice the slope) smoothed across by
#: [1, 2, 1] (four times the value): this scale makes it a derivative per pixel.
SOBEL_SCALE = 1.0 / 8.0


class SampledImage:
    """A grey image made ready to be sampled at many real pixel coordinates at once, by exact
    bilinear interpolation (not ``cv2.remap``'s, whose weights are fixed point to 1/32 px), the
    border replicated. In the cell of corner ``(x0, y0)`` the interpolant is ``a + b fx + c fy
    + d fx fy`` with ``a = I00``, ``b = I10 - I00``, ``c = I01 - I00``, ``d = I11 - I10 - I01 +
    I00`` (``fx = x - x0``, ``fy = y - y0``); the four are kept per cell, so a sample is one
    gather of its cell (``cv2.remap`` nearest at the cell's integer corner, which is exact) and
    three multiply-adds in float32, where numpy gathered the four corners one by one: the
    sampling is most of :func:`fit_warp`'s iterations, the front-end's hottest loop with
    anchored tracks (docs/benchmarks.md)."""

    def __init__(self, gray: np.ndarray):
        image = np.asarray(gray, np.float32)
        if image.ndim != 2 or min(image.shape) < 2 or max(image.shape) >= 32767:
            raise ValueError(f"a grey image of 2x2 to 32766x32766 pixels is sampled (the "
                             f"bounds of cv2.remap), got shape {image.shape}")
        self.shape = image.shape
        a = image[:-1, :-1]
        b = cv2.subtract(image[:-1, 1:], a)
        c = cv2.subtract(image[1:, :-1], a)
        d = cv2.subtract(cv2.subtract(image[1:, 1:], image[1:, :-1]), b)
        self._cells = cv2.merge([a, b, c, d])

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The image at ``x``, ``y`` (one shape, any), float32 of that shape."""
        x, y = np.broadcast_arrays(x, y)
        shape, count = x.shape, x.size
        if not count:
            return np.zeros(shape, np.float32)
        cells_h, cells_w = self._cells.shape[:2]
        x = self._rows(np.clip(x, 0.0, cells_w))
        y = self._rows(np.clip(y, 0.0, cells_h))
        x0 = np.minimum(np.floor(x), cells_w - 1)  # the last pixel: the last cell, fx = 1
        y0 = np.minimum(np.floor(y), cells_h - 1)
        cell = cv2.remap(self._cells, x0, y0, cv2.INTER_NEAREST)
        fx, fy = x - x0, y - y0
        out = cell[..., 0] + fx * (cell[..., 1] + fy * cell[..., 3]) + fy * cell[..., 2]
        return out.ravel()[:count].reshape(shape)

    #: cv2.remap's maps are 2-D and under 32767 on a side (SHRT_MAX).
    _SIDE = 32767

    @classmethod
    def _rows(cls, values: np.ndarray) -> np.ndarray:
        """``values`` as a float32 map for cv2.remap: rows of its last axis where they fit,
        else flattened into rows of 1024 (the last padded)."""
        if values.ndim == 2 and max(values.shape) < cls._SIDE:
            return values.astype(np.float32)
        flat = values.astype(np.float32).ravel()
        width = min(len(flat), 1024)
        rows = -(-len(flat) // width)
        if rows >= cls._SIDE:
            raise ValueError(f"at most {(cls._SIDE - 1) * 1024} points are sampled at once, "
                             f"got {len(flat)}")
        return np.resize(flat, (rows, width))


def _normalised(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row less its mean, and its standard deviation."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    return centred, np.sqrt(np.mean(centred**2, axis=1))


#: The warps a patch is fitted under, each with its number of parameters: the affine map
#: ``u -> c + A u`` and the homography (eight parameters: the affine map's six and the
#: perspective's two, which an affine map fitted to a plane seen at a slant turns into an
#: offset of its centre; ``anchored_tracks.py``).
WARP_PARAMETERS = {"affine": 6, "homography": 8}

def warp_parameters(warp: str) -> int:
    """How many parameters ``warp`` has (:data:`WARP_PARAMETERS`); ValueError naming the known
    warps for any other."""
    if warp not in WARP_PARAMETERS:
        raise ValueError(f"unknown warp {warp!r}: one of {', '.join(WARP_PARAMETERS)}")
    return WARP_PARAMETERS[warp]


#: A patch whose Hessian's least eigenvalue is below this share of its largest is not fitted
#: (a flat patch, or an edge, along which it would slide).
MIN_EIGENVALUE_RATIO = 1e-8


@dataclass(frozen=True)
class Templates:
    """Patches prepared for :func:`fit_warp`, row ``i`` describing patch ``i``: the patch
    normalised to zero mean (``values``, (N, M)) and its contrast (``contrast``), and the
    Gauss-Newton step's matrix ``H^-1 SD^T`` (``descent``, (N, P, M), ``P`` the warp's
    parameters: the inverse-compositional steepest-descent images ``SD`` premultiplied by
    their Hessian's inverse, so a step is one product); ``usable`` is false for a flat patch
    or a singular Hessian. Kept in float32, the precision of the frame they are fitted to."""

    values: np.ndarray
    contrast: np.ndarray
    descent: np.ndarray
    usable: np.ndarray

    def __len__(self) -> int:
        return len(self.usable)

    def take(self, rows) -> "Templates":
        """The patches of ``rows`` (indices or a boolean mask), in that order."""
        return Templates(self.values[rows], self.contrast[rows], self.descent[rows],
                         self.usable[rows])

    @staticmethod
    def join(a: "Templates", b: "Templates") -> "Templates":
        """``a``'s patches followed by ``b``'s."""
        return Templates(*(np.concatenate([x, y]) for x, y in
                           zip((a.values, a.contrast, a.descent, a.usable),
                               (b.values, b.contrast, b.descent, b.usable))))


def _scaled_offsets(half: int) -> tuple[np.ndarray, np.ndarray]:
    """A ``2 half + 1`` square patch's pixel offsets from its centre over ``half`` (so in
    [-1, 1], which keeps the warp's parameters of one magnitude), x and y, row by row."""
    offsets = np.arange(-half, half + 1, dtype=float) / half
    return tuple(a.ravel() for a in np.meshgrid(offsets, offsets))


def _patch_points(half: int) -> np.ndarray:
    """(3, M) float32: a patch's scaled offsets (:func:`_scaled_offsets`) as homogeneous
    points, the columns a warp multiplies (in float32, the sampling's precision: 4e-5 px at
    640 px)."""
    sx, sy = _scaled_offsets(half)
    return np.stack([sx, sy, np.ones_like(sx)]).astype(np.float32)


def identity_warps(centres: np.ndarray, *, half: int) -> np.ndarray:
    """(N, 3, 3): the warps from a patch's scaled offsets to image pixels that leave the
    patches as they are, centred at ``centres`` (N, 2)."""
    centres = np.asarray(centres, float).reshape(-1, 2)
    warps = np.tile(np.diag([float(half), float(half), 1.0]), (len(centres), 1, 1))
    warps[:, :2, 2] = centres
    return warps


def warp_centres(warps: np.ndarray) -> np.ndarray:
    """(N, 2): where the warps put their patches' centres."""
    return warps[:, :2, 2] / warps[:, 2:, 2]


def centre_jacobians(warps: np.ndarray, *, half: int) -> np.ndarray:
    """(N, 2, 2): each warp's derivative at its patch's centre, image pixels per patch pixel
    (the affine map's ``A``; for a homography ``G``, ``(G[:2, :2] g22 - G[:2, 2] G[2, :2]) /
    (g22^2 half)``)."""
    g22 = warps[:, 2, 2][:, None, None]
    return ((warps[:, :2, :2] * g22 - warps[:, :2, 2:] * warps[:, 2:, :2])
            / (g22**2 * half))


def prepare_templates(image: SampledImage, centres: np.ndarray, *, half: int,
                      warp: str = "affine") -> Templates:
    """The ``2 half + 1`` square patches of ``image`` around ``centres`` (N, 2), made ready for
    :func:`fit_warp` under ``warp`` (:data:`WARP_PARAMETERS`). The steepest-descent images are
    the patch's gradient times the warp's Jacobian at the identity, in the scaled offsets
    ``s``: for the affine map ``(gx sx, gx sy, gy sx, gy sy, gx, gy)``, for the homography
    also ``-(gx sx + gy sy) (sx, sy)``. The gradient is Sobel's (:data:`SOBEL_SCALE`) of a
    patch sampled one pixel wider: bilinear interpolation at whole-pixel offsets commutes with
    a convolution, so this is the image's Sobel interpolated at the patch's pixels (away from
    the image's edge, where the border is replicated, not reflected as ``cv2.Sobel`` does)."""
    centres = np.asarray(centres, float).reshape(-1, 2)
    side = 2 * half + 3
    offsets = np.arange(-half - 1, half + 2, dtype=float)
    wide = image(centres[:, :1, None] + offsets[None, None, :],
                 centres[:, 1:, None] + offsets[None, :, None])  # (N, side, side): [row, col]
    across = wide[:, :, 2:] - wide[:, :, :-2]  # (N, side, side - 2)
    down = wide[:, 2:, :] - wide[:, :-2, :]
    gx = SOBEL_SCALE * (across[:, :-2] + 2.0 * across[:, 1:-1] + across[:, 2:])
    gy = SOBEL_SCALE * (down[:, :, :-2] + 2.0 * down[:, :, 1:-1] + down[:, :, 2:])
    m = (side - 2) ** 2
    values, contrast = _normalised(wide[:, 1:-1, 1:-1].reshape(-1, m).astype(float))
    sx, sy = _scaled_offsets(half)
    gx, gy = gx.reshape(-1, m) * half, gy.reshape(-1, m) * half  # per unit of scaled offset
    columns = [gx * sx, gx * sy, gy * sx, gy * sy, gx, gy]
    if warp_parameters(warp) == 8:  # the homography's last row
        radial = gx * sx + gy * sy
        columns += [-radial * sx, -radial * sy]
    steepest_t = np.stack(columns, axis=1)  # (N, P, M)
    hessian = steepest_t @ steepest_t.transpose(0, 2, 1)
    eigenvalues = np.linalg.eigvalsh(hessian)  # ascending
    usable = (contrast > 1e-3) & (eigenvalues[:, 0] > MIN_EIGENVALUE_RATIO * eigenvalues[:, -1])
    descent = np.zeros(steepest_t.shape, np.float32)
    descent[usable] = np.linalg.inv(hessian[usable]) @ steepest_t[usable]
    return Templates(values.astype(np.float32), contrast, descent, usable)


def _inverse_parameter_warps(p: np.ndarray) -> np.ndarray:
    """(N, 3, 3): the inverses, up to scale, of the warps of parameters ``p`` (N, 6 or 8) about
    the identity, ``W = [[1 + p0, p1, p4], [p2, 1 + p3, p5], [p6, p7, 1]]`` (``p6 = p7 = 0``
    for the affine map): their adjugates, ``W^-1 det W``. A warp is defined up to scale and
    :func:`fit_warp` scales its warps to ``G[2, 2] = 1``, so the determinant is not needed
    (and a batch is not refused for one singular step, as ``np.linalg.inv`` would)."""
    a, b, d, e, c, f = (p[:, i] for i in range(6))
    a, e = 1.0 + a, 1.0 + e
    g, h = (p[:, 6], p[:, 7]) if p.shape[1] == 8 else (np.zeros(len(p)),) * 2
    return np.stack([e - f * h, c * h - b, b * f - c * e,
                     f * g - d, a - c * g, c * d - a * f,
                     d * h - e * g, b * g - a * h, a * e - b * d], axis=1).reshape(-1, 3, 3)


def fit_warp(templates: Templates, current: SampledImage, guesses: np.ndarray,
             warps: np.ndarray | None = None, *, half: int, iterations: int = 20,
             epsilon: float = 0.005) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each template's patch found in ``current`` under the warp ``G`` (3x3, from the patch's
    scaled offsets to pixels; affine or a homography, as the templates were prepared) by
    inverse-compositional Gauss-Newton, from ``warps`` (N, 3, 3) moved to centre on
    ``guesses`` (N, 2), or from :func:`identity_warps` there when None. Each step
    ``dp = H^-1 sum SD^T e`` is composed inverted, ``G <- G W(dp)^-1``.

    A step that raises the patch's residual (mean squared ``e``) is taken back and halved,
    from the warp of the least residual yet. Inverse-compositional steps use the template's
    gradients for the frame's: where the two patches differ by more than a warp (noise, blur,
    a change of light) the full step can overshoot, and undamped it cycled between two warps
    on many of the realistic camera's patches, which then never converged (docs/vins.md,
    "Anchors that converge").

    Returns the centres (N, 2), the warps and whether each converged (a last step of the
    patch's centre under ``epsilon`` pixels, the warp finite, the template usable). A fit whose
    steps were halved below ``epsilon`` converged in that sense too: no step along its
    direction lowers the residual, a stationary point of the fit if not of the frame's truth
    (on the blurred frame of the tests, hardly nearer the point than its start). Its warp is the
    last one, within ``epsilon`` of the best in its centre."""
    points = _patch_points(half)
    guesses = np.asarray(guesses, float).reshape(-1, 2)
    if warps is None:
        warps = identity_warps(guesses, half=half)
    else:
        # Moved onto the guesses: G <- T(guess - centre) G.
        warps = np.asarray(warps, float).reshape(-1, 3, 3).copy()
        warps[:, :2, :] += (guesses - warp_centres(warps))[:, :, None] * warps[:, 2:, :]
    active = templates.usable.copy()
    converged = np.zeros(len(templates), bool)
    best_cost = np.full(len(templates), np.inf)
    best_warps, last_steps = warps.copy(), np.zeros((len(templates), templates.descent.shape[1]))
    for _ in range(iterations):
        k = np.flatnonzero(active)
        if not len(k):
            break
        g = warps[k]
        error = _patch_error(templates, k, current, g, points)
        cost = np.mean(error**2, axis=1)
        # A step that raised the residual is taken back and halved, from the best warp yet.
        # (A NaN residual is not worse: its step is NaN and the track is given up below.)
        worse = cost > best_cost[k]
        better = k[~worse]
        best_cost[better], best_warps[better] = cost[~worse], g[~worse]
        base = best_warps[k]
        step = np.where(worse[:, None], 0.5 * last_steps[k],
                        (templates.descent[k] @ error[:, :, None])[:, :, 0])
        last_steps[k] = step
        with np.errstate(all="ignore"):
            g = base @ _inverse_parameter_warps(step)
            g = g / g[:, 2:, 2:]
        warps[k] = g
        # A singular step leaves a warp that is not finite: that track is given up, not
        # sampled again.
        lost = ~np.isfinite(g).all(axis=(1, 2))
        done = ~lost & (np.linalg.norm(warp_centres(g) - warp_centres(base), axis=1) < epsilon)
        converged[k[done]] = True
        active[k[done | lost]] = False
    return warp_centres(warps), warps, converged


def _patch_error(templates: Templates, rows: np.ndarray, current: SampledImage,
                 warps: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, M): the patches of ``current`` under ``warps`` (n, 3, 3), each brought to its
    template's mean and contrast, less the templates of ``rows``. A homography that takes a
    patch pixel to or past the line at infinity (``w <= 0``) has folded the patch: the image
    has nothing there to compare (sampled, the pixel would be clamped to the image's border),
    so that patch's residual is NaN, which gives its track up (:func:`fit_warp`)."""
    mapped = warps.astype(np.float32) @ points  # (n, 3, M): the patch's pixels, homogeneous
    folded = ~(mapped[:, 2] > 0.0).all(axis=1)
    w = np.where(folded[:, None], np.float32(1.0), mapped[:, 2])
    warped, warped_std = _normalised(current(mapped[:, 0] / w, mapped[:, 1] / w))
    gain = (templates.contrast[rows] / np.maximum(warped_std, 1e-9)).astype(np.float32)
    error = warped * gain[:, None] - templates.values[rows]
    error[folded] = np.nan
    return error


def refine_affine(previous: SampledImage, current: SampledImage, starts: np.ndarray,
                  guesses: np.ndarray, *, half: int, iterations: int = 20,
                  epsilon: float = 0.005, max_shift: float = 0.5,
                  max_deformation: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """``guesses`` (N, 2), Lucas-Kanade's positions in ``current`` of the features at
    ``starts`` in ``previous`` (both grey images, :class:`SampledImage`), refined under an
    affine warp of the ``2 half + 1`` square patch (module docstring).
    Returns the positions and whether each was refined (else it is its guess): converged
    (a last step of the patch's centre under ``epsilon`` pixels) within ``max_shift`` of its
    guess, the patch's linear map within ``max_deformation`` of the identity in every entry.
    A patch whose Hessian is singular to working precision (a flat one) is not refined."""
    guesses = np.asarray(guesses, float).reshape(-1, 2)
    templates = prepare_templates(previous, starts, half=half)
    centre, warps, converged = fit_warp(templates, current, guesses, half=half,
                                        iterations=iterations, epsilon=epsilon)
    with np.errstate(invalid="ignore"):
        deformation = np.abs(centre_jacobians(warps, half=half) - np.eye(2)).max(axis=(1, 2))
    refined = (converged
               & (np.linalg.norm(centre - guesses, axis=1) <= max_shift)
               & (deformation <= max_deformation))
    return np.where(refined[:, None], centre, guesses), refined
