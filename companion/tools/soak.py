"""Soak: the simulated mission flown again and again in one process, for as long as asked,
with the process's memory, threads and open files sampled, to show what a long-running
service must not do: grow, leak, or miss its setpoint deadline (issue 27; docs/reliability.md).

Each mission is :func:`companion.launch.simulated.run` to the end (take-off, the flight, the
landing), on the clock the mission names (real time for the soak itself, as on the vehicle;
lockstep to test this module quickly). Between two missions the flight's threads, sockets and
renderer must all be gone, so the process after mission *k* should look like the process
after mission 1. A sampler thread reads ``/proc/self`` every ``sample_period_s`` meanwhile,
for the peaks.

The verdict (:func:`verdict`) compares each later mission's end with the end of the last
warm-up mission (``warm_up_missions``: the first missions fill the caches and the allocator's
heap — imports, the network session, the renderer's shaders; a 30-minute real-time soak grew
by about 110 MB over its first three missions and then held, docs/reliability.md):

- resident memory *held* grew by at most ``max_rss_growth_mb``: each mission's end is judged
  by the lower of it and the next mission's end (:func:`held_rss_mb`; the last one on its
  own), so memory a mission's end still held and the next mission gave back is not growth (a
  30-minute soak's mission 20 ended 76 MB above the rest and its next mission back among
  them), while a leak, which stays, is judged at full size. Its trend after the warm-up (a
  least squares line through the missions' ends, judged over ``min_trend_minutes`` or more)
  is at most ``max_rss_slope_mb_per_h``;
- the thread count and the open file descriptors are back to the warm-up's;
- no setpoint deadline was missed: the watchdog never sent a setpoint, and no flight stopped
  on a loop lagging past ``[flight] max_loop_lag_s`` (each mission's 99th percentile of the
  lag is reported beside);
- every mission landed without a collision.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from autonomy.options import option, validate

#: The failsafes that mean the application missed its own deadline.
DEADLINE_FAILSAFES = ("event loop stalled", "setpoint deadline missed")


@dataclass(frozen=True)
class SoakOptions:
    """How long to soak and what counts as a pass (module docstring)."""

    minutes: float = option(30.0, gt=0.0, doc="fly missions until this much wall time passed")
    warm_up_missions: int = option(3, ge=1, doc="missions before the baseline is taken")
    sample_period_s: float = option(5.0, gt=0.0, doc="how often the sampler reads /proc/self")
    max_rss_growth_mb: float = option(64.0, ge=0.0, doc="resident memory growth allowed from "
                                      "the warm-up's end to any later mission's end, MB")
    max_rss_slope_mb_per_h: float = option(32.0, ge=0.0, doc="the trend of resident memory "
                                           "over the missions' ends allowed, MB per hour")
    min_trend_minutes: float = option(10.0, ge=0.0, doc="the trend is judged over at least "
                                      "this much wall time after the warm-up (a short soak's "
                                      "line through a few missions says nothing per hour)")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True)
class ProcessSample:
    """The process at one moment: wall seconds since the soak began, resident memory (MB),
    threads (the kernel's count, Python's and native ones alike) and open file descriptors."""

    t_s: float
    rss_mb: float
    threads: int
    open_files: int


#: Held while a sample reads ``/proc/self``: a sample taken in one thread while another
#: thread's sample had ``status`` or the ``fd`` directory open counted that descriptor as the
#: process's (the 30-minute soak's "extra open file" after one mission, docs/reliability.md).
SAMPLING = threading.Lock()


def sample_process(t0: float) -> ProcessSample:
    """Read this process's resident memory and threads from ``/proc/self/status`` and count
    ``/proc/self/fd``; Linux, as the vehicle. One sample at a time (:data:`SAMPLING`), so
    the count holds the descriptor of this sample's own listing and nothing of another's."""
    fields = {}
    with SAMPLING:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                key, _, value = line.partition(":")
                fields[key] = value.split()
        open_files = len(os.listdir("/proc/self/fd"))
    return ProcessSample(round(time.monotonic() - t0, 3), int(fields["VmRSS"][0]) / 1024.0,
                         int(fields["Threads"][0]), open_files)


class Sampler:
    """Samples the process every ``period_s`` in a daemon thread until :meth:`stop`."""

    def __init__(self, t0: float, period_s: float):
        self.t0, self.period_s = t0, period_s
        self.samples: list[ProcessSample] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak-sampler", daemon=True)

    def __enter__(self) -> "Sampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.samples.append(sample_process(self.t0))


def soak(fly_mission: Callable[[], dict], options: SoakOptions,
         report: Callable[[dict], None] = lambda record: None) -> dict:
    """Fly ``fly_mission()`` (a flight's summary) again and again until ``options.minutes`` of
    wall time have passed (and at least once after the warm-up, for a verdict), give
    ``report`` each mission's record as it ends, and return the soak's result: the missions'
    records, the sampler's peaks and :func:`verdict`'s findings."""
    t0 = time.monotonic()
    missions = []
    with Sampler(t0, options.sample_period_s) as sampler:
        while (len(missions) <= options.warm_up_missions
               or time.monotonic() - t0 < 60.0 * options.minutes):
            summary = fly_mission()
            record = mission_record(len(missions), summary, sample_process(t0))
            missions.append(record)
            report(record)
    peaks = {"rss_mb": max([s.rss_mb for s in sampler.samples] + [0.0]),
             "threads": max([s.threads for s in sampler.samples] + [0])}
    problems = verdict(missions, options)
    return {"minutes": round((time.monotonic() - t0) / 60.0, 2), "missions": missions,
            "samples": len(sampler.samples), "peaks": peaks, "problems": problems,
            "passed": not problems}


def mission_record(index: int, summary: dict, after: ProcessSample) -> dict:
    """What the soak keeps of one mission: its outcome, its deadline figures and the process
    sampled after it."""
    return {"mission": index, "final_state": summary["final_state"],
            "collisions": summary["collisions"], "reached_goal": summary["reached_goal"],
            "failsafes": summary["failsafes"],
            "watchdog_setpoints": summary["watchdog_setpoints"],
            "loop_lag_ms_p99": round(summary["loop_lag_ms_p99"], 2),
            "t_s": after.t_s, "rss_mb": round(after.rss_mb, 1), "threads": after.threads,
            "open_files": after.open_files,
            # memory blocks the interpreter holds: a leak of Python objects (numpy arrays
            # included) grows it, the C allocator's fragmentation, which moves RSS, does not
            "python_blocks": sys.getallocatedblocks()}


def verdict(missions: list[dict], options: SoakOptions) -> list[str]:
    """Every way ``missions`` (:func:`mission_record`, more than ``warm_up_missions``) fail
    the module docstring's bounds, each in one sentence; empty when the soak passed."""
    baseline, later = missions[options.warm_up_missions - 1], \
        missions[options.warm_up_missions:]
    problems = []
    growth = max(held_rss_mb(later)) - baseline["rss_mb"]
    if growth > options.max_rss_growth_mb:
        problems.append(f"resident memory held {growth:.1f} MB more than after the warm-up "
                        f"(allowed {options.max_rss_growth_mb:g})")
    judged = [baseline, *later]
    slope = rss_slope_mb_per_h(judged)
    long_enough = judged[-1]["t_s"] - baseline["t_s"] >= 60.0 * options.min_trend_minutes
    if long_enough and slope > options.max_rss_slope_mb_per_h:
        problems.append(f"resident memory trends up {slope:.1f} MB/h "
                        f"(allowed {options.max_rss_slope_mb_per_h:g})")
    for key, what in (("threads", "threads"), ("open_files", "open files")):
        grown = [m["mission"] for m in later if m[key] > baseline[key]]
        if grown:
            problems.append(f"more {what} than after the warm-up after missions "
                            f"{', '.join(map(str, grown))}")
    for m in missions:
        problems.extend(f"mission {m['mission']}: {p}" for p in _mission_problems(m))
    return problems


def _mission_problems(record: dict) -> list[str]:
    problems = []
    if record["final_state"] != "landed" or record["collisions"]:
        problems.append(f"ended {record['final_state']} with {record['collisions']} collisions")
    if record["watchdog_setpoints"]:
        problems.append(f"the watchdog sent {record['watchdog_setpoints']} setpoints "
                        "(a setpoint deadline missed)")
    missed = [f for f in record["failsafes"] if f.startswith(DEADLINE_FAILSAFES)]
    if missed:
        problems.append(f"stopped on {missed[0]}")
    return problems


def held_rss_mb(missions: list[dict]) -> list[float]:
    """Each mission's resident memory at its end that the next mission's end still held,
    ``min(rss_k, rss_k+1)``, MB; the last mission's own."""
    rss = [m["rss_mb"] for m in missions]
    return [min(here, after) for here, after in zip(rss, rss[1:])] + rss[-1:]


def rss_slope_mb_per_h(missions: list[dict]) -> float:
    """The least-squares trend of resident memory over ``missions``' ends, MB per hour of
    wall time (0 with fewer than two ends or no time between them)."""
    hours = np.array([m["t_s"] for m in missions]) / 3600.0
    if len(missions) < 2 or np.ptp(hours) == 0.0:
        return 0.0
    return float(np.polyfit(hours, [m["rss_mb"] for m in missions], 1)[0])
