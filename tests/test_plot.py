"""The top view of a flight: a readable PNG where the path, the trunks and free space are where
the world says they are, and clear errors for input that cannot be drawn."""

import math

import cv2
import numpy as np
import pytest

from companion.tools.plot import top_view
from drivers.sim.world import build_world


@pytest.fixture(scope="module")
def dome():
    return build_world("dome", 0)


@pytest.fixture(scope="module")
def flight(dome, tmp_path_factory):
    """A route of the dome flown along its planned path, drawn once for the module."""
    route = dome.routes[0]
    xy = dome.find_path(route.start[:2], route.goal[:2], 1.0)
    path = np.column_stack([xy, np.full(len(xy), dome.cruise_height)])
    out = tmp_path_factory.mktemp("plot") / "flight" / "top.png"
    view = top_view(dome, path, start=route.start, goal=route.goal, waypoints=xy[1:-1],
                    collisions=[[0.0, -24.0]], out=out, title="dome-1")
    return view, path, cv2.imread(str(out), cv2.IMREAD_COLOR)


def test_writes_a_png_of_the_expected_size(flight):
    view, _, image = flight
    assert image is not None, "not a readable PNG"
    assert view.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert image.shape == (view.height, view.width, 3)
    # the dome is 50 m square, shown with 2 m around it, its long side 1000 px by default
    assert view.px_per_m == pytest.approx(1000 / 54)
    assert view.width - 1000 == view.height - 1000 + 80 - 86  # label margins: 80 wide, 86 high


def is_coloured(bgr) -> bool:
    return int(bgr.max()) - int(bgr.min()) > 80


def test_path_pixels_are_coloured_where_the_path_goes(flight):
    view, path, image = flight
    for a, b in zip(path, path[1:]):
        col, row = view.pixel(0.5 * (a[:2] + b[:2]))  # mid-segment, away from the markers
        patch = image[row - 1:row + 2, col - 1:col + 2].reshape(-1, 3)
        assert any(is_coloured(p) for p in patch), (a, b, patch)


def test_trunks_are_dark_and_open_ground_light(flight, dome):
    view, _, image = flight
    for trunk in dome.cylinders:
        col, row = view.pixel(trunk.centre)
        assert image[row, col].max() < 80, trunk.centre
    rng = np.random.default_rng(1)
    samples = rng.uniform(-20, 20, (200, 2))
    clearance = dome.obstacle_clearance(np.column_stack([samples, np.full(200, 1.5)]))
    vertices = flight[1][:, :2]
    route = np.concatenate([np.linspace(a, b, 100) for a, b in zip(vertices, vertices[1:])])
    for xy, c in zip(samples, clearance):
        far_from_path = np.linalg.norm(route - xy, axis=1).min() > 1.0
        if c > 1.3 and far_from_path:
            col, row = view.pixel(xy)
            assert image[row, col].min() > 230, (xy, c, image[row, col])
        if 0.1 < c < 0.9 and far_from_path:  # the robot-radius band: lighter than solid
            col, row = view.pixel(xy)
            assert 120 < image[row, col].min() < 220, (xy, c, image[row, col])


def test_a_path_leaving_the_world_widens_the_map(dome, tmp_path):
    path = np.array([[0.0, 0.0, 1.5], [40.0, 0.0, 1.5]])
    view = top_view(dome, path, start=path[0], goal=path[-1], out=tmp_path / "wide.png")
    assert view.pixel((40.0, 0.0))[0] < view.width - 20
    assert view.px_per_m == pytest.approx(1000 / 69)


@pytest.mark.parametrize("path, message", [
    (np.zeros((0, 3)), "path_xyz is empty"),
    ([], "path_xyz is empty"),
    ([[0.0, 0.0, 1.5], [1.0, math.nan, 1.5]], r"path_xyz has non-finite values in rows \[1\]"),
    ([[0.0, 0.0], [1.0, 1.0]], r"path_xyz must have shape \(N, 3\)"),
])
def test_bad_paths_are_clear_errors(dome, tmp_path, path, message):
    with pytest.raises(ValueError, match=message):
        top_view(dome, path, start=[0, 0, 0], goal=[1, 1, 1.5], out=tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_bad_markers_are_clear_errors(dome, tmp_path):
    path = [[0.0, 0.0, 1.5], [1.0, 0.0, 1.5]]
    with pytest.raises(ValueError, match="goal has non-finite"):
        top_view(dome, path, start=[0, 0, 0], goal=[math.inf, 0, 1.5], out=tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"collisions must have shape"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], collisions=[1.0, 2.0, 3.0, 4.0],
                 out=tmp_path / "x.png")
    with pytest.raises(ValueError, match="size_px"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], out=tmp_path / "x.png", size_px=10)
