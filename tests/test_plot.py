"""The figures' shared plumbing and the top view of a flight: a readable PNG where the path, the
trunks and free space are where the world says they are, a legend naming what is drawn, clear
errors for input that cannot be drawn, and one line naming the ``plots`` extra where
matplotlib is missing."""

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import _build_parser, main
from companion.cli.sim import DEFAULT_PLOT, plot_destination
from companion.tools import plot
from companion.tools.plot import top_view
from drivers.sim.host import SimMission
from drivers.sim.faults import Fault
from drivers.sim.world import build_world

LEGEND = ("path (coloured by time)", "start", "goal", "waypoint", "collision", "obstacle",
          "within the robot radius (1 m)", "free")


@pytest.fixture(scope="module")
def dome():
    return build_world("dome", 0)


@pytest.fixture(scope="module")
def flight(dome, tmp_path_factory):
    """A route of the dome flown along its planned path at 1 m/s, drawn once for the module."""
    route = dome.routes[0]
    xy = dome.find_path(route.start[:2], route.goal[:2], 1.0)
    path = np.column_stack([xy, np.full(len(xy), dome.cruise_height)])
    times = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    out = tmp_path_factory.mktemp("plot") / "flight" / "top.png"
    view = top_view(dome, path, start=route.start, goal=route.goal, waypoints=xy[1:-1],
                    collisions=[[0.0, -24.0]], times=times, out=out, title="dome-1",
                    caption="world dome, seed 0")
    return view, path, cv2.imread(str(out), cv2.IMREAD_COLOR)


def test_writes_a_png_of_the_size_it_reports(flight):
    view, _, image = flight
    assert image is not None, "not a readable PNG"
    assert view.path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert image.shape == (view.height, view.width, 3)
    assert view.width == 1000  # size_px
    # the dome is 50 m square, shown with 2 m around it, inside the image and at least
    # half its width
    for corner in ((-27, -27), (27, 27)):
        column, row = view.pixel(corner)
        assert 0 <= column < view.width and 0 <= row < view.height, corner
    assert 500 < 54 * view.px_per_m < 1000


def is_coloured(bgr) -> bool:
    """Not one of the map's greys (nor white, nor black)."""
    return int(bgr.max()) - int(bgr.min()) > 50


def test_path_pixels_are_coloured_where_the_path_goes(flight):
    view, path, image = flight
    for a, b in zip(path, path[1:]):
        col, row = view.pixel(0.5 * (a[:2] + b[:2]))  # mid-segment, away from the markers
        patch = image[row - 1:row + 2, col - 1:col + 2].reshape(-1, 3)
        assert any(is_coloured(p) for p in patch), (a, b, patch)


def test_the_path_is_coloured_by_time(dome, tmp_path):
    """Two legs, the second ten times as long in time as the first: each leg has the colour
    of its middle time (by time, not by sample: by sample they would be at 1/4 and 3/4)."""
    from matplotlib import colormaps

    path = np.array([[-20.0, -24.0, 1.5], [-10.0, -24.0, 1.5], [20.0, -24.0, 1.5]])
    view = top_view(dome, path, start=path[0], goal=path[-1], times=[0.0, 1.0, 11.0],
                    out=tmp_path / "t.png")
    image = cv2.imread(str(view.path))
    for x, t in ((-15.0, 0.5), (5.0, 6.0)):
        expected = np.array(colormaps[plot.PATH_COLOURS](t / 11.0)[2::-1]) * 255  # as BGR
        pixel = image[view.pixel((x, -24.0))[::-1]]
        assert np.abs(pixel - expected).max() < 20, (x, pixel, expected)
    assert view.colour_bar == "time (s)"


def test_markers_land_where_the_mapping_says(flight, dome):
    view, _, image = flight
    route = dome.routes[0]
    for xy, (r, g, b) in ((route.goal, (255, 127, 14)), (route.start, (44, 160, 44))):
        pixel = image[view.pixel(xy)[::-1]].astype(int)
        assert np.abs(pixel - (b, g, r)).max() < 30, (xy, pixel)  # tab:orange, tab:green


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


def test_the_legend_names_every_element_drawn(flight, dome, tmp_path):
    view, *_ = flight
    assert view.legend == LEGEND
    path = np.array([[0.0, 0.0, 1.5], [5.0, 0.0, 1.5]])
    bare = top_view(dome, path, start=path[0], goal=path[-1], out=tmp_path / "bare.png")
    assert bare.legend == tuple(name for name in LEGEND if name not in ("waypoint", "collision"))
    assert bare.colour_bar == "fraction of the flight (samples)"  # no times given


def test_a_path_leaving_the_world_widens_the_map(dome, flight, tmp_path):
    path = np.array([[0.0, 0.0, 1.5], [40.0, 0.0, 1.5]])
    view = top_view(dome, path, start=path[0], goal=path[-1], out=tmp_path / "wide.png")
    assert view.pixel((42.0, 0.0))[0] < view.pixel((-27.0, 0.0))[0] + 69 * view.px_per_m + 1
    # 69 m across, not 54 m (to a rounding of the map's height to whole pixels)
    assert view.px_per_m == pytest.approx(flight[0].px_per_m * 54 / 69, rel=1e-3)


