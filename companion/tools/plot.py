"""The figures of the reports, drawn with matplotlib: the plumbing they share, and a flight
seen from above.

matplotlib is the optional ``plots`` extra (``pip install -e '.[plots]'``), as in evo: the
vehicle never draws, so it does not need it. :func:`missing_extra` says, in one line, when it
is not installed; the command line refuses a ``--plot`` then, before anything runs. Figures are
made on the Agg canvas without pyplot (no global state, no display), laid out above a caption
of small text that says what produced them (by matplotlib's constrained layout; the top view
by hand), and written as PNG at :data:`DPI` dots per inch, exactly their size (no tight
bounding box), so that a point of the data lands on a pixel that can be computed
(:class:`TopView`). The charts of the evaluations are drawn beside their data
(:func:`companion.tools.eval.nav.navigation_figure`,
:func:`companion.tools.eval.rescale.absrel_figure`).

The top view (:func:`top_view`) answers the first questions about a simulated flight — where
it went, how close it came to things, where it hit them. Its map is the world's exact
clearance (:meth:`drivers.sim.world.World.obstacle_clearance`) sampled on a grid at the flight
height: solid dark, the band a :data:`~drivers.sim.world.ROBOT_RADIUS` robot cannot enter
light grey, free space near white. World ``x`` is east (right) and ``y`` north (up).
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.sim.world import ROBOT_RADIUS, World

#: The extra that installs matplotlib, and the line that says it is missing.
EXTRA = "plots"
MISSING = f"the plots need matplotlib: pip install -e '.[{EXTRA}]'"
#: Dots per inch of every figure: a figure of w x h inches is a PNG of 100 w x 100 h pixels.
DPI = 100
#: Size of the caption's text, points, and the room below and above it, inches.
CAPTION_POINTS, CAPTION_PAD_IN = 7.5, 0.06

SOLID = "#2d2d2d"
"""Colour of space inside obstacles."""
BAND = "#afafaf"
"""Colour of free space closer than the robot radius to an obstacle."""
FREE = "#f6f6f6"
"""Colour of the rest of free space."""
START, GOAL, WAYPOINT, COLLISION = "tab:green", "tab:orange", "tab:blue", "tab:red"
"""Marker colours."""
PATH_COLOURS = "viridis"
"""The colour map of the path, from its start to its end."""

MARGIN_M = 2.0
"""Metres of map shown around the world's bounds and everything drawn."""
MAP_CELL_M = 0.1
"""The clearance map's finest cell, metres; coarser where the map is over 1000 cells across."""


class MissingExtra(ImportError):
    """matplotlib, the ``plots`` extra, is not installed; the message is :data:`MISSING`."""


def missing_extra() -> str | None:
    """:data:`MISSING` when matplotlib cannot be imported, else None."""
    try:
        _matplotlib()
    except MissingExtra:
        return MISSING
    return None


def _matplotlib():
    """matplotlib's ``(Figure, FigureCanvasAgg)``, or :class:`MissingExtra`."""
    try:
        import matplotlib  # noqa: F401 - first, so that a matplotlib hidden from imports is missing
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingExtra(MISSING) from None
    return Figure, FigureCanvasAgg


def png_path(out) -> Path:
    """``out`` as a Path, or a ValueError unless its name ends in .png (before the drawing)."""
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ValueError(f"expected a .png file name (the plot is a PNG), got {str(out)!r}")
    return out


def new_figure(width_in: float, height_in: float, caption: str, *, constrained: bool = True):
    """A matplotlib Figure of ``width_in`` x ``height_in`` inches on the Agg canvas with
    ``caption`` at its bottom left (:func:`wrap_caption`); laid out by matplotlib's
    constrained layout above the caption unless not ``constrained`` (the caller places its
    axes). :class:`MissingExtra` without matplotlib."""
    Figure, FigureCanvasAgg = _matplotlib()
    figure = Figure(figsize=(width_in, height_in), dpi=DPI,
                    layout="constrained" if constrained else None)
    FigureCanvasAgg(figure)
    text, room_in = wrap_caption(caption, width_in)
    if constrained:
        figure.get_layout_engine().set(rect=(0.0, room_in / height_in, 1.0,
                                             1.0 - room_in / height_in))
    figure.text(0.01, CAPTION_PAD_IN / height_in, text, fontsize=CAPTION_POINTS, color="0.3",
                ha="left", va="bottom")
    return figure


