"""The test suite's CPU by test file and each worker's busy span: a pytest plugin, then a report.

    SUITE_CPU_DIR=/tmp/suite PYTHONPATH=benchmarks python -m pytest -q -m 'not realtime' -p suite_cpu
    python benchmarks/suite_cpu.py /tmp/suite

Each test's CPU is read with ``getrusage`` of the process (the pytest-xdist worker) and of its
children it has waited for (the flights run as subprocesses), from the test's start to its end;
processes nobody waits for (Ray's) are not counted. One JSON line a test, a file per worker.
The report: CPU seconds per test file, costliest first, and per worker its first start, last
end and CPU (README, "Tests").
"""

import json
import os
import resource
import sys
import time
from collections import Counter
from pathlib import Path

_started: dict[str, tuple[float, float]] = {}


def _cpu_s() -> float:
    own, waited = (resource.getrusage(who) for who in
                   (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + waited.ru_utime + waited.ru_stime


def pytest_runtest_logstart(nodeid, location):
    _started[nodeid] = (time.time(), _cpu_s())


def pytest_runtest_logfinish(nodeid, location):
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if worker is None or nodeid not in _started:  # the controller relays the workers' tests
        return
    start, cpu = _started.pop(nodeid)
    line = {"id": nodeid, "start": start, "end": time.time(), "cpu_s": _cpu_s() - cpu}
    with open(Path(os.environ["SUITE_CPU_DIR"]) / f"{worker}.jsonl", "a") as out:
        out.write(json.dumps(line) + "\n")


def main() -> None:
    records = {path.stem: [json.loads(line) for line in path.read_text().splitlines()]
               for path in sorted(Path(sys.argv[1]).glob("*.jsonl"))}
    by_file = Counter()
    for tests in records.values():
        for test in tests:
            by_file[test["id"].split("::")[0]] += test["cpu_s"]
    first = min(test["start"] for tests in records.values() for test in tests)
    for worker, tests in records.items():
        print(f"{worker}: {min(t['start'] for t in tests) - first:.0f} to "
              f"{max(t['end'] for t in tests) - first:.0f} s, "
              f"{sum(t['cpu_s'] for t in tests):.0f} CPU s")
    print(f"all files: {sum(by_file.values()):.0f} CPU s")
    for name, cpu in by_file.most_common():
        print(f"{cpu:8.1f}  {name}")


if __name__ == "__main__":
    main()
