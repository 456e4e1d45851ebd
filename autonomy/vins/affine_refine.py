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
change between frames is not read as motion. The scale no longer biases the centre; what is
left is the frame's noise, which adds up as a random walk.

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
1.007 for a reason not found, and it triples the front-end's time (docs/vins.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: Sobel's 3x3 derivative is a central difference (twice the slope) smoothed across by
#: [1, 2, 1] (four times the value): this scale makes it a derivative per pixel.
SOBEL_SCALE = 1.0 / 8.0


def bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) at real pixel coordinates ``x``, ``y`` (any one shape S;
    returns S or S + (C,)), with exact float weights, unlike ``cv2.remap``'s 1/32 px fixed
    point; the border replicated."""
    h, w = image.shape[:2]
    flat = image.reshape(h * w, -1)
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.int64), w - 2)  # floor: x >= 0
    y0 = np.minimum(y.astype(np.int64), h - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    i = y0 * w + x0
    top = flat[i] * (1.0 - fx) + flat[i + 1] * fx
    bottom = flat[i + w] * (1.0 - fx) + flat[i + w + 1] * fx
    out = top * (1.0 - fy) + bottom * fy
    return out if image.ndim == 3 else out[..., 0]


def _normalised(patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row less its mean, and its standard deviation."""
    centred = patches - patches.mean(axis=1, keepdims=True)
    return centred, np.sqrt(np.mean(centred**2, axis=1))


