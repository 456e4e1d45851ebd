"""The synthetic stand-in for a relative-depth network: calibrated errors, sane output, drift.

Run as a script (``.venv/bin/python tests/test_depth_synthetic.py``) it prints the calibration
table of docs/synthetic_depth.md from the same frames and sequence the tests use.
"""

import math

import cv2
import numpy as np
import pytest

from autonomy.depth.synthetic import SyntheticDepthOptions, SyntheticNetwork, affine_fit_abs_rel
from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.options import OptionError
from drivers.sim.options import WORLD_NAMES
from drivers.sim.render import Renderer
from drivers.sim.world import build_world
from tests.test_sim_render import EGL_PROBLEM

CAMERA = PinholeCamera.from_hfov(640, 480, math.radians(90.0))
POSES = 8  # views along each world's first route
CALLS_PER_POSE = 5  # frames the stand-in runs per view, so its slow processes move between views
CALIBRATION_SEED = 0


def route_poses(world, count):
    """``count`` optical-frame poses evenly along the first route, looking along it, 0.1 rad
    nose-down, at cruise height."""
    route = world.routes[0]
    path = world.find_path(route.start[:2], route.goal[:2], 1.0)
    legs = np.diff(path, axis=0)
    lengths = np.linalg.norm(legs, axis=1)
    starts = np.r_[0.0, np.cumsum(lengths)]
    poses = []
    for s in np.linspace(0.0, starts[-1], count, endpoint=False):
        k = min(int(np.searchsorted(starts, s, side="right")) - 1, len(legs) - 1)
        here = path[k] + legs[k] * (s - starts[k]) / lengths[k]
        R_W_B = rot_z(math.atan2(legs[k][1], legs[k][0])) @ so3_exp(np.array([0.0, 0.1, 0.0]))
        poses.append(make_pose(R_W_B @ R_BODY_CAMERA, np.array([*here, route.cruise_height])))
    return poses


def render_route(name):
    """Ground-truth depth images (POSES, H, W) along ``name``'s first route."""
    world = build_world(name, seed=0)
    with Renderer(world, CAMERA, far=100.0) as renderer:
        return np.stack([renderer.render(T)[1] for T in route_poses(world, POSES)])


def calibration_abs_rel(depths, seed=CALIBRATION_SEED):
    """Per-view affine-fit AbsRel of the stand-in, run CALLS_PER_POSE frames on each view."""
    network = SyntheticNetwork(seed=seed)
    values = []
    for depth in depths:
        for _ in range(CALLS_PER_POSE):
            out = network(depth)
        values.append(affine_fit_abs_rel(out, depth))
    return np.array(values)


@pytest.fixture(scope="module")
def routes():
    if EGL_PROBLEM is not None:
        pytest.skip(f"no OpenGL: {EGL_PROBLEM}")
    return {name: render_route(name) for name in WORLD_NAMES}


