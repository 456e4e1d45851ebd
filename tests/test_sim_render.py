"""The simulated camera: real OpenGL (EGL, Mesa's llvmpipe without a GPU) against the geometry."""

import math

import cv2
import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from drivers.sim.options import WORLD_NAMES
from drivers.sim.render import SKY_RGB, RenderError, Renderer, create_context
from drivers.sim.world import build_world

CAMERA = PinholeCamera.from_hfov(640, 480, math.radians(90.0))
FAR = 100.0


def _egl_problem():
    try:
        create_context().release()
    except RenderError as error:
        return str(error)
    return None


EGL_PROBLEM = _egl_problem()
needs_egl = pytest.mark.skipif(EGL_PROBLEM is not None, reason=f"no OpenGL: {EGL_PROBLEM}")


@pytest.fixture(scope="module", params=WORLD_NAMES)
def renderer(request):
    if EGL_PROBLEM is not None:
        pytest.skip(f"no OpenGL: {EGL_PROBLEM}")
    with Renderer(build_world(request.param, seed=0), CAMERA, far=FAR) as r:
        yield r


@pytest.fixture(scope="module")
def sewer_renderer():
    if EGL_PROBLEM is not None:
        pytest.skip(f"no OpenGL: {EGL_PROBLEM}")
    with Renderer(build_world("sewer", seed=0), CAMERA) as r:
        yield r


def look(position, yaw, pitch=0.0, roll=0.0):
    """Optical-frame pose of a camera on a body at ``position`` with heading ``yaw``, nose-up
    ``pitch`` and right-wing-down ``roll``, radians."""
    R_W_B = rot_z(yaw) @ so3_exp(np.array([0.0, -pitch, 0.0])) @ so3_exp(np.array([roll, 0, 0]))
    return make_pose(R_W_B @ R_BODY_CAMERA, np.asarray(position, dtype=float))


def route_views(world):
    """Poses along the routes: at each end, looking along the planned path, slightly down."""
    poses = []
    for route in world.routes[:3]:
        path = world.find_path(route.start[:2], route.goal[:2], 1.0)
        for here, there in ((path[0], path[1]), (path[-1], path[-2])):
            yaw = math.atan2(*(there - here)[::-1])
            poses.append(look([*here, route.cruise_height], yaw, pitch=-0.15))
    return poses


# ---- an independent ray caster over the world's primitives -----------------------------------


