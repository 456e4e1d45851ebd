"""Speed benchmarks behind ``companion bench``: library calls, the CLI only prints them.

Timings are medians over repeated runs, and every speed-up is reported against a baseline
measured in the same run, because the machines this runs on (2 shared cores in CI, an Orin in
the field) make absolute numbers drift between runs.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from typing import Callable

import numpy as np

from autonomy.depth.rescale import METHODS, RescaleOptions, fit


class BenchmarkError(Exception):
    """The benchmark could not run as asked; the message says why."""


@dataclasses.dataclass(frozen=True)
class RescaleScene:
    """A synthetic frame: the network's relative disparity and the VINS anchors in it."""

    relative_disparity: np.ndarray  # (H, W) float32
    anchor_disparity: np.ndarray  # (N,) relative disparity at the anchors
    anchor_depth: np.ndarray  # (N,) metric depth of the anchors, metres
    anchor_pixels: np.ndarray  # (N, 2) where the anchors are, (u, v) pixel centres


def synthetic_scene(shape: tuple[int, int], anchors: int, seed: int = 0) -> RescaleScene:
    """A corridor-like frame: a floor and far wall, two near boxes, a patch of sky.

    The network's output is modelled as it errs: an unknown scale and shift of a mildly
    non-linear function of true disparity (x = 3·(1/z)^0.9 + 0.1), with 1 % pixel noise.
    The anchors are ``anchors`` random pixels whose VINS depths carry 3 % noise, 5 % of them gross
    outliers (depth doubled), as a sliding-window VINS delivers them.
    """
    height, width = shape
    if not 0 < anchors <= height * width:
        raise BenchmarkError(f"cannot place {anchors} anchors in a {height}x{width} image")
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float64)
    depth = np.full(shape, 30.0)
    floor = rows > height * 0.45
    depth[floor] = np.minimum(30.0, 1.2 * height / (rows[floor] - height * 0.45 + 1.0))
    for top, left, size, metres in ((0.35, 0.15, 0.3, 2.0), (0.40, 0.65, 0.2, 4.5)):
        box = (rows >= top * height) & (rows < (top + size) * height) \
            & (cols >= left * width) & (cols < (left + size) * width)
        depth[box] = metres
    relative = 3.0 * (1.0 / depth) ** 0.9 + 0.1
    relative *= 1.0 + 0.01 * rng.standard_normal(shape)
    relative[: height // 10, : width // 4] = 0.0  # sky: the network's "infinitely far"
    pick = rng.choice(height * width, size=anchors, replace=False)
    anchor_depth = depth.reshape(-1)[pick] * (1.0 + 0.03 * rng.standard_normal(anchors))
    outliers = rng.random(anchors) < 0.05
    anchor_depth[outliers] *= 2.0
    return RescaleScene(relative.astype(np.float32), relative.reshape(-1)[pick].astype(float),
                        anchor_depth, np.column_stack([pick % width, pick // width]).astype(float))


def interleaved_medians_ms(calls: list[Callable[[], object]], repeats: int) -> list[float]:
    """Median times in ms of several calls, after one warm-up call each; the calls run in
    turn each repeat so load drifts hit all alike."""
    for call in calls:
        call()
    samples: list[list[float]] = [[] for _ in calls]
    for _ in range(repeats):
        for call, times in zip(calls, samples):
            start = time.perf_counter()
            call()
            times.append(time.perf_counter() - start)
    return [1e3 * statistics.median(times) for times in samples]


def run_rescale_benchmark(options: RescaleOptions, *, anchors: int = 150,
                          shape: tuple[int, int] = (480, 640), repeats: int = 30) -> dict:
    """Time every rescaling method on one synthetic frame.

    For each method: ``fit_ms`` (fitting the anchors), ``depth_ms`` (applying the fit to the
    whole image the way the product does, through the lookup table) and ``direct_ms`` (the
    baseline: the same fitted curve evaluated directly at every pixel), medians over
    ``repeats`` runs, the last two interleaved.
    """
    scene = synthetic_scene(shape, anchors)
    results = {}
    for method in METHODS:
        method_options = dataclasses.replace(options, method=method)
        fit_ms, = interleaved_medians_ms([lambda: fit(scene.anchor_disparity, scene.anchor_depth,
                                                      options=method_options)], repeats)
        model = fit(scene.anchor_disparity, scene.anchor_depth, options=method_options)
        if not model.ok:
            raise BenchmarkError(f"{method} found no fit on the benchmark scene: {model.detail}")
        depth_ms, direct_ms = interleaved_medians_ms(
            [lambda: model.depth(scene.relative_disparity),
             lambda: model.depth(scene.relative_disparity, exact=True)], repeats)
        results[method] = {"fit_ms": round(fit_ms, 4), "depth_ms": round(depth_ms, 4),
                           "direct_ms": round(direct_ms, 4)}
    return {"anchors": anchors, "image": list(shape), "methods": results}


def format_rescale_table(result: dict) -> str:
    """The benchmark result as a table a person reads."""
    height, width = result["image"]
    lines = [f"rescale benchmark: {result['anchors']} anchors, {height}x{width} image "
             "(medians, ms)",
             f"{'method':<28}{'fit':>9}{'depth':>9}{'direct':>9}{'direct/depth':>14}"]
    for method, row in result["methods"].items():
        ratio = row["direct_ms"] / row["depth_ms"]
        lines.append(f"{method:<28}{row['fit_ms']:>9.3f}{row['depth_ms']:>9.3f}"
                     f"{row['direct_ms']:>9.3f}{ratio:>13.1f}x")
    return "\n".join(lines)
