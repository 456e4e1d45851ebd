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

Its two halves, :func:`prepare_templates` (a patch made ready once) and :func:`fit_affine` (the
fit from a given map), also serve ``anchored_tracks.py``, whose templates outlive a frame.

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


def _inverse_2x2(m: np.ndarray) -> np.ndarray:
    """The inverses of a stack of 2x2 matrices (N, 2, 2), in closed form."""
    determinant = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    adjugate = np.stack([np.stack([m[:, 1, 1], -m[:, 0, 1]], axis=1),
                         np.stack([-m[:, 1, 0], m[:, 0, 0]], axis=1)], axis=1)
    return adjugate / determinant[:, None, None]


def with_gradients(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float32: a grey image, its d/dx and its d/dy, per pixel (the template
    side of :func:`refine_affine`, computed once per frame)."""
    image = image.astype(np.float32)
    return np.dstack([image, cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=SOBEL_SCALE),
                      cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=SOBEL_SCALE)])


@dataclass(frozen=True)
class Templates:
    """Patches prepared for :func:`fit_affine`, row ``i`` describing patch ``i``: the patch
    normalised to zero mean (``values``, (N, M)) and its contrast (``contrast``), the
    inverse-compositional steepest-descent images transposed (``steepest_t``, (N, 6, M)) and
    their Hessian's inverse (``inverse``, (N, 6, 6)); ``usable`` is false for a flat patch or
    a singular Hessian."""

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


def _offsets(half: int) -> tuple[np.ndarray, np.ndarray]:
    """A ``2 half + 1`` square patch's pixel offsets from its centre, x and y, row by row."""
    offsets = np.arange(-half, half + 1, dtype=float)
    return tuple(a.ravel() for a in np.meshgrid(offsets, offsets))


def prepare_templates(image: np.ndarray, centres: np.ndarray, *, half: int) -> Templates:
    """The ``2 half + 1`` square patches of ``image`` (:func:`with_gradients` of a grey image)
    around ``centres`` (N, 2), made ready for :func:`fit_affine`."""
    ux, uy = _offsets(half)
    centres = np.asarray(centres, float).reshape(-1, 2)
    sampled = bilinear(image, centres[:, :1] + ux, centres[:, 1:] + uy)  # (N, M, 3)
    values, contrast = _normalised(sampled[..., 0])
    gx, gy = sampled[..., 1], sampled[..., 2]
    steepest = np.stack([gx * ux, gx * uy, gy * ux, gy * uy, gx, gy], axis=2)  # (N, M, 6)
    steepest_t = np.ascontiguousarray(steepest.transpose(0, 2, 1))  # (N, 6, M)
    hessian = steepest_t @ steepest
    eigenvalues = np.linalg.eigvalsh(hessian)  # ascending
    usable = (contrast > 1e-3) & (eigenvalues[:, 0] > 1e-8 * eigenvalues[:, -1])
    inverse = np.zeros_like(hessian)
    inverse[usable] = np.linalg.inv(hessian[usable])
    return Templates(values, contrast, steepest_t, inverse, usable)


def fit_affine(templates: Templates, current: np.ndarray, guesses: np.ndarray,
               linear: np.ndarray | None = None, *, half: int, iterations: int = 20,
               epsilon: float = 0.005) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each template's patch found in ``current`` (a grey image) under ``u -> c + A u`` by
    inverse-compositional Gauss-Newton from ``c = guesses`` and ``A = linear`` (the identity
    when None). Returns ``c`` (N, 2), ``A`` (N, 2, 2) and whether each converged (a last step
    of the patch's centre under ``epsilon`` pixels, the warp finite, the template usable)."""
    ux, uy = _offsets(half)
    n = len(templates)
    current = current.astype(np.float32)
    centre = np.asarray(guesses, float).reshape(-1, 2).copy()
    linear = (np.tile(np.eye(2), (n, 1, 1)) if linear is None
              else np.asarray(linear, float).reshape(-1, 2, 2).copy())
    active = templates.usable.copy()
    converged = np.zeros(n, bool)
    for _ in range(iterations):
        k = np.flatnonzero(active)
        if not len(k):
            break
        c, a = centre[k], linear[k]
        wx = c[:, :1] + a[:, 0, :1] * ux + a[:, 0, 1:] * uy
        wy = c[:, 1:] + a[:, 1, :1] * ux + a[:, 1, 1:] * uy
        warped, warped_std = _normalised(bilinear(current, wx, wy))
        error = (warped * (templates.contrast[k] / np.maximum(warped_std, 1e-9))[:, None]
                 - templates.values[k])
        step = np.einsum("nij,nj->ni", templates.inverse[k],
                         (templates.steepest_t[k] @ error[:, :, None])[:, :, 0])
        a = a @ _inverse_2x2(np.eye(2) + step[:, :4].reshape(-1, 2, 2))
        moved = (a @ step[:, 4:, None])[:, :, 0]
        centre[k], linear[k] = c - moved, a
        done = np.linalg.norm(moved, axis=1) < epsilon
        converged[k[done]] = True
        # A singular step leaves a warp that is not finite: that track is given up, not
        # sampled again.
        lost = ~(np.isfinite(a).all(axis=(1, 2)) & np.isfinite(moved).all(axis=1))
        converged[k[lost]] = False
        active[k[done | lost]] = False
    return centre, linear, converged


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
    centre, linear, converged = fit_affine(templates, current, guesses, half=half,
                                           iterations=iterations, epsilon=epsilon)
    deformation = np.abs(linear - np.eye(2)).max(axis=(1, 2))
    refined = (converged
               & (np.linalg.norm(centre - guesses, axis=1) <= max_shift)
               & (deformation <= max_deformation))
    return np.where(refined[:, None], centre, guesses), refined
