"""Speed of one planning round: median milliseconds for 75 primitives against 8 depth frames.

    python benchmarks/planner.py [--repeats 200] [--naive-repeats 5]

Renders a 640x480 (90 degree) depth image of a floor, a field of pillars and a far backdrop from
8 poses 12 Hz apart along a 2 m/s flight at 1.5 m, with a 60x40 patch of each image at
confidence 0, feeds them to Planner.add_depth, and times Planner.plan (every speed tier tried
when none of a faster one is safe), and the same round with the fastest tier alone (the paper's
75 arcs, speed_tiers=1), wall and CPU time (on a shared machine the CPU time leaves out the time
other processes took the core). The rounds are timed in turn, so that the load falls on all
alike. Baselines in the same run: the same round against the newest frame alone
(history_frames=1); the same round with the height wave (``height_swing`` 0.08 m: twice the
points, at its crest and trough); the fastest tier's check with every point judged (no primitive
left off at its first occupied point), which must agree on which primitives are safe; and a
naive check of the same points and rules taking each ring window's minimum by slicing the range
image (no table), which also confirms the table's verdicts. Last, every point's sphere against
the newest frame by the ring rule and by the exact per-ray rule (every pixel ray through the
sphere sees its surface beyond the ray's exit point): the ring rule must never call free what
the exact rule does not. Then the round where planning costs most: on the axis of a 3 m
corridor, where most spheres near the vehicle need the block rule and slower tiers may be tried.
Prints one JSON object.
"""

import argparse
import json
import math
import time

import cv2
import numpy as np

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z
from autonomy.messages import DepthDiagnostics, MetricDepth
from autonomy.planning.history import _tangent_span, ray_norms
from autonomy.planning.planner import Planner, PlannerOptions

CAMERA = PinholeCamera.from_hfov(640, 480, math.radians(90.0))
DIAGNOSTICS = DepthDiagnostics(80, 80, 0.0, "poly1", 0.0)
ALTITUDE = 1.5


def scene(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """A floor (z <= 0), a backdrop wall 40 m ahead and 40 pillars 0.4-0.8 m across, 6 m
    tall, in the 4-30 m ahead."""
    boxes = [(np.array([-100.0, -100.0, -1.0]), np.array([100.0, 100.0, 0.0])),
             (np.array([40.0, -100.0, -1.0]), np.array([41.0, 100.0, 100.0]))]
    for _ in range(40):
        c = np.array([rng.uniform(4.0, 30.0), rng.uniform(-12.0, 12.0)])
        half = rng.uniform(0.2, 0.4)
        boxes.append((np.array([*(c - half), 0.0]), np.array([*(c + half), 6.0])))
    return boxes


def corridor() -> list[tuple[np.ndarray, np.ndarray]]:
    """A 3 m wide, 3 m high corridor along x, its floor 1.5 m below the flight height, closed
    60 m ahead: a 1 m sphere on its axis has 0.5 m to spare all round."""
    lo, hi = ALTITUDE - 1.5, ALTITUDE + 1.5
    return [(np.array(a, float), np.array(b, float)) for a, b in (
        ((-50.0, 1.5, -1.0), (80.0, 2.0, 50.0)), ((-50.0, -2.0, -1.0), (80.0, -1.5, 50.0)),
        ((-50.0, -50.0, lo - 0.5), (80.0, 50.0, lo)), ((-50.0, -50.0, hi), (80.0, 50.0, hi + 0.5)),
        ((60.0, -50.0, -1.0), (61.0, 50.0, 50.0)))]


def corridor_round_ms(repeats: int) -> tuple[float, str, float]:
    """Median milliseconds of a planning round on the corridor's axis, 8 frames 0.05 s apart
    at 1 m/s with a 3 degree heading error, and the chosen plan's kind and speed."""
    planner = Planner(CAMERA)
    T_B_C = make_pose(R_BODY_CAMERA, np.zeros(3))
    heading = math.radians(3.0)
    for k in range(8):
        T_W_B = make_pose(rot_z(heading), np.array([0.05 * k - 0.4, 0.0, ALTITUDE]))
        depth = render(T_W_B @ T_B_C, corridor())
        planner.add_depth(MetricDepth(0.05 * k, depth, np.ones_like(depth), False, DIAGNOSTICS),
                          T_W_B @ T_B_C)
    velocity, goal = np.array([1.0, 0.0, 0.0]), np.array([50.0, 0.0, ALTITUDE])
    ms = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        plan = planner.plan(0.4, T_W_B, velocity, goal)
        ms.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ms)), plan.kind, plan.primitive.speed


