"""The simulated camera: real OpenGL (EGL, Mesa's llvmpipe without a GPU) against the geometry."""

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from autonomy.vins.frontend import FrontendOptions
from drivers.sim.options import WORLD_NAMES
from drivers.sim.render import SKY_RGB, RenderError, Renderer, create_context
from drivers.sim.world import LOW_TEXTURE_MATERIAL, build_world

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


@pytest.fixture(scope="module", params=WORLD_NAMES)
def realistic_renderer(request):
    if EGL_PROBLEM is not None:
        pytest.skip(f"no OpenGL: {EGL_PROBLEM}")
    with Renderer(build_world(request.param, seed=0, profile="realistic"), CAMERA, far=FAR) as r:
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


def ray_rods(origin, directions, rods):
    """Distance of rays to solid cylinders of any direction (side or flat ends), inf if none."""
    best = np.full(len(directions), np.inf)
    for rod in rods:
        length = np.linalg.norm(rod.b - rod.a)
        u = (rod.b - rod.a) / length
        o_along, d_along = (origin - rod.a) @ u, directions @ u
        o_across = origin - rod.a - o_along * u
        d_across = directions - d_along[:, None] * u
        a, b = (d_across**2).sum(1), 2 * d_across @ o_across
        disc = b * b - 4 * a * (o_across @ o_across - rod.radius**2)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
            along = o_along + t * d_along
            side = np.where((disc >= 0) & (t > 0) & (along >= 0) & (along <= length), t, np.inf)
            for end in (0.0, length):
                t_end = (end - o_along) / d_along
                off_axis = np.linalg.norm(o_across + t_end[:, None] * d_across, axis=1)
                side = np.minimum(side, np.where((t_end > 0) & (off_axis <= rod.radius), t_end,
                                                 np.inf))
        best = np.minimum(best, side)
    return best


def ray_cast_depth(world, T_W_C, pixels):
    """z-depth of the first surface (floor, panels, boxes, trunks and poles, rods) through each
    pixel centre."""
    rays_C = np.column_stack([(pixels[:, 0] - CAMERA.cx) / CAMERA.fx,
                              (pixels[:, 1] - CAMERA.cy) / CAMERA.fy, np.ones(len(pixels))])
    directions = rays_C @ T_W_C[:3, :3].T  # z_C = 1, so the ray parameter is the z-depth
    origin = T_W_C[:3, 3]
    boxes = [world.floor, *world.boxes]
    t = ray_boxes(origin, directions, np.array([b.lo for b in boxes]),
                  np.array([b.hi for b in boxes])).min(axis=1)
    t = np.minimum(t, ray_cylinders(origin, directions, world.cylinders))
    t = np.minimum(t, ray_rods(origin, directions, world.rods))
    return np.where(t <= FAR, t, np.nan)


def assert_depth_matches_ray_cast(world, T_W_C, depth, pixels):
    """The rendered depth at ``pixels`` (x, y) against the ray cast: the same pixels hit
    something, and it lies within 1 cm + 0.5 % (facets, float32) of the true surface."""
    expected = ray_cast_depth(world, T_W_C, pixels.astype(float))
    rendered = depth[pixels[:, 1], pixels[:, 0]]
    both = np.isfinite(expected) & np.isfinite(rendered)
    agree_on_hit = np.isfinite(expected) == np.isfinite(rendered)
    close = np.abs(rendered - expected) <= 0.01 + 0.005 * expected
    assert agree_on_hit.mean() >= 0.995  # at most a few silhouette pixels differ
    assert close[both].mean() >= 0.99
    assert np.median(np.abs(rendered - expected)[both]) < 1e-3


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
        assert_depth_matches_ray_cast(world, T_W_C, depth, pixels)


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


def test_the_four_channel_read_is_the_same_colour_with_an_opaque_alpha(renderer):
    T_W_C = route_views(renderer.world)[0]
    rgb, depth = renderer.render(T_W_C)
    rgba, depth4 = renderer.render(T_W_C, alpha=True)
    assert rgba.shape == (480, 640, 4)
    np.testing.assert_array_equal(rgba[..., :3], rgb)
    assert (rgba[..., 3] == 255).all()
    np.testing.assert_array_equal(depth4, depth)


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


# ---- the realistic profile ----------------------------------------------------------------------


