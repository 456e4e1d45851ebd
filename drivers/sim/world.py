"""The three simulated worlds, built from a seed, after the paper's environments.

Yang et al. fly a mine (confined tunnels with sharp turns opening into a large cavern), a sewer
(two large concrete rooms joined by a long hallway) and a dome (a small forest of trees and
pillars under open sky). Here each is a 2.5-D world, z up (ENU), floor at z = 0:

- an *enclosed* world (mine, sewer) is a ceiling-height map on a 0.5 m grid: a free cell is open
  from the floor up to its ceiling height, a cell of height 0 is solid rock. Rooms, tunnels and
  pillars are rectangles carved into it; walls, ceiling steps and ceilings are generated from
  the map as axis-aligned panels, merged along runs, so the renderer's mesh and the clearance
  below are the same geometry;
- an *open* world (dome) is open ground with vertical cylinders (tree trunks) and boxes
  (pillars), and sky above.

:meth:`World.obstacle_clearance` is the exact Euclidean distance to those primitives (panels and
boxes: distance to an axis-aligned box ``|p - clip(p, lo, hi)|``; trunks: distance to a finite
vertical cylinder), so what the camera sees and what the vehicle collides with agree (the
renderer's trunks are 16-sided prisms within 1 % of the radius of these cylinders).
:meth:`World.find_path` plans on that clearance: A* on a 0.25 m grid of the cells whose clearance
at flight height is at least the robot radius, then shortcutting the cell path wherever the
straight segment keeps the clearance (checked on the exact function, not the grid).

The ``realistic`` profile (:func:`build_world`) builds the same world and adds what makes real
flight hard: thin poles and a tripod near the routes (the tripod's legs and head are
:class:`Rod` primitives, cylinders of any direction, whose clearance is exact too),
low-texture stretches of the mine's and sewer's walls, and dust in the mine
(:attr:`World.visibility`, drawn by the renderer).
"""

from __future__ import annotations

import heapq
import math
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

from drivers.sim.options import PROFILES, WORLD_NAMES

CELL = 0.5
"""Grid of the enclosed worlds' ceiling-height maps, metres."""

PLAN_CELL = 0.25
"""Grid of :meth:`World.find_path`'s search, metres."""

CRUISE_HEIGHT = 1.5
"""Flight height of the routes, metres above the floor."""

ROBOT_RADIUS = 1.0
"""Radius every route leaves room for (the paper's vehicle), metres."""


@dataclass(frozen=True, eq=False)
class Route:
    """A start on the floor and a goal at cruise height, joined by a path with room for a
    :data:`ROBOT_RADIUS` robot (compare the arrays, not the routes)."""

    name: str
    start: np.ndarray  # (3,) world ENU, z = 0
    goal: np.ndarray  # (3,) world ENU, z = cruise_height
    cruise_height: float


@dataclass(frozen=True, eq=False)
class Box:
    """A solid axis-aligned box ``lo <= p <= hi``; zero thickness along one axis makes it a
    panel (a wall, a ceiling step, a ceiling or the floor), seen only from the side its
    ``facing`` (+1 or -1 along that axis) points to: the open side."""

    lo: np.ndarray  # (3,)
    hi: np.ndarray  # (3,)
    material: str
    facing: float = 0.0


@dataclass(frozen=True, eq=False)
class Cylinder:
    """A solid vertical cylinder standing on the floor (a tree trunk)."""

    centre: np.ndarray  # (2,) x, y
    radius: float
    height: float
    material: str


@dataclass(frozen=True, eq=False)
class Rod:
    """A solid cylinder of any direction from ``a`` to ``b`` with flat ends square to its axis
    (a tripod's leg or head)."""

    a: np.ndarray  # (3,)
    b: np.ndarray  # (3,)
    radius: float
    material: str


@dataclass(frozen=True)
class Materials:
    """Which texture (drivers.sim.textures.MATERIALS) each kind of surface wears."""

    floor: str
    wall: str
    ceiling: str