def render(T_W_C: np.ndarray, boxes) -> np.ndarray:
    """Optical-axis depth of the nearest box per pixel (slab test), NaN where none."""
    d = CAMERA.rays().reshape(-1, 3) @ T_W_C[:3, :3].T
    o = T_W_C[:3, 3]
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in boxes:
            t1, t2 = (lo - o) / d, (hi - o) / d
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (far >= near) & (far > 0)
            best = np.where(hit, np.minimum(best, np.maximum(near, 0.0)), best)
    return np.where(np.isfinite(best), best, np.nan).astype(np.float32).reshape(480, 640)


def _window(x: float, y: float, z: float, rho: float):
    """Pixel slices of the bounding box of the image of the sphere of radius rho at (x, y, z),
    clipped to the image, and whether it was clipped."""
    (u0,), (u1,) = _tangent_span(np.array([x]), np.array([z]), rho, CAMERA.fx, CAMERA.cx)
    (v0,), (v1,) = _tangent_span(np.array([y]), np.array([z]), rho, CAMERA.fy, CAMERA.cy)
    i0, i1 = (int(np.clip(np.floor(a + 0.5), 0, 639)) for a in (u0, u1))
    j0, j1 = (int(np.clip(np.floor(a + 0.5), 0, 479)) for a in (v0, v1))
    clipped = u0 < -0.5 or u1 > 639.5 or v0 < -0.5 or v1 > 479.5
    return (slice(j0, j1 + 1), slice(i0, i1 + 1)), clipped


def naive_free(planner: Planner, T_W_S: np.ndarray, now: float) -> np.ndarray:
    """The history's rules point by point, each ring window's minimum by slicing the range
    image."""
    h = planner.history
    R, start = T_W_S[:3, :3], T_W_S[:3, 3]
    points = planner.tiers[0].points_S @ R.T + start
    radius = h.robot_radius
    verdicts = []
    for p in points:
        strong, weak = None, None
        for frame in reversed(h._frames):
            if frame.t < now - h.max_age_s:
                continue
            image = frame.table[0]
            x, y, z = frame.R_C_W @ p + frame.t_C_W
            if z <= 0:
                continue
            u, v = CAMERA.fx * x / z + CAMERA.cx, CAMERA.fy * y / z + CAMERA.cy
            if not (-0.5 <= u < 639.5 and -0.5 <= v < 479.5):
                continue
            if z <= radius:
                if np.sum((p - start) ** 2) > (2 * radius) ** 2:
                    continue
                d = image[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))]
                distance = math.sqrt(x * x + y * y + z * z)
                if d >= 0 and d < distance:
                    strong = False
                elif weak is None and _rays_pass(image, np.array([x, y, z]), radius):
                    weak = True
            elif z + radius <= h.max_range:
                q = h.ring_fractions
                lows, clipped = [], None
                for k in range(len(q) - 1):
                    window, cut = _window(x, y, z, q[k] * radius)
                    clipped = cut if clipped is None else clipped
                    b2 = (q[k + 1] * radius) ** 2
                    lows.append((image[window].min(),
                                 math.sqrt(x * x + y * y + z * z - b2)
                                 + math.sqrt(radius * radius - b2)))
                known = min(low for low, _ in lows) >= 0
                ok = all(low >= threshold for low, threshold in lows)
                if known and not ok:
                    strong = False
                elif known and not clipped:
                    strong = True
                elif known and weak is None:
                    weak = True
            if strong is not None:
                break
        verdicts.append(strong if strong is not None else bool(weak))
    return np.array(verdicts)


