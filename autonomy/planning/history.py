"""A short history of depth frames and the collision check of spheres against it.

After NanoMap (Florence et al., 2018) as Lee et al. (2024) use it: the planner checks a point
``c`` that stands for the sphere ``B(c, R)`` of the robot radius ``R`` against the newest depth
frames, not a fused map, and looks further back in time only where the newer frames cannot tell.

**The exact rule.** In one frame, with ``c = (x, y, z)`` in that camera's optical frame and
``L = |c|``, the sphere lies in observed free space when every pixel ray through it sees its
surface beyond the point where the ray *leaves* the sphere. A unit ray ``d`` at angle ``theta``
from the centre ray passes the centre at the distance ``b = L sin(theta)`` (its impact) and,
for ``b <= R``, leaves the sphere at the distance along the ray

    s2(b) = sqrt(L² - b²) + sqrt(R² - b²)          (= d.c + sqrt((d.c)² - L² + R²))

which falls from ``L + R`` on the centre ray to the tangent distance ``sqrt(L² - R²)`` at the
rim (both terms fall as ``b`` grows). A surface seen on the ray at a distance ``r >= s2(b)`` is
beyond the sphere; ``r < s2(b)`` puts it inside (or in front of, hiding) the sphere.

**Ranges, not depths.** Each frame's image is stored as the *range* along each pixel's ray,
``r = z_pixel * sqrt(1 + ((u - cx)/fx)² + ((v - cy)/fy)²)``, so the rule compares a range with
``s2(b)``, which depends on the impact ``b`` alone. (With depths one compares ``z_pixel`` with
``s2(b) d_z``, and ``d_z``, the cosine of the ray to the optical axis, varies across a window by
up to ``cos(gamma - alpha) - cos(gamma + alpha)`` for a sphere of angular radius ``alpha`` seen
at ``gamma`` off axis: a bound over the window loses far more than the one multiply per pixel
that ranges cost when the frame is added.)

**Rings.** The rays of impact ``b <= q R`` form the cone of half-angle ``asin(q R / L)`` about
the centre ray: the tangent cone of the concentric sphere ``B(c, q R)``. Its image's bounding
box, exact from the tangent lines (in the x-z plane the sphere is a disc of radius ``q R`` at
``(x, z)``, so ``u = fx tan(atan2(x, z) ± asin(q R / sqrt(x² + z²))) + cx``; likewise ``v``) is
the *window* ``W(q)``. With ``1 = q_0 > q_1 > ... > q_{n-1} > q_n = 0`` the sphere is judged

    free  when  min over W(q_k) of r  >=  T_k = s2(q_{k+1} R)    for every k = 0 .. n-1.

Conservative: a pixel whose ray has impact ``b`` in ``(q_{k+1} R, q_k R]`` lies in ``W(q_k)``,
where the test asks ``r >= s2(q_{k+1} R) >= s2(b)`` (``s2`` falls with ``b``), and the centre ray
(``b = 0``) is in ``W(q_{n-1})`` with ``T_{n-1} = L + R``. So *free* implies the exact rule on
every pixel ray through the sphere. The rest is caution: the pixels of a square window outside
its cone (the corners, up to ``sqrt(2) q_k R`` off the centre ray, the outer window's missing
the sphere), and on a ray of ring ``k`` the test asks at most ``R sqrt(1 - q_{k+1}²) -
R sqrt(1 - q_k²) + sqrt(L² - q_{k+1}² R²) - sqrt(L² - q_k² R²)`` more than the exact rule.
The fractions, ``q_k = sqrt(1 - (k/n)²)``, make the first difference ``R / n`` in every ring:
the far side ``sqrt(R² - b²)`` of the sphere is cut into ``n`` equal steps in depth, which puts
most rings near the rim, where ``s2`` falls fastest (its slope is infinite at the rim). For
``n = 4``, ``q = 1, 0.968, 0.866, 0.661``: the outer window may see a surface at the tangent
distance plus about ``R / 4``, where the old single test (every pixel at least ``z + R`` deep)
asked for the sphere's far side ``R`` farther; that is what lets the planner fly 1.5 m over a
floor with ``R = 1``. A fraction of the angular radius, ``q`` in place of ``f`` (the cone of
half-angle ``f alpha``), differs from it only through ``asin``; the impact is what ``s2``
depends on. The outer window is read first: if its minimum is at least ``L + R`` (every
``T_k``) the sphere is free, if below ``T_0`` occupied, and only in between are the ``n - 1``
inner windows read (each is inside the outer one, so the shortcut skips no pixel that a ray
through the sphere needs; it skips only pixels that widening, below, may add to an inner
window). In open space most spheres are decided by one window.

One frame's verdict on a point:

- *unseen*: the centre is behind the camera or outside the image, the sphere reaches the camera
  plane (``z <= R``; see near the vehicle), or its far side lies beyond ``max_range``
  (``z + R > max_range``). Windows are clipped to the image: a frame judges the part of the
  sphere it sees;
- *unknown* when any pixel of any window (the outer window holds the others, unless one was
  widened, below) is NaN, non-positive or of low confidence (:func:`_known_range`: one less
  disparate than every confident pixel counts as the farthest confident depth, or as
  ``far_tail_share`` of its own where more); *free* by the ring rule; *occupied* otherwise.
  Depths beyond ``max_range`` count as ``max_range``: the farthest point of the sphere has
  ``z + R <= max_range``, so such a pixel's ray is free past the sphere (its range
  ``max_range / d_z`` exceeds every exit distance ``s2 <= (z + R) / d_z`` on that ray). So a
  sky rendered as ``max_range`` or beyond is free, but a NaN sky is unknown, and unknown is
  unsafe: in the simulator NaN means "nothing within range", from a network it
  means "no answer", and the history cannot tell which, so the renderer or the depth stage
  must write ``max_range`` (confident) where it knows the sky is empty.

Which frame decides: a *strong* verdict is *occupied*, or *free* with the outer window inside
the image; *free* on a clipped window is *weak*. The newest frame with a strong verdict decides;
failing one, the newest weak *free*; failing both the point is unknown, which the planner treats
as unsafe. So space outside every frame's view, beyond range or of low confidence is unsafe
unless an older frame saw it free, and an obstacle that has left the view is remembered as long
as its frame is kept. The exact rule changes none of this: it concerns how one frame reads its
pixels, while clipping (the frame saw part of the sphere) and the order of frames concern which
frame may speak.

Near the vehicle: the vehicle is at ``start``, so its own sphere ``B(start, R)`` is free (the
planner never checks the start point). A sphere that reaches the camera plane (``z <= R``) has
no bounded image (the cone of rays through it is not in front of the camera), so the exact rule
cannot be applied through windows. Such a point within ``2 R`` of ``start`` (the first second
or so of a primitive) is occupied (strong) when a surface is seen in front of its centre (the
centre's pixel nearer than ``L``); free (weak) when the image's least range is at least
``L + R`` (every ray through its sphere leaves it within ``L + R``); else it is judged ray by
ray on ``NEAR_BLOCK_PX`` blocks of pixels (:meth:`DepthHistory._judge_by_blocks`: the exact rule
with each block's least range against the largest exit distance of any of its rays), free
(weak) when every block meeting the sphere passes, occupied (strong) when the known pixels of
a block meeting it fail (whatever unknown pixels its blocks hold).
Weak, because the part of such a sphere outside the view is not seen by this frame: older
frames, taken from farther back, usually see these spheres whole, and their strong verdict
wins. Occupied is strong, because a surface was measured within the block rule's reach: an
older frame from farther back may have missed it (a realistic sewer flight's estimated depth
read a thin pipe 1.0–1.4 m away at 2.4–3.8 m, then rightly at 0.7–0.9 m; the older frames'
free verdicts flew the vehicle into it). (An earlier rule judged such a point by its
centre's ray alone; in simulation it let a braking vehicle graze the corner of a hallway's
entrance, whose edge no centre ray met. The whole-image test alone found nothing free near the
vehicle between walls nearer than about 2 m.) A sphere within ``2 R`` that the rings refuse
gets the block rule too, as a second opinion: in a narrow passage the rings' caution (about
``R / n``) is most of the room there is. A frame must see the point: one beside, below or
behind every camera stays unknown, and farther than ``2 R`` from the start a sphere reaching a
frame's camera plane is unseen by that frame.

Speed: each frame keeps a sparse table of its range image, ``table[k][v, u]`` the minimum over
the ``2^k x 2^k`` square anchored at ``(u, v)``, with unknown pixels stored as -1 so that one
minimum answers both questions (negative: unknown). A ``w x h`` window is answered exactly by
4 look-ups at level ``k = floor(log2(min(w, h)))`` when its long side is at most ``2^(k+1)``
(square-ish windows, the usual case), else 16 once its short side is at least half its long
side; a thinner window (clipped at the image border) is first widened inside the image,
which only adds pixels (conservative). The outer windows of all points go through one
gather, the inner windows of those it leaves undecided through a second. The planner needs
every point of a primitive free, so it passes each point's primitive as its group: a primitive
found occupied somewhere is not looked up in older frames (in a cluttered view this halves the
points the older frames judge), and within a frame the block rule is left off the points of a
primitive that the rings or a centre ray found occupied.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from autonomy.geometry import PinholeCamera, invert_pose

_UNKNOWN = np.float32(-1.0)

HOLE_FILL_PX = 15
"""Unknown pixels within this many pixels of known ones take the nearest range among those
(:func:`fill_small_holes`)."""

NEAR_BLOCK_PX = (32, 16)
"""Sides of the square pixel blocks the spheres near the vehicle are checked against, ray by
ray, coarse first (cheap; a sphere it frees is free) and the finer only for what the coarse
refuses (powers of two: the blocks are read from the sparse minimum table)."""

NEAR_CELL_M = 0.05
"""Spheres near the vehicle are checked by the block rule per cube of this side: the arcs'
first points nearly coincide, and one sphere about the cube's centre, grown by its half
diagonal, holds the sphere of every point in the cube."""


@dataclass(frozen=True)
class CheckResult:
    """The verdict on ``N`` points.

    ``free`` (N,) bool; ``clearance`` (N,) metres, in the deciding frame, by which the observed
    surface clears the ring rule, ``min_k (min over W(q_k) of r - T_k)``, or ``min over W(1)
    of r - (L + R)`` where the outer window decided alone: a lower bound on how far beyond the
    sphere's exit point the surface lies along any pixel ray through it (>= 0 where free;
    +inf where the point was judged by its ray alone; NaN where unknown);
    ``frame`` (N,) the deciding frame's time, NaN where unknown; ``occupied`` (N,) bool: not
    free, and a frame measured a surface too near the point for its rule (a point neither free
    nor occupied was unknown to every frame that judged it: out of view, beyond range).
    """

    free: np.ndarray
    clearance: np.ndarray
    frame: np.ndarray
    occupied: np.ndarray


class _Frame:
    """One depth frame: its pose, camera, time, the sparse minimum table of its ranges and, per
    side in ``NEAR_BLOCK_PX``, the least range of each such square block (raveled, -1 where
    any pixel is unknown) and the least of its known pixels (+inf where none is known)."""

    def __init__(self, table: np.ndarray, T_W_C: np.ndarray, camera: PinholeCamera, t: float):
        T_C_W = invert_pose(T_W_C)
        self.R_C_W = T_C_W[:3, :3]
        self.t_C_W = T_C_W[:3, 3]
        self.table = table
        self.flat = table.reshape(-1)
        self.least = float(table[0].min())  # negative when any pixel is unknown
        self.blocks = {side: table[side.bit_length() - 1, ::side, ::side].reshape(-1)
                       for side in NEAR_BLOCK_PX}
        known = np.where(table[0] >= 0.0, table[0], np.float32(np.inf))
        self.known_blocks = {side: _block_minima(known, side) for side in NEAR_BLOCK_PX}
        self.camera = camera
        self.focal = np.array([[camera.fx], [camera.fy]])  # image x, y: (2, 1) for broadcasting
        self.centre = np.array([[camera.cx], [camera.cy]])
        self.edge = np.array([[camera.width - 0.5], [camera.height - 0.5]])
        self.t = t


class DepthHistory:
    """The newest ``max_frames`` depth frames, at most ``max_age_s`` older than the newest, and
    the sphere check described in the module docstring."""

    def __init__(self, *, robot_radius: float = 1.0, min_confidence: float = 0.3,
                 max_range: float = 10.0, max_frames: int = 8, max_age_s: float = 2.0,
                 rings: int = 4, near_tail_share: float = 0.0, far_tail_share: float = 0.0):
        if not robot_radius > 0.0:
            raise ValueError(f"robot_radius must be > 0, got {robot_radius}")
        if not 0.0 <= min_confidence <= 1.0:
            raise ValueError(f"min_confidence must be in [0, 1], got {min_confidence}")
        if not max_range > robot_radius:
            raise ValueError(f"max_range must exceed robot_radius, got {max_range}")
        if max_frames < 1:
            raise ValueError(f"max_frames must be >= 1, got {max_frames}")
        if not max_age_s > 0.0:
            raise ValueError(f"max_age_s must be > 0, got {max_age_s}")
        if not 1 <= rings <= 16:
            raise ValueError(f"rings must be in [1, 16], got {rings}")
        if not 0.0 <= near_tail_share <= 1.0:
            raise ValueError(f"near_tail_share must be in [0, 1], got {near_tail_share}")
        if not 0.0 <= far_tail_share <= 1.0:
            raise ValueError(f"far_tail_share must be in [0, 1], got {far_tail_share}")
        self.robot_radius = float(robot_radius)
        self.min_confidence = float(min_confidence)
        self.max_range = float(max_range)
        self.max_frames = int(max_frames)
        self.max_age_s = float(max_age_s)
        self.near_tail_share = float(near_tail_share)
        self.far_tail_share = float(far_tail_share)
        #: The impact fractions q_0 = 1 > ... > q_{n-1} of the windows and q_1 .. q_n = 0 of
        #: their thresholds (module docstring: rings).
        k = np.arange(rings + 1) / rings
        self.ring_fractions = np.sqrt(1.0 - k * k)
        self._frames: list[_Frame] = []
        self._ray_norms: tuple[PinholeCamera, np.ndarray] | None = None
        self._block_rays: tuple[PinholeCamera, dict] | None = None

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def times(self) -> list[float]:
        """Times of the kept frames, oldest first."""
        return [f.t for f in self._frames]

    def clear(self) -> None:
        """Forget every frame."""
        self._frames.clear()

    def add(self, depth, confidence, T_W_C, camera: PinholeCamera, t: float) -> None:
        """Keep a frame: ``depth`` (H, W) metres (NaN unknown), ``confidence`` (H, W) in [0, 1],
        the camera's pose ``T_W_C`` when it was taken at time ``t``. Drops the oldest frames
        beyond ``max_frames`` or ``max_age_s`` before the newest."""
        check_camera(camera)
        shape = (camera.height, camera.width)
        depth = np.asarray(depth)
        confidence = np.asarray(confidence)
        if depth.shape != shape:
            raise ValueError(f"depth image must have the camera's shape {shape}, "
                             f"got {depth.shape}")
        if confidence.shape != shape:
            raise ValueError(f"confidence must have the depth image's shape {shape}, "
                             f"got {confidence.shape}")
        if not math.isfinite(t):
            raise ValueError(f"frame time must be finite, got {t!r}")
        T_W_C = as_pose(T_W_C, "T_W_C")
        image = _known_range(depth, confidence, self.min_confidence, self.max_range,
                             self._norms(camera), self.near_tail_share, self.far_tail_share)
        image = fill_small_holes(image, HOLE_FILL_PX)
        frame = _Frame(min_table(image), T_W_C, camera, float(t))
        bisect.insort(self._frames, frame, key=lambda f: f.t)
        newest = self._frames[-1].t
        self._frames = [f for f in self._frames[-self.max_frames:]
                        if f.t >= newest - self.max_age_s]

    def check(self, points_W, start_W=None, now: float | None = None,
              groups=None, radius: float | None = None) -> CheckResult:
        """Judge the spheres of radius ``robot_radius`` (or the smaller ``radius``) about
        ``points_W`` (N, 3).

        ``start_W`` (3,): the vehicle's present position (module docstring: near the vehicle;
        without it no point is judged by its ray); ``now``: ignore frames older than
        ``now - max_age_s``; ``groups`` (N,) int >= 0: for a caller that needs every point of
        a group free (a primitive), once a frame finds one point of a group occupied the
        group's other points are not judged further (reported not free, clearance and frame
        NaN: the group is unsafe whatever they are). All points go through each frame in one
        vectorised pass, newest frame first; a frame only sees the points no newer frame has
        decided strongly.
        """
        points = np.asarray(points_W, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {points.shape}")
        n = len(points)
        R = self._radius(radius)
        if groups is not None:
            groups = np.asarray(groups)
            if groups.shape != (n,) or groups.dtype.kind not in "iu" or (groups < 0).any():
                raise ValueError(f"groups must be {n} integers >= 0, one per point")
        near = np.zeros(n, dtype=bool)
        if start_W is not None:
            start = np.asarray(start_W, dtype=float).reshape(3)
            near = np.sum((points - start) ** 2, axis=1) <= (2.0 * R) ** 2
        frames = [f for f in self._frames if now is None or f.t >= now - self.max_age_s]
        verdict = np.zeros(n, dtype=np.int8)  # 0 undecided, 1 free, 2 occupied (strong)
        clearance = np.full(n, np.nan)
        frame_t = np.full(n, np.nan)
        weak_clearance = np.full(n, np.nan)
        weak_t = np.full(n, np.nan)
        surface_near = np.zeros(n, dtype=bool)
        pending = np.arange(n)
        for frame in reversed(frames):
            if len(pending) == 0:
                break
            free, strong, gap = self._judge(frame, points[pending], near[pending], R,
                                            np.isnan(weak_t[pending]),
                                            None if groups is None else groups[pending])
            surface_near[pending[~free & np.isfinite(gap)]] = True
            decided = strong
            index = pending[decided]
            verdict[index] = np.where(free[decided], 1, 2)
            clearance[index] = gap[decided]
            frame_t[index] = frame.t
            weak = free & ~strong & np.isnan(weak_t[pending])
            weak_t[pending[weak]] = frame.t
            weak_clearance[pending[weak]] = gap[weak]
            pending = pending[~decided]
            if groups is not None and (strong & ~free).any():
                unsafe = np.zeros(groups.max() + 1, dtype=bool)
                unsafe[groups[verdict == 2]] = True
                dropped = unsafe[groups[pending]]
                weak_t[pending[dropped]] = np.nan  # not judged: neither free nor unknown
                pending = pending[~dropped]
        use_weak = (verdict == 0) & ~np.isnan(weak_t)
        clearance[use_weak] = weak_clearance[use_weak]
        frame_t[use_weak] = weak_t[use_weak]
        free = (verdict == 1) | use_weak
        return CheckResult(free, clearance, frame_t, (verdict == 2) | (surface_near & ~free))

    def _radius(self, radius: float | None) -> float:
        """The sphere's radius of a check: ``robot_radius``, or a smaller positive one."""
        if radius is None:
            return self.robot_radius
        if not 0.0 < radius <= self.robot_radius:
            raise ValueError(f"radius must be in (0, {self.robot_radius:g}], got {radius!r}")
        return float(radius)

    def _norms(self, camera: PinholeCamera) -> np.ndarray:
        """``|(x/z, y/z, 1)|`` of every pixel's ray (float32), kept for the last camera."""
        if self._ray_norms is None or self._ray_norms[0] != camera:
            self._ray_norms = (camera, ray_norms(camera))
        return self._ray_norms[1]

    def _blocks(self, camera: PinholeCamera, side: int) -> tuple[np.ndarray, ...]:
        """``(directions, spread, cos(spread), sin(spread))`` of :func:`block_rays` (float32)
        for ``side``, kept for the last camera."""
        if self._block_rays is None or self._block_rays[0] != camera:
            self._block_rays = (camera, {})
        kept = self._block_rays[1]
        if side not in kept:
            directions, spread = block_rays(camera, side)
            kept[side] = tuple(a.astype(np.float32) for a in
                               (directions, spread, np.cos(spread), np.sin(spread)))
        return kept[side]

    def _judge_by_blocks(self, frame: _Frame, p: np.ndarray, R: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(free, clearance, occupied)`` of spheres of radius ``R`` about ``p`` (M, 3), camera
        frame, by the exact rule on every pixel block (for spheres near the vehicle): a ray at angle
        ``theta`` from the centre's direction meets the sphere when ``b = L sin(theta) <= R``
        (and, from outside it, ``theta < 90°``) and leaves it at ``s2(theta) = L cos(theta) +
        sqrt(R² - b²)``, which falls as ``theta`` grows. A block whose rays lie within
        ``delta`` of its centre ray, at ``theta_c`` from the centre's direction, has no ray
        nearer in angle than ``theta_c - delta``; its least range must reach ``s2`` there.
        Free when every block meeting the sphere is known and passes (of a sphere reaching the
        camera plane only the part in view: the caller makes that verdict weak); the
        clearance is the least margin. Occupied when the known pixels of a block meeting it
        fail, whatever unknown pixels the blocks hold: a surface was measured there. Points are
        taken per :data:`NEAR_CELL_M` cube (the caution that costs is the cube's half
        diagonal, 4 cm)."""
        centres, inverse = _cells(p, NEAR_CELL_M)
        radius = R + NEAR_CELL_M * math.sqrt(0.75)
        free, margin, occupied = self._blocks_rule(frame, centres, radius, NEAR_BLOCK_PX[0])
        for side in NEAR_BLOCK_PX[1:]:
            again = np.flatnonzero(~free)
            if len(again) == 0:
                break
            free[again], margin[again], occupied[again] = self._blocks_rule(
                frame, centres[again], radius, side)
        return free[inverse], margin[inverse], occupied[inverse]

    def _blocks_rule(self, frame: _Frame, p: np.ndarray, R: float, side: int):
        """The block rule of :meth:`_judge_by_blocks` on spheres of radius ``R``, with blocks
        of ``side`` pixels."""
        directions, spread, cos_spread, sin_spread = self._blocks(frame.camera, side)
        p = p.astype(np.float32)
        L = np.sqrt(np.sum(p * p, axis=1))
        cos_c = directions @ (p / L[:, None]).T  # (K, M)
        # only blocks within the sphere's angular radius (all, from inside it) can meet it
        reach = np.where(L > R, np.arcsin(np.minimum(R / L, 1.0)), np.pi)
        block, point = np.nonzero(cos_c >= np.cos(np.minimum(spread[:, None] + reach, np.pi)))
        cos_c = np.clip(cos_c[block, point], -1.0, 1.0)
        sin_c = np.sqrt(1.0 - cos_c * cos_c)
        cos_d, sin_d = cos_spread[block], sin_spread[block]
        within = cos_c >= cos_d  # the block holds the centre's direction: theta can be 0
        cos_t = np.where(within, 1.0, cos_c * cos_d + sin_c * sin_d)  # cos(theta_c - delta)
        sin_t = np.where(within, 0.0, sin_c * cos_d - cos_c * sin_d)
        Lp = L[point]
        b = Lp * sin_t
        meets = (b <= R) & ((Lp <= R) | (cos_t > 0.0))
        exit_distance = Lp * cos_t + np.sqrt(np.maximum(R * R - b * b, 0.0))
        ranges = frame.blocks[side][block]
        m = len(p)
        margin = np.full(m, np.inf, dtype=np.float32)
        np.minimum.at(margin, point[meets], (ranges - exit_distance)[meets])
        unknown = np.zeros(m, dtype=bool)
        unknown[point[meets & (ranges < 0.0)]] = True
        occupied = np.zeros(m, dtype=bool)
        occupied[point[meets & (frame.known_blocks[side][block] < exit_distance)]] = True
        known = ~unknown
        return (known & (margin >= 0.0), np.where(known, margin.astype(float), np.nan),
                occupied)

    def _judge(self, frame: _Frame, points: np.ndarray, near: np.ndarray, R: float,
               unfreed: np.ndarray | None = None, groups: np.ndarray | None = None):
        """``(free, strong, clearance)`` of one frame on the spheres of radius ``R`` about
        ``points`` (M, 3); a point neither free nor strong is unknown to this frame. Module
        docstring for the rules. ``unfreed``: the points no newer frame has called free
        (weakly); only those get the block rule where it could only call them weakly free.
        ``groups`` (M,): the block rule, the costly part, is left off the points whose group
        this frame finds occupied by the other rules (they stay unknown, or occupied by the
        rings)."""
        cam = frame.camera
        H, W = cam.height, cam.width
        unfreed = np.ones(len(points), dtype=bool) if unfreed is None else unfreed
        p = points @ frame.R_C_W.T + frame.t_C_W
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam.fx * x / z + cam.cx
            v = cam.fy * y / z + cam.cy
        in_image = (z > 0.0) & (u >= -0.5) & (u < W - 0.5) & (v >= -0.5) & (v < H - 0.5)
        free = np.zeros(len(p), dtype=bool)
        strong = np.zeros(len(p), dtype=bool)
        gap = np.full(len(p), np.nan)
        rest = np.flatnonzero(near & in_image & (z <= R))
        if len(rest):
            rest = self._judge_by_ray(frame, p, u, v, R, rest, free, strong, gap)
            rest = rest[unfreed[rest]]
        whole = np.flatnonzero(in_image & (z > R) & (z + R <= self.max_range))
        retry = np.zeros(0, dtype=np.intp)
        if len(whole):
            clipped = self._judge_by_rings(frame, p[whole], R, whole, free, strong, gap)
            # near the vehicle, where a narrow passage leaves little room, a sphere the rings
            # refuse gets the finer block-by-block rule (the rings' caution is about R / n)
            retry = whole[near[whole] & strong[whole] & ~free[whole]]
        if groups is not None and len(rest) + len(retry):
            occupied = strong & ~free
            occupied[retry] = False  # the block rule may yet free these
            dead = np.isin(groups, groups[occupied])
            rest, retry = rest[~dead[rest]], retry[~dead[retry]]
        if len(rest):
            # a known pixel too near is a surface measured there: no older frame overrules it
            free[rest], gap[rest], strong[rest] = self._judge_by_blocks(frame, p[rest], R)
        if len(retry):
            again, again_gap, _ = self._judge_by_blocks(frame, p[retry], R)
            freed = retry[again]
            free[freed], gap[freed] = True, again_gap[again]
            strong[freed] = ~clipped[np.searchsorted(whole, freed)]
        return free, strong, gap

    def _judge_by_ray(self, frame: _Frame, p: np.ndarray, u: np.ndarray, v: np.ndarray,
                      R: float, ray: np.ndarray, free: np.ndarray, strong: np.ndarray,
                      gap: np.ndarray) -> np.ndarray:
        """The near-vehicle rule's first steps on the points ``ray`` (those reaching the
        camera plane), written into ``free``, ``strong``, ``gap``: occupied if the centre's
        pixel sees a surface in front of the centre, free if the image's least range exceeds
        ``L + R``. The points left for the block rule."""
        d = frame.table[0, np.floor(v[ray] + 0.5).astype(np.intp),
                        np.floor(u[ray] + 0.5).astype(np.intp)]
        distance = np.sqrt(np.sum(p[ray] ** 2, axis=1))
        nearest = frame.least  # the image's least range, negative if any pixel is unknown
        free[ray] = (nearest >= 0.0) & (nearest >= distance + R)
        strong[ray] = (d >= 0.0) & (d < distance)
        gap[ray[free[ray]]] = nearest - (distance[free[ray]] + R)
        # the rest, ray by ray, block by block (a sphere holding the camera meets every ray,
        # so one unknown pixel keeps it from being free, but a measured surface may still
        # make it occupied)
        return ray[~free[ray] & ~strong[ray]]

    def _judge_by_rings(self, frame: _Frame, c: np.ndarray, R: float, whole: np.ndarray,
                        free: np.ndarray, strong: np.ndarray, gap: np.ndarray) -> np.ndarray:
        """The ring rule on the spheres about ``c`` (M, 3, camera frame; ``z > R``, within
        range), the points ``whole``, written into ``free``, ``strong``, ``gap``; whether
        each one's outer window was clipped to the image (a free verdict is then weak)."""
        H, W = frame.camera.height, frame.camera.width
        xy, zs = c[:, :2].T, c[:, 2]
        q = self.ring_fractions
        b2 = (q[1:, None] * R) ** 2  # threshold k: exit distance s2 at impact q_{k+1} R
        L2 = np.sum(xy * xy, axis=0) + zs * zs
        T = np.sqrt(L2 - b2) + np.sqrt(R * R - b2)  # (n, m), T[-1] = L + R
        lo, hi = _tangent_span(xy, zs, R, frame.focal, frame.centre)
        clipped = (lo < -0.5).any(axis=0) | (hi > frame.edge).any(axis=0)
        low = window_min(frame.flat, H, W, lo, hi)
        margin = np.where(low >= T[-1], low - T[-1], low - T[0])
        known = low >= 0.0
        inner = np.flatnonzero((low >= T[0]) & (low < T[-1]))  # the outer ring passes
        if len(inner) and len(q) > 2:
            n, m = len(q) - 2, len(inner)
            radii = np.repeat(q[1:-1] * R, m)  # window k: the sphere B(c, q_k R)
            lo, hi = _tangent_span(np.tile(xy[:, inner], n), np.tile(zs[inner], n), radii,
                                   frame.focal, frame.centre)
            rings = window_min(frame.flat, H, W, lo, hi).reshape(n, m)
            margin[inner] = np.minimum(margin[inner], (rings - T[1:, inner]).min(axis=0))
            known[inner] = rings.min(axis=0) >= 0.0
        is_free = known & (margin >= 0.0)
        free[whole] = is_free
        strong[whole] = known & (~is_free | ~clipped)
        gap[whole] = np.where(known, margin, np.nan)
        return clipped