@dataclass(frozen=True, eq=False)
class World:
    """A world built by :func:`build_world`; treat it as immutable.

    ``heights`` is the enclosed worlds' ceiling-height map (rows along y, columns along x, cell
    ``(j, i)`` covering ``origin + (i, j) * CELL`` to one cell further; 0 = solid), None for an
    open world. ``boxes``, ``cylinders`` and ``rods`` are every obstacle surface except the floor,
    which is ``floor`` (a panel at z = 0 big enough to fill the view).

    ``profile`` is the :data:`~drivers.sim.options.PROFILES` entry that built it. A world with
    ``visibility`` (metres; None = clear air) is filled with a haze of colour ``haze_rgb`` (linear
    RGB in [0, 1]): the camera sees ``lerp(surface, haze_rgb, 1 - exp(-distance / visibility))``.
    """

    name: str
    seed: int
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of the flyable area
    routes: tuple[Route, ...]
    boxes: tuple[Box, ...]
    cylinders: tuple[Cylinder, ...]
    floor: Box
    outdoor: bool
    heights: np.ndarray | None = None
    origin: np.ndarray | None = None  # (2,) x, y of the height map's corner
    cruise_height: float = CRUISE_HEIGHT
    rods: tuple[Rod, ...] = ()
    profile: str = "ideal"
    visibility: float | None = None
    haze_rgb: tuple[float, float, float] | None = None
    _box_lo: np.ndarray = field(init=False, repr=False)
    _box_hi: np.ndarray = field(init=False, repr=False)
    _cylinders: np.ndarray = field(init=False, repr=False)
    _rods: np.ndarray = field(init=False, repr=False)
    _plan_cache: dict = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        lo = np.array([b.lo for b in self.boxes]).reshape(-1, 3)
        hi = np.array([b.hi for b in self.boxes]).reshape(-1, 3)
        cyl = np.array([[*c.centre, c.radius, c.height] for c in self.cylinders]).reshape(-1, 4)
        rods = np.array([[*r.a, *r.b, r.radius] for r in self.rods]).reshape(-1, 7)
        for name, value in (("_box_lo", lo), ("_box_hi", hi), ("_cylinders", cyl),
                            ("_rods", rods)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        if self.visibility is not None and not (math.isfinite(self.visibility)
                                                and self.visibility > 0.0):
            raise ValueError(f"visibility must be None or > 0 metres, got {self.visibility}")

    # ---- clearance ---------------------------------------------------------------------------

    def obstacle_clearance(self, points) -> np.ndarray:
        """``(N,)`` Euclidean distance, metres, from each of ``(N, 3)`` world points (one ``(3,)``
        point gives a ``(1,)`` array) to the nearest solid surface other than the floor plane:
        walls, ceilings, pillars, trunks, poles, tripods. 0 inside solid. About 50 us for one
        point."""
        p = np.asarray(points, dtype=float)
        if p.shape == (3,):
            p = p[None]
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3) or (3,), got {np.shape(points)}")
        if not np.all(np.isfinite(p)):
            raise ValueError("points must be finite")
        clearance = np.full(len(p), np.inf)
        for start in range(0, len(p), 2048):  # bounded (chunk, obstacles, 3) temporaries
            chunk = p[start:start + 2048]
            clearance[start:start + 2048] = np.minimum(self._box_distance(chunk),
                                                       self._cylinder_distance(chunk))
            if len(self._rods):
                clearance[start:start + 2048] = np.minimum(clearance[start:start + 2048],
                                                           _rod_distance(chunk, self._rods))
        if self.heights is not None:
            clearance[self._inside_rock(p)] = 0.0
        return clearance

    def _box_distance(self, p: np.ndarray) -> np.ndarray:
        if not len(self._box_lo):
            return np.full(len(p), np.inf)
        nearest = np.clip(p[:, None, :], self._box_lo[None], self._box_hi[None])
        return np.sqrt(((p[:, None, :] - nearest) ** 2).sum(axis=2).min(axis=1))

    def _cylinder_distance(self, p: np.ndarray) -> np.ndarray:
        """Distance to a vertical cylinder on the floor: ``hypot(max(0, r_xy - R), max(0, z -
        h))``."""
        if not len(self._cylinders):
            return np.full(len(p), np.inf)
        c = self._cylinders
        radial = np.hypot(p[:, None, 0] - c[None, :, 0], p[:, None, 1] - c[None, :, 1])
        outward = np.maximum(radial - c[None, :, 2], 0.0)
        above = np.maximum(p[:, None, 2] - c[None, :, 3], 0.0)
        return np.hypot(outward, above).min(axis=1)

    def _inside_rock(self, p: np.ndarray) -> np.ndarray:
        """Whether each point is in the height map's solid: above its cell's ceiling, or
        outside the map."""
        i = np.floor((p[:, 0] - self.origin[0]) / CELL).astype(int)
        j = np.floor((p[:, 1] - self.origin[1]) / CELL).astype(int)
        rows, cols = self.heights.shape
        inside_map = (i >= 0) & (i < cols) & (j >= 0) & (j < rows)
        ceiling = np.zeros(len(p))
        ceiling[inside_map] = self.heights[j[inside_map], i[inside_map]]
        return p[:, 2] >= ceiling

    # ---- path planning -----------------------------------------------------------------------

    def find_path(self, start_xy, goal_xy, radius: float, height: float | None = None
                  ) -> np.ndarray | None:
        """``(M, 2)`` polyline from ``start_xy`` to ``goal_xy`` along which every point, at
        ``height`` (default the cruise height), has clearance >= ``radius``; None if there is
        none (or either end lacks the clearance).

        The search grid keeps the :data:`PLAN_CELL` cells whose centre's exact clearance is at
        least ``radius + margin``, margin = half a cell diagonal plus half the 5 cm sampling step.
        Clearance is 1-Lipschitz, so any point within that margin of a kept centre has
        clearance >= ``radius``. A* (8-connected, no corner cutting, octile heuristic) finds the
        cell path; it is then shortened by string pulling: from each vertex, go straight to the
        farthest following vertex whose segment, sampled every 5 cm, stays in kept cells.
        """
        start, goal = (np.asarray(v, dtype=float).reshape(-1) for v in (start_xy, goal_xy))
        if start.shape != (2,) or goal.shape != (2,):
            raise ValueError("start_xy and goal_xy must be (x, y) pairs")
        if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal))
                and math.isfinite(radius) and radius >= 0.0):
            raise ValueError("start_xy, goal_xy must be finite and radius finite and >= 0")
        height = self.cruise_height if height is None else float(height)
        free, corner = self._free_cells(radius + PLAN_CELL * math.sqrt(0.5) + 0.025, height)
        cells = _astar(free, self._cell_of(start, corner), self._cell_of(goal, corner))
        if cells is None:
            return None
        points = [start, *(corner + (np.array(cells[1:-1]) + 0.5) * PLAN_CELL), goal]
        return _string_pull(points, lambda a, b: _segment_in(free, corner, a, b))

    def _cell_of(self, xy: np.ndarray, corner: np.ndarray) -> tuple[int, int]:
        i, j = np.floor((xy - corner) / PLAN_CELL).astype(int)
        return int(i), int(j)

    def _free_cells(self, clearance: float, height: float) -> tuple[np.ndarray, np.ndarray]:
        """Boolean grid (x index, y index) of planning cells with at least ``clearance`` at
        ``height``, and the grid's corner; cached, as routes are planned repeatedly."""
        key = (round(clearance, 6), round(height, 6))
        if key not in self._plan_cache:
            xmin, ymin, xmax, ymax = self.bounds
            corner = np.array([xmin, ymin])
            nx = int(math.ceil((xmax - xmin) / PLAN_CELL))
            ny = int(math.ceil((ymax - ymin) / PLAN_CELL))
            gx, gy = np.meshgrid(xmin + (np.arange(nx) + 0.5) * PLAN_CELL,
                                 ymin + (np.arange(ny) + 0.5) * PLAN_CELL, indexing="ij")
            centres = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height)], axis=1)
            open_air = ~self._inside_rock(centres) if self.heights is not None \
                else np.ones(len(centres), bool)
            free = np.zeros(len(centres), bool)
            free[open_air] = self.obstacle_clearance(centres[open_air]) >= clearance
            self._plan_cache[key] = (free.reshape(nx, ny), corner)
        return self._plan_cache[key]

    # ---- mesh --------------------------------------------------------------------------------

    @property
    def materials(self) -> tuple[str, ...]:
        """Every material the world's surfaces wear, in a fixed order (the texture layers)."""
        names = [self.floor.material] + [b.material for b in self.boxes] \
            + [c.material for c in self.cylinders] + [r.material for r in self.rods]
        return tuple(dict.fromkeys(names))


