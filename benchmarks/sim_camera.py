"""Time per frame of the simulated camera, ideal against realistic, each world, interleaved.

    python benchmarks/sim_camera.py [--frames 100]

A vehicle flies each world's first route at cruise height, 1 m/s along the path, turning at
0.3 rad/s (a gentle corner), and the camera head shoots a frame at every pose: the ideal head
(render and read back: the baseline) and the realistic one in the realistic world (its thin
obstacles, the mine's dust) with ``[sim_camera]`` defaults (a wider
render for the lens, motion blur, lens, vignetting, noise, auto-exposure), alternating frame
by frame so that both see the same load. After a warm-up of 10 frames each, prints one JSON
object per world: medians and 90th percentiles in milliseconds, and their ratio.
"""

import argparse
import json
import math
import statistics
import time

import numpy as np

from autonomy.geometry import rot_to_quat
from drivers.camera.options import CameraOptions
from drivers.sim.camera import CameraHead
from drivers.sim.options import WORLD_NAMES
from drivers.sim.quadrotor import VehicleState
from drivers.sim.render import Renderer
from drivers.sim.sensor import SensorOptions
from drivers.sim.world import build_world
from sim_render import poses_along_route

WARM_UP = 10
SPEED, YAW_RATE = 1.0, 0.3


def states_along_route(world, frames: int) -> list[VehicleState]:
    """Vehicle states along the first route: the body where :func:`poses_along_route` puts
    the camera, flying forward at :data:`SPEED` and yawing at :data:`YAW_RATE`."""
    states = []
    for T_W_C in poses_along_route(world, frames):
        forward = T_W_C[:3, 2] * np.array([1.0, 1.0, 0.0])
        forward /= np.linalg.norm(forward)
        yaw = math.atan2(forward[1], forward[0])
        R_W_B = np.array([[math.cos(yaw), -math.sin(yaw), 0.0],
                          [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        states.append(VehicleState(0.0, T_W_C[:3, 3], SPEED * forward, rot_to_quat(R_W_B),
                                   np.array([0.0, 0.0, YAW_RATE]), np.zeros(3), False))
    return states


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args()
    camera = CameraOptions()
    for name in WORLD_NAMES:
        worlds = {"ideal": build_world(name, seed=0),
                  "realistic": build_world(name, seed=0, profile="realistic")}
        states = states_along_route(worlds["ideal"], args.frames + WARM_UP)
        heads = {"ideal": CameraHead(camera.pinhole(), camera.rate_hz, camera.T_B_C()),
                 "realistic": CameraHead(camera.pinhole(), camera.rate_hz, camera.T_B_C(),
                                         SensorOptions(), name, np.random.default_rng(0))}
        renderers = {k: Renderer(worlds[k], head.render_camera) for k, head in heads.items()}
        times: dict[str, list[float]] = {k: [] for k in heads}
        try:
            for k, state in enumerate(states):
                for profile, head in heads.items():
                    start = time.perf_counter()
                    head.shoot(renderers[profile], 0.05 * k, state)
                    if k >= WARM_UP:
                        times[profile].append((time.perf_counter() - start) * 1e3)
        finally:
            for renderer in renderers.values():
                renderer.close()
        medians = {k: statistics.median(v) for k, v in times.items()}
        print(json.dumps({
            "world": name, "frames": args.frames,
            **{f"{k}_median_ms": round(v, 2) for k, v in medians.items()},
            **{f"{k}_p90_ms": round(percentile(v, 90), 2) for k, v in times.items()},
            "ratio": round(medians["realistic"] / medians["ideal"], 2),
        }), flush=True)


if __name__ == "__main__":
    main()
