"""A stand-in for a monocular relative-depth network, for simulation without an ONNX model.

:class:`SyntheticNetwork` turns ground-truth metric depth ``z`` (float32 metres, NaN unknown)
into affine-invariant relative disparity that errs the way a small network such as Depth
Anything V2 Small does. With ``d = 1 / z`` on the *known* pixels (finite, ``0 < z <=
far_depth``), ``D`` the frame's 99th-percentile known disparity and ``t`` the frame number,

    x      = (d / D) ** gamma_t                 known pixels: monotone power-law distortion
    x      = sky_level                          unknown, sky and far pixels: near zero
    x      = open_w(log x), then * T^c          thin structures lost, texture copied
    y      = G_sigma * (x * exp(e_t(u, v)))     smooth error field, then blurred depth edges
    output = s_t * (y + b_t)                    affine drift of the scale and shift

where ``gamma_t = exp(gamma_spread * g_t)``, ``e_t`` is a ``field_grid`` x ``field_grid`` grid
of values ``field_sigma * n_t`` upsampled bicubically to the image, ``G_sigma`` a Gaussian of
``edge_blur`` pixels per 640 pixels of width, ``s_t = exp(scale_spread * a_t)`` and
``b_t = max_shift * (1 + tanh c_t) / 2``. Every one of ``g, n, a, c`` is a unit-variance AR(1)
process ``u_t = rho u_(t-1) + sqrt(1 - rho^2) w_t`` with ``rho = exp(-1 / frames)`` for its
time constant in frames, started from its stationary distribution so the first frame is as wrong
as any later one. The output is finite and non-negative everywhere.

Two failure modes of relative-depth networks on such scenes come with the realistic profile
(:meth:`SyntheticDepthOptions.for_profile`): ``open_w`` is a grey-scale opening of the log
disparity with a disk, so a pole or a tripod leg at most ``thin_width_px`` wide takes the
disparity of the wall behind it (lost; a wider structure keeps its shape), and
``T^c`` multiplies disparity by the image's fine luminance detail to the power
``texture_copy`` (``T`` = luminance over its Gaussian blur of :data:`TEXTURE_SCALE` pixels), so
the texture of a flat wall reads as relief.

:func:`affine_fit_abs_rel` is the calibration metric, the affine-invariant evaluation of MiDaS
(Ranftl et al. 2020) and Depth Anything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from autonomy.options import option, validate

#: Image width at which ``edge_blur`` is given; the blur scales with the width.
REFERENCE_WIDTH = 640
#: Stride of the pixel subsample the frame's disparity percentile is taken on.
PERCENTILE_STRIDE = 4
#: Gaussian sigma, pixels at 640 pixels of width, below which image detail counts as texture.
TEXTURE_SCALE = 4.0


@dataclass(frozen=True)
class SyntheticDepthOptions:
    """The error model of the synthetic stand-in (config section ``[synthetic_depth]``)."""

    gamma_spread: float = option(0.1, ge=0.0, le=0.5, doc="std of log gamma, the exponent of "
                                 "the power-law distortion of disparity")
    gamma_frames: float = option(300.0, ge=1.0, doc="time constant of gamma's drift, frames")
    field_sigma: float = option(0.09, ge=0.0, le=1.0, doc="std of the smooth multiplicative "
                                "error field, as log disparity")
    field_grid: int = option(4, ge=2, le=64, doc="nodes per side of the grid the error field "
                             "is upsampled from (coarser = smoother)")
    field_frames: float = option(30.0, ge=1.0, doc="time constant of the error field, frames")
    edge_blur: float = option(1.5, ge=0.0, le=50.0, doc="Gaussian sigma smearing depth edges, "
                              "pixels at 640 pixels of width")
    scale_spread: float = option(0.2, ge=0.0, le=2.0, doc="std of the log of the output scale "
                                 "s_t")
    max_shift: float = option(0.02, ge=0.0, le=1.0, doc="largest output shift b_t, as a share "
                              "of the frame's 99th-percentile disparity")
    drift_frames: float = option(100.0, ge=1.0, doc="time constant of the scale and shift "
                                 "drift, frames")
    sky_level: float = option(0.01, ge=0.0, le=0.1, doc="disparity of sky, far and unknown "
                              "pixels, as a share of the 99th-percentile disparity")
    far_depth: float = option(80.0, gt=0.0, doc="depth beyond which a pixel counts as far, "
                              "like sky, metres")
    thin_width_px: float = option(4.0, ge=0.0, le=64.0, doc="near structures at most this "
                                  "wide are lost into what lies behind them, pixels at 640 "
                                  "pixels of width (realistic profile)")
    texture_copy: float = option(0.1, ge=0.0, le=1.0, doc="log disparity added per unit of "
                                 "the image's fine log-luminance detail: texture read as "
                                 "relief (realistic profile)")

    def __post_init__(self) -> None:
        validate(self)

    def for_profile(self, profile: str) -> "SyntheticDepthOptions":
        """These options in the simulator's ``profile``: ``realistic`` as they are, ``ideal``
        without the failure modes on thin structures and texture (the stand-in before them)."""
        if profile == "realistic":
            return self
        if profile == "ideal":
            return replace(self, thin_width_px=0.0, texture_copy=0.0)
        raise ValueError(f"profile must be ideal or realistic, got {profile!r}")


class SyntheticNetwork:
    """Relative disparity from ground-truth depth, one frame per call (see the module doc).

    Without ``options``, the defaults of the ideal profile. The same ``seed`` gives the same
    outputs for the same sequence of depth images.
    """

    def __init__(self, options: SyntheticDepthOptions | None = None, seed: int = 0):
        # no options: the defaults without the realistic profile's failure modes
        self.options = options or SyntheticDepthOptions().for_profile("ideal")
        if not isinstance(self.options, SyntheticDepthOptions):
            raise TypeError(f"options must be SyntheticDepthOptions, got {self.options!r}")
        self._rng = np.random.default_rng(seed)
        grid = (self.options.field_grid, self.options.field_grid)
        self._gamma, self._scale, self._shift = self._rng.standard_normal(3)
        self._field = self._rng.standard_normal(grid)
        self._upsampling: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, depth: np.ndarray, image: np.ndarray | None = None) -> np.ndarray:
        """Relative disparity (float32, same shape) for the next frame's ground-truth depth;
        ``image`` (RGB uint8, the frame's) feeds the texture copy, which needs one when
        ``texture_copy`` is on."""
        z = _checked_depth(depth)
        o = self.options
        known = (z > 0.0) & (z <= o.far_depth)  # False where z is NaN
        gamma = math.exp(o.gamma_spread * self._gamma)
        log_x = np.log(np.where(known, z, 1.0))  # log (d / D) = log z_ref - log z
        log_x -= _log_reference_depth(z, known)
        log_x *= -gamma
        log_x[~known] = math.log(o.sky_level) if o.sky_level > 0 else -np.inf
        log_x = self._thin_structures_lost(log_x)
        if o.texture_copy > 0:
            log_x += o.texture_copy * _fine_log_luminance(_checked_image(image, z.shape))
        log_x += self._error_field(z.shape)
        y = np.exp(log_x)
        sigma = o.edge_blur * z.shape[1] / REFERENCE_WIDTH
        if sigma > 0:
            y = cv2.GaussianBlur(y, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        shift = o.max_shift * (1.0 + math.tanh(self._shift)) / 2.0
        out = math.exp(o.scale_spread * self._scale) * (y + shift)  # >= 0: y, shift >= 0
        self._step()
        return out

    def _thin_structures_lost(self, log_x: np.ndarray) -> np.ndarray:
        """Grey-scale opening of the log disparity with a disk: anything nearer than its
        surroundings and at most ``thin_width_px`` wide (rounded to even pixels) takes the
        disparity of what lies behind it; wider structures keep their shape."""
        width = self.options.thin_width_px * log_x.shape[1] / REFERENCE_WIDTH
        if round(width / 2) < 1:
            return log_x
        size = 2 * round(width / 2) + 1  # an odd disk removes what is at most size - 1 wide
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        finite = np.where(np.isfinite(log_x), log_x, np.float32(-1e6)).astype(np.float32)
        opened = cv2.morphologyEx(finite, cv2.MORPH_OPEN, disk, borderType=cv2.BORDER_REFLECT)
        return np.where(np.isfinite(log_x), opened, log_x)

    def _error_field(self, shape: tuple[int, int]) -> np.ndarray:
        """log of the multiplicative error: the grid times field_sigma, bicubic to ``shape``.

        Bicubic interpolation is separable, so the upsampled field is ``U_rows @ grid @
        U_cols.T`` with ``U`` the interpolation matrices, kept per image shape.
        """
        if shape not in self._upsampling:
            n = self.options.field_grid
            self._upsampling[shape] = (_bicubic_matrix(n, shape[0]), _bicubic_matrix(n, shape[1]))
        rows, cols = self._upsampling[shape]
        grid = (self.options.field_sigma * self._field).astype(np.float32)
        return rows @ grid @ cols.T

    def _step(self) -> None:
        """Advance every AR(1) process one frame."""
        o = self.options
        self._gamma = _ar1(self._gamma, o.gamma_frames, self._rng)
        self._field = _ar1(self._field, o.field_frames, self._rng)
        self._scale = _ar1(self._scale, o.drift_frames, self._rng)
        self._shift = _ar1(self._shift, o.drift_frames, self._rng)


def _ar1(u, frames: float, rng: np.random.Generator):
    """One step of a unit-variance AR(1): ``rho u + sqrt(1 - rho^2) w``, rho = exp(-1/frames)."""
    rho = math.exp(-1.0 / frames)
    return rho * u + math.sqrt(1.0 - rho * rho) * rng.standard_normal(np.shape(u))


def _bicubic_matrix(n: int, size: int) -> np.ndarray:
    """(size, n) matrix taking n grid values to ``size`` samples, as cv2's bicubic resize does
    (column j is the resized unit vector e_j)."""
    return cv2.resize(np.eye(n, dtype=np.float32), (n, size), interpolation=cv2.INTER_CUBIC)


def _checked_image(image, shape: tuple[int, int]) -> np.ndarray:
    """``image`` as (H, W, 3) uint8 of the depth's ``shape``; ValueError for anything else."""
    if image is None:
        raise ValueError("texture_copy needs the frame's image: call the stand-in with "
                         "(depth, image), or set [synthetic_depth] texture_copy = 0")
    array = np.asarray(image)
    if array.shape != (*shape, 3) or array.dtype != np.uint8:
        raise ValueError(f"image must be RGB uint8 of shape {(*shape, 3)}, got "
                         f"{array.shape} {array.dtype}")
    return array


def _fine_log_luminance(image: np.ndarray) -> np.ndarray:
    """The image's fine detail: log luminance minus its Gaussian blur of
    :data:`TEXTURE_SCALE` pixels per 640 of width (what a network may read as relief)."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32)
    log_l = np.log(grey + 1.0)
    sigma = TEXTURE_SCALE * image.shape[1] / REFERENCE_WIDTH
    return log_l - cv2.GaussianBlur(log_l, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def _checked_depth(depth) -> np.ndarray:
    """``depth`` as a float32 2-D array; ValueError for anything else."""
    array = np.asarray(depth)
    if array.ndim != 2 or array.size == 0:
        raise ValueError(f"depth must be a non-empty 2-D image, got shape {array.shape}")
    if array.dtype == np.bool_ or not (np.issubdtype(array.dtype, np.floating)
                                       or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"depth must be real-valued metres, got dtype {array.dtype}")
    return array.astype(np.float32, copy=False)


def _log_reference_depth(z: np.ndarray, known: np.ndarray) -> float:
    """log z_ref, z_ref = 1 / D the 1st-percentile known depth, taken on a pixel subsample;
    0 when no pixel is known."""
    step = PERCENTILE_STRIDE
    sub = z[::step, ::step][known[::step, ::step]]
    if sub.size == 0:
        sub = z[known]
    return math.log(float(np.percentile(sub, 1.0))) if sub.size else 0.0


def affine_fit_abs_rel(relative_disparity, depth, *, min_depth: float = 0.1,
                       max_depth: float = 40.0) -> float:
    """AbsRel of ``relative_disparity`` against ``depth`` after the best affine fit.

    Over the pixels where the depth ``z*`` is finite and in ``[min_depth, max_depth]`` and the
    output ``r`` is finite, ``a, b`` minimise ``sum (a r + b - 1 / z*)^2``; the predicted depth
    is ``z = 1 / max(a r + b, 1 / max_depth)`` (the clamp of the MiDaS evaluation, so a pixel
    fitted at or beyond infinity counts as ``max_depth``), and

        AbsRel = mean |z - z*| / z*.

    NaN when fewer than two pixels qualify. ValueError when the shapes differ.
    """
    r = np.asarray(relative_disparity, dtype=np.float64)
    gt = np.asarray(depth, dtype=np.float64)
    if r.shape != gt.shape:
        raise ValueError(f"shapes differ: relative_disparity {r.shape}, depth {gt.shape}")
    if not 0.0 < min_depth < max_depth:
        raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (gt >= min_depth) & (gt <= max_depth)
    r, gt = r[valid], gt[valid]
    if r.size < 2:
        return math.nan
    design = np.column_stack([r, np.ones_like(r)])
    (a, b), *_ = np.linalg.lstsq(design, 1.0 / gt, rcond=None)
    pred = 1.0 / np.maximum(a * r + b, 1.0 / max_depth)
    return float(np.mean(np.abs(pred - gt) / gt))

