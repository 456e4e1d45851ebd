"""The simulated worlds: built from a seed, routes a 1 m robot can fly, exact clearance; the
realistic profile's thin obstacles, low-texture walls and dust."""

import functools
import hashlib
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from drivers.sim.options import PROFILES, WORLD_NAMES
from drivers.sim.world import (
    LOW_TEXTURE_MATERIAL,
    MINE_VISIBILITY,
    PIPE_DIAMETERS,
    ROBOT_RADIUS,
    TRIPOD_LEG_ANGLE,
    build_world,
)


def geometry_of(world):
    """Everything that defines a world, as plain arrays and strings."""
    return (
        world.bounds,
        [(b.lo.tolist(), b.hi.tolist(), b.material, b.facing) for b in world.boxes],
        [(c.centre.tolist(), c.radius, c.height, c.material) for c in world.cylinders],
        [(r.name, r.start.tolist(), r.goal.tolist(), r.cruise_height) for r in world.routes],
        None if world.heights is None else world.heights.tolist(),
        [(r.a.tolist(), r.b.tolist(), r.radius, r.material) for r in world.rods],
        (world.profile, world.visibility, world.haze_rgb),
    )


@functools.cache
def world(name, seed=0, profile="ideal"):
    """Worlds are immutable: build each once per test session."""
    return build_world(name, seed, profile)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("name", WORLD_NAMES)
def test_same_seed_builds_the_same_world_and_another_seed_a_different_one(name, profile):
    assert geometry_of(build_world(name, 3, profile)) == geometry_of(world(name, 3, profile))
    assert geometry_of(world(name, 3, profile)) != geometry_of(world(name, 4, profile))


# sha256 of repr() of the first five entries of geometry_of, as the code before the realistic
# profile built them (commit 5b2d9ae): the ideal profile must keep building exactly these.
TODAYS_WORLDS = {
    ("mine", 0): "57d78a25178fc0f6", ("mine", 1): "9cc36b5224176593",
    ("mine", 7): "9d5f7f20a6ee2f57", ("sewer", 0): "74485b4068a94652",
    ("sewer", 1): "d9de11384946fd46", ("sewer", 7): "5798b988f9ab165c",
    ("dome", 0): "108a60c0a2c18c60", ("dome", 1): "20bf0ed91bf0e862",
    ("dome", 7): "f314352e69b628b3",
}


@pytest.mark.parametrize("name, seed", sorted(TODAYS_WORLDS))
def test_ideal_profile_builds_todays_worlds_bit_for_bit(name, seed):
    ideal = world(name, seed)
    digest = hashlib.sha256(repr(geometry_of(ideal)[:5]).encode()).hexdigest()[:16]
    assert digest == TODAYS_WORLDS[name, seed]
    assert geometry_of(build_world(name, seed, profile="ideal")) == geometry_of(ideal)
    assert (ideal.profile, ideal.rods, ideal.visibility, ideal.haze_rgb) == ("ideal", (), None,
                                                                             None)
    assert LOW_TEXTURE_MATERIAL not in ideal.materials


def test_unknown_world_is_refused_with_the_known_names():
    with pytest.raises(ValueError, match="unknown world 'cave'.*mine, sewer, dome"):
        build_world("cave")


@pytest.mark.parametrize("profile", ["", "Realistic", None])
def test_unknown_profile_is_refused_with_the_choices(profile):
    with pytest.raises(ValueError, match=r"unknown profile .*choose one of: ideal, realistic"):
        build_world("mine", 0, profile)


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_bad_seed_is_refused(seed):
    with pytest.raises(ValueError, match="seed"):
        build_world("dome", seed)


def samples_along(path, step=0.02):
    """Points every ``step`` metres along an (M, 2) polyline."""
    pieces = [a + np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)[:, None]
              * (b - a) for a, b in zip(path[:-1], path[1:])]
    return np.concatenate(pieces)