def analytic_depth(height=120, width=160):
    """A floor seen from 1.5 m up to its horizon at mid-image, sky above, a wall 4 m ahead
    filling the middle third of the columns down from the upper quarter."""
    rows = np.arange(height, dtype=np.float64)[:, None] - (height - 1) / 2
    focal = width / 2
    with np.errstate(divide="ignore"):
        floor = np.where(rows > 0, 1.5 * focal / rows, np.nan)
    depth = np.broadcast_to(floor, (height, width)).copy()
    wall = np.s_[height // 4:, width // 3: 2 * width // 3]
    depth[wall] = np.fmin(depth[wall], 4.0)
    return depth.astype(np.float32)


def spearman(a, b):
    """Rank correlation of two 1-D arrays (ties broken by order; fine for continuous data)."""
    ra, rb = (np.argsort(np.argsort(x)).astype(float) for x in (a, b))
    return float(np.corrcoef(ra, rb)[0, 1])


# ---- calibration on the simulator's worlds ----------------------------------------------------


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_affine_fit_error_is_that_of_a_small_network(routes, name):
    values = calibration_abs_rel(routes[name])
    assert 0.05 <= np.median(values) <= 0.10, values
    assert values.min() > 0.02, values


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_metric_is_zero_for_exact_disparity(routes, name):
    depths = routes[name]
    with np.errstate(divide="ignore"):
        exact = [affine_fit_abs_rel(1.0 / d, d) for d in depths]
    assert max(exact) < 1e-4


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_nearer_pixels_get_larger_output(routes, name):
    network = SyntheticNetwork(seed=3)
    for depth in routes[name][::3]:
        out = network(depth)
        known = np.isfinite(depth) & (depth <= 40.0)
        assert spearman(out[known][::7], 1.0 / depth[known][::7]) > 0.95


def test_sky_is_near_zero_and_output_is_finite_and_non_negative(routes):
    network = SyntheticNetwork(seed=5)
    for depth in routes["dome"]:
        out = network(depth)
        assert out.dtype == np.float32 and out.shape == depth.shape
        assert np.isfinite(out).all() and (out >= 0).all()
        sky = np.isnan(depth).astype(np.uint8)
        # sky well away from the scene's blurred edges
        open_sky = cv2.erode(sky, np.ones((21, 21), np.uint8)).astype(bool)
        assert open_sky.any()
        assert out[open_sky].max() < 0.05 * np.percentile(out, 99)


# ---- behaviour over time and seeds ------------------------------------------------------------


def test_same_seed_same_outputs_and_different_seeds_differ():
    depth = analytic_depth()
    networks = [SyntheticNetwork(seed=s) for s in (1, 1, 2)]
    outs = [[network(depth) for _ in range(3)] for network in networks]
    for a, b in zip(outs[0], outs[1]):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(outs[0][0], outs[2][0])


def test_output_drifts_but_the_error_stays_bounded_over_many_frames():
    depth = analytic_depth()
    network = SyntheticNetwork(seed=7)
    outs = [network(depth) for _ in range(200)]
    values = np.array([affine_fit_abs_rel(out, depth) for out in outs])
    assert not np.allclose(outs[0], outs[1])  # frame-to-frame change
    assert np.abs(outs[-1] / outs[0] - 1).max() > 0.05  # drift over the run
    assert values.max() < 0.2 and np.median(values) > 0.02, values
    assert all(np.isfinite(out).all() and (out >= 0).all() for out in outs)


def test_unknown_depth_is_treated_as_far():
    depth = analytic_depth()
    depth[0, :5] = [0.0, -2.0, np.inf, -np.inf, 1e6]
    out = SyntheticNetwork(seed=1)(depth)
    assert np.isfinite(out).all() and (out >= 0).all()
    assert out[0, :5].max() < 0.05 * np.percentile(out, 99)


def test_integer_depth_is_accepted_as_metres():
    out = SyntheticNetwork()(np.full((30, 40), 3, dtype=np.uint16))
    assert out.dtype == np.float32 and out.shape == (30, 40) and np.isfinite(out).all()


# ---- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize("depth", [
    np.ones(5), np.ones((2, 3, 4)), np.ones((0, 4)), np.ones((4, 4), dtype=bool),
    np.ones((4, 4), dtype=complex), np.array([["a", "b"]]),
])
def test_bad_depth_images_are_refused(depth):
    with pytest.raises(ValueError, match="depth must be"):
        SyntheticNetwork()(depth)


@pytest.mark.parametrize("field, value", [
    ("gamma_spread", -0.1), ("field_sigma", 2.0), ("field_grid", 1), ("edge_blur", -1.0),
    ("far_depth", 0.0), ("gamma_frames", 0.5), ("max_shift", math.nan), ("field_grid", 2.5),
])
def test_bad_options_are_refused(field, value):
    with pytest.raises(OptionError, match=field):
        SyntheticDepthOptions(**{field: value})


def test_metric_refuses_mismatched_shapes_and_is_nan_without_pixels():
    with pytest.raises(ValueError, match="shapes differ"):
        affine_fit_abs_rel(np.ones((2, 2)), np.ones((2, 3)))
    assert math.isnan(affine_fit_abs_rel(np.ones((2, 2)), np.full((2, 2), np.nan)))