def check_camera(camera) -> None:
    """A TypeError or ValueError naming why the history cannot use ``camera``."""
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    if 2 * camera.height < camera.width or 2 * camera.width < camera.height:
        raise ValueError(f"camera {camera.width}x{camera.height} is more elongated than "
                         "2:1, which the window look-up does not support")
    if min(camera.width, camera.height) < NEAR_BLOCK_PX[0]:
        raise ValueError(f"camera {camera.width}x{camera.height} is smaller than the "
                         f"{NEAR_BLOCK_PX[0]}-pixel blocks of the near-vehicle check")


def _block_minima(image: np.ndarray, side: int) -> np.ndarray:
    """The minimum of each ``side`` x ``side`` block of ``image`` (H, W), raveled row by row
    as ``image[::side, ::side]`` is (the blocks at the right and bottom edges clipped)."""
    H, W = image.shape
    if H % side or W % side:
        image = np.pad(image, ((0, -H % side), (0, -W % side)), constant_values=np.inf)
    rows = image.reshape(-1, side, image.shape[1]).min(axis=1)  # contiguous reductions
    return rows.reshape(len(rows), -1, side).min(axis=2).reshape(-1)


def min_table(image: np.ndarray) -> np.ndarray:
    """The sparse table ``(L, H, W)`` of minima over ``2^k x 2^k`` squares anchored at each
    pixel (top-left), ``k = 0 .. floor(log2(min(H, W)))``; entries whose square leaves the
    image hold the minimum over its part inside and are never read. ``image``: float32, finite.

    Level k is the minimum of level k − 1 at the four corners ``(0|b, 0|b)``, b = 2^(k−1),
    whose squares tile the new one: one erosion by a four-point kernel anchored at its
    top-left, outside the image +inf (OpenCV's, about 3x numpy's two shifted minima)."""
    H, W = image.shape
    levels = int(math.floor(math.log2(min(H, W)))) + 1
    table = np.empty((levels, H, W), dtype=np.float32)
    table[0] = image
    for k in range(1, levels):
        cv2.erode(table[k - 1], _corner_kernel(1 << (k - 1)), dst=table[k], anchor=(0, 0),
                  borderType=cv2.BORDER_CONSTANT, borderValue=math.inf)
    return table