def wrap_caption(caption: str, width_in: float) -> tuple[str, float]:
    """``caption`` broken into lines that fit ``width_in`` inches (about 0.55 em a character),
    and the inches of figure height it takes (1.3 em a line, with padding)."""
    lines = textwrap.wrap(caption, width=int(0.98 * width_in * 72 / (0.55 * CAPTION_POINTS)),
                          break_long_words=False, break_on_hyphens=False)
    return "\n".join(lines), len(lines) * 1.3 * CAPTION_POINTS / 72 + 2 * CAPTION_PAD_IN


def caption_of(figure) -> str:
    """The caption :func:`new_figure` put on ``figure``, its line breaks as spaces."""
    return " ".join(figure.texts[0].get_text().split())


def save(figure, out) -> Path:
    """Write ``figure`` as a PNG to ``out`` (a .png name, :func:`png_path`; its folders
    created), at :data:`DPI` and exactly the figure's size; OSError if it cannot be written."""
    out = png_path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.canvas.print_png(str(out))  # not savefig: no rcParams' bbox or dpi in the way
    return out


# --------------------------------------------------------------------------------------------
# A flight from above

@dataclass(frozen=True)
class TopView:
    """Where :func:`top_view` wrote its image, how world coordinates map onto it, and what its
    legend and colour bar say."""

    path: Path
    width: int
    height: int
    px_per_m: float
    origin: tuple[float, float]  # (column, row) of world (0, 0), pixels from the top left
    legend: tuple[str, ...]  # the labels of the legend, top to bottom
    colour_bar: str  # the label of the path's colour bar

    def pixel(self, xy) -> tuple[int, int]:
        """(column, row) of the image pixel showing world point ``xy`` (x east, y north)."""
        column, row = self.origin
        return (int(math.floor(column + float(xy[0]) * self.px_per_m)),
                int(math.floor(row - float(xy[1]) * self.px_per_m)))


def flight_caption(mission) -> str:
    """"world dome, seed 0, pair 1, estimated depth, lockstep clock": what a simulated
    ``mission`` (:class:`drivers.sim.host.SimMission`) flew, for a top view's caption."""
    via = "".join(f" via {', '.join(f'{v:g}' for v in point)}" for point in mission.via)
    goal = f"pair {mission.pair}" if mission.goal is None else \
        f"pair {mission.pair}'s start{via} to goal {', '.join(f'{v:g}' for v in mission.goal)}"
    faults = "".join(f", fault {fault.kind}" for fault in mission.faults)
    return (f"world {mission.world}, seed {mission.seed}, {goal}, {mission.depth} depth, "
            f"{mission.clock} clock{faults}")


def top_view(world: World, path_xyz, *, start, goal, waypoints=(), collisions=(), times=None,
             out, title: str = "", caption: str = "", height: float | None = None,
             size_px: int = 1000) -> TopView:
    """Draw the flown ``path_xyz`` ((N, 3) world points, in time order) over ``world`` seen
    from above and write it as a PNG to ``out`` (its folders created).

    ``start`` and ``goal`` are one point each, ``waypoints`` and ``collisions`` (K, 2) or
    (K, 3) points; only x and y are drawn. The map is the clearance at ``height`` (default the
    world's cruise height). The path is coloured by ``times`` (N seconds, a colour bar in
    seconds) or, without them, by its fraction of the samples. A legend names every element;
    ``title`` heads the figure and ``caption`` (what produced it) is set under it. The image
    is ``size_px`` wide. Returns the image's geometry; ValueError for empty or non-finite
    input, :class:`MissingExtra` without matplotlib.
    """
    out = png_path(out)
    path = _points("path_xyz", path_xyz, columns=(3,), allow_empty=False)
    times = None if times is None else _times(times, path)
    start_xy = _points("start", np.reshape(start, (1, -1)), columns=(2, 3), allow_empty=False)
    goal_xy = _points("goal", np.reshape(goal, (1, -1)), columns=(2, 3), allow_empty=False)
    marks = {name: _points(name, value, columns=(2, 3), allow_empty=True)
             for name, value in (("waypoints", waypoints), ("collisions", collisions))}
    if not size_px >= 600:
        raise ValueError(f"size_px must be >= 600, got {size_px!r}")
    height = world.cruise_height if height is None else float(height)
    if not math.isfinite(height):
        raise ValueError(f"height must be finite, got {height!r}")

    drawn = np.concatenate([path[:, :2], start_xy[:, :2], goal_xy[:, :2],
                            *(m[:, :2] for m in marks.values())])
    extent = _extent(world.bounds, drawn)
    figure, axes, colour_bar = _top_view_figure(extent, size_px, caption)
    _draw_map(axes, world, extent, height)
    colours = _draw_path(axes, colour_bar, path[:, :2], times)
    _draw_marker(axes, start_xy, "s", START, "start")
    _draw_marker(axes, goal_xy, "*", GOAL, "goal", size=16)
    _draw_marker(axes, marks["waypoints"], "D", WAYPOINT, "waypoint", size=7)
    _draw_marker(axes, marks["collisions"], "X", COLLISION, "collision")
    legend = _legend(axes)
    axes.set(xlim=extent[:2], ylim=extent[2:], xlabel="x east (m)", ylabel="y north (m)",
             title=title)
    figure.canvas.draw()  # places the map for good: the equal aspect is applied in drawing
    view = _view(figure, axes, out, legend, colours)
    save(figure, out)
    return view


