"""Wall and CPU time of one whole simulated flight, and what OpenBLAS's thread pool costs it.

    python benchmarks/flight_cpu.py [--repeats 3] [--world dome] [--threads 2]

Flies ``companion sim fly --world W --json --no-plot --no-record`` (lockstep, the world's first pair,
estimated depth) in a child process, ``--repeats`` times with OpenBLAS at one thread (the
application's default, companion/__init__.py) and as many times with ``--threads`` threads
(OpenBLAS's default is one per core), interleaved. Reports the medians of wall seconds and of
the child's CPU seconds (user + system), and checks that every flight's summary is the same:
the thread count changes the cost, never the flight.
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time


def fly(world: str, threads: int) -> tuple[float, float, dict]:
    """(wall s, CPU s, summary) of one flight in a child process."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(threads))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "companion", "sim", "fly", "--world", world,
                          "--json", "--no-plot", "--no-record"], env=env, capture_output=True, text=True,
                         check=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, json.loads(run.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--world", default="dome")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 2)
    args = parser.parse_args()
    counts = (1, args.threads)
    times = {n: {"wall_s": [], "cpu_s": []} for n in counts}
    summaries = []
    for _ in range(args.repeats):
        for n in counts:
            wall, cpu, summary = fly(args.world, n)
            times[n]["wall_s"].append(wall)
            times[n]["cpu_s"].append(cpu)
            summaries.append(summary)
    report = {f"openblas_threads_{n}": {k: round(statistics.median(v), 2)
                                        for k, v in t.items()} for n, t in times.items()}
    report["flights"] = len(summaries)
    report["identical_summaries"] = all(s == summaries[0] for s in summaries)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