_UNIT_RAYS = CAMERA.rays() / ray_norms(CAMERA)[..., None]


def _rays_pass(image: np.ndarray, c: np.ndarray, radius: float) -> bool:
    """The exact per-ray rule on every pixel: each known ray through the sphere about ``c``
    (camera frame) sees its surface beyond the ray's exit distance; no unknown ray meets it."""
    b = _UNIT_RAYS @ c
    disc = b * b - c @ c + radius * radius
    hit = disc >= 0.0
    return bool(np.all(image[hit] >= b[hit] + np.sqrt(disc[hit])))


def exact_versus_rings(planner: Planner, T_W_S: np.ndarray) -> dict:
    """Every point's sphere in the newest frame by the exact per-ray rule and the ring rule:
    counts of free, of free by rings but not exactly (must be 0) and the reverse."""
    h = planner.history
    frame = h._frames[-1]
    image = frame.table[0]
    unit = _UNIT_RAYS
    radius = h.robot_radius
    points = planner.tiers[0].points_S @ T_W_S[:3, :3].T + T_W_S[:3, 3]
    seen = []
    exact = []
    for p in points:
        c = frame.R_C_W @ p + frame.t_C_W
        x, y, z = c
        u, v = CAMERA.fx * x / z + CAMERA.cx, CAMERA.fy * y / z + CAMERA.cy
        if not (z > radius and z + radius <= h.max_range and -0.5 <= u < 639.5
                and -0.5 <= v < 479.5):
            continue
        window, _ = _window(x, y, z, radius)
        r = image[window]
        b = unit[window] @ c
        disc = b * b - c @ c + radius * radius
        hit = disc >= 0.0
        seen.append(p)
        exact.append(bool(r.min() >= 0 and np.all(r[hit] >= b[hit] + np.sqrt(disc[hit]))))
    exact = np.array(exact)
    rings = h._judge(frame, np.array(seen), np.zeros(len(seen), dtype=bool), radius)[0]
    return {"points_seen_whole": len(seen), "exact_free": int(exact.sum()),
            "rings_free": int(rings.sum()), "rings_free_exact_not": int(np.sum(rings & ~exact)),
            "exact_free_rings_not": int(np.sum(exact & ~rings))}


def every_point_check(planner: Planner, T_W_S: np.ndarray, now: float) -> np.ndarray:
    """The baseline of :meth:`Planner.check` (fastest tier): every point judged, no group
    left off once one of its points is occupied; which primitives are safe."""
    tier = planner.tiers[0]
    result = planner.history.check(tier.points_S @ T_W_S[:3, :3].T + T_W_S[:3, 3],
                                   start_W=T_W_S[:3, 3], now=now)
    return np.logical_and.reduceat(result.free, tier.starts)


def interleaved(rounds: dict, repeats: int) -> tuple[dict, dict]:
    """Wall and CPU milliseconds per call of each of ``rounds`` (name: no-argument callable),
    ``repeats`` each after a warm-up, the rounds taken in turn so that the load of a shared
    machine falls on all of them alike."""
    wall = {name: [] for name in rounds}
    cpu = {name: [] for name in rounds}
    for name, call in rounds.items():
        call()
    for _ in range(repeats):
        for name, call in rounds.items():
            w0, c0 = time.perf_counter(), time.process_time()
            call()
            cpu[name].append((time.process_time() - c0) * 1e3)
            wall[name].append((time.perf_counter() - w0) * 1e3)
    return wall, cpu


