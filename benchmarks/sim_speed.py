"""How fast a lockstep simulated flight runs, ideal profile against realistic, each world.

    python benchmarks/sim_speed.py [--worlds dome mine] [--repeats 1]

Flies ``companion sim fly --world W --clock lockstep --json --no-plot --no-record`` (the
world's first pair, estimated depth) in a child process, once with ``[sim] profile = ideal``
and once with ``realistic`` (the VINS estimating the camera-IMU offset, as the realistic
profile needs), interleaved ``--repeats`` times. Prints one JSON object per flight: simulated
seconds flown (take-off to landed), wall seconds of the child process (start-up included),
and their ratio, the speed over real time.
"""

import argparse
import json
import subprocess
import sys
import time

PROFILES = {
    "ideal": ["--set", "sim.profile=ideal"],
    "realistic": ["--set", "sim.profile=realistic", "--set", "vins.estimate_time_offset=true"],
}


def fly(world: str, overrides: list[str]) -> tuple[float, dict]:
    """(wall s, summary) of one flight in a child process (which exits 1 when the flight
    did not reach its goal, still printing its summary)."""
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "companion", "sim", "fly", "--world", world,
                          "--clock", "lockstep", "--json", "--no-plot", "--no-record",
                          *overrides], capture_output=True, text=True)
    if not run.stdout.strip():
        raise SystemExit(f"sim fly --world {world} {' '.join(overrides)} failed:\n{run.stderr}")
    return time.perf_counter() - start, json.loads(run.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["dome", "mine"])
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()
    for world in args.worlds:
        for _ in range(args.repeats):
            for profile, overrides in PROFILES.items():
                wall, summary = fly(world, overrides)
                flown = summary["flight_time_s"]
                print(json.dumps({"world": world, "profile": profile,
                                  "simulated_s": round(flown, 1), "wall_s": round(wall, 1),
                                  "speed": round(flown / wall, 2),
                                  "reached_goal": summary["reached_goal"]}), flush=True)


if __name__ == "__main__":
    main()