def facing(world, target_xy, distance):
    """The camera at flight height ``distance`` from ``target_xy``, level, looking at it, from
    the side with the most clearance. The realistic profile keeps 2.8 m round every pole and
    tripod clear at flight height, so at 2.5 m nothing stands between."""
    headings = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)
    positions = np.column_stack([target_xy + distance * np.column_stack(
        [np.cos(headings), np.sin(headings)]), np.full(16, world.cruise_height)])
    k = int(np.argmax(world.obstacle_clearance(positions)))
    return look(positions[k], headings[k] + math.pi), positions[k]


@needs_egl
def test_a_pole_in_view_is_drawn_at_its_distance(realistic_renderer):
    world = realistic_renderer.world
    pole = world.cylinders[-1]  # the realistic profile's poles come last
    distance = 2.5
    T_W_C, position = facing(world, pole.centre, distance)
    _, depth = realistic_renderer.render(T_W_C)
    # a level camera looking at the axis: the pole covers the columns |x_n| < tan(asin(r / D))
    # round the centre, and pixel x_n's ray meets its circle at z-depth
    # (D - sqrt(r^2 (1 + x_n^2) - x_n^2 D^2)) / (1 + x_n^2)
    columns = np.arange(CAMERA.width)
    x_n = (columns - CAMERA.cx) / CAMERA.fx
    half_width = math.tan(math.asin(pole.radius / distance))
    on = np.abs(x_n) < half_width - 1.0 / CAMERA.fx  # a pixel inside the silhouette
    beside = (np.abs(x_n) > half_width + 1.0 / CAMERA.fx) & (np.abs(x_n) < 0.2)
    assert on.sum() >= 2 * CAMERA.fx * pole.radius / distance - 3  # 3 px or more
    front = (distance - np.sqrt(pole.radius**2 * (1 + x_n[on]**2) - x_n[on]**2 * distance**2)) \
        / (1 + x_n[on]**2)
    # the facets stray at most 1 % of r from the circle, radially: along a ray meeting the
    # circle at incidence i, 1 % of r / cos(i)
    sin_i = np.abs(x_n[on]) * distance / np.sqrt(1 + x_n[on]**2) / pole.radius
    tolerance = 0.01 * pole.radius / np.sqrt(1 - sin_i**2) + 1e-4
    rows = depth[200:280]  # the pole's middle: about 1.5 m +- 0.6 m high
    assert np.all(np.abs(rows[:, on] - front) <= tolerance)
    assert not np.any(rows[:, beside] <= distance + 1.0)  # beside it, what lies behind, or sky
    # and the ray cast through the primitives agrees, pole and all
    v, u = np.mgrid[200:280, 300:340]
    assert_depth_matches_ray_cast(world, T_W_C, depth, np.column_stack([u.ravel(), v.ravel()]))


