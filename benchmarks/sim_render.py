"""Render + readback time of the simulated camera per frame, each world, with an in-run baseline.

    python benchmarks/sim_render.py [--frames 200] [--width 640] [--height 480]

For each world, a camera flies the first route's planned path at cruise height (looking along
it, slightly down) and every frame is rendered and read back (RGB uint8 and float32 depth), as
`sim record` does. After a warm-up of 20 frames the median and 90th percentile over ``--frames``
frames are printed. The baseline, measured in the same run, is an empty frame: the dome's
camera looking straight up into open sky, so the frame is cleared, every triangle is culled or
clipped and both attachments are read back: the part of a frame no scene can avoid.
Prints one JSON object per line; milliseconds.
"""

import argparse
import json
import math
import statistics
import time

import numpy as np

from autonomy.geometry import R_BODY_CAMERA, PinholeCamera, make_pose, rot_z, so3_exp
from drivers.sim.options import WORLD_NAMES
from drivers.sim.render import Renderer
from drivers.sim.world import build_world

WARM_UP = 20


def poses_along_route(world, frames: int) -> list[np.ndarray]:
    """``frames`` camera poses evenly along the first route's path, looking along it."""
    route = world.routes[0]
    path = world.find_path(route.start[:2], route.goal[:2], 1.0)
    lengths = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    poses = []
    for s in np.linspace(0.0, lengths[-1] * 0.999, frames):
        k = int(np.searchsorted(lengths, s, side="right")) - 1
        direction = (path[k + 1] - path[k]) / (lengths[k + 1] - lengths[k])
        position = path[k] + (s - lengths[k]) * direction
        R_W_B = rot_z(math.atan2(direction[1], direction[0])) @ so3_exp(np.array([0, 0.15, 0]))
        poses.append(make_pose(R_W_B @ R_BODY_CAMERA, [*position, route.cruise_height]))
    return poses


def timed_ms(call, count: int) -> list[float]:
    times = []
    for k in range(count):
        start = time.perf_counter()
        call(k)
        times.append((time.perf_counter() - start) * 1e3)
    return times


def baseline_ms(renderer: Renderer, frames: int) -> list[float]:
    """Frame times of a camera looking straight up into the open sky."""
    up = make_pose(np.eye(3), [0.0, 0.0, 20.0])  # z_C = world z: up, above the treetops
    rgb, depth = renderer.render(up)
    assert np.isnan(depth).all(), "the baseline frame must be empty"
    timed_ms(lambda k: renderer.render(up), WARM_UP)
    return timed_ms(lambda k: renderer.render(up), frames)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    args = parser.parse_args()
    camera = PinholeCamera.from_hfov(args.width, args.height, math.radians(90.0))
    for name in WORLD_NAMES:
        world = build_world(name, seed=0)
        poses = poses_along_route(world, args.frames)
        with Renderer(world, camera) as renderer:
            info = renderer._ctx.info
            timed_ms(lambda k: renderer.render(poses[k]), WARM_UP)
            frame = timed_ms(lambda k: renderer.render(poses[k]), args.frames)
            if world.outdoor:
                empty = baseline_ms(renderer, args.frames)
        print(json.dumps({
            "world": name, "image": [args.height, args.width], "frames": args.frames,
            "render_readback_ms_median": round(statistics.median(frame), 2),
            "render_readback_ms_p90": round(float(np.percentile(frame, 90)), 2),
            "renderer": info["GL_RENDERER"],
        }))
    print(json.dumps({"baseline": "empty frame (all sky)", "image": [args.height, args.width],
                      "frames": args.frames,
                      "clear_readback_ms_median": round(statistics.median(empty), 2)}))


if __name__ == "__main__":
    main()
