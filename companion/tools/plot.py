"""A flight drawn from above on its world's map, as a PNG made with OpenCV alone.

One picture answers the first questions about a simulated flight — where it went, how close it
came to things, where it hit them — without a plotting library on the vehicle or in CI
(matplotlib is deliberately not a dependency). The map is the world's exact clearance
(:meth:`drivers.sim.world.World.obstacle_clearance`) sampled on a grid at the flight height:
solid dark, the band a :data:`~drivers.sim.world.ROBOT_RADIUS` robot cannot enter light grey,
free space near white. World ``x`` is east (right) and ``y`` north (up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.sim.world import ROBOT_RADIUS, World

SOLID = (45, 45, 45)
"""Colour (BGR, as everywhere here) of space inside obstacles."""
BAND = (175, 175, 175)
"""Colour of free space closer than the robot radius to an obstacle."""
FREE = (246, 246, 246)
"""Colour of the rest of free space."""
START, GOAL, WAYPOINT, COLLISION = (0, 160, 0), (0, 140, 255), (170, 120, 0), (0, 0, 230)
"""Marker colours."""

MARGIN_M = 2.0
"""Metres of map shown around the world's bounds and everything drawn."""
_LEFT, _TOP, _RIGHT, _BOTTOM = 60, 40, 20, 46  # pixels around the map for labels
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class TopView:
    """Where :func:`top_view` wrote its image and how world coordinates map onto it."""

    path: Path
    width: int
    height: int
    px_per_m: float
    x0: float  # world x of the map's left edge, metres
    y1: float  # world y of the map's top edge, metres

    def pixel(self, xy) -> tuple[int, int]:
        """(column, row) of the image pixel showing world point ``xy`` (x east, y north)."""
        x, y = float(xy[0]), float(xy[1])
        return (int(math.floor(_LEFT + (x - self.x0) * self.px_per_m)),
                int(math.floor(_TOP + (self.y1 - y) * self.px_per_m)))


def top_view(world: World, path_xyz, *, start, goal, waypoints=(), collisions=(), out,
             title: str = "", height: float | None = None, size_px: int = 1000) -> TopView:
    """Draw the flown ``path_xyz`` ((N, 3) world points, in time order) over ``world`` seen
    from above and write it as a PNG to ``out``.

    ``start`` and ``goal`` are one point each, ``waypoints`` and ``collisions`` (K, 2) or
    (K, 3) points; only x and y are drawn. The map is the clearance at ``height`` (default the
    world's cruise height) on cells of at least 0.1 m, scaled so the map's long side is
    ``size_px`` pixels. The path is coloured by sample index, blue at its start to red at its
    end (by time, for a path sampled at a fixed rate);
    a scale bar, east/north ticks in metres and the ``title`` (ASCII) frame it. Parent folders
    of ``out`` are created. Returns the image's geometry; raises ValueError for empty or
    non-finite input.
    """
    path = _points("path_xyz", path_xyz, columns=(3,), allow_empty=False)
    start_xy = _points("start", np.reshape(start, (1, -1)), columns=(2, 3), allow_empty=False)
    goal_xy = _points("goal", np.reshape(goal, (1, -1)), columns=(2, 3), allow_empty=False)
    marks = {name: _points(name, value, columns=(2, 3), allow_empty=True)
             for name, value in (("waypoints", waypoints), ("collisions", collisions))}
    if not size_px >= 100:
        raise ValueError(f"size_px must be >= 100, got {size_px!r}")
    height = world.cruise_height if height is None else float(height)
    if not math.isfinite(height):
        raise ValueError(f"height must be finite, got {height!r}")

    drawn = np.concatenate([path[:, :2], start_xy[:, :2], goal_xy[:, :2],
                            *(m[:, :2] for m in marks.values())])
    xmin, ymin, xmax, ymax = world.bounds
    x0, y0 = min(xmin, drawn[:, 0].min()) - MARGIN_M, min(ymin, drawn[:, 1].min()) - MARGIN_M
    x1, y1 = max(xmax, drawn[:, 0].max()) + MARGIN_M, max(ymax, drawn[:, 1].max()) + MARGIN_M
    scale = size_px / max(x1 - x0, y1 - y0)
    map_w, map_h = round((x1 - x0) * scale), round((y1 - y0) * scale)
    view = TopView(Path(out), _LEFT + map_w + _RIGHT, _TOP + map_h + _BOTTOM, scale, x0, y1)

    canvas = np.full((view.height, view.width, 3), 255, np.uint8)
    canvas[_TOP:_TOP + map_h, _LEFT:_LEFT + map_w] = _clearance_map(
        world, x0, y1, map_w, map_h, scale, height)
    _draw_path(canvas, view, path)
    _draw_marker(canvas, view, start_xy[0], START, cv2.MARKER_SQUARE)
    _draw_marker(canvas, view, goal_xy[0], GOAL, cv2.MARKER_STAR)
    for point in marks["waypoints"]:
        _draw_marker(canvas, view, point, WAYPOINT, cv2.MARKER_DIAMOND)
    for point in marks["collisions"]:
        _draw_marker(canvas, view, point, COLLISION, cv2.MARKER_TILTED_CROSS)
    _draw_axes(canvas, view, map_w, map_h, x1, y0)
    _draw_scale_bar(canvas, view, map_h, x1 - x0)
    cv2.putText(canvas, title, (_LEFT, 20), _FONT, 0.6, (0, 0, 0), 1, cv2.LINE_AA)

    write_image(canvas, view.path)
    return view


