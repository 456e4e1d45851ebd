"""Procedural, tileable surface textures for the simulated worlds, made from a seed.

Every texture is a square RGB image that repeats seamlessly, so a surface can be tiled with it
(the renderer maps one repeat to :data:`TILE_METRES` of surface). Flat colours would starve the
feature tracker (Shi and Tomasi, "Good Features to Track", CVPR 1994, need 2-D intensity
structure in every window), so each material layers

- fractal noise made by spectral synthesis: white noise shaped to a power spectrum
  ``P(k) ~ k^-beta`` (Fournier, Fussell and Carpenter, CACM 1982). The inverse FFT is periodic,
  which makes the noise tileable by construction;
- drawn detail with sharp edges (cracks, stones, bricks, blades of grass, painted numbers),
  drawn at all nine periodic offsets so it wraps across the tile's edges too.

All but one: ``smooth_concrete``, the realistic profile's low-texture wall, is faint noise alone.

The same material and seed always give the same image.
"""

from __future__ import annotations

import zlib
from typing import Callable

import cv2
import numpy as np

SIZE = 512
"""Texture edge length in pixels (a power of two, for mipmapping)."""

TILE_METRES = 2.0
"""Surface length covered by one repeat of a texture: 512 px per 2 m, about 4 mm per texel."""


def fractal_noise(rng: np.random.Generator, beta: float, stretch: tuple[float, float] = (1, 1),
                  size: int = SIZE) -> np.ndarray:
    """Zero-mean, unit-variance periodic noise with power spectrum ``~ k^-beta``.

    ``stretch = (sx, sy)`` scales the frequency axes before the power law, so ``sy > 1`` damps
    vertical variation and gives streaks along the image's rows' direction (bark, wood grain).
    """
    spectrum = np.fft.rfft2(rng.standard_normal((size, size)))
    fy = np.fft.fftfreq(size)[:, None] * stretch[1]
    fx = np.fft.rfftfreq(size)[None, :] * stretch[0]
    k = np.hypot(fx, fy)
    k[0, 0] = np.inf  # no mean
    noise = np.fft.irfft2(spectrum * k ** (-beta / 2.0), s=(size, size))
    return (noise - noise.mean()) / noise.std()


def _wrapped(draw: Callable[[np.ndarray, int, int], None], image: np.ndarray) -> None:
    """Call ``draw(image, dx, dy)`` at the nine periodic offsets, so the shape tiles."""
    size = image.shape[0]
    for dy in (-size, 0, size):
        for dx in (-size, 0, size):
            draw(image, dx, dy)


def _cracks(rng, image, count, colour, steps=(6, 20), thickness=(1, 3)):
    """Random-walk polylines: cracks in rock and concrete, furrows in bark."""
    for _ in range(count):
        point = rng.uniform(0, SIZE, 2)
        heading = rng.uniform(0, 2 * np.pi)
        points = [point.copy()]
        for _ in range(rng.integers(*steps)):
            heading += rng.normal(0, 0.5)
            point = point + rng.uniform(4, 14) * np.array([np.cos(heading), np.sin(heading)])
            points.append(point.copy())
        pts = np.round(np.array(points)).astype(np.int32)
        width = int(rng.integers(*thickness))
        _wrapped(lambda im, dx, dy: cv2.polylines(im, [pts + (dx, dy)], False, colour, width,
                                                  cv2.LINE_AA), image)


def _blobs(rng, image, count, radius, colours, shade=0.0):
    """Filled ellipses (stones, flecks, stains); ``shade`` darkens a rim below each one."""
    for _ in range(count):
        centre = rng.uniform(0, SIZE, 2).astype(int)
        axes = tuple(int(a) for a in rng.uniform(*radius, 2).clip(1))
        angle = float(rng.uniform(0, 180))
        colour = tuple(float(c) for c in colours[rng.integers(len(colours))]
                       * rng.uniform(0.75, 1.25))
        if shade:
            dark = tuple(c * (1 - shade) for c in colour)
            _wrapped(lambda im, dx, dy: cv2.ellipse(im, (centre[0] + dx, centre[1] + dy + 2),
                                                    axes, angle, 0, 360, dark, -1), image)
        _wrapped(lambda im, dx, dy: cv2.ellipse(im, (centre[0] + dx, centre[1] + dy), axes, angle,
                                                0, 360, colour, -1, cv2.LINE_AA), image)


