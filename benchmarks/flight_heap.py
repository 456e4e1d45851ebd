"""Where a process flying mission after mission keeps Python memory: tracemalloc's growth
between the end of the warm-up and the end of the run, by allocation site.

    python benchmarks/flight_heap.py [--warm-up 2] [--missions 3] [--top 5]

`companion sim soak` records the interpreter's allocated blocks after each mission
(``python_blocks``); when they climb, this says who holds them. It flies the soak's short dome
mission in lockstep on true depth (the allocation sites are the same in real time, the run
shorter), ``--warm-up`` missions before the first snapshot, ``--missions`` between the two,
with a full collection before each. Prints one JSON object: the blocks gained per mission
(all sites), then the ``--top`` sites by blocks gained, each with its innermost frames.
"""

import argparse
import gc
import json
import logging
import tracemalloc

from companion.config import Config
from companion.launch import simulated

SHORT_GOAL = (-19.14, -11.82, 1.5)  # tests/test_soak.py's mission


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--warm-up", type=int, default=2)
    parser.add_argument("--missions", type=int, default=3)
    parser.add_argument("--top", type=int, default=5)
    args = parser.parse_args()
    logging.disable(logging.CRITICAL)
    config = Config()
    mission = simulated.SimMission(world="dome", goal=SHORT_GOAL, depth="truth")
    for _ in range(args.warm_up):
        simulated.run(config, mission)
    tracemalloc.start(16)
    gc.collect()
    before = tracemalloc.take_snapshot()
    for _ in range(args.missions):
        simulated.run(config, mission)
    gc.collect()
    after = tracemalloc.take_snapshot()
    growth = after.compare_to(before, "traceback")
    print(json.dumps({
        "missions": args.missions,
        "blocks_per_mission": sum(stat.count_diff for stat in growth) / args.missions,
        "sites": [{"blocks": stat.count_diff, "bytes": stat.size_diff,
                   "innermost": [f"{frame.filename}:{frame.lineno}"
                                 for frame in list(stat.traceback)[-4:]]}
                  for stat in growth[:args.top]]}, indent=1))


if __name__ == "__main__":
    main()
