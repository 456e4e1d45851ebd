"""Cost of the VINS odometry's IMU propagation when no keyframe comes (a frozen or blacked-out
camera, or standing before initialisation): ``Propagator`` against ``propagate`` from the
keyframe every time, on the same samples in the same run.

    python benchmarks/vins_propagation.py [--outage 5] [--rate 200] [--odometry-rate 30]

Simulates ``--outage`` seconds of IMU at ``--rate`` Hz after the last keyframe, the odometry
asking for the newest state ``--odometry-rate`` times a second, and reports the median and the
last call's milliseconds of each method (from scratch grows with the outage; resumed does
not), checking that both give the same states bit for bit.
"""

import argparse
import json
import statistics
import time

import numpy as np

from autonomy.messages import ImuSample
from autonomy.vins.imu_buffer import ImuBuffer, NavState, Propagator, propagate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--outage", type=float, default=5.0)
    parser.add_argument("--rate", type=float, default=200.0)
    parser.add_argument("--odometry-rate", type=float, default=30.0)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    start = NavState(0.0, np.eye(3), np.zeros(3), np.zeros(3))
    bias_g, bias_a = np.zeros(3), np.zeros(3)
    buffer, propagator = ImuBuffer(), Propagator()
    times = {"from_scratch_ms": [], "resumed_ms": []}
    same, next_ask = True, 0.0
    for k in range(int(args.outage * args.rate)):
        t = k / args.rate
        buffer.add(ImuSample(t, rng.normal(0, 0.1, 3), rng.normal([0, 0, 9.81], 0.5)))
        if t < next_ask:
            continue
        next_ask += 1.0 / args.odometry_rate
        pieces = buffer.pieces(0.0, t)
        begin = time.perf_counter()
        scratch = propagate(start, pieces, bias_g, bias_a)
        middle = time.perf_counter()
        resumed = propagator.propagate(start, pieces, bias_g, bias_a)
        end = time.perf_counter()
        times["from_scratch_ms"].append(1e3 * (middle - begin))
        times["resumed_ms"].append(1e3 * (end - middle))
        same &= bool(np.array_equal(scratch.R_W_B, resumed.R_W_B)
                     and np.array_equal(scratch.position, resumed.position))
    print(json.dumps({"outage_s": args.outage, "calls": len(times["resumed_ms"]),
                      **{f"{k}_median": round(statistics.median(v), 3) for k, v in times.items()},
                      **{f"{k}_last": round(v[-1], 3) for k, v in times.items()},
                      "identical": same}))


if __name__ == "__main__":
    main()
