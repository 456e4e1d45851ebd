"""The rescaler on real depth: 7-Scenes frames (Kinect depth, real scene structure).

The network is simulated from the true depth the way relative-disparity networks err (an
unknown scale, shift and mild power of true disparity, with pixel noise); the anchors are
real Shi-Tomasi corners of the real colour image, refined to sub-pixel and sampled with the
paper's nearest-surface rule, with 3 % depth noise as a VINS gives. Skips without the data.
"""

from pathlib import Path

import cv2
import numpy as np
import pytest

from autonomy.depth import metrics
from autonomy.depth.anchors import sample_nearest_surface
from autonomy.depth.rescale import METHODS, fit

FRAMES = Path(__file__).resolve().parents[2] / "shared/data/rgbd/7scenes_tsdf_fusion/data/rgbd-frames"
pytestmark = pytest.mark.skipif(not FRAMES.is_dir(), reason=f"real RGB-D frames not found at {FRAMES}")


def load_frame(index):
    colour = cv2.imread(str(FRAMES / f"frame-{index:06d}.color.png"), cv2.IMREAD_GRAYSCALE)
    raw = cv2.imread(str(FRAMES / f"frame-{index:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
    depth = raw.astype(np.float32) / 1000.0
    depth[(raw == 0) | (raw == 65535)] = np.nan  # 7-Scenes marks missing depth both ways
    return colour, depth


def simulated_network(depth, rng):
    relative = 2.0 * (1.0 / depth) ** 0.85 + 0.05
    relative *= 1.0 + 0.02 * rng.standard_normal(depth.shape)
    return np.where(np.isfinite(relative), relative, np.nanmedian(relative)).astype(np.float32)


def vins_like_anchors(colour, depth, relative, rng):
    corners = cv2.goodFeaturesToTrack(colour, maxCorners=150, qualityLevel=0.01, minDistance=10)
    corners = cv2.cornerSubPix(colour, corners, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.01))
    pixels = corners.reshape(-1, 2).astype(float)
    u, v = np.rint(pixels).astype(int).T
    anchor_depth = depth[v.clip(0, depth.shape[0] - 1), u.clip(0, depth.shape[1] - 1)]
    anchor_depth = anchor_depth * (1.0 + 0.03 * rng.standard_normal(len(anchor_depth)))
    return sample_nearest_surface(relative, pixels), anchor_depth


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    out = []
    for index in (150, 165, 180, 195):
        colour, depth = load_frame(index)
        relative = simulated_network(depth, rng)
        out.append((depth, relative, *vins_like_anchors(colour, depth, relative, rng)))
    return out


@pytest.mark.parametrize("method", METHODS)
def test_every_method_gives_usable_metric_depth_on_real_frames(method, frames):
    for depth, relative, x, z in frames:
        model = fit(x, z, method)
        assert model.ok, model.detail
        result = metrics.evaluate(model.depth(relative), depth)
        assert result.abs_rel < 0.06, (method, result)  # measured 0.029-0.040
        assert result.delta1 > 0.98, (method, result)


def test_monotone_spline_is_accurate_and_rarely_overestimates_on_real_frames(frames):
    for depth, relative, x, z in frames:
        result = metrics.evaluate(fit(x, z, "monotone_spline").depth(relative), depth)
        assert result.abs_rel < 0.05, result  # measured 0.031-0.035
        assert result.delta1 > 0.99, result
        assert result.overestimate_rate < 0.01, result
