"""Speed of the VINS back-end on one core: milliseconds per keyframe on simulated flights.

    python benchmarks/vins_backend.py [--duration 20] [--worlds mine sewer dome] [--dataset DIR]

Records a simulated flight per world (seed 0; or uses the EuRoC/ASL dataset given), pins the
process to one CPU (and OpenCV to one thread), and runs the whole VINS over it with the
default options, exactly as ``companion eval vio`` does. The back-end time is
``Vins.add_frame`` on keyframe frames (the smoother update, landmark gate, map); the front-end
time on the same frames is the baseline of the same run. Keyframes come at 10 Hz on these
flights (``keyframe_interval_s``), with 150 tracks. Prints one JSON object.
"""

import argparse
import json
import os
import tempfile
from pathlib import Path

import cv2

from autonomy.vins import VinsOptions
from companion.tools.eval.vio import read_vio_dataset, run_vins, score_vio
from drivers.camera.options import CameraOptions
from drivers.sim.imu import ImuOptions
from drivers.sim.options import WORLD_NAMES, SimOptions
from drivers.sim.record import record_dataset
from drivers.sim.quadrotor import VehicleOptions


def measure(root: Path) -> dict:
    data = read_vio_dataset(root)
    trace = run_vins(data, VinsOptions())
    score = score_vio(trace, data)
    timing = {key: round(score[key], 2)
              for key in ("backend_ms_median", "backend_ms_p95", "frontend_ms_median")}
    return {"dataset": str(root), "keyframes": score["keyframes"],
            "keyframe_rate_hz": round(score["keyframes"] / (trace.t[-1] - trace.t[0]), 2),
            **timing, "resets": score["resets"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--worlds", nargs="+", default=list(WORLD_NAMES), choices=WORLD_NAMES)
    parser.add_argument("--dataset", type=Path, help="a recorded dataset instead of new flights")
    args = parser.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    cv2.setNumThreads(1)
    if args.dataset is not None:
        print(json.dumps({"cpus": 1, "runs": [measure(args.dataset)]}))
        return
    runs = []
    with tempfile.TemporaryDirectory() as scratch:
        for world in args.worlds:
            root = Path(scratch) / world
            record_dataset(root, SimOptions(world=world, seed=0), CameraOptions(),
                           VehicleOptions(), ImuOptions(), duration=args.duration)
            runs.append({"world": world, **measure(root)})
    print(json.dumps({"cpus": 1, "duration_s": args.duration, "runs": runs}))


if __name__ == "__main__":
    main()