#: Pixels of the top view around its map: left of it (ticks, label), right of it (legend),
#: above it (title), under it (ticks, label), and the colour bar under those (with its label).
_LEFT_PX, _LEGEND_PX, _TITLE_PX, _X_AXIS_PX, _COLOUR_BAR_PX = 70, 250, 36, 50, 74


def _top_view_figure(extent, size_px: int, caption: str):
    """``(figure, map axes, colour bar axes)``, placed by hand: the map as wide as the legend
    leaves room for and exactly as high as its equal aspect makes it, the colour bar under it,
    the caption under that."""
    map_w = size_px - _LEFT_PX - _LEGEND_PX
    map_h = round(map_w * (extent[3] - extent[2]) / (extent[1] - extent[0]))
    caption_px = round(wrap_caption(caption, size_px / DPI)[1] * DPI)
    below = caption_px + _COLOUR_BAR_PX + _X_AXIS_PX
    width, height = size_px, _TITLE_PX + map_h + below
    figure = new_figure(width / DPI, height / DPI, caption, constrained=False)
    axes = figure.add_axes((_LEFT_PX / width, below / height, map_w / width, map_h / height))
    colour_bar = figure.add_axes(((_LEFT_PX + 0.2 * map_w) / width, (caption_px + 40) / height,
                                  0.6 * map_w / width, 12 / height))
    return figure, axes, colour_bar


def _extent(bounds, drawn: np.ndarray) -> tuple[float, float, float, float]:
    """``(x0, x1, y0, y1)``: the world's bounds and every point drawn, :data:`MARGIN_M`
    around them."""
    xmin, ymin, xmax, ymax = bounds
    return (min(xmin, drawn[:, 0].min()) - MARGIN_M, max(xmax, drawn[:, 0].max()) + MARGIN_M,
            min(ymin, drawn[:, 1].min()) - MARGIN_M, max(ymax, drawn[:, 1].max()) + MARGIN_M)


def _view(figure, axes, out: Path, legend: tuple[str, ...], colour_bar: str) -> TopView:
    """The pixel geometry of the drawn ``axes``: matplotlib's display coordinates are pixels
    from the bottom left at the figure's dpi, the image's rows count from the top."""
    width, height = (int(round(v)) for v in figure.bbox.size)
    (c0, r0), (c1, _) = axes.transData.transform([(0.0, 0.0), (1.0, 0.0)])
    return TopView(out, width, height, float(c1 - c0), (float(c0), height - float(r0)), legend,
                   colour_bar)


def _times(value, path: np.ndarray) -> np.ndarray:
    """The path's times as a finite array of one value per point, or a ValueError."""
    times = _points("times", np.reshape(value, (-1, 1)), columns=(1,), allow_empty=False)
    if len(times) != len(path):
        raise ValueError(f"times has {len(times)} values for {len(path)} path points")
    return times[:, 0]