if __name__ == "__main__":
    if EGL_PROBLEM is not None:
        raise SystemExit(f"no OpenGL: {EGL_PROBLEM}")
    print("world   median  min    max    (affine-fit AbsRel per view, seed 0)")
    for world_name in WORLD_NAMES:
        v = calibration_abs_rel(render_route(world_name))
        print(f"{world_name:7} {np.median(v):.3f}   {v.min():.3f}  {v.max():.3f}")


# ---- the realistic profile's failure modes -------------------------------------------------

def _quiet(**changes) -> SyntheticDepthOptions:
    """No drift, error field, blur or shift: only the failure mode under test acts."""
    base = dict(gamma_spread=0.0, field_sigma=0.0, edge_blur=0.0, scale_spread=0.0,
                max_shift=0.0, thin_width_px=0.0, texture_copy=0.0)
    base.update(changes)
    return SyntheticDepthOptions(**base)


def _wall_with_poles(widths):
    """A wall 8 m away with poles 3 m away, ``widths`` pixels wide, 40 px apart."""
    depth = np.full((120, 320), 8.0, np.float32)
    for k, width in enumerate(widths):
        depth[:, 40 + 40 * k: 40 + 40 * k + width] = 3.0
    return depth


def test_poles_narrower_than_the_thin_width_are_lost_and_wider_ones_kept():
    # 640 px reference width: thin_width_px 8 is 4 px on this 320 px image
    depth = _wall_with_poles([2, 3, 6, 9])
    ideal = SyntheticNetwork(_quiet())(depth)
    out = SyntheticNetwork(_quiet(thin_width_px=8.0))(depth)
    wall = float(ideal[60, 10])
    for k, width in enumerate([2, 3, 6, 9]):
        pole = out[60, 40 + 40 * k: 40 + 40 * k + width]
        if width < 4:
            assert pole == pytest.approx(wall, rel=1e-5)  # the wall behind it
        else:
            assert pole == pytest.approx(ideal[60, 40 + 40 * k], rel=1e-5)
    # far side: nothing nearer than its surroundings changes
    assert np.allclose(out[:, :38], ideal[:, :38])


def test_texture_on_a_flat_wall_reads_as_relief_in_proportion_to_texture_copy():
    depth = np.full((120, 160), 5.0, np.float32)
    rng = np.random.default_rng(0)
    image = np.repeat(rng.integers(40, 220, (120, 160, 1), dtype=np.uint8), 3, axis=2)
    flat = SyntheticNetwork(_quiet())(depth, image)
    assert np.ptp(flat) == pytest.approx(0.0, abs=1e-6)
    spreads = [np.log(SyntheticNetwork(_quiet(texture_copy=c))(depth, image)).std()
               for c in (0.05, 0.1)]
    assert spreads[0] > 0.005
    assert spreads[1] == pytest.approx(2 * spreads[0], rel=0.01)


def test_texture_copy_needs_the_image():
    with pytest.raises(ValueError, match="texture_copy needs the frame's image"):
        SyntheticNetwork(_quiet(texture_copy=0.1))(np.ones((20, 30), np.float32))
    with pytest.raises(ValueError, match="RGB uint8 of shape"):
        SyntheticNetwork(_quiet(texture_copy=0.1))(np.ones((20, 30), np.float32),
                                                   np.zeros((20, 30), np.uint8))


def test_the_ideal_profile_is_the_stand_in_without_failure_modes():
    options = SyntheticDepthOptions()
    assert options.thin_width_px > 0 and options.texture_copy > 0
    ideal = options.for_profile("ideal")
    assert (ideal.thin_width_px, ideal.texture_copy) == (0.0, 0.0)
    assert options.for_profile("realistic") is options
    assert SyntheticNetwork().options == ideal
    with pytest.raises(ValueError, match="ideal or realistic"):
        options.for_profile("perfect")
