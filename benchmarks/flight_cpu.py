"""Wall and CPU time of one whole simulated flight, in two arms flown in turn.

    python benchmarks/flight_cpu.py [--repeats 3] [--world dome] [--threads 2] [-- SIM FLY ARGS]
    python benchmarks/flight_cpu.py --baseline TREE [--repeats 3] [-- SIM FLY ARGS]

Flies ``companion sim fly --world W --json --no-plot --no-record [SIM FLY ARGS]`` (lockstep, the
world's first pair unless the arguments say otherwise) in a child process, ``--repeats`` times
in each arm, interleaved, so that the host's load falls on both alike:

- without ``--baseline``: OpenBLAS at one thread (the application's default,
  companion/__init__.py) against ``--threads`` threads (OpenBLAS's default is one per core);
- with ``--baseline TREE``: the code of another checkout (a ``git worktree`` of the commit
  before a change) against this one. Each child runs in its checkout's root (``python -m``
  puts it first on the path), so relative paths among the arguments are read in each.

Reports the medians of wall seconds and of the child's CPU seconds (user + system), the ratio
of the second arm's CPU to the first's, the summary fields that differ between flights of one
arm (lockstep flights are deterministic: only wall-clock figures such as the link's load
may), and those that differ between the arms' first flights (none beyond those for a change
that must not change a flight).
"""

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: This checkout's root.
ROOT = Path(__file__).resolve().parent.parent


def fly(fly_args: list[str], env: dict, root: Path) -> tuple[float, float, dict]:
    """(wall s, CPU s, summary) of one flight in a child process run in ``root``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "companion", "sim", "fly", "--json", "--no-plot",
                          "--no-record", *fly_args], env=env, capture_output=True, text=True,
                         check=True, cwd=root)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, json.loads(run.stdout)


def arms(args) -> dict[str, tuple[dict, Path]]:
    """The two arms' environments and checkouts, the reference arm first."""
    if args.baseline is None:
        return {f"openblas_threads_{n}": (dict(os.environ, OPENBLAS_NUM_THREADS=str(n)), ROOT)
                for n in (args.threads, 1)}
    tree = Path(args.baseline).resolve()
    if not (tree / "companion" / "__main__.py").is_file():
        sys.exit(f"--baseline {tree}: not a checkout of this project (no companion/__main__.py)")
    return {"baseline": (dict(os.environ), tree), "this_tree": (dict(os.environ), ROOT)}


def _differing(first: dict, second: dict) -> set[str]:
    """The summary fields whose values differ."""
    return {key for key in first.keys() | second.keys() if first.get(key) != second.get(key)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--world", default="dome")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--baseline", metavar="TREE", help="another checkout to fly against")
    parser.add_argument("fly_args", nargs="*", help="more `sim fly` arguments (after --)")
    args = parser.parse_args()
    fly_args = ["--world", args.world, *args.fly_args]
    environments = arms(args)
    times = {name: {"wall_s": [], "cpu_s": []} for name in environments}
    summaries = {name: [] for name in environments}
    for _ in range(args.repeats):
        for name, (env, root) in environments.items():
            wall, cpu, summary = fly(fly_args, env, root)
            times[name]["wall_s"].append(wall)
            times[name]["cpu_s"].append(cpu)
            summaries[name].append(summary)
    report = {name: {k: round(statistics.median(v), 2) for k, v in t.items()}
              for name, t in times.items()}
    reference, measured = environments
    report["cpu_ratio"] = round(report[measured]["cpu_s"] / report[reference]["cpu_s"], 3)
    report["flights"] = sum(len(s) for s in summaries.values())
    report["fields_differing_within_arms"] = sorted(set().union(
        *(_differing(flown[0], s) for flown in summaries.values() for s in flown)))
    report["fields_differing_between_arms"] = sorted(
        _differing(summaries[reference][0], summaries[measured][0]))
    print(json.dumps(report))


if __name__ == "__main__":
    main()