@needs_egl
def test_realistic_depth_matches_the_ray_cast_at_poles_and_the_tripod(realistic_renderer):
    world = realistic_renderer.world
    rng = np.random.default_rng(3)
    apex = world.rods[0].b
    poses = route_views(world)[:2] + [facing(world, apex[:2], 2.5)[0],
                                      facing(world, world.cylinders[-2].centre, 4.0)[0]]
    for T_W_C in poses:
        _, depth = realistic_renderer.render(T_W_C)
        pixels = np.column_stack([rng.integers(0, CAMERA.width, 3000),
                                  rng.integers(0, CAMERA.height, 3000)])
        assert_depth_matches_ray_cast(world, T_W_C, depth, pixels)
    # the tripod: every pixel on its head and legs or within 3 pixels of them
    T_W_C = poses[2]
    _, depth = realistic_renderer.render(T_W_C)
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    rays = np.column_stack([((u - CAMERA.cx) / CAMERA.fx).ravel(),
                            ((v - CAMERA.cy) / CAMERA.fy).ravel(), np.ones(u.size)])
    tripod = (ray_rods(T_W_C[:3, 3], rays @ T_W_C[:3, :3].T, world.rods) < 3.5) \
        .reshape(u.shape)
    assert tripod.sum() >= 1000  # the legs and head cover a thousand pixels or more
    around = cv2.dilate(tripod.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    assert_depth_matches_ray_cast(world, T_W_C, depth, np.column_stack([u[around], v[around]]))


@needs_egl
def test_mine_dust_fades_contrast_as_exp_of_distance_over_visibility():
    world = build_world("mine", 0, "realistic")
    clear = replace(world, visibility=None, haze_rgb=None)
    T_W_C = route_views(world)[1]  # down a tunnel into the cavern: 2 to 40 m
    with Renderer(world, CAMERA, far=FAR) as hazy, Renderer(clear, CAMERA, far=FAR) as clean:
        rgb, depth = hazy.render(T_W_C)
        rgb_clear, depth_clear = clean.render(T_W_C)
    np.testing.assert_array_equal(depth, depth_clear)  # the depth is the surface's, dust or not
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    distance = depth * np.sqrt(1 + ((u - CAMERA.cx) / CAMERA.fx)**2
                               + ((v - CAMERA.cy) / CAMERA.fy)**2)
    grey, grey_clear = rgb.mean(axis=2), rgb_clear.mean(axis=2)
    # RMS contrast in 1 m shells of distance, with and without dust
    shells, ratios = [], []
    for near in np.arange(2.0, 25.0):
        shell = (distance >= near) & (distance < near + 1.0)
        if shell.sum() >= 2000 and grey_clear[shell].std() >= 5.0:
            shells.append(np.exp(-distance[shell] / world.visibility).mean())
            ratios.append(grey[shell].std() / grey_clear[shell].std())
    shells, ratios = np.array(shells), np.array(ratios)
    assert len(shells) >= 15 and shells.min() < 0.15  # out to beyond 20 m
    np.testing.assert_allclose(ratios, shells, rtol=0.05, atol=0.005)
    # far off, the dust's own colour
    far = distance > 30.0
    assert far.sum() > 1000
    haze = np.mean(world.haze_rgb) * 255
    assert np.all(np.abs(grey[far] - haze) <= math.exp(-3.0) * 255 + 1.0)


def wall_views(world, material, distance=2.0):
    """Level views ``distance`` square in front of the middle of each wall stretch of
    ``material`` at least 3 m long and 3 m high."""
    for box in world.boxes:
        if box.material != material or box.lo[2] > 0.0 or box.hi[2] < 3.0:
            continue
        across = 0 if box.lo[0] == box.hi[0] else 1
        if box.lo[across] != box.hi[across] or box.hi[1 - across] - box.lo[1 - across] < 3.0:
            continue
        normal = np.zeros(2)
        normal[across] = box.facing
        middle = (box.lo[:2] + box.hi[:2]) / 2
        yield look([*(middle + distance * normal), 1.5], math.atan2(-normal[1], -normal[0]))


@needs_egl
@pytest.mark.parametrize("name, textured", [("mine", "rock"), ("sewer", "brick")])
def test_low_texture_walls_give_the_tracker_few_corners(name, textured):
    """Two walls side by side in one frame, seen square from 2 m: the front-end's Shi-Tomasi
    detector (its own settings) finds its corners on the textured wall, hardly any on the
    smooth one, whose strongest corner response is a hundredth of the textured wall's."""
    world = build_world(name, 0, "realistic")
    crops = {}
    with Renderer(world, CAMERA, far=FAR) as renderer:
        for material in (LOW_TEXTURE_MATERIAL, textured):
            for T_W_C in wall_views(world, material):
                rgb, depth = renderer.render(T_W_C)
                if np.all(np.abs(depth[140:340, 220:420] - 2.0) < 0.01):  # all wall
                    crops[material] = cv2.cvtColor(rgb[140:340, 220:420], cv2.COLOR_RGB2GRAY)
                    break
    smooth, rough = crops[LOW_TEXTURE_MATERIAL], crops[textured]
    frontend = FrontendOptions()
    corners = cv2.goodFeaturesToTrack(np.hstack([smooth, rough]), frontend.max_features,
                                      frontend.quality_level, frontend.min_distance,
                                      blockSize=frontend.block_size).reshape(-1, 2)
    on_smooth = int(np.sum(corners[:, 0] < smooth.shape[1]))
    assert len(corners) - on_smooth >= 20 and on_smooth <= 2, (on_smooth, len(corners))
    strongest = [cv2.cornerMinEigenVal(image, frontend.block_size).max()
                 for image in (smooth, rough)]
    assert strongest[0] < 0.01 * strongest[1]