@pytest.mark.parametrize("profile", PROFILES)
@pytest.mark.parametrize("seed", [0, 1, 7])
@pytest.mark.parametrize("name", WORLD_NAMES)
def test_every_route_has_a_path_with_room_for_a_1m_robot(name, seed, profile):
    w = world(name, seed, profile)
    assert 5 <= len(w.routes) <= 6  # as in the paper
    for route in w.routes:
        assert route.start[2] == 0.0 and route.goal[2] == route.cruise_height
        ends = np.array([route.start, route.goal, [*route.start[:2], route.cruise_height]])
        assert np.all(w.obstacle_clearance(ends) >= ROBOT_RADIUS), route.name
        path = w.find_path(route.start[:2], route.goal[:2], ROBOT_RADIUS)
        assert path is not None, route.name
        np.testing.assert_array_equal(path[0], route.start[:2])
        np.testing.assert_array_equal(path[-1], route.goal[:2])
        xy = samples_along(path)
        flown = np.column_stack([xy, np.full(len(xy), route.cruise_height)])
        assert w.obstacle_clearance(flown).min() >= ROBOT_RADIUS, route.name


# ---- the realistic profile ----------------------------------------------------------------------


def thin_obstacles(realistic):
    """The poles (cylinders the ideal world lacks) and the tripod's rods of a realistic world."""
    ideal = world(realistic.name, realistic.seed)
    return realistic.cylinders[len(ideal.cylinders):], realistic.rods


@pytest.mark.parametrize("seed", [0, 1, 7])
@pytest.mark.parametrize("name", WORLD_NAMES)
def test_realistic_worlds_add_poles_and_a_tripod_in_the_way_of_the_routes(name, seed):
    ideal, realistic = world(name, seed), world(name, seed, "realistic")
    assert realistic.profile == "realistic"
    # the same world underneath: the ideal world's trunks, and its surfaces (walls may be cut
    # into stretches, so compare the clearance away from the new obstacles)
    assert geometry_of(realistic)[2][:len(ideal.cylinders)] == geometry_of(ideal)[2]
    poles, rods = thin_obstacles(realistic)
    assert len(poles) >= 4
    for pole in poles:
        assert 2 * pole.radius in PIPE_DIAMETERS
        if realistic.heights is not None:  # a pipe from the floor to the ceiling
            i, j = np.floor((pole.centre - realistic.origin) / 0.5).astype(int)
            assert pole.height == realistic.heights[j, i]
    legs, head = rods[:3], rods[3]
    apex = legs[0].b
    for leg in legs:  # three thin legs from the floor, splayed 22 degrees, meeting at the top
        np.testing.assert_array_equal(leg.b, apex)
        axis = leg.b - leg.a
        assert leg.a[2] == 0.0 and leg.radius <= 0.02
        assert math.acos(axis[2] / np.linalg.norm(axis)) == pytest.approx(TRIPOD_LEG_ANGLE)
    assert 1.3 <= apex[2] <= 1.6 and head.radius < 0.1
    np.testing.assert_allclose((head.a[:2] + head.b[:2]) / 2, apex[:2])
    # they matter: the path each route's planner takes in the ideal world runs into one of them
    blocked = 0
    for route in ideal.routes:
        xy = samples_along(ideal.find_path(route.start[:2], route.goal[:2], ROBOT_RADIUS))
        flown = np.column_stack([xy, np.full(len(xy), route.cruise_height)])
        blocked += realistic.obstacle_clearance(flown).min() < ROBOT_RADIUS
    assert blocked >= len(ideal.routes) - 1
    # and nothing else changed: away from them, the clearance is the ideal world's
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = ideal.bounds
    points = rng.uniform([xmin, ymin, 0.0], [xmax, ymax, 6.0], (3000, 3))
    before = ideal.obstacle_clearance(points)
    axes = np.array([*(c.centre for c in poles), apex[:2]])
    far = np.linalg.norm(points[:, None, :2] - axes[None], axis=2).min(axis=1) - 1.0 > before
    assert far.mean() > 0.5
    np.testing.assert_array_equal(realistic.obstacle_clearance(points[far]), before[far])