def write_image(canvas: np.ndarray, out: Path) -> Path:
    """Write ``canvas`` to ``out`` (its folders created); OSError if OpenCV cannot."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), canvas):
        raise OSError(f"could not write the image to {out} (is the name a .png?)")
    return out


def png_path(out) -> Path:
    """``out`` as a Path, or a ValueError unless its name ends in .png (before the drawing)."""
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ValueError(f"{out}: the plot is a PNG; give a name ending in .png")
    return out


def text(canvas: np.ndarray, words: str, at: tuple[int, int], scale: float = 0.4,
         colour=(0, 0, 0)) -> None:
    """Anti-aliased Hershey text with its baseline's left end at ``at``."""
    cv2.putText(canvas, words, at, _FONT, scale, colour, 1, cv2.LINE_AA)


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


def _clearance_map(world: World, x0: float, y1: float, width: int, height: int, scale: float,
                   z: float) -> np.ndarray:
    """The (height, width, 3) map image: clearance at ``z`` on a grid of cells of at least
    0.1 m (one query of all cell centres), resized to pixels with nearest neighbour."""
    cell = max(0.1, 1.0 / scale)
    nx, ny = max(1, round(width / (cell * scale))), max(1, round(height / (cell * scale)))
    cx, cy = width / scale / nx, height / scale / ny  # exact cell sizes tiling the map
    gx, gy = np.meshgrid(x0 + (np.arange(nx) + 0.5) * cx, y1 - (np.arange(ny) + 0.5) * cy)
    centres = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    clearance = world.obstacle_clearance(centres).reshape(ny, nx)
    grid = np.empty((ny, nx, 3), np.uint8)
    grid[:] = FREE
    grid[clearance < ROBOT_RADIUS] = BAND
    grid[clearance <= 0.0] = SOLID
    return cv2.resize(grid, (width, height), interpolation=cv2.INTER_NEAREST)


def _draw_path(canvas: np.ndarray, view: TopView, path: np.ndarray) -> None:
    """The polyline, each segment coloured by its time along the path (blue -> red)."""
    pixels = [view.pixel(p) for p in path]
    if len(pixels) == 1:
        cv2.circle(canvas, pixels[0], 3, (255, 0, 0), -1, cv2.LINE_AA)
    for k, (a, b) in enumerate(zip(pixels, pixels[1:])):
        f = k / max(1, len(pixels) - 2)
        cv2.line(canvas, a, b, (round(255 * (1 - f)), 0, round(255 * f)), 2, cv2.LINE_AA)


def _draw_marker(canvas: np.ndarray, view: TopView, xy, colour, kind: int) -> None:
    """A marker with a white halo, so it stays visible on dark rock and on the path."""
    at = view.pixel(xy)
    cv2.drawMarker(canvas, at, (255, 255, 255), kind, 18, 5, cv2.LINE_AA)
    cv2.drawMarker(canvas, at, colour, kind, 16, 2, cv2.LINE_AA)


def nice_step(length: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``length``."""
    power = 10.0 ** math.floor(math.log10(length))
    return max(m * power for m in (1, 2, 5) if m * power <= length)


def _draw_axes(canvas: np.ndarray, view: TopView, map_w: int, map_h: int, x1: float,
               y0: float) -> None:
    """Ticks in metres along the bottom (x, east) and left (y, north) edges, axis names, and
    a north arrow in the map's top-right corner."""
    black, small = (0, 0, 0), 0.4
    step = nice_step(max(x1 - view.x0, view.y1 - y0) / 6)
    cv2.rectangle(canvas, (_LEFT - 1, _TOP - 1), (_LEFT + map_w, _TOP + map_h), black, 1)
    for x in np.arange(math.ceil(view.x0 / step) * step, x1, step):
        col = view.pixel((x, 0))[0]
        cv2.line(canvas, (col, _TOP + map_h), (col, _TOP + map_h + 5), black, 1)
        cv2.putText(canvas, f"{x:g}", (col - 10, _TOP + map_h + 18), _FONT, small, black, 1,
                    cv2.LINE_AA)
    for y in np.arange(math.ceil(y0 / step) * step, view.y1, step):
        row = view.pixel((0, y))[1]
        cv2.line(canvas, (_LEFT - 6, row), (_LEFT - 1, row), black, 1)
        cv2.putText(canvas, f"{y:g}", (4, row + 4), _FONT, small, black, 1, cv2.LINE_AA)
    cv2.putText(canvas, "x east (m)", (_LEFT + map_w // 2 - 40, view.height - 8), _FONT, 0.45,
                black, 1, cv2.LINE_AA)
    cv2.putText(canvas, "y north (m)", (4, _TOP - 6), _FONT, small, black, 1, cv2.LINE_AA)
    tip = (_LEFT + map_w - 20, _TOP + 12)
    cv2.arrowedLine(canvas, (tip[0], tip[1] + 30), tip, black, 2, cv2.LINE_AA, tipLength=0.3)
    cv2.putText(canvas, "N", (tip[0] - 18, tip[1] + 26), _FONT, 0.5, black, 1, cv2.LINE_AA)


def _draw_scale_bar(canvas: np.ndarray, view: TopView, map_h: int, width_m: float) -> None:
    """A bar of a round number of metres, about a fifth of the map wide, bottom left."""
    metres = nice_step(width_m / 5)
    left, base = _LEFT + 12, _TOP + map_h - 14
    right = left + round(metres * view.px_per_m)
    cv2.rectangle(canvas, (left - 3, base - 20), (right + 3, base + 6), (255, 255, 255), -1)
    cv2.rectangle(canvas, (left, base - 2), (right, base + 2), (0, 0, 0), -1)
    cv2.putText(canvas, f"{metres:g} m", (left, base - 7), _FONT, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