def test_the_caption_is_wrapped_to_the_figure_and_keeps_every_word():
    words = "seeds 0..4; code revision " + "0123456789abcdef" * 2 + "+dirty.0123456789ab"
    caption = " ".join([words] * 6)
    figure = plot.new_figure(4.0, 3.0, caption)
    assert len(figure.texts[0].get_text().splitlines()) > 1
    assert plot.caption_of(figure) == caption


def test_the_caption_of_a_flight_says_what_flew():
    assert plot.flight_caption(SimMission(world="sewer", seed=3, pair=2)) == \
        "world sewer, seed 3, pair 2, estimated depth, lockstep clock"
    mission = SimMission(goal=(1.0, 2.5, 1.5), depth="truth", clock="realtime",
                         faults=(Fault("camera_freeze"),))
    assert plot.flight_caption(mission) == ("world dome, seed 0, pair 0's start to goal 1, 2.5, "
                                            "1.5, truth depth, realtime clock, fault "
                                            "camera_freeze")
    through = SimMission(world="sewer", pair=5, goal=(39.0, 12.0, 1.5), via=((34.0, 7.0, 1.5),))
    assert plot.flight_caption(through) == ("world sewer, seed 0, pair 5's start via 34, 7, 1.5 "
                                            "to goal 39, 12, 1.5, estimated depth, lockstep "
                                            "clock")


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


def test_bad_markers_times_and_names_are_clear_errors(dome, tmp_path):
    path = [[0.0, 0.0, 1.5], [1.0, 0.0, 1.5]]
    with pytest.raises(ValueError, match="goal has non-finite"):
        top_view(dome, path, start=[0, 0, 0], goal=[math.inf, 0, 1.5], out=tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"collisions must have shape"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], collisions=[1.0, 2.0, 3.0, 4.0],
                 out=tmp_path / "x.png")
    with pytest.raises(ValueError, match="times has 3 values for 2 path points"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], times=[0, 1, 2], out=tmp_path / "x.png")
    with pytest.raises(ValueError, match="size_px"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], out=tmp_path / "x.png", size_px=10)
    with pytest.raises(ValueError, match=r"expected a \.png file name .*x\.jpg'$"):
        top_view(dome, path, start=[0, 0], goal=[1, 0], out=tmp_path / "x.jpg")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------- without the plots extra

@pytest.fixture
def no_matplotlib(monkeypatch):
    """matplotlib as if not installed: every import of it, or of a part of it, fails."""
    for name in [n for n in sys.modules if n == "matplotlib" or n.startswith("matplotlib.")]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


def test_a_missing_matplotlib_is_one_line_naming_the_extra(no_matplotlib, dome, tmp_path):
    assert plot.missing_extra() == plot.MISSING == \
        "the plots need matplotlib: pip install -e '.[plots]'"
    with pytest.raises(plot.MissingExtra, match=r"^the plots need matplotlib: .*\[plots\]'$"):
        top_view(dome, [[0.0, 0.0, 1.5]], start=[0, 0], goal=[1, 0], out=tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_matplotlib_is_found_where_it_is_installed():
    assert plot.missing_extra() is None


@pytest.mark.parametrize("argv", [
    ["eval", "nav", "--quick", "--plot", "nav.png"],
    ["eval", "nav", "--merge", "runs.jsonl", "--plot", "nav.png"],
    ["eval", "rescale", "--quick", "--plot", "absrel.png"],
    ["replay", "flight.mcap", "--plot", "top.png"],
    ["sim", "fly", "--plot", "top.png"],
])
def test_asking_for_a_plot_without_matplotlib_is_a_usage_error_before_anything_runs(
        no_matplotlib, capsys, argv):
    """Refused with the arguments: exit status 2, the extra named on the last line, nothing
    evaluated or flown (none of the files named exists, and these commands would fail or fly
    minutes otherwise)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1].endswith(f"argument --plot: {plot.MISSING}")
    assert "Traceback" not in err


def _sim_fly_args(*argv: str):
    return _build_parser().parse_args(["sim", "fly", *argv])


def test_sim_fly_without_matplotlib_flies_without_its_default_top_view(no_matplotlib, capsys):
    assert plot_destination(_sim_fly_args()) is None
    assert capsys.readouterr().err.splitlines() == [
        f"sim fly: no top view drawn (sim-fly.png): {plot.MISSING}"]
    assert plot_destination(_sim_fly_args("--no-plot")) is None
    assert capsys.readouterr().err == ""  # no plot asked for, none missed


def test_sim_fly_draws_its_top_view_by_default_where_matplotlib_is(capsys):
    assert plot_destination(_sim_fly_args()) == DEFAULT_PLOT == Path("sim-fly.png")
    assert plot_destination(_sim_fly_args("--plot", "here/top.png")) == Path("here/top.png")
    assert plot_destination(_sim_fly_args("--plot", "top.png", "--no-plot")) is None
    assert capsys.readouterr().err == ""