def _corner_kernel(b: int) -> np.ndarray:
    """The ``(b + 1) x (b + 1)`` structuring element of its four corners."""
    kernel = np.zeros((b + 1, b + 1), np.uint8)
    kernel[::b, ::b] = 1
    return kernel


def window_min(flat: np.ndarray, H: int, W: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Minimum of a sparse table's image (``flat``, the table raveled) over the pixels whose
    squares ``[i - 1/2, i + 1/2]`` meet the windows ``[lo, hi]`` (``lo``, ``hi`` (2, M): image
    ``u`` then ``v``), clipped to the image.

    A window thinner than 2:1 is first widened inside the image; then with
    ``b = 2^floor(log2(short side)) > short side / 2``, ``n`` squares of side ``b`` per axis,
    evenly placed from one end to the other, cover it exactly: ``n = 2`` when the long side is
    at most ``2 b`` (every window no more elongated than ``2 b / short side``, so every square
    one: 4 look-ups), else ``n = 4`` (``long side <= 2 short side < 4 b``: 16 look-ups).
    (Written for few numpy calls: the planner calls it twice per frame per round.)
    """
    last_pixel = np.array([[W - 1], [H - 1]])
    first, last = (np.minimum(np.maximum(np.floor(x + 0.5), 0), last_pixel).astype(np.intp)
                   for x in (lo, hi))
    length = last - first + 1
    size = np.maximum(length, (length[::-1] + 1) >> 1)  # widened to at most 2:1
    start = np.minimum(np.maximum(first - ((size - length) >> 1), 0), last_pixel + 1 - size)
    (i0, j0), (w, h) = start, size
    k = np.frexp(np.minimum(w, h).astype(np.float64))[1] - 1  # floor(log2(short side))
    b = np.left_shift(1, k)
    base = (k * H + j0) * W + i0  # the top-left square in level k
    right, down = w - b, (h - b) * W
    out = np.minimum(np.minimum(flat[base], flat[base + right]),
                     np.minimum(flat[base + down], flat[base + down + right]))
    four = np.flatnonzero(np.maximum(w, h) > 2 * b)
    if len(four):
        steps = np.arange(4)[:, None]
        cols = steps * right[four] // 3  # (4, F)
        rows = steps * (h[four] - b[four]) // 3 * W
        out[four] = flat[base[four] + rows[:, None, :] + cols[None, :, :]].min(axis=(0, 1))
    return out


def _tangent_span(s: np.ndarray, z: np.ndarray, R, f, c):
    """Image coordinates ``f tan(alpha -+ beta) + c`` of the tangent lines from the camera to
    the disc of radius R (a number or one per disc) at ``(s, z)``, z > R: ``tan alpha = s / z``,
    ``tan beta = R / sqrt(s² + z² - R²)``, by the tangent addition formula. With ``s`` (2, M)
    the image ``x`` and ``y`` of spheres and ``f``, ``c`` (2, 1): their windows' corners."""
    ta = s / z
    tb = R / np.sqrt(s * s + z * z - R * R)
    with np.errstate(divide="ignore"):
        return f * (ta - tb) / (1.0 + ta * tb) + c, f * (ta + tb) / (1.0 - ta * tb) + c


def block_rays(camera: PinholeCamera, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``block x block`` pixel block (row-major, the last row and column of blocks cut
    by the image border): ``(directions (K, 3), spread (K,))``, the unit ray through its
    centre and the largest angle from it to any ray through the block, reached at a corner
    (the rays within an angle of a direction meet the image plane in a convex set), radians."""
    def edges(size: int) -> tuple[np.ndarray, np.ndarray]:
        lo = np.arange(0, size, block) - 0.5
        return lo, np.minimum(lo + block, size - 0.5)

    u_lo, u_hi = edges(camera.width)
    v_lo, v_hi = edges(camera.height)

    def unit(u, v):
        xy = np.stack(np.broadcast_arrays((u - camera.cx) / camera.fx,
                                          (v - camera.cy) / camera.fy, 1.0), axis=-1)
        return xy / np.linalg.norm(xy, axis=-1, keepdims=True)

    centre = unit((u_lo + u_hi)[None, :] / 2, (v_lo + v_hi)[:, None] / 2)
    spread = np.zeros(centre.shape[:2])
    for u in (u_lo, u_hi):
        for v in (v_lo, v_hi):
            cos = np.sum(centre * unit(u[None, :], v[:, None]), axis=-1)
            spread = np.maximum(spread, np.arccos(np.clip(cos, -1.0, 1.0)))
    return centre.reshape(-1, 3), spread.reshape(-1)


def _cells(p: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """The centres of the cubes of ``side`` (a grid through the origin) that hold the points
    ``p`` (M, 3), and each point's cube."""
    index = np.floor(p / side).astype(np.int64) + (1 << 20)  # >= 0 within 50 km at 5 cm
    keys = (index[:, 0] << 42) | (index[:, 1] << 21) | index[:, 2]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return (np.floor(p[first] / side) + 0.5) * side, inverse


def ray_norms(camera: PinholeCamera) -> np.ndarray:
    """(H, W) float32 ``sqrt(1 + ((u - cx)/fx)² + ((v - cy)/fy)²)``: range over depth on each
    pixel's ray."""
    a = (np.arange(camera.width) - camera.cx) / camera.fx
    b = (np.arange(camera.height) - camera.cy) / camera.fy
    return np.sqrt(1.0 + b[:, None] ** 2 + a[None, :] ** 2).astype(np.float32)


def _known_range(depth: np.ndarray, confidence: np.ndarray, min_confidence: float,
                 max_range: float, norms: np.ndarray, near_tail_share: float = 0.0,
                 far_tail_share: float = 0.0) -> np.ndarray:
    """float32 range along each pixel's ray of the depth clipped to ``max_range``, -1 where
    unknown (NaN, <= 0, or low confidence and nearer than every confident pixel while
    ``near_tail_share`` is 0 or no confident pixel lies within ``max_range``).

    A low-confidence pixel at or beyond ``max_range`` (the sky, a far wall no landmark lies
    on) counts as ``max_range``: the rescaling curve is monotone, so a pixel less disparate
    than the anchors reads farther than they do, and its error lies beyond the range the check
    trusts. One nearer than ``max_range`` counts as the farthest confident depth not beyond
    its own (:func:`_confident_floor`), a lower bound: confidence follows the relative
    disparity, and the curve is monotone, so a pixel less disparate than a confident one is
    farther than it, whatever its own error. That is the farthest confident depth ``d*`` in
    the middle of a long hallway whose walls carry landmarks only near by, and the confident
    surface just nearer on a floor whose disparities fall between the landmarks'. A
    low-confidence pixel nearer than every confident one has no such bound. Its depth is the
    rescaling curve's straight near tail, which never reads a pixel farther than the nearest
    landmark; it counts as ``near_tail_share`` of that depth, the share that makes it err
    toward the vehicle as rarely as confident depth does (docs/planner.md), or stays unknown
    with a share of 0, or when no confident pixel lies within range (the whole image is then a
    guess).
    Without it a hallway whose near walls carry no landmark (no texture the tracker can
    hold) leaves every sphere near the vehicle unknown.

    The far tail, a low-confidence pixel farther than every confident one in range, is the
    curve's straight tail past the farthest landmark. With ``far_tail_share`` above 0 it
    counts as that share of its own depth where that is more than its floor (the farthest
    confident depth, to within a bin): without it a view whose landmarks lie within 5 m
    bounds everything beyond at 5 m, and the arcs that need more room ahead (the fastest
    tier's) are never free. The share is measured as the near tail's is (docs/planner.md, the
    far tail).

    The unsure pixels are gathered once and worked on alone (in a view with landmarks most
    pixels are confident); every value is what the same float32 operations give on the whole
    image."""
    d = depth.astype(np.float32, copy=False)
    reading = read_depth(d, confidence, min_confidence, max_range)
    top = np.float32(max_range)
    ranges = np.where(reading.confident | reading.beyond, np.minimum(d, top) * norms, _UNKNOWN)
    unsure = np.flatnonzero(reading.unsure)
    if len(unsure) == 0:
        return ranges
    flat = d.reshape(-1)
    confident = flat[reading.in_range.reshape(-1)]  # the in-range confident depths
    own = flat[unsure]
    floor = _confident_floor(own, confident, max_range)
    if len(confident):  # none in range: no tail
        if near_tail_share > 0.0:
            floor = np.where(floor > 0.0, floor, own * np.float32(near_tail_share))
        if far_tail_share > 0.0:
            floor = np.where(own > confident.max(),
                             np.maximum(floor, own * np.float32(far_tail_share)), floor)
    ranges.reshape(-1)[unsure] = np.where(floor > 0.0, np.minimum(floor, top)
                                          * norms.reshape(-1)[unsure], _UNKNOWN)
    return ranges


class DepthReading(NamedTuple):
    """How the check reads a metric depth frame's pixels (:func:`_known_range`), as masks:
    ``confident`` (valid, at least ``min_confidence``), ``beyond`` (valid, less confident, at
    or beyond ``max_range``: counts as ``max_range``), ``unsure`` (valid, less confident,
    within it) and ``in_range`` (confident within it); the unsure pixels' tails on demand."""

    confident: np.ndarray
    beyond: np.ndarray
    unsure: np.ndarray
    in_range: np.ndarray

    def near_tail(self, depth: np.ndarray) -> np.ndarray:
        """The unsure pixels nearer than every in-range confident one (none without one). The
        check finds them by their floor's bins, to within one bin."""
        return self._past_confident(depth, np.less, np.min, np.inf)

    def far_tail(self, depth: np.ndarray) -> np.ndarray:
        """The unsure pixels farther than every in-range confident one (none without one)."""
        return self._past_confident(depth, np.greater, np.max, -np.inf)

    def _past_confident(self, depth, beyond, extreme, initial) -> np.ndarray:
        """The unsure pixels whose depth is ``beyond`` the ``extreme`` in-range confident
        depth."""
        if not self.in_range.any():
            return np.zeros_like(self.unsure)
        return self.unsure & beyond(depth, extreme(depth, where=self.in_range, initial=initial))


def read_depth(depth: np.ndarray, confidence: np.ndarray, min_confidence: float,
               max_range: float) -> DepthReading:
    """The :class:`DepthReading` of ``depth`` (H, W) metres (NaN or <= 0: invalid) with its
    ``confidence`` (H, W)."""
    d = np.asarray(depth)
    with np.errstate(invalid="ignore"):
        valid = d > 0.0  # NaN: False
        confident = valid & (confidence >= min_confidence)
        beyond = valid & ~confident & (d >= max_range)
        unsure = valid & ~confident & ~beyond
    return DepthReading(confident, beyond, unsure, confident & (d < max_range))


#: Log-spaced depth bins over (``max_range`` / 1000, ``max_range``) in which
#: :func:`_confident_floor` looks up the confident depths: 0.7 % wide.
FLOOR_BINS = 1024
FLOOR_STEP = math.log(1000.0) / FLOOR_BINS


def _confident_floor(depths: np.ndarray, confident: np.ndarray, max_range: float) -> np.ndarray:
    """float32, for each of the unsure pixels' ``depths`` (valid, within ``max_range``) the
    greatest depth ``e`` with a ``confident`` depth (the in-range confident pixels') in ``[e,
    own depth)``, 0 where there is none: the lower edge of the farthest of the
    :data:`FLOOR_BINS` bins below the pixel's own that holds a confident depth. Up to two bins
    (1.4 %) below the exact farthest confident depth not beyond the pixel's, so still a lower
    bound, at one histogram's cost."""
    held = np.bincount(_floor_bin(confident, max_range), minlength=FLOOR_BINS) > 0
    low = max_range / 1000.0
    edges = (low * np.exp(FLOOR_STEP * np.arange(FLOOR_BINS))).astype(np.float32)
    edges[0] = 0.0  # the first bin also holds every depth below ``low``
    # the floor of bin b: the lower edge of the farthest held bin below b
    below = np.concatenate([[0.0], np.maximum.accumulate(np.where(held, edges, 0.0))[:-1]])
    return below.astype(np.float32)[_floor_bin(depths, max_range)]


def _floor_bin(depths: np.ndarray, max_range: float) -> np.ndarray:
    """The :data:`FLOOR_BINS` bin of each depth (finite, > 0; the first bin holds every depth
    below ``max_range / 1000``, the last every one beyond the range)."""
    low = max_range / 1000.0
    bins = np.log(np.maximum(depths, np.float32(low)) * np.float32(1.0 / low)) \
        * np.float32(1.0 / FLOOR_STEP)
    return np.minimum(bins, FLOOR_BINS - 1).astype(np.intp)


def fill_small_holes(image: np.ndarray, reach_px: int) -> np.ndarray:
    """``image`` (range, ``_UNKNOWN`` where unknown) with every unknown pixel that has known
    pixels within ``reach_px`` (Chebyshev distance) given the least of their ranges: a grey
    erosion of the known ranges over a ``(2 reach + 1)`` square. A sliver of low-confidence
    pixels (an edge the network blurred, a patch of floor no landmark lies on) then stops
    vetoing every sphere whose window touches it, and takes the nearest surface around it,
    the cautious guess; an unknown region wider than ``2 reach`` keeps an unknown core (the
    sky without depth, a covered lens). An obstacle hidden entirely inside a small hole is
    missed: that is the price, and why ``reach_px`` is small."""
    unknown = image < 0.0
    if not unknown.any():
        return image
    side = 2 * reach_px + 1
    known = np.where(unknown, np.float32(np.inf), image)
    nearest = cv2.erode(known, np.ones((side, side), np.uint8))
    return np.where(unknown & np.isfinite(nearest), nearest, image).astype(np.float32)


def as_pose(T, name: str) -> np.ndarray:
    """A finite 4x4 rigid pose, or a ValueError naming it."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 pose, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name} must be finite, got {T.tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0.0:
        raise ValueError(f"{name} must hold a rotation (orthonormal, det +1)")
    return T
