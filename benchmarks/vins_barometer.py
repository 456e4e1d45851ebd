"""What the barometer costs the VINS back-end: milliseconds per keyframe over a recorded flight.

    python benchmarks/vins_barometer.py RECORDING [--runs 2] [--sigma 0.2]

Replays a flight recording's VINS (``companion replay RECORDING --vins-only``, the recording's
own config) with ``[vins] barometer_sigma_m`` 0 and ``--sigma``, in turn (A B A B: the host's
load falls on both alike), pinned to one CPU with OpenCV on one thread, and times
``SlidingWindowSmoother.add_keyframe`` (the smoother's update, the landmark gate, the barometer's
factors). The recording must have the barometer's pressures (``/imu``'s ``pressure_pa``: a
``companion sim fly`` flight of 2026-12-07 or later). ``benchmarks/vins_backend.py`` cannot
time it: ``sim record``'s datasets carry no barometer. Prints one JSON object: per arm, each
run's keyframes, median and p95 milliseconds.
"""

import argparse
import contextlib
import io
import json
import os
import time

import cv2
import numpy as np

from autonomy.vins.backend import SlidingWindowSmoother
from companion import cli


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("recording")
    parser.add_argument("--runs", type=int, default=2, help="runs of each arm, alternated")
    parser.add_argument("--sigma", type=float, default=0.2,
                        help="the barometer arm's [vins] barometer_sigma_m")
    args = parser.parse_args()
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    cv2.setNumThreads(1)
    seconds: list[float] = []
    timed = SlidingWindowSmoother.add_keyframe

    def add_keyframe(self, *arguments, **keywords):
        started = time.perf_counter()
        result = timed(self, *arguments, **keywords)
        seconds.append(time.perf_counter() - started)
        return result

    SlidingWindowSmoother.add_keyframe = add_keyframe
    arms = {"off": 0.0, "barometer": args.sigma}
    report: dict[str, list] = {arm: [] for arm in arms}
    for _ in range(args.runs):
        for arm, sigma in arms.items():
            seconds.clear()
            with contextlib.redirect_stdout(io.StringIO()):
                status = cli.main(["replay", args.recording, "--vins-only", "--json",
                                   "--set", f"vins.barometer_sigma_m={sigma}"])
            if status:
                raise SystemExit(f"companion replay {args.recording} failed ({status})")
            milliseconds = np.array(seconds) * 1e3
            report[arm].append({"keyframes": len(milliseconds),
                                "median_ms": round(float(np.median(milliseconds)), 3),
                                "p95_ms": round(float(np.percentile(milliseconds, 95)), 3)})
    print(json.dumps(report))


if __name__ == "__main__":
    main()