def with_gradients(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float32: a grey image, its d/dx and its d/dy, per pixel (the template
    side of :func:`refine_affine`, computed once per frame)."""
    image = image.astype(np.float32)
    return np.dstack([image, cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=SOBEL_SCALE),
                      cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=SOBEL_SCALE)])


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
    normalised to zero mean (``values``, (N, M)) and its contrast (``contrast``), the
    inverse-compositional steepest-descent images transposed (``steepest_t``, (N, P, M), ``P``
    the warp's parameters) and their Hessian's inverse (``inverse``, (N, P, P)); ``usable`` is
    false for a flat patch or a singular Hessian."""

    values: np.ndarray
    contrast: np.ndarray
    steepest_t: np.ndarray
    inverse: np.ndarray
    usable: np.ndarray

    def __len__(self) -> int:
        return len(self.usable)

    def take(self, rows) -> "Templates":
        """The patches of ``rows`` (indices or a boolean mask), in that order."""
        return Templates(self.values[rows], self.contrast[rows], self.steepest_t[rows],
                         self.inverse[rows], self.usable[rows])

    @staticmethod
    def join(a: "Templates", b: "Templates") -> "Templates":
        """``a``'s patches followed by ``b``'s."""
        return Templates(*(np.concatenate([x, y]) for x, y in
                           zip((a.values, a.contrast, a.steepest_t, a.inverse, a.usable),
                               (b.values, b.contrast, b.steepest_t, b.inverse, b.usable))))


def _scaled_offsets(half: int) -> tuple[np.ndarray, np.ndarray]:
    """A ``2 half + 1`` square patch's pixel offsets from its centre over ``half`` (so in
    [-1, 1], which keeps the warp's parameters of one magnitude), x and y, row by row."""
    offsets = np.arange(-half, half + 1, dtype=float) / half
    return tuple(a.ravel() for a in np.meshgrid(offsets, offsets))


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


def prepare_templates(image: np.ndarray, centres: np.ndarray, *, half: int,
                      warp: str = "affine") -> Templates:
    """The ``2 half + 1`` square patches of ``image`` (:func:`with_gradients` of a grey image)
    around ``centres`` (N, 2), made ready for :func:`fit_warp` under ``warp``
    (:data:`WARP_PARAMETERS`). The steepest-descent images are the patch's gradient times the
    warp's Jacobian at the identity, in the scaled offsets ``s``: for the affine map ``(gx sx,
    gx sy, gy sx, gy sy, gx, gy)``, for the homography also ``-(gx sx + gy sy) (sx, sy)``."""
    sx, sy = _scaled_offsets(half)
    centres = np.asarray(centres, float).reshape(-1, 2)
    sampled = bilinear(image, centres[:, :1] + half * sx, centres[:, 1:] + half * sy)
    values, contrast = _normalised(sampled[..., 0])
    gx, gy = sampled[..., 1] * half, sampled[..., 2] * half  # per unit of scaled offset
    columns = [gx * sx, gx * sy, gy * sx, gy * sy, gx, gy]
    if warp_parameters(warp) == 8:  # the homography's last row
        radial = gx * sx + gy * sy
        columns += [-radial * sx, -radial * sy]
    steepest_t = np.ascontiguousarray(np.stack(columns, axis=1))  # (N, P, M)
    hessian = steepest_t @ steepest_t.transpose(0, 2, 1)
    eigenvalues = np.linalg.eigvalsh(hessian)  # ascending
    usable = (contrast > 1e-3) & (eigenvalues[:, 0] > MIN_EIGENVALUE_RATIO * eigenvalues[:, -1])
    inverse = np.zeros_like(hessian)
    inverse[usable] = np.linalg.inv(hessian[usable])
    return Templates(values, contrast, steepest_t, inverse, usable)


def _parameter_warps(p: np.ndarray) -> np.ndarray:
    """(N, 3, 3): the warps of parameters ``p`` (N, 6 or 8) about the identity."""
    h = np.tile(np.eye(3), (len(p), 1, 1))
    h[:, :2, :2] += p[:, :4].reshape(-1, 2, 2)
    h[:, :2, 2] = p[:, 4:6]
    if p.shape[1] == 8:
        h[:, 2, :2] = p[:, 6:]
    return h


def fit_warp(templates: Templates, current: np.ndarray, guesses: np.ndarray,
             warps: np.ndarray | None = None, *, half: int, iterations: int = 20,
             epsilon: float = 0.005) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each template's patch found in ``current`` (a grey image) under the warp ``G`` (3x3,
    from the patch's scaled offsets to pixels; affine or a homography, as the templates were
    prepared) by inverse-compositional Gauss-Newton, from ``warps`` (N, 3, 3) moved to centre
    on ``guesses`` (N, 2), or from :func:`identity_warps` there when None. Each step
    ``dp = H^-1 sum SD^T e`` is composed inverted, ``G <- G W(dp)^-1``. Returns the centres
    (N, 2), the warps and whether each converged (a last step of the patch's centre under
    ``epsilon`` pixels, the warp finite, the template usable)."""
    sx, sy = _scaled_offsets(half)
    guesses = np.asarray(guesses, float).reshape(-1, 2)
    if warps is None:
        warps = identity_warps(guesses, half=half)
    else:
        # Moved onto the guesses: G <- T(guess - centre) G.
        warps = np.asarray(warps, float).reshape(-1, 3, 3).copy()
        warps[:, :2, :] += (guesses - warp_centres(warps))[:, :, None] * warps[:, 2:, :]
    current = current.astype(np.float32)
    active = templates.usable.copy()
    converged = np.zeros(len(templates), bool)
    for _ in range(iterations):
        k = np.flatnonzero(active)
        if not len(k):
            break
        g = warps[k]
        hx, hy, hw = (g[:, i, :1] * sx + g[:, i, 1:2] * sy + g[:, i, 2:] for i in range(3))
        warped, warped_std = _normalised(bilinear(current, hx / hw, hy / hw))
        error = (warped * (templates.contrast[k] / np.maximum(warped_std, 1e-9))[:, None]
                 - templates.values[k])
        step = np.einsum("nij,nj->ni", templates.inverse[k],
                         (templates.steepest_t[k] @ error[:, :, None])[:, :, 0])
        before = warp_centres(g)
        with np.errstate(all="ignore"):
            g = g @ np.linalg.inv(_parameter_warps(step))
            g = g / g[:, 2:, 2:]
        warps[k] = g
        # A singular step leaves a warp that is not finite: that track is given up, not
        # sampled again.
        lost = ~np.isfinite(g).all(axis=(1, 2))
        done = ~lost & (np.linalg.norm(warp_centres(g) - before, axis=1) < epsilon)
        converged[k[done]] = True
        active[k[done | lost]] = False
    return warp_centres(warps), warps, converged


def refine_affine(previous: np.ndarray, current: np.ndarray, starts: np.ndarray,
                  guesses: np.ndarray, *, half: int, iterations: int = 20,
                  epsilon: float = 0.005, max_shift: float = 0.5,
                  max_deformation: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """``guesses`` (N, 2), Lucas-Kanade's positions in ``current`` (a grey image) of the
    features at ``starts`` in ``previous`` (:func:`with_gradients` of the previous image),
    refined under an affine warp of the ``2 half + 1`` square patch (module docstring).
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