def ray_boxes(origin, directions, lo, hi):
    """Entry distance of rays into axis-aligned boxes (slab method; panels are boxes of zero
    thickness), inf where missed: (rays, boxes)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo[None] - origin) / directions[:, None]
        t2 = (hi[None] - origin) / directions[:, None]
    parallel = directions[:, None] == 0.0
    inside = (origin >= lo[None]) & (origin <= hi[None])
    t_near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = t_near.max(axis=2), t_far.min(axis=2)
    return np.where((enter <= leave) & (enter > 0.0), enter, np.inf)


def ray_cylinders(origin, directions, cylinders):
    """Distance of rays to vertical cylinders standing on the floor (side or top), inf if none."""
    best = np.full(len(directions), np.inf)
    for c in cylinders:
        o, d = origin[:2] - c.centre, directions[:, :2]
        a, b, k = (d * d).sum(1), 2 * (d @ o), o @ o - c.radius**2
        disc = b * b - 4 * a * k
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
            z = origin[2] + t * directions[:, 2]
            side = np.where((disc >= 0) & (t > 0) & (z >= 0) & (z <= c.height), t, np.inf)
            t_top = (c.height - origin[2]) / directions[:, 2]
            xy = origin[:2] + t_top[:, None] * d
            top = np.where((t_top > 0) & (np.linalg.norm(xy - c.centre, axis=1) <= c.radius),
                           t_top, np.inf)
        best = np.minimum(best, np.minimum(side, top))
    return best


def ray_cast_depth(world, T_W_C, pixels):
    """z-depth of the first surface (floor, panels, boxes, trunks) through each pixel centre."""
    rays_C = np.column_stack([(pixels[:, 0] - CAMERA.cx) / CAMERA.fx,
                              (pixels[:, 1] - CAMERA.cy) / CAMERA.fy, np.ones(len(pixels))])
    directions = rays_C @ T_W_C[:3, :3].T  # z_C = 1, so the ray parameter is the z-depth
    origin = T_W_C[:3, 3]
    boxes = [world.floor, *world.boxes]
    t = ray_boxes(origin, directions, np.array([b.lo for b in boxes]),
                  np.array([b.hi for b in boxes])).min(axis=1)
    t = np.minimum(t, ray_cylinders(origin, directions, world.cylinders))
    return np.where(t <= FAR, t, np.nan)


# ---- tests ------------------------------------------------------------------------------------


def test_missing_egl_library_is_named_in_the_error():
    with pytest.raises(RenderError, match=r"EGL is unavailable \(could not load "
                                          r"libEGL-missing\.so\.9\).*libegl1"):
        Renderer(build_world("dome"), CAMERA, libegl="libEGL-missing.so.9")


def test_camera_facing_a_wall_sees_its_distance(sewer_renderer):
    # room A's west wall is the plane x = 0
    _, depth = sewer_renderer.render(look([3.25, 3.0, 1.5], yaw=math.pi))
    assert depth[240, 320] == pytest.approx(3.25, abs=1e-4)
    centre = depth[200:280, 280:360]  # the wall is square to the optical axis: all at 3.25 m
    np.testing.assert_allclose(centre, 3.25, atol=1e-4)


@needs_egl
def test_depth_matches_an_independent_ray_cast(renderer):
    world = renderer.world
    rng = np.random.default_rng(1)
    route = world.routes[0]
    here = np.array([*route.start[:2], 1.2])
    poses = route_views(world)[:2] + [look(here, yaw=0.7, pitch=0.35, roll=0.2)]
    for T_W_C in poses:
        _, depth = renderer.render(T_W_C)
        pixels = np.column_stack([rng.integers(0, CAMERA.width, 3000),
                                  rng.integers(0, CAMERA.height, 3000)])
        expected = ray_cast_depth(world, T_W_C, pixels.astype(float))
        rendered = depth[pixels[:, 1], pixels[:, 0]]
        both = np.isfinite(expected) & np.isfinite(rendered)
        agree_on_hit = np.isfinite(expected) == np.isfinite(rendered)
        close = np.abs(rendered - expected) <= 0.01 + 0.005 * expected
        assert agree_on_hit.mean() >= 0.995  # at most a few silhouette pixels differ
        assert close[both].mean() >= 0.99
        assert np.median(np.abs(rendered - expected)[both]) < 1e-3


@needs_egl
def test_open_sky_has_no_depth_and_the_ground_has():
    dome = build_world("dome")
    with Renderer(dome, CAMERA, far=FAR) as renderer:
        rgb, depth = renderer.render(look([0.0, 0.0, 1.5], yaw=0.3, pitch=0.5))
    sky = ~np.isfinite(depth)
    assert sky[:40].mean() > 0.5  # looking up: the top rows are mostly sky
    assert np.isfinite(depth[-40:]).all()  # the bottom rows: ground and trunks, pitch 29 deg
    np.testing.assert_allclose(rgb[sky].mean(axis=0), np.array(SKY_RGB) * 255, atol=1.0)
    assert np.nanmin(depth) > 0.0


def spread_corners(rgb):
    """Shi-Tomasi corners as a feature tracker finds them, and how many cells of a 4x4 grid
    hold at least one."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=400, qualityLevel=0.01, minDistance=10)
    corners = np.zeros((0, 2)) if corners is None else corners.reshape(-1, 2)
    cells = {(int(x * 4 / CAMERA.width), int(y * 4 / CAMERA.height)) for x, y in corners}
    return len(corners), len(cells)


@needs_egl
def test_textures_give_a_tracker_well_spread_corners(renderer):
    for T_W_C in route_views(renderer.world):
        count, cells = spread_corners(renderer.render(T_W_C)[0])
        assert count >= 100 and cells >= 12, (renderer.world.name, count, cells)


@needs_egl
def test_rendering_is_repeatable_and_rows_start_at_the_top(renderer):
    T_W_C = route_views(renderer.world)[0]
    rgb, depth = renderer.render(T_W_C)
    rgb2, depth2 = renderer.render(T_W_C)
    assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    np.testing.assert_array_equal(rgb, rgb2)
    np.testing.assert_array_equal(depth, depth2)
    # pitched down, the floor is nearest at the bottom of the image
    assert np.nanmedian(depth[-20:]) < np.nanmedian(depth[220:260])


@pytest.mark.parametrize("pose, message", [
    (np.full((4, 4), np.nan), "finite"),
    (np.eye(3), "4x4"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "rigid"),
    (np.diag([-1.0, 1.0, 1.0, 1.0]), "rigid"),
])
def test_bad_poses_are_refused(sewer_renderer, pose, message):
    with pytest.raises(ValueError, match=message):
        sewer_renderer.render(pose)


@pytest.mark.parametrize("near, far", [(0.0, 10.0), (1.0, 0.5), (0.1, np.inf)])
def test_bad_clip_planes_are_refused(near, far):
    with pytest.raises(ValueError, match="near"):
        Renderer(build_world("sewer"), CAMERA, near=near, far=far)
