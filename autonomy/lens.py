"""A calibrated camera: pinhole intrinsics and lens distortion, and its rectification.

Two lens models cover the cameras of such vehicles, with the names and coefficient orders of
Kalibr and OpenCV:

- ``radtan`` (Brown-Conrady, OpenCV's default model; a RealSense colour stream, most USB
  cameras): coefficients ``(k1, k2, p1, p2[, k3])``, the map in
  :func:`autonomy.geometry.distort_normalised`;
- ``equidistant`` (Kannala-Brandt, OpenCV's ``cv2.fisheye``; fisheye lenses, an OAK's wide
  lenses): coefficients ``(k1, k2, k3, k4)``. A ray at angle ``theta`` from the optical axis is
  imaged at radius ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``
  in normalised coordinates, along the ray's own azimuth.

The rest of the stack (the VINS, the depth network, the planner) works on an ideal pinhole
image: :class:`Rectifier` resamples each frame through the lens model onto
:meth:`CameraModel.rectified`, once per frame, so all three see the same geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera, distort_normalised

DISTORTION_MODELS = {"none": (0,), "radtan": (4, 5), "equidistant": (4,)}
"""Each lens model and the coefficient counts it takes."""


@dataclass(frozen=True)
class CameraModel:
    """A camera's intrinsics ``pinhole`` (the distorted image's focal lengths and principal
    point) and its lens ``distortion`` model with ``coefficients`` (module docstring)."""

    pinhole: PinholeCamera
    distortion: str = "none"
    coefficients: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        counts = DISTORTION_MODELS.get(self.distortion)
        if counts is None:
            raise ValueError(f"unknown distortion model {self.distortion!r}; expected one of "
                             f"{', '.join(DISTORTION_MODELS)}")
        coefficients = tuple(float(c) for c in self.coefficients)
        if len(coefficients) not in counts:
            raise ValueError(f"{self.distortion} distortion takes "
                             f"{' or '.join(map(str, counts))} coefficients, got "
                             f"{len(coefficients)}")
        if not all(math.isfinite(c) for c in coefficients):
            raise ValueError(f"distortion coefficients must be finite, got {coefficients}")
        object.__setattr__(self, "coefficients", coefficients)

    @property
    def is_pinhole(self) -> bool:
        """No distortion: frames need no resampling. An ``equidistant`` lens never is one:
        with all coefficients 0 it is the ideal fisheye ``r = f theta``, not ``f tan(theta)``."""
        return self.distortion == "none" or (self.distortion == "radtan"
                                             and not any(self.coefficients))

    def distort(self, normalised: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates ``(N, 2)`` of ideal ones ``(N, 2)`` (``X/Z, Y/Z``)."""
        xy = np.asarray(normalised, dtype=float).reshape(-1, 2)
        if self.distortion == "radtan":
            return distort_normalised(self.coefficients, xy)
        if self.distortion == "equidistant":
            return _distort_equidistant(self.coefficients, xy)
        return xy.copy()

    def rectified(self, hfov_deg: float = 0.0) -> PinholeCamera:
        """The ideal pinhole the rectified frames follow: the same size and principal point;
        the same focal lengths, or with ``hfov_deg`` > 0 square pixels spanning that
        horizontal field of view (a fisheye's full view does not fit a pinhole image, so the
        user picks how much of it to keep)."""
        p = self.pinhole
        if hfov_deg <= 0.0:
            return p
        if not hfov_deg < 180.0:
            raise ValueError(f"a pinhole image spans less than 180 degrees, got {hfov_deg}")
        f = (p.width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return PinholeCamera(p.width, p.height, f, f, p.cx, p.cy)


def _distort_equidistant(coefficients, xy: np.ndarray) -> np.ndarray:
    k1, k2, k3, k4 = coefficients
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(r > 1e-12, theta_d / r, 1.0)
    return xy * scale[:, None]


class Rectifier:
    """Resamples frames of ``model`` onto the ideal pinhole ``target`` (bilinear).

    For each target pixel the ray through it is distorted by the lens model and looked up in
    the source image: ``map(u, v) = K_src distort(K_target^-1 (u, v, 1))``. The maps are made
    once; a 640x480 colour frame then takes about a millisecond (``cv2.remap``). Target pixels
    whose ray falls outside the source image are black.
    """

    def __init__(self, model: CameraModel, target: PinholeCamera):
        self.model, self.target = model, target
        rays = target.rays()[..., :2].reshape(-1, 2)
        distorted = model.distort(rays)
        p = model.pinhole
        self._map_u = (p.fx * distorted[:, 0] + p.cx).reshape(target.height, target.width)
        self._map_v = (p.fy * distorted[:, 1] + p.cy).reshape(target.height, target.width)
        self._map_u = self._map_u.astype(np.float32)
        self._map_v = self._map_v.astype(np.float32)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The rectified image of a source frame of ``model``'s size."""
        return self._remap(image, cv2.INTER_LINEAR, 0)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """A depth image of the source frame's pixels moved onto the target's (nearest pixel:
        depths are not blended across edges); NaN outside the source."""
        return self._remap(depth, cv2.INTER_NEAREST, float("nan"))

    def _remap(self, image: np.ndarray, interpolation: int, border: float) -> np.ndarray:
        p = self.model.pinhole
        if image.shape[:2] != (p.height, p.width):
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, the camera model "
                             f"is {p.width}x{p.height}")
        out = cv2.remap(image, self._map_u, self._map_v, interpolation,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=border)
        out.setflags(write=False)
        return out