def rod_surface(a, b, radius, step=0.001):
    """Points at most ``step`` apart covering the surface of the solid cylinder from ``a`` to
    ``b``: side and both flat ends."""
    axis = b - a
    length = np.linalg.norm(axis)
    u = axis / length
    e1 = np.cross([0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0], u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    turns = np.linspace(0, 2 * np.pi, int(np.ceil(2 * np.pi * radius / step)), endpoint=False)
    ring = np.cos(turns)[:, None] * e1 + np.sin(turns)[:, None] * e2
    t = np.linspace(0.0, length, int(np.ceil(length / step)) + 1)
    side = a + t[:, None, None] * u + radius * ring[None]
    radii = np.linspace(0.0, radius, int(np.ceil(radius / step)) + 1)
    disc = (radii[:, None, None] * ring[None]).reshape(-1, 3)
    return np.concatenate([side.reshape(-1, 3), a + disc, b + disc])


def inside_rod(points, a, b, radius):
    """Whether each point lies in the solid cylinder from ``a`` to ``b`` (by its definition)."""
    u = (b - a) / np.linalg.norm(b - a)
    t = (points - a) @ u
    radial = np.linalg.norm(points - a - t[:, None] * u, axis=1)
    return (t >= 0) & (t <= np.linalg.norm(b - a)) & (radial <= radius)


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_clearance_to_the_thin_obstacles_is_exact(name):
    """Against brute force: the nearest of surface points 1 mm apart on every pole and rod,
    beside the ideal world's own clearance; inside a leg or pole it is 0."""
    ideal, realistic = world(name), world(name, 0, "realistic")
    poles, rods = thin_obstacles(realistic)
    rng = np.random.default_rng(2)
    pole = poles[0]
    # queries up to 0.45 m from the pole: along it in the enclosed worlds (whose poles end in
    # the ceiling), round its top in the dome; the pole's surface is sampled 0.7 m beyond them,
    # farther than the pole's side from any of them
    low, high = (pole.height - 1.5, pole.height + 0.3) if realistic.outdoor else (0.5, 2.5)
    solids = [(np.array([*pole.centre, low - 0.7]),
               np.array([*pole.centre, min(pole.height, high + 0.7)]), pole.radius)]
    solids += [(r.a, r.b, r.radius) for r in rods]
    apex = rods[0].b
    queries = np.concatenate([
        rng.uniform([*(pole.centre - 0.4), low], [*(pole.centre + 0.4), high], (300, 3)),
        rng.uniform([*(apex[:2] - 0.8), 0.0], [*(apex[:2] + 0.8), apex[2] + 0.3], (600, 3)),
    ])
    middles = np.array([(a + b) / 2 for a, b, _ in solids])
    np.testing.assert_array_equal(realistic.obstacle_clearance(middles), 0.0)
    inside = np.zeros(len(queries), bool)
    for a, b, radius in solids:
        inside |= inside_rod(queries, a, b, radius)
    np.testing.assert_array_equal(realistic.obstacle_clearance(queries[inside]), 0.0)
    outside = queries[~inside]
    tree = cKDTree(np.concatenate([rod_surface(a, b, r) for a, b, r in solids]))
    brute = np.minimum(tree.query(outside)[0], ideal.obstacle_clearance(outside))
    exact = realistic.obstacle_clearance(outside)
    assert np.all(exact <= brute + 1e-9)  # a surface point is never nearer than the nearest
    assert np.all(brute - exact <= 0.0008)  # nor the nearest farther than the sampling allows
    assert np.sum(exact < 0.3) >= 200  # most of them close to the thin obstacles


def test_realistic_mine_and_sewer_have_low_texture_walls_and_only_the_mine_has_dust():
    for name in WORLD_NAMES:
        realistic = world(name, 0, "realistic")
        walls = [b for b in realistic.boxes if b.lo[2] != b.hi[2]]
        smooth = sum(np.ptp(np.stack([b.lo, b.hi])[:, :2], axis=0).max() * (b.hi[2] - b.lo[2])
                     for b in walls if b.material == LOW_TEXTURE_MATERIAL)
        area = sum(np.ptp(np.stack([b.lo, b.hi])[:, :2], axis=0).max() * (b.hi[2] - b.lo[2])
                   for b in walls)
        if name == "dome":
            assert smooth == 0.0
        else:  # a share of the wall area, from the seed
            assert 0.15 <= smooth / area <= 0.45, (name, smooth / area)
        assert realistic.visibility == (MINE_VISIBILITY if name == "mine" else None)
        assert (realistic.haze_rgb is None) == (name != "mine")


def test_worlds_have_the_papers_shapes_and_sizes():
    mine, sewer, dome = (build_world(name) for name in WORLD_NAMES)
    ceilings = np.unique(mine.heights[mine.heights > 0])
    assert ceilings.max() >= 8.0 and ceilings.min() <= 4.0  # a high cavern, low tunnels
    cavern = mine.heights == ceilings.max()
    assert cavern.sum() * 0.25 >= 25 * 20  # the cavern: >= 500 m^2 (0.5 m cells)
    hallway = sewer.heights == 3.0
    assert hallway.any(axis=0).sum() * 0.5 >= 38  # a hallway at least 38 m long
    assert 3.0 <= hallway.any(axis=1).sum() * 0.5 <= 3.5  # and 3-3.5 m wide
    xmin, ymin, xmax, ymax = dome.bounds
    assert (xmax - xmin, ymax - ymin) == (50.0, 50.0) and dome.outdoor
    assert len(dome.cylinders) >= 30 and len(dome.boxes) >= 5  # trees and pillars


def test_find_path_fails_where_no_path_exists():
    sewer = build_world("sewer")
    route = sewer.routes[0]  # from room A through the 3-3.5 m hallway to room B
    assert sewer.find_path(route.start[:2], route.goal[:2], radius=1.8) is None
    xmin, ymin, xmax, ymax = sewer.bounds
    assert sewer.find_path(route.start[:2], [xmax + 5.0, ymax], 1.0) is None  # in rock
    with pytest.raises(ValueError):
        sewer.find_path(route.start[:2], [np.nan, 0.0], 1.0)
    with pytest.raises(ValueError):
        sewer.find_path(route.start[:2], route.goal[:2], -1.0)


# ---- clearance against geometry known by construction -----------------------------------------


def test_clearance_to_a_trunk_and_over_its_top_in_the_dome():
    dome = build_world("dome")
    trunk = dome.cylinders[0]
    outward = np.array([1.0, 0.0])
    beside = [*(trunk.centre + outward * (trunk.radius + 0.3)), 1.0]
    above = [*trunk.centre, trunk.height + 0.4]
    inside = [*(trunk.centre + outward * trunk.radius * 0.5), 1.0]
    np.testing.assert_allclose(dome.obstacle_clearance(np.array([beside, above, inside])),
                               [0.3, 0.4, 0.0], atol=1e-12)


def test_clearance_to_a_pillar_in_the_dome():
    dome = build_world("dome")
    pillar = dome.boxes[0]
    centre = (pillar.lo + pillar.hi) / 2
    in_front = centre + [pillar.hi[0] - centre[0] + 0.25, 0.0, 0.0]
    in_front[2] = 1.0
    diagonal = np.array([pillar.hi[0] + 0.3, pillar.hi[1] + 0.4, 1.0])
    np.testing.assert_allclose(dome.obstacle_clearance(np.array([in_front, diagonal, centre])),
                               [0.25, 0.5, 0.0], atol=1e-12)


def test_clearance_to_walls_ceiling_and_rock_in_the_sewer():
    sewer = build_world("sewer")  # room A spans x, y >= 0 from the corner (0, 0)
    ceiling = sewer.heights[int(3 / 0.5), int(3 / 0.5)]
    points = np.array([
        [0.7, 3.0, 1.0],  # 0.7 m from the west wall
        [0.3, 0.4, 1.0],  # in the corner: 0.3 m from one wall, 0.4 m from the other
        [3.0, 3.0, ceiling - 0.2],  # 0.2 m under the ceiling
        [-1.0, 3.0, 1.0],  # inside the wall's rock
        [3.0, 3.0, ceiling + 0.5],  # above the ceiling
    ])
    np.testing.assert_allclose(sewer.obstacle_clearance(points), [0.7, 0.3, 0.2, 0.0, 0.0],
                               atol=1e-12)


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_clearance_is_vectorised(name):
    world = build_world(name)
    rng = np.random.default_rng(0)
    xmin, ymin, xmax, ymax = world.bounds
    points = rng.uniform([xmin, ymin, 0.0], [xmax, ymax, 6.0], (5000, 3))
    together = world.obstacle_clearance(points)
    assert together.shape == (5000,)
    one_by_one = [world.obstacle_clearance(p)[0] for p in points[:50]]
    np.testing.assert_array_equal(together[:50], one_by_one)
    assert np.all(together >= 0.0) and np.any(together > 1.0)
    if world.heights is not None:  # enclosed: some of the points fall in rock
        assert np.any(together == 0.0)


@pytest.mark.parametrize("points", [np.zeros((4, 2)), np.array([[0.0, np.inf, 1.0]])])
def test_clearance_refuses_bad_points(points):
    with pytest.raises(ValueError):
        build_world("mine").obstacle_clearance(points)
