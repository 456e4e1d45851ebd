"""What a recorded frame's PNGs cost to write and read, by PNG setting, each world.

    python benchmarks/euroc_png.py [--frames 60] [--repeats 5]

`sim record` (and every test that records a flight) writes each camera frame as two PNGs, the
colour image and the uint16 depth (drivers/dataset/euroc.py), and `eval vio` / `eval depth`
read them back. For each world, ``--frames`` frames are rendered along the first route (as
benchmarks/sim_render.py flies it); each is encoded and decoded ``--repeats`` times with every
setting, the settings interleaved frame by frame so the host's load falls on all alike. Prints
one JSON object per world, setting and image: the median write and read milliseconds and the
mean size in kB. The baseline is zlib level 1 with libpng's adaptive filter choice (the writer's
setting before 2026-11-27).
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).parent))
from sim_render import poses_along_route  # noqa: E402

from drivers.camera.options import CameraOptions  # noqa: E402
from drivers.dataset.euroc import PNG_SETTINGS, depth_to_millimetres  # noqa: E402
from drivers.sim.options import WORLD_NAMES  # noqa: E402
from drivers.sim.render import Renderer  # noqa: E402
from drivers.sim.world import build_world  # noqa: E402

SETTINGS = {
    "level 1, adaptive filter (baseline)": [cv2.IMWRITE_PNG_COMPRESSION, 1],
    "level 1, sub filter": [cv2.IMWRITE_PNG_COMPRESSION, 1,
                            cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB],
    "level 1, RLE, sub filter": [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
                                 cv2.IMWRITE_PNG_STRATEGY_RLE,
                                 cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB],
    "the writer's (PNG_SETTINGS)": PNG_SETTINGS,
}


def frames(world_name: str, count: int) -> list[tuple[str, object]]:
    """``count`` (colour BGR, depth uint16 mm) pairs rendered along the world's first route."""
    world = build_world(world_name, 0)
    renderer = Renderer(world, CameraOptions().pinhole())
    try:
        rendered = [tuple(image.copy() for image in renderer.render(pose))  # buffers reused
                    for pose in poses_along_route(world, count)]
    finally:
        renderer.close()
    return [(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), depth_to_millimetres(depth))
            for rgb, depth in rendered]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for world in WORLD_NAMES:
        times = {(s, k): ([], [], []) for s in SETTINGS for k in ("colour", "depth")}
        for colour, depth in frames(world, args.frames):
            for _ in range(args.repeats):
                for setting, params in SETTINGS.items():
                    for kind, image in (("colour", colour), ("depth", depth)):
                        start = time.perf_counter()
                        ok, encoded = cv2.imencode(".png", image, params)
                        middle = time.perf_counter()
                        cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED)
                        end = time.perf_counter()
                        writes, reads, sizes = times[setting, kind]
                        writes.append(middle - start)
                        reads.append(end - middle)
                        sizes.append(encoded.nbytes)
        for (setting, kind), (writes, reads, sizes) in times.items():
            print(json.dumps({"world": world, "setting": setting, "image": kind,
                              "write_ms": round(1e3 * statistics.median(writes), 2),
                              "read_ms": round(1e3 * statistics.median(reads), 2),
                              "size_kb": round(statistics.mean(sizes) / 1e3, 1)}))


if __name__ == "__main__":
    main()