def _median(ms: list[float]) -> float:
    return round(float(np.median(ms)), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--naive-repeats", type=int, default=3)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    boxes = scene(rng)
    options = PlannerOptions()
    # 8 frames, the newest alone, and the paper's library alone (the fastest tier: 75 arcs)
    planners = {n: Planner(CAMERA, PlannerOptions(history_frames=n)) for n in (8, 1)}
    planners["75"] = Planner(CAMERA, PlannerOptions(speed_tiers=1))
    planners["wave"] = Planner(CAMERA, PlannerOptions(height_swing=0.08))
    T_B_C = make_pose(R_BODY_CAMERA, np.zeros(3))
    add_ms = []
    for k in range(8):
        t = k * options.period_s
        T_W_B = make_pose(rot_z(0.02 * k), np.array([2.0 * t, 0.0, ALTITUDE]))
        depth = render(T_W_B @ T_B_C, boxes)
        confidence = np.ones_like(depth)
        confidence[300:340, 500:560] = 0.0
        for planner in planners.values():
            t0 = time.perf_counter()
            planner.add_depth(MetricDepth(t, depth, confidence, False, DIAGNOSTICS),
                              T_W_B @ T_B_C)
            add_ms.append((time.perf_counter() - t0) * 1e3)
    now = 8 * options.period_s
    velocity, goal = np.array([2.0, 0.0, 0.0]), np.array([60.0, 0.0, ALTITUDE])
    plans = {n: planner.plan(now, T_W_B, velocity, goal) for n, planner in planners.items()}
    fastest = planners["75"]
    T_W_S = plans["75"].T_W_S
    rounds = {n: (lambda p=planner: p.plan(now, T_W_B, velocity, goal))
              for n, planner in planners.items()}
    rounds["check"] = lambda: fastest.check(now, T_W_S)
    rounds["check_every_point"] = lambda: every_point_check(fastest, T_W_S, now)
    wall, cpu = interleaved(rounds, args.repeats)
    planner = planners[8]
    T_W_S = plans[8].T_W_S
    free = planner.history.check(planner.tiers[0].points_S @ T_W_S[:3, :3].T + T_W_S[:3, 3],
                                 start_W=T_W_S[:3, 3], now=now).free
    naive_ms = []
    for _ in range(args.naive_repeats):
        t0 = time.perf_counter()
        naive = naive_free(planner, T_W_S, now)
        naive_ms.append((time.perf_counter() - t0) * 1e3)
    median = float(np.median(wall[8]))
    versus = exact_versus_rings(planner, T_W_S)
    corridor_ms, corridor_kind, corridor_speed = corridor_round_ms(max(5, args.repeats // 10))
    print(json.dumps({
        "image": [480, 640], "primitives": len(planner.tiers[0].library),
        "points": len(planner.tiers[0].points_S), "threads": 1,
        "safe_primitives": plans[8].safe_count, "safe_primitives_1_frame": plans[1].safe_count,
        "plan_ms_median": round(median, 3),
        "plan_ms_p90": round(float(np.percentile(wall[8], 90)), 3),
        "plan_1_frame_ms_median": _median(wall[1]),
        "plan_fastest_tier_only_ms_median": _median(wall["75"]),
        "plan_fastest_tier_only_cpu_ms_median": _median(cpu["75"]),
        "plan_height_wave_ms_median": _median(wall["wave"]),
        "safe_primitives_height_wave": plans["wave"].safe_count,
        "check_fastest_tier_ms_median": _median(wall["check"]),
        "check_fastest_tier_every_point_ms_median": _median(wall["check_every_point"]),
        "check_agrees_with_every_point": bool(np.array_equal(
            fastest.check(now, T_W_S)[0], every_point_check(fastest, T_W_S, now))),
        "tiers_tried": len(planner.tiers) if plans[8].kind == "stop" else 1,
        "add_depth_ms_median": round(float(np.median(add_ms)), 3),
        "naive_check_ms_median": round(float(np.median(naive_ms)), 1),
        "naive_over_plan": round(float(np.median(naive_ms)) / median, 1),
        "naive_agrees_on_points": round(float(np.mean(naive == free)), 4),
        "rings": len(planner.history.ring_fractions) - 1, "newest_frame": versus,
        "corridor_plan_ms_median": round(corridor_ms, 3), "corridor_plan": corridor_kind,
        "corridor_plan_speed": corridor_speed,
    }))


if __name__ == "__main__":
    main()