def _rod_distance(p: np.ndarray, rods: np.ndarray) -> np.ndarray:
    """Distance from ``(N, 3)`` points to the nearest of ``(K, 7)`` rods ``(a, b, radius)``.

    In a rod's own frame (axial coordinate ``t = (p - a) . u`` along the unit axis ``u``, length
    ``L``, radial distance ``rho`` from the axis) the nearest point of a solid finite cylinder is
    on its side, its flat end or its rim, and the distance is ``hypot(max(0, rho - R), max(0, -t,
    t - L))``: exact, 0 inside."""
    a, b, radius = rods[:, :3], rods[:, 3:6], rods[:, 6]
    axis = b - a
    length = np.linalg.norm(axis, axis=1)
    u = axis / length[:, None]
    rel = p[:, None, :] - a[None]  # (N, K, 3)
    t = (rel * u[None]).sum(axis=2)
    rho = np.linalg.norm(rel - t[..., None] * u[None], axis=2)
    outward = np.maximum(rho - radius[None], 0.0)
    beyond = np.maximum(np.maximum(-t, t - length[None]), 0.0)
    return np.hypot(outward, beyond).min(axis=1)


def _segment_in(free: np.ndarray, corner: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether every sample of segment ab, every 5 cm, lies in a cell marked free."""
    steps = max(1, int(math.ceil(np.linalg.norm(b - a) / 0.05)))
    xy = a + np.linspace(0.0, 1.0, steps + 1)[:, None] * (b - a)
    i, j = np.floor((xy - corner) / PLAN_CELL).astype(int).T
    inside = (i >= 0) & (i < free.shape[0]) & (j >= 0) & (j < free.shape[1])
    return bool(np.all(inside) and np.all(free[i, j]))


def _string_pull(points: list[np.ndarray], visible) -> np.ndarray:
    """Shorten a polyline: from each kept vertex, jump to the last vertex of the longest run of
    following vertices that are each ``visible`` from it."""
    path, i = [points[0]], 0
    while i < len(points) - 1:
        j = i + 1
        while j + 1 < len(points) and visible(points[i], points[j + 1]):
            j += 1
        path.append(points[j])
        i = j
    return np.array(path)


def _astar(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]
           ) -> list[tuple[int, int]] | None:
    """Shortest 8-connected path of free cells (octile distance heuristic), or None."""
    nx, ny = free.shape
    for i, j in (start, goal):
        if not (0 <= i < nx and 0 <= j < ny and free[i, j]):
            return None
    moves = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1)
             if di or dj]

    def octile(i, j):
        dx, dy = abs(i - goal[0]), abs(j - goal[1])
        return max(dx, dy) + (math.sqrt(2) - 1) * min(dx, dy)

    best = {start: 0.0}
    parent = {start: None}
    frontier = [(octile(*start), 0.0, start)]
    while frontier:
        _, cost, cell = heapq.heappop(frontier)
        if cell == goal:
            path = []
            while cell is not None:
                path.append(cell)
                cell = parent[cell]
            return path[::-1]
        if cost > best[cell]:
            continue
        for di, dj, step in moves:
            i, j = cell[0] + di, cell[1] + dj
            if not (0 <= i < nx and 0 <= j < ny and free[i, j]):
                continue
            if di and dj and not (free[cell[0] + di, cell[1]] and free[cell[0], cell[1] + dj]):
                continue  # no corner cutting
            new = cost + step
            if new < best.get((i, j), math.inf):
                best[(i, j)] = new
                parent[(i, j)] = cell
                heapq.heappush(frontier, (new + octile(i, j), new, (i, j)))
    return None


# ---- enclosed worlds: the height map and its panels ----------------------------------------


class HeightMap:
    """A ceiling-height map under construction: carve rectangles, then make panels."""

    def __init__(self, xmin: float, ymin: float, xmax: float, ymax: float, rock: str):
        self.origin = np.array([xmin, ymin])
        self.heights = np.zeros((round((ymax - ymin) / CELL), round((xmax - xmin) / CELL)))
        self.wall_material = np.full(self.heights.shape, rock, dtype=object)

    def _slices(self, x0, y0, x1, y1, grow=0):
        i0, j0 = np.round((np.array([x0, y0]) - self.origin) / CELL).astype(int) - grow
        i1, j1 = np.round((np.array([x1, y1]) - self.origin) / CELL).astype(int) + grow
        return slice(max(j0, 0), max(j1, 0)), slice(max(i0, 0), max(i1, 0))

    def carve(self, x0, y0, x1, y1, ceiling: float, wall: str | None = None) -> None:
        """Open the rectangle up to ``ceiling`` (keeping any higher ceiling already there);
        ``wall`` names the material of the rock around it."""
        if wall is not None:
            self.wall_material[self._slices(x0, y0, x1, y1, grow=1)] = wall
        rows, cols = self._slices(x0, y0, x1, y1)
        self.heights[rows, cols] = np.maximum(self.heights[rows, cols], ceiling)

    def fill(self, x0, y0, x1, y1, material: str) -> None:
        """Make the rectangle solid again (a pillar), wearing ``material``."""
        index = self._slices(x0, y0, x1, y1)
        self.heights[index] = 0.0
        self.wall_material[index] = material

    def all_open(self, x0, y0, x1, y1) -> bool:
        return bool(np.all(self.heights[self._slices(x0, y0, x1, y1)] > 0))

    def panels(self, ceiling_material: str) -> list[Box]:
        """Walls where neighbouring cells' heights differ (from the lower height to the higher,
        wearing the lower cell's wall material) merged along each grid line, and ceilings merged
        into rectangles of equal height."""
        padded = np.pad(self.heights, 1)
        material = np.pad(self.wall_material, 1, mode="edge")
        panels = []
        for axis in (0, 1):  # 0: walls on lines of constant x, 1: of constant y
            h = padded if axis == 0 else padded.T
            m = material if axis == 0 else material.T
            for line in range(h.shape[1] - 1):
                a, b = h[:, line], h[:, line + 1]
                low_side = np.where(a < b, m[:, line], m[:, line + 1])
                facing = np.where(a < b, 1.0, -1.0)  # towards the higher (open) cell
                runs = _runs([(lo, hi, mat, f) if lo != hi else None for lo, hi, mat, f in
                              zip(np.minimum(a, b), np.maximum(a, b), low_side, facing)])
                for start, stop, (lo, hi, mat, f) in runs:
                    across = self.origin[axis] + line * CELL  # padded index line+1 -> line
                    along = self.origin[1 - axis] + (np.array([start, stop]) - 1) * CELL
                    box_lo, box_hi = np.zeros(3), np.zeros(3)
                    box_lo[axis] = box_hi[axis] = across
                    box_lo[1 - axis], box_hi[1 - axis] = along
                    box_lo[2], box_hi[2] = lo, hi
                    panels.append(Box(box_lo, box_hi, mat, f))
        for (j0, i0, j1, i1), height in _rectangles(self.heights):
            lo = np.array([*(self.origin + np.array([i0, j0]) * CELL), height])
            hi = np.array([*(self.origin + np.array([i1, j1]) * CELL), height])
            panels.append(Box(lo, hi, ceiling_material, -1.0))
        return panels


def _runs(values: list) -> list[tuple[int, int, tuple]]:
    """``(start, stop, value)`` of each run of equal, non-None consecutive values."""
    runs, start = [], None
    for k, value in enumerate([*values, None]):
        if start is not None and value != values[start]:
            runs.append((start, k, values[start]))
            start = None
        if start is None and value is not None:
            start = k
    return runs


def _rectangles(heights: np.ndarray) -> list[tuple[tuple[int, int, int, int], float]]:
    """Greedy cover of the open cells by rectangles of equal height: ``((j0, i0, j1, i1),
    height)`` with half-open cell ranges."""
    done = heights <= 0
    rows, cols = heights.shape
    found = []
    for j in range(rows):
        for i in range(cols):
            if done[j, i]:
                continue
            h = heights[j, i]
            i1 = i
            while i1 < cols and not done[j, i1] and heights[j, i1] == h:
                i1 += 1
            j1 = j + 1
            while j1 < rows and np.all(~done[j1, i:i1] & (heights[j1, i:i1] == h)):
                j1 += 1
            done[j:j1, i:i1] = True
            found.append(((j, i, j1, i1), float(h)))
    return found


# ---- the three worlds ------------------------------------------------------------------------


def _snap(value: float) -> float:
    return round(value / CELL) * CELL


def _mine(rng: np.random.Generator) -> dict:
    """Two tunnels, 3-4 m wide and 3.2-4 m high, each of 4 straight legs joined by right-angle
    turns, opening into a cavern of about 30 x 25 m with an 8-10 m ceiling and rock pillars."""
    cw, cd = _snap(rng.uniform(28, 34)), _snap(rng.uniform(22, 28))
    grid = HeightMap(-40, -36, cw + 40, cd + 36, "rock")  # room for 2 x 16 m legs each way
    grid.carve(0, 0, cw, cd, _snap(rng.uniform(8, 10)))
    anchors = {}
    # west tunnel leaves the cavern heading -x, east tunnel heading +x
    for name, door, heading in (("west", (0.0, _snap(rng.uniform(6, cd - 6))), (-1, 0)),
                                ("east", (cw, _snap(rng.uniform(6, cd - 6))), (1, 0))):
        width, ceiling = _snap(rng.uniform(3.0, 4.0)), rng.uniform(3.2, 4.0)
        point, direction, legs = np.array(door), np.array(heading), []
        for leg in range(4):
            length = _snap(rng.uniform(10, 16))
            end = point + direction * length
            legs.append((point, end))
            point = end
            turn = 1 if rng.random() < 0.5 else -1  # the next leg turns left or right
            direction = np.array([-direction[1], direction[0]]) * turn if leg % 2 == 0 \
                else np.array(heading)
        for a, b in legs:
            lo, hi = np.minimum(a, b) - width / 2, np.maximum(a, b) + width / 2
            grid.carve(*lo, *hi, ceiling)
        anchors[name + "_end"] = legs[-1][1]
        anchors[name + "_bend"] = legs[1][1]
    pillars = 0
    for _ in range(200):  # up to 4 rock pillars in the cavern, >= 4 m from any rock
        w, d = _snap(rng.uniform(2, 4)), _snap(rng.uniform(2, 4))
        x, y = _snap(rng.uniform(4, cw - 4 - w)), _snap(rng.uniform(4, cd - 4 - d))
        if pillars < 4 and grid.all_open(x - 4, y - 4, x + w + 4, y + d + 4):
            grid.fill(x, y, x + w, y + d, "rock")
            pillars += 1
    anchors.update(cavern_near=np.array([3.0, 3.0]), cavern_far=np.array([cw - 3.0, cd - 3.0]),
                   cavern_corner=np.array([cw - 3.0, 3.0]))
    pairs = [("west_end", "cavern_far"), ("east_end", "cavern_near"), ("west_end", "east_end"),
             ("cavern_corner", "west_bend"), ("east_bend", "cavern_near"),
             ("cavern_near", "cavern_far")]
    return dict(grid=grid, anchors=anchors, pairs=pairs,
                materials=Materials(floor="gravel", wall="rock", ceiling="rock_dark"))


def _sewer(rng: np.random.Generator) -> dict:
    """Two rooms of about 20 x 16 m with 5-6 m ceilings and square columns, joined by a
    hallway 3-3.5 m wide, 3 m high and 38-42 m long."""
    wa, da = _snap(rng.uniform(18, 24)), _snap(rng.uniform(14, 20))
    wb, db = _snap(rng.uniform(18, 24)), _snap(rng.uniform(14, 20))
    length, width = _snap(rng.uniform(38, 42)), _snap(rng.uniform(3.0, 3.5))
    hall_y = _snap(rng.uniform(5, min(da, db) - 5 - width))
    b_x = wa + length
    grid = HeightMap(-3, -3, b_x + wb + 3, max(da, db) + 3, "brick")
    grid.carve(0, 0, wa, da, rng.uniform(5, 6), wall="brick")
    grid.carve(b_x, 0, b_x + wb, db, rng.uniform(5, 6), wall="brick")
    grid.carve(wa, hall_y, b_x, hall_y + width, 3.0, wall="concrete")
    for x0, w, d in ((0.0, wa, da), (b_x, wb, db)):  # columns on a 6 m grid, 1 m square
        for cx in np.arange(x0 + 6, x0 + w - 5, 6.0):
            for cy in np.arange(6.0, d - 5, 6.0):
                grid.fill(cx - 0.5, cy - 0.5, cx + 0.5, cy + 0.5, "painted")
    mid = hall_y + width / 2
    anchors = dict(a_door=np.array([wa - 2.5, mid]), a_far=np.array([2.5, 2.5]),
                   a_top=np.array([2.5, da - 2.5]), b_door=np.array([b_x + 2.5, mid]),
                   b_far=np.array([b_x + wb - 2.5, db - 2.5]),
                   b_low=np.array([b_x + wb - 2.5, 2.5]), hall=np.array([wa + length / 2, mid]))
    pairs = [("a_far", "b_far"), ("a_top", "b_low"), ("b_far", "a_top"), ("a_far", "a_top"),
             ("b_low", "b_far"), ("hall", "a_door")]
    return dict(grid=grid, anchors=anchors, pairs=pairs,
                materials=Materials(floor="concrete_wet", wall="brick", ceiling="concrete"))


def _dome(rng: np.random.Generator) -> dict:
    """A 50 x 50 m clearing: about 45 tree trunks (radius 0.15-0.35 m, 8-14 m tall) and 10
    painted pillars (0.6-1.2 m square, 3-6 m tall), every pair at least 2.6 m apart so a 1 m
    robot fits between any two, and 3 m of open ground around every route end."""
    half = 25.0
    ends = {f"w{k}": np.array([-half + 2.0, y]) for k, y in enumerate((-15.0, 0.0, 15.0))}
    ends.update({f"e{k}": np.array([half - 2.0, y]) for k, y in enumerate((-15.0, 0.0, 15.0))})
    ends.update(n=np.array([0.0, half - 2.0]), s=np.array([0.0, -half + 2.0]))
    placed: list[tuple[np.ndarray, float]] = []  # (centre, footprint radius)

    def place(footprint: float) -> np.ndarray | None:
        for _ in range(200):
            c = rng.uniform(-half + 3, half - 3, 2)
            if all(np.linalg.norm(c - e) > 3.0 + footprint for e in ends.values()) and all(
                    np.linalg.norm(c - o) > 2.6 + footprint + r for o, r in placed):
                placed.append((c, footprint))
                return c
        return None

    cylinders, boxes = [], []
    for _ in range(45):
        radius = rng.uniform(0.15, 0.35)
        c = place(radius)
        if c is not None:
            cylinders.append(Cylinder(c, float(radius), float(rng.uniform(8, 14)), "bark"))
    for _ in range(10):
        half_side = rng.uniform(0.3, 0.6)
        c = place(half_side * math.sqrt(2))
        if c is not None:
            boxes.append(Box(np.array([*(c - half_side), 0.0]),
                             np.array([*(c + half_side), rng.uniform(3, 6)]), "painted"))
    pairs = [("w0", "e2"), ("w1", "e1"), ("w2", "e0"), ("s", "n"), ("e0", "w2"), ("n", "e1")]
    return dict(cylinders=cylinders, boxes=boxes, anchors=ends, pairs=pairs,
                bounds=(-half, -half, half, half), materials=Materials("grass", "", ""))


_BUILDERS = {"mine": _mine, "sewer": _sewer, "dome": _dome}


# ---- the realistic profile's world effects (docs/simulator.md, "Worlds") -------------------

PIPE_DIAMETERS = (0.0422, 0.0483, 0.0603, 0.0730, 0.0889, 0.1016)
"""Outside diameters of the poles, metres: steel pipe of nominal sizes 1 1/4 to 3 1/2 inches
(ASME B36.10M), what sign posts, railing posts and service pipes are made of; radii 2.1-5.1 cm."""

POLE_HEIGHT_OUTDOORS = (3.0, 6.0)
"""Height range of the dome's poles (posts), metres; underground a pole is a pipe from the floor
to the ceiling."""

TRIPOD_HEIGHT = (1.3, 1.6)
"""Height range of a tripod's head above the floor, metres: a camera or survey tripod at working
height, its head about at the flight height."""

TRIPOD_LEG_ANGLE = math.radians(22.0)
"""Splay of each tripod leg from the vertical, radians: a tripod's standard leg angle."""

TRIPOD_LEG_RADIUS = 0.015
"""Radius of a tripod leg, metres (a 30 mm tube)."""

TRIPOD_HEAD = (0.07, 0.06)
"""Radius and thickness of a tripod's head plate, metres."""

THIN_MATERIAL = "painted"
"""What the poles and tripods wear."""

MINE_VISIBILITY = 10.0
"""Visibility in the realistic mine's dust, metres: the distance over which image contrast falls
by ``1/e`` (a meteorological optical range, 5 % contrast, of about 30 m)."""

MINE_HAZE_RGB = (0.33, 0.31, 0.28)
"""Colour the mine's dust tends to with distance: grey-brown rock dust in the lamp's light."""

LOW_TEXTURE_MATERIAL = "smooth_concrete"
"""The low-texture wall surface of the realistic mine (shotcrete) and sewer (painted concrete)."""

LOW_TEXTURE_SHARE = 0.3
"""Share of the wall stretches of the realistic mine and sewer that wear
:data:`LOW_TEXTURE_MATERIAL`."""

LOW_TEXTURE_STRETCH = 4.0
"""Length of a wall stretch, metres: walls are cut at multiples of it along their length."""

_RING = 0.8
"""Free ring kept around every thin obstacle's blocking disc, metres (see
:func:`_thin_obstacles`)."""


def _route_bands(base: World) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per route: candidate points ``(M, 2)`` along the base world's path, every 0.25 m, shifted
    sideways by -1.5 to 1.5 m, and each one's sideways distance ``(M,)``."""
    bands = []
    offsets = np.arange(-6, 7) * 0.25
    for route in base.routes:
        path = base.find_path(route.start[:2], route.goal[:2], ROBOT_RADIUS)
        if path is None:  # no route of the ideal worlds lacks one (tests/test_sim_world.py)
            bands.append((np.zeros((0, 2)), np.zeros(0)))
            continue
        points, normals = [], []
        for a, b in zip(path[:-1], path[1:]):
            length = float(np.linalg.norm(b - a))
            if length == 0.0:
                continue
            steps = max(1, int(math.ceil(length / 0.25)))
            points.append(a + np.linspace(0.0, 1.0, steps, endpoint=False)[:, None] * (b - a))
            normals.append(np.tile([-(b - a)[1] / length, (b - a)[0] / length], (steps, 1)))
        points, normals = np.concatenate(points), np.concatenate(normals)
        band = points[:, None, :] + offsets[None, :, None] * normals[:, None, :]
        bands.append((band.reshape(-1, 2), np.tile(np.abs(offsets), len(points))))
    return bands


def _thin_obstacles(base: World, rng: np.random.Generator) -> tuple[list[Cylinder], list[Rod]]:
    """A tripod near one route and a pole near each route of ``base``, on or beside the path
    the route's planner flies there, leaving every route a path for the robot.

    Why a route keeps its path: seen at flight height ``h``, an obstacle reaching ``e`` from its
    axis at heights ``>= h - R`` blocks the robot's centre (radius ``R``) only inside the disc of
    radius ``R + e`` round its axis. It is placed only where the clearance, to the world and to
    the obstacles already placed, is at least ``2 R + e + ring``; clearance is 1-Lipschitz, so the
    annulus of width ``ring`` round that disc keeps clearance ``>= R`` and any path through the
    disc can go round it instead. ``ring`` is :data:`_RING`, wide enough for the planner's
    0.25 m grid to find the way round too. Route ends keep ``R`` plus a margin from every
    obstacle's whole footprint. :func:`build_world` still checks every route and drops
    obstacles (last placed first) until each has its path."""
    h, radius = base.cruise_height, ROBOT_RADIUS
    bands = _route_bands(base)
    points = np.concatenate([p for p, _ in bands])
    sideways = np.concatenate([s for _, s in bands])
    owner = np.concatenate([np.full(len(p), k) for k, (p, _) in enumerate(bands)])
    clearance = base.obstacle_clearance(np.column_stack([points, np.full(len(points), h)]))
    ends = np.array([end[:2] for r in base.routes for end in (r.start, r.goal)])
    to_ends = np.linalg.norm(points[:, None] - ends[None], axis=2).min(axis=1)
    xmin, ymin, xmax, ymax = base.bounds
    placed: list[tuple[np.ndarray, float]] = []  # (axis xy, reach at flight height)

    def pick(routes, reach_flight: float, reach_floor: float) -> np.ndarray | None:
        free = clearance.copy()
        for centre, reach in placed:
            free = np.minimum(free, np.linalg.norm(points - centre, axis=1) - reach)
        margin = reach_floor + 0.5
        ok = (np.isin(owner, routes) & (free >= 2 * radius + reach_flight + _RING)
              & (to_ends >= radius + margin)
              & (points[:, 0] >= xmin + margin) & (points[:, 0] <= xmax - margin)
              & (points[:, 1] >= ymin + margin) & (points[:, 1] <= ymax - margin))
        on_path = ok & (sideways <= 0.5)  # in the robot's way if possible, else beside it
        choices = np.flatnonzero(on_path if on_path.any() else ok)
        if not len(choices):
            return None
        return points[choices[rng.integers(len(choices))]]

    cylinders, rods = [], []
    head_radius, head_thickness = TRIPOD_HEAD
    height = float(rng.uniform(*TRIPOD_HEIGHT))
    spread = height * math.tan(TRIPOD_LEG_ANGLE)  # feet's distance from the axis
    low = max(0.0, h - radius)  # the lowest height that reaches the robot at flight height
    reach_flight = max(head_radius, spread * (1 - low / height) + 2 * TRIPOD_LEG_RADIUS)
    centre = pick(range(len(base.routes)), reach_flight, spread + 2 * TRIPOD_LEG_RADIUS)
    if centre is not None:
        placed.append((centre, reach_flight))
        apex = np.array([*centre, height])
        yaw = rng.uniform(0.0, 2 * math.pi)
        for k in range(3):
            angle = yaw + 2 * math.pi * k / 3
            foot = np.array([*(centre + spread * np.array([math.cos(angle), math.sin(angle)])),
                             0.0])
            rods.append(Rod(foot, apex.copy(), TRIPOD_LEG_RADIUS, THIN_MATERIAL))
        rods.append(Rod(apex - [0, 0, head_thickness / 3], apex + [0, 0, 2 * head_thickness / 3],
                        head_radius, THIN_MATERIAL))
    for k in range(len(base.routes)):
        pole_radius = float(rng.choice(PIPE_DIAMETERS)) / 2
        centre = pick([k], pole_radius, pole_radius)
        if centre is None:
            continue
        placed.append((centre, pole_radius))
        if base.heights is None:
            pole_height = float(rng.uniform(*POLE_HEIGHT_OUTDOORS))
        else:  # floor to ceiling: the lowest ceiling over the pole's footprint
            lo = np.floor((centre - pole_radius - base.origin) / CELL).astype(int)
            hi = np.floor((centre + pole_radius - base.origin) / CELL).astype(int)
            pole_height = float(base.heights[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1].min())
        cylinders.append(Cylinder(centre, pole_radius, pole_height, THIN_MATERIAL))
    return cylinders, rods


def _low_texture_walls(panels: list[Box], rng: np.random.Generator) -> list[Box]:
    """``panels`` with each wall cut into stretches at multiples of :data:`LOW_TEXTURE_STRETCH`
    along its length, a :data:`LOW_TEXTURE_SHARE` of them (drawn from ``rng``) wearing
    :data:`LOW_TEXTURE_MATERIAL`, neighbours of one material merged again. Painted columns
    keep their paint. The surfaces are the same; only their texture changes."""
    out = []
    for panel in panels:
        if panel.lo[2] == panel.hi[2] or panel.material == "painted":
            out.append(panel)  # a ceiling, or a painted column
            continue
        along = 1 if panel.lo[0] == panel.hi[0] else 0
        start, stop = panel.lo[along], panel.hi[along]
        cuts = np.arange(math.floor(start / LOW_TEXTURE_STRETCH) + 1,
                         math.ceil(stop / LOW_TEXTURE_STRETCH)) * LOW_TEXTURE_STRETCH
        edges = [start, *cuts.tolist(), stop]
        smooth = rng.random(len(edges) - 1) < LOW_TEXTURE_SHARE
        pieces = _runs([LOW_TEXTURE_MATERIAL if s else panel.material for s in smooth])
        for first, last, material in pieces:
            lo, hi = panel.lo.copy(), panel.hi.copy()
            lo[along], hi[along] = edges[first], edges[last]
            out.append(Box(lo, hi, material, panel.facing))
    return out


def build_world(name: str, seed: int = 0, profile: str = "ideal") -> World:
    """The world ``name`` (one of :data:`WORLD_NAMES`) generated from ``seed``; the same
    (name, seed, profile) always gives the same world.

    ``profile`` (one of :data:`~drivers.sim.options.PROFILES`): ``ideal`` is the world alone;
    ``realistic`` is the same world (the same draws, the same surfaces) with the effects of
    docs/simulator.md drawn from further streams of the seed: thin poles and a tripod near the
    routes (every route keeps its path for a :data:`ROBOT_RADIUS` robot), low-texture stretches
    of the mine's and sewer's walls, and dust in the mine (:data:`MINE_VISIBILITY`)."""
    if name not in WORLD_NAMES:
        raise ValueError(f"unknown world {name!r}; choose one of: {', '.join(WORLD_NAMES)}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r}; choose one of: {', '.join(PROFILES)}")
    world = _build_ideal(name, int(seed))
    if profile == "ideal":
        return world
    streams = {effect: np.random.default_rng([int(seed), zlib.crc32(name.encode()),
                                              zlib.crc32(effect.encode())])
               for effect in ("thin", "walls")}
    poles, rods = _thin_obstacles(world, streams["thin"])
    boxes = list(world.boxes)
    if world.heights is not None:
        boxes = _low_texture_walls(boxes, streams["walls"])
    hazy = name == "mine"
    while True:
        realistic = replace(world, boxes=tuple(boxes), cylinders=(*world.cylinders, *poles),
                            rods=tuple(rods), profile=profile,
                            visibility=MINE_VISIBILITY if hazy else None,
                            haze_rgb=MINE_HAZE_RGB if hazy else None)
        if all(realistic.find_path(r.start[:2], r.goal[:2], ROBOT_RADIUS) is not None
               for r in realistic.routes) or not (poles or rods):
            return realistic
        if poles:  # should not happen (see _thin_obstacles); drop the last placed and retry
            poles.pop()
        else:
            rods.clear()


def _build_ideal(name: str, seed: int) -> World:
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    spec = _BUILDERS[name](rng)
    materials: Materials = spec["materials"]
    routes = tuple(
        Route(f"{name}-{k + 1}:{a}->{b}", np.array([*spec["anchors"][a], 0.0]),
              np.array([*spec["anchors"][b], CRUISE_HEIGHT]), CRUISE_HEIGHT)
        for k, (a, b) in enumerate(spec["pairs"]))
    grid: HeightMap | None = spec.get("grid")
    if grid is None:
        xmin, ymin, xmax, ymax = spec["bounds"]
        floor = Box(np.array([xmin - 150, ymin - 150, 0.0]), np.array([xmax + 150, ymax + 150,
                                                                        0.0]), materials.floor, 1.0)
        return World(name, int(seed), spec["bounds"], routes, tuple(spec["boxes"]),
                     tuple(spec["cylinders"]), floor, outdoor=True)
    open_rows, open_cols = np.nonzero(grid.heights > 0)
    bounds = (float(grid.origin[0] + open_cols.min() * CELL),
              float(grid.origin[1] + open_rows.min() * CELL),
              float(grid.origin[0] + (open_cols.max() + 1) * CELL),
              float(grid.origin[1] + (open_rows.max() + 1) * CELL))
    floor = Box(np.array([bounds[0], bounds[1], 0.0]), np.array([bounds[2], bounds[3], 0.0]),
                materials.floor, 1.0)
    heights = grid.heights.copy()
    heights.setflags(write=False)
    return World(name, int(seed), bounds, routes, tuple(grid.panels(materials.ceiling)), (),
                 floor, outdoor=False, heights=heights, origin=grid.origin.copy())