def _blur_wrapped(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of a periodic image (pads with its own opposite edges, then crops)."""
    pad = int(3 * sigma)
    padded = np.pad(image, pad, mode="wrap")
    return cv2.GaussianBlur(padded, (0, 0), sigma)[pad:-pad, pad:-pad]


def _tinted(value: np.ndarray, tint) -> np.ndarray:
    return value[..., None] * np.asarray(tint, dtype=float)[None, None, :]


def _stains(rng, image, count, strength):
    """Large soft dark patches (water, soot), periodic because the blur wraps."""
    mask = np.zeros((SIZE, SIZE), np.float32)
    _blobs(rng, mask, count, (15, 70), [np.array([1.0])])
    mask = _blur_wrapped(mask, 12)
    image *= (1.0 - strength * mask.clip(0, 1))[..., None]


def rock(rng, tint=(0.62, 0.56, 0.5)) -> np.ndarray:
    value = 0.55 + 0.16 * fractal_noise(rng, 2.2) + 0.09 * fractal_noise(rng, 1.3)
    image = _tinted(value, tint)
    _blobs(rng, image, 500, (2, 6), [np.array([0.85, 0.82, 0.75]), np.array([0.2, 0.19, 0.18])])
    _cracks(rng, image, 40, (0.1, 0.09, 0.08), thickness=(2, 4))
    return image


def gravel(rng) -> np.ndarray:
    image = _tinted(0.45 + 0.1 * fractal_noise(rng, 1.8), (0.6, 0.55, 0.5))
    greys = [np.array([0.45, 0.42, 0.39]), np.array([0.35, 0.33, 0.3]),
             np.array([0.55, 0.52, 0.47])]
    _blobs(rng, image, 500, (3, 11), greys, shade=0.25)
    return image


def concrete(rng, base=0.62) -> np.ndarray:
    value = base + 0.06 * fractal_noise(rng, 2.0) + 0.05 * fractal_noise(rng, 1.0)
    image = _tinted(value, (0.95, 0.95, 0.9))
    for row in range(0, SIZE, 128):  # formwork joints every 0.5 m
        cv2.line(image, (0, row), (SIZE, row), (0.3, 0.3, 0.28), 2)
    _blobs(rng, image, 1200, (2, 5), [np.array([0.25, 0.25, 0.24]), np.array([0.9, 0.9, 0.85]),
                                     np.array([0.45, 0.42, 0.38])])  # aggregate and pits
    _cracks(rng, image, 16, (0.2, 0.2, 0.19), thickness=(2, 3))
    _stains(rng, image, 14, 0.4)
    return image


def brick(rng) -> np.ndarray:
    """Running bond: 8 bricks of 250 mm per row, 32 courses of 62.5 mm, 10 mm mortar joints."""
    image = _tinted(0.75 + 0.05 * fractal_noise(rng, 1.5), (0.8, 0.78, 0.72))  # mortar
    brick_w, brick_h, joint = SIZE // 8, SIZE // 32, 3
    for course in range(32):
        offset = (course % 2) * brick_w // 2
        for k in range(-1, 8):
            colour = np.array([0.55, 0.26, 0.18]) * rng.uniform(0.6, 1.25) \
                + rng.uniform(-0.04, 0.04, 3)
            x0, y0 = k * brick_w + offset + joint, course * brick_h + joint
            _wrapped(lambda im, dx, dy: cv2.rectangle(
                im, (x0 + dx, y0 + dy), (x0 + brick_w - 2 * joint + dx, y0 + brick_h - 2 * joint
                                         + dy), tuple(float(c) for c in colour), -1), image)
    image *= (1.0 + 0.12 * fractal_noise(rng, 1.2))[..., None]
    _stains(rng, image, 10, 0.55)
    return image


def bark(rng) -> np.ndarray:
    value = 0.42 + 0.14 * fractal_noise(rng, 1.8, stretch=(1, 8)) \
        + 0.06 * fractal_noise(rng, 1.0)
    image = _tinted(value, (0.55, 0.42, 0.3))
    _cracks(rng, image, 40, (0.08, 0.06, 0.05), steps=(4, 10), thickness=(2, 4))
    _blobs(rng, image, 120, (2, 5), [np.array([0.45, 0.5, 0.35]), np.array([0.6, 0.55, 0.45])])
    return image


def grass(rng) -> np.ndarray:
    soil = _tinted(0.5 + 0.12 * fractal_noise(rng, 1.6), (0.5, 0.4, 0.28))
    turf = _tinted(0.5 + 0.12 * fractal_noise(rng, 1.4), (0.35, 0.55, 0.2))
    patchy = _blur_wrapped(fractal_noise(rng, 3.0).astype(np.float32), 3)
    image = np.where((patchy > -0.6)[..., None], turf, soil)
    for _ in range(1600):  # blades of grass
        start = rng.uniform(0, SIZE, 2)
        end = start + rng.uniform(6, 16) * np.array([rng.normal(0, 0.4), -1.0])
        colour = tuple(float(c) for c in np.array([0.35, 0.6, 0.2]) * rng.uniform(0.5, 1.4))
        a, b = start.astype(int), end.astype(int)
        _wrapped(lambda im, dx, dy: cv2.line(im, (a[0] + dx, a[1] + dy), (b[0] + dx, b[1] + dy),
                                             colour, 1, cv2.LINE_AA), image)
    _blobs(rng, image, 60, (2, 6), [np.array([0.55, 0.5, 0.45])], shade=0.5)  # pebbles
    return image


PAINTS = (np.array([0.8, 0.2, 0.15]), np.array([0.9, 0.7, 0.15]), np.array([0.2, 0.4, 0.75]),
          np.array([0.85, 0.85, 0.8]), np.array([0.25, 0.6, 0.35]))


def painted(rng) -> np.ndarray:
    """Painted concrete with stripes, stencilled numbers and chipped paint."""
    paint, stripe = (PAINTS[i] for i in rng.choice(len(PAINTS), 2, replace=False))
    image = _tinted(0.85 + 0.06 * fractal_noise(rng, 1.8), paint)
    for row in range(32, SIZE, 128):  # a band of diagonal stripes every 0.5 m
        for x in range(-SIZE, SIZE, 48):
            band = np.array([[x, row], [x + 24, row], [x + 56, row + 40], [x + 32, row + 40]])
            cv2.fillPoly(image, [band.astype(np.int32)], tuple(float(c) for c in stripe))
    stencil = np.zeros((SIZE, SIZE), np.uint8)  # cv2.putText draws on 8-bit images only
    for _ in range(6):
        text = str(int(rng.integers(10, 99)))
        origin = (int(rng.uniform(0, SIZE - 90)), int(rng.uniform(60, SIZE - 10)))
        cv2.putText(stencil, text, origin, cv2.FONT_HERSHEY_SIMPLEX, 2.0, 255, 5)
    image[stencil > 0] = 0.1
    _blobs(rng, image, 90, (2, 9), [np.array([0.55, 0.55, 0.52])])  # chipped to concrete
    _stains(rng, image, 8, 0.4)
    return image


def smooth_concrete(rng) -> np.ndarray:
    """Smooth painted or sprayed concrete (shotcrete): the low-texture wall of the realistic
    profile. Only a faint, broad mottling (2 % RMS of the albedo, ``k^-3`` so almost no fine
    detail) and a fainter grain (0.4 %): no joints, aggregate, cracks or stains, so Shi-Tomasi
    finds little there beside the textured surfaces."""
    value = 0.6 + 0.012 * fractal_noise(rng, 3.0) + 0.0024 * fractal_noise(rng, 1.0)
    return _tinted(value, (0.93, 0.92, 0.88))


MATERIALS: dict[str, Callable[[np.random.Generator], np.ndarray]] = {
    "rock": rock,
    "rock_dark": lambda rng: rock(rng, tint=(0.48, 0.45, 0.42)),
    "gravel": gravel,
    "concrete": concrete,
    "concrete_wet": lambda rng: concrete(rng, base=0.42),
    "brick": brick,
    "bark": bark,
    "grass": grass,
    "painted": painted,
    "smooth_concrete": smooth_concrete,
}
"""Every material a world may name, and the function that paints it."""


def make_texture(material: str, seed: int) -> np.ndarray:
    """The ``(SIZE, SIZE, 3)`` uint8 RGB texture of ``material`` for world seed ``seed``."""
    if material not in MATERIALS:
        raise ValueError(f"unknown material {material!r}; known: {', '.join(MATERIALS)}")
    rng = np.random.default_rng([seed, zlib.crc32(material.encode())])
    image = MATERIALS[material](rng)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
