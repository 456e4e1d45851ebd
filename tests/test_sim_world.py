"""The simulated worlds: built from a seed, routes a 1 m robot can fly, exact clearance."""

import numpy as np
import pytest

from drivers.sim.options import WORLD_NAMES
from drivers.sim.world import ROBOT_RADIUS, build_world


def geometry_of(world):
    """Everything that defines a world, as plain arrays and strings."""
    return (
        world.bounds,
        [(b.lo.tolist(), b.hi.tolist(), b.material, b.facing) for b in world.boxes],
        [(c.centre.tolist(), c.radius, c.height, c.material) for c in world.cylinders],
        [(r.name, r.start.tolist(), r.goal.tolist(), r.cruise_height) for r in world.routes],
        None if world.heights is None else world.heights.tolist(),
    )


@pytest.mark.parametrize("name", WORLD_NAMES)
def test_same_seed_builds_the_same_world_and_another_seed_a_different_one(name):
    assert geometry_of(build_world(name, 3)) == geometry_of(build_world(name, 3))
    assert geometry_of(build_world(name, 3)) != geometry_of(build_world(name, 4))


def test_unknown_world_is_refused_with_the_known_names():
    with pytest.raises(ValueError, match="unknown world 'cave'.*mine, sewer, dome"):
        build_world("cave")


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_bad_seed_is_refused(seed):
    with pytest.raises(ValueError, match="seed"):
        build_world("dome", seed)


def samples_along(path, step=0.02):
    """Points every ``step`` metres along an (M, 2) polyline."""
    pieces = [a + np.linspace(0.0, 1.0, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)[:, None]
              * (b - a) for a, b in zip(path[:-1], path[1:])]
    return np.concatenate(pieces)


@pytest.mark.parametrize("seed", [0, 1, 7])
@pytest.mark.parametrize("name", WORLD_NAMES)
def test_every_route_has_a_path_with_room_for_a_1m_robot(name, seed):
    world = build_world(name, seed)
    assert 5 <= len(world.routes) <= 6  # as in the paper
    for route in world.routes:
        assert route.start[2] == 0.0 and route.goal[2] == route.cruise_height
        ends = np.array([route.start, route.goal, [*route.start[:2], route.cruise_height]])
        assert np.all(world.obstacle_clearance(ends) >= ROBOT_RADIUS), route.name
        path = world.find_path(route.start[:2], route.goal[:2], ROBOT_RADIUS)
        assert path is not None, route.name
        np.testing.assert_array_equal(path[0], route.start[:2])
        np.testing.assert_array_equal(path[-1], route.goal[:2])
        xy = samples_along(path)
        flown = np.column_stack([xy, np.full(len(xy), route.cruise_height)])
        assert world.obstacle_clearance(flown).min() >= ROBOT_RADIUS, route.name


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
