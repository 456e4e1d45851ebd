"""Lockstep speed of the simulator: simulated seconds per wall-clock second.

    python benchmarks/sim_lockstep.py [--duration 60] [--repeats 3] [--worlds mine sewer dome]

Four loops over the same simulated minute, each timed ``--repeats`` times per world,
interleaved, medians reported:

- ``flight``: the recording flight (quadrotor dynamics and controller, IMU model at 200 Hz)
  with the camera rendered and read back at 20 Hz (RGB + depth, 640x480), samples discarded
  instead of written to disk;
- ``realistic``: the same flight on the realistic profile: the realistic world (the mine's
  dust, thin obstacles), the IMU's error sources, and the camera sensor of ``[sim_camera]``'s
  defaults (a wider render for the lens, motion blur, noise, auto-exposure);
- ``physics``: the same flight without the camera, the baseline in the same run;
- ``serve``: the MAVLink vehicle in lockstep (dynamics, IMU, mock PX4 streaming HIGHRES_IMU at
  200 Hz and its other telemetry to a UDP peer on loopback), no camera.

Prints one JSON object: speed = simulated seconds / wall seconds for each, per world.
"""

import argparse
import asyncio
import json
import statistics
import time

import numpy as np

from drivers.camera.options import CameraOptions
from drivers.sim import record
from drivers.sim.imu import ImuOptions
from drivers.sim.mock_px4 import Px4Options
from drivers.sim.render import Renderer
from drivers.sim.serve import serve
from drivers.sim.quadrotor import VehicleOptions
from drivers.sim.sensor import Lens, SensorOptions
from drivers.sim.world import WORLD_NAMES, build_world


class Discard:
    """A sink that keeps nothing: the benchmark times the simulation, not the disk."""

    def add_imu(self, *sample) -> None: ...
    def add_groundtruth(self, *sample) -> None: ...
    def add_frame(self, *sample) -> None: ...
    def add_camera_truth(self, *truth) -> None: ...


class NoCamera:
    """A renderer stand-in for the physics-only baseline: empty images, no OpenGL."""

    def __init__(self, camera):
        self.rgb = np.zeros((camera.height, camera.width, 3), np.uint8)
        self.depth = np.zeros((camera.height, camera.width), np.float32)

    def render(self, T_W_C):
        return self.rgb, self.depth


def time_flight(world, renderer, duration: float, profile: str = "ideal") -> float:
    """Wall seconds of ``duration`` simulated seconds of the recording flight in ``profile``
    (``renderer`` draws the camera head's render camera: :func:`realistic_renderer`)."""
    start = time.perf_counter()
    record.fly(world, world.routes[0], Discard(), duration=duration, seed=0,
               camera=CameraOptions(), vehicle=VehicleOptions(),
               imu=ImuOptions().for_profile(profile),
               sensor=SensorOptions().for_profile(profile), renderer=renderer)
    return time.perf_counter() - start


def realistic_renderer(name: str) -> Renderer:
    """The realistic world ``name``, drawn wide enough for the realistic camera's lens."""
    lens = Lens(CameraOptions().pinhole(), SensorOptions().distortion)
    return Renderer(build_world(name, 0, "realistic"), lens.render_camera)


def time_serve(world, duration: float) -> float:
    start = time.perf_counter()
    asyncio.run(serve("udpout://127.0.0.1:14999", world, clock_mode="lockstep",
                      px4_options=Px4Options(imu_rate_hz=200.0), duration=duration))
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--worlds", nargs="+", default=list(WORLD_NAMES), choices=WORLD_NAMES)
    args = parser.parse_args()
    camera = CameraOptions()
    result = {"simulated_seconds": args.duration, "camera_hz": camera.rate_hz,
              "imu_hz": ImuOptions().rate_hz, "image": [camera.height, camera.width]}
    for name in args.worlds:
        world = build_world(name, 0)
        walls = {"flight": [], "realistic": [], "physics": [], "serve": []}
        with Renderer(world, camera.pinhole()) as renderer, \
                realistic_renderer(name) as wide_renderer:
            # warm-up: shader compilation, first uploads
            time_flight(world, renderer, 1.0)
            time_flight(wide_renderer.world, wide_renderer, 1.0, "realistic")
            for _ in range(args.repeats):
                walls["flight"].append(time_flight(world, renderer, args.duration))
                walls["realistic"].append(time_flight(wide_renderer.world, wide_renderer,
                                                      args.duration, "realistic"))
                walls["physics"].append(time_flight(world, NoCamera(camera), args.duration))
                walls["serve"].append(time_serve(world, args.duration))
        result[name] = {f"{loop}_speed": round(args.duration / statistics.median(times), 2)
                        for loop, times in walls.items()}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