def _points(name: str, value, *, columns: tuple[int, ...], allow_empty: bool) -> np.ndarray:
    """``value`` as a finite float (K, c) array with c in ``columns``, or a ValueError naming
    ``name`` and what is wrong."""
    array = np.asarray(value, dtype=float)
    if array.size == 0:
        if allow_empty:
            return np.zeros((0, columns[0]))
        raise ValueError(f"{name} is empty; nothing to draw")
    if array.ndim != 2 or array.shape[1] not in columns:
        shapes = " or ".join(f"(N, {c})" for c in columns)
        raise ValueError(f"{name} must have shape {shapes}, got {array.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
    if len(bad):
        raise ValueError(f"{name} has non-finite values in rows {bad[:5].tolist()}")
    return array


def _draw_map(axes, world: World, extent, z: float) -> None:
    """The clearance at ``z`` over ``extent`` as an image in metres: one query of the centres
    of cells of at least :data:`MAP_CELL_M`, each cell one colour."""
    from matplotlib.colors import to_rgb

    x0, x1, y0, y1 = extent
    cell = max(MAP_CELL_M, max(x1 - x0, y1 - y0) / 1000)
    nx, ny = max(1, round((x1 - x0) / cell)), max(1, round((y1 - y0) / cell))
    gx, gy = np.meshgrid(x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx,
                         y1 - (np.arange(ny) + 0.5) * (y1 - y0) / ny)  # first row at the top
    centres = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    clearance = world.obstacle_clearance(centres).reshape(ny, nx)
    image = np.empty((ny, nx, 3))
    image[:] = to_rgb(FREE)
    image[clearance < ROBOT_RADIUS] = to_rgb(BAND)
    image[clearance <= 0.0] = to_rgb(SOLID)
    axes.imshow(image, extent=extent, origin="upper", interpolation="nearest", zorder=0)


def _draw_path(axes, colour_bar, xy: np.ndarray, times: np.ndarray | None) -> str:
    """The path as segments coloured by time (``times``, seconds) or by the fraction of the
    samples, with its colour bar on the ``colour_bar`` axes; the colour bar's label."""
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize

    along = np.linspace(0.0, 1.0, len(xy)) if times is None else times
    label = "fraction of the flight (samples)" if times is None else "time (s)"
    norm = Normalize(along[0], along[-1] if along[-1] > along[0] else along[0] + 1.0)
    if len(xy) == 1:
        mappable = axes.scatter(xy[:, 0], xy[:, 1], c=along, cmap=PATH_COLOURS, norm=norm, s=12,
                                zorder=2)
    else:
        mappable = LineCollection(np.stack([xy[:-1], xy[1:]], axis=1), cmap=PATH_COLOURS,
                                  norm=norm, linewidths=2.2, zorder=2)
        mappable.set_array(0.5 * (along[:-1] + along[1:]))
        axes.add_collection(mappable, autolim=False)
    axes.figure.colorbar(mappable, cax=colour_bar, orientation="horizontal", label=label)
    return label


def _draw_marker(axes, points: np.ndarray, marker: str, colour: str, label: str,
                 size: float = 11) -> None:
    """``points`` as markers with a white edge, so they stay visible on dark rock and on the
    path; nothing (and no legend entry) for none."""
    if len(points):
        axes.plot(points[:, 0], points[:, 1], linestyle="none", marker=marker, markersize=size,
                  markerfacecolor=colour, markeredgecolor="white", markeredgewidth=1.2,
                  label=label, zorder=3)


def _legend(axes) -> tuple[str, ...]:
    """The legend beside the map: the path, the markers drawn, the map's colours."""
    from matplotlib import colormaps
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles, _ = axes.get_legend_handles_labels()
    handles = [Line2D([], [], color=colormaps[PATH_COLOURS](0.5), linewidth=2.2,
                      label="path (coloured by time)"), *handles,
               Patch(facecolor=SOLID, label="obstacle"),
               Patch(facecolor=BAND, edgecolor="0.6",
                     label=f"within the robot radius ({ROBOT_RADIUS:g} m)"),
               Patch(facecolor=FREE, edgecolor="0.6", label="free")]
    legend = axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                         fontsize=9, borderaxespad=0.0)
    return tuple(text.get_text() for text in legend.get_texts())
