"""Navigation success over worlds, start/goal pairs and seeds, behind ``companion eval nav``.

The paper's navigation experiment (Yang, Tian, Goel, Tabib, Section IV) flies every start/goal
pair of each world several times, planning once on ground-truth depth ("GT") and once on the
rescaled estimate, and counts successes, collisions and timeouts. Here each trial is one
``companion sim fly`` (:func:`companion.launch.simulated.run`, lockstep, deterministic): the
whole stack over MAVLink against the simulator, ``--depth truth`` for ``gt`` and
``--depth estimated``.

Trials and seeds. Trial k (k = 0, 1, ...) of every pair flies seed ``s_k = S + k``
(:func:`trial_seed`), S the base ``--seed``. The seed draws the world (the layout of its trunks,
pillars, tunnel bends and room sizes), the sensor noise and the stand-in network's errors, so
the trials of a pair are different draws of its world; both depth sources fly the same seeds
(a paired comparison), and trial k is exactly ``companion sim fly --world W --pair P
--seed S+k --depth truth|estimated``. Lockstep flights do not depend on the machine's speed
or on how many run side by side, so on one machine the result depends only on the arguments
and the config; on another CPU the floating-point rounding of its libraries may fly other
flights (docs/simulator.md, "Reproducible flights").

Time limit. ``timeout_s`` (120 s) of simulated navigation, from the switch to Offboard (after
the take-off) to the goal: it is the application's own ``[flight] mission_timeout_s``, set to
``timeout_s`` for the trials, so a trial out of time ends as on the vehicle (the "mission
timeout" failsafe: stop, hold, land).

Outcomes (:func:`outcome`), one per trial:

- ``collision``: the simulator recorded a collision (with a wall, or the vehicle flown down
  onto the floor: ``floor_contact``), whatever else happened;
- ``success``: the goal was reached (the application said so and the true closest approach
  confirms it, :func:`companion.launch.simulated.run`) without a collision, within the time limit;
- ``timeout``: everything else: out of time, and also a flight that ended early without the
  goal (a failsafe such as no safe primitive, an abort on the ground, or a landing the truth
  did not confirm). The Markdown report counts those separately as "ended early" within the
  timeouts;
- ``error``: the trial raised instead of flying to an end (its record keeps the exception as
  ``error`` and the ``traceback``); the run goes on with the other trials.

The JSON keeps the four counts, which add up to ``trials``.

``mean_time_s`` is the mean ``flight_time_s`` (take-off to landed) of the successful trials,
None without one. The issues' other goals are read off every trial's record too:
``mean_speed_mps``, the successes' mean of path length over navigation time (the path is
the whole flight's, in truth, so the climb after take-off and the descent to land, about 3 m
of a 50-80 m flight, make it a few percent more than the speed while navigating);
``least_clearance_m``, the least true clearance of any trial's flight; and
``vins_error_median_m`` / ``vins_error_worst_m``, the median and the largest distance between
the application's position and the truth when navigation ended (the VINS's drift over the
flight). Each is None without a trial that has it.

Parts. Since the result depends only on the arguments, an evaluation too long for one sitting
can be flown in parts (one ``--seed S --trials 1`` or one ``--worlds W`` each, every part with
``--runs``) and reported as one: :func:`read_runs` merges the parts' records into those of
the whole run, refusing parts that overlap, flew different time limits, fly one depth source
without the other, or come from different code, configs or library versions (each record
carries the git revision, the config's hash and the libraries' versions,
:mod:`~companion.tools.eval.provenance`). With ``--runs``
each record is added to the file as its trial completes, so an interrupted run loses only the
trials in flight, and ``--resume`` flies only the trials its file lacks. Trials run in worker
processes on this machine, or as tasks on a Ray cluster (``--cluster``;
:mod:`~companion.tools.eval.executor`); a tqdm progress bar on stderr counts them as they
finish, with their outcomes, the trials in flight and an ETA.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, TextIO

import numpy as np
from tqdm import tqdm

from autonomy.navigation.behaviours import GOAL_STOP_REASON
from companion.launch import simulated
from companion.report import mean_or_none, show
from companion.tools.eval import executor, provenance
from companion.tools.eval.records import numbered_lines, parse_object
from companion.tools.eval.vio import EvaluationError
from companion.tools import plot
from drivers.sim.options import WORLD_NAMES
from drivers.sim.world import build_world

#: The report's depth sources and what each flies
#: (:data:`companion.launch.simulated.DEPTH_SOURCES`).
DEPTH_SOURCES = {"gt": "truth", "estimated": "estimated"}
#: How the reports name the depth sources.
SOURCE_NAMES = {"gt": "GT", "estimated": "estimated"}
#: A trial's outcomes, in the order they are counted and drawn.
OUTCOMES = ("success", "collision", "timeout", "error")
#: Trials per start/goal pair and depth source by default.
TRIALS = 5
#: Simulated seconds of navigation a trial may take to reach its goal (the paper's 120 s).
TIMEOUT_S = 120.0
#: The failsafe the application raises when ``[flight] mission_timeout_s`` runs out.
MISSION_TIMEOUT = "mission timeout"
#: The world of ``--quick`` when none is given: the fastest to fly.
QUICK_WORLD = "dome"


@dataclass(frozen=True)
class Trial:
    """One flight: ``pair`` of ``world`` on ``depth`` (a key of :data:`DEPTH_SOURCES`), the
    ``index``-th trial of its pair, flying ``seed``, its VINS on ``tracks`` (``sim fly
    --tracks``: the tracker's, or the truth's, to bound what a better tracker could give)."""

    world: str
    pair: int
    depth: str
    index: int
    seed: int
    tracks: str = "tracker"

    def mission(self) -> simulated.SimMission:
        """The simulated mission this trial flies (lockstep)."""
        return simulated.SimMission(world=self.world, seed=self.seed, pair=self.pair,
                                    depth=DEPTH_SOURCES[self.depth], tracks=self.tracks)


def trial_seed(base: int, index: int) -> int:
    """The seed of trial ``index`` (0, 1, ...) of every pair: ``base + index``, so trial k is
    ``companion sim fly --seed base+k`` and trial 0 flies the base seed itself."""
    if base < 0 or index < 0:
        raise ValueError(f"seed and trial index must be non-negative, got {base}, {index}")
    return base + index


def plan_trials(worlds: Iterable[str], pairs: Iterable[int] | None, trials: int,
                seed: int, tracks: str = "tracker") -> list[Trial]:
    """Every trial to fly: per world (in the order given, duplicates dropped) each pair of
    ``pairs`` (default: all the world's pairs) × ``trials`` × both depth sources, the two
    sources of one seed side by side. EvaluationError for an unknown world, a pair the world
    does not have, or fewer than one trial."""
    if trials < 1:
        raise EvaluationError(f"trials must be at least 1, got {trials}")
    if seed < 0:
        raise EvaluationError(f"seed must be non-negative, got {seed}")
    worlds, pairs = list(dict.fromkeys(worlds)), None if pairs is None else tuple(pairs)
    if not worlds:
        raise EvaluationError("no world to fly")
    unknown = [w for w in worlds if w not in WORLD_NAMES]
    if unknown:
        raise EvaluationError(f"unknown world {unknown[0]!r}; choose from "
                              f"{', '.join(WORLD_NAMES)}")
    return [Trial(world, pair, depth, k, trial_seed(seed, k), tracks)
            for world in worlds for pair in _pairs_of(world, pairs, seed)
            for k in range(trials) for depth in DEPTH_SOURCES]


def _pairs_of(world: str, pairs: tuple[int, ...] | None, seed: int) -> list[int]:
    """``pairs`` (duplicates dropped), checked against the world's start/goal pairs."""
    count = len(build_world(world, seed).routes)
    if pairs is None:
        return list(range(count))
    chosen = list(dict.fromkeys(pairs))
    bad = [p for p in chosen if not 0 <= p < count]
    if bad:
        raise EvaluationError(f"{world} has start/goal pairs 0..{count - 1}, not {bad[0]}")
    return chosen


def trial_config(config, timeout_s: float):
    """``config`` with ``[flight] mission_timeout_s`` set to ``timeout_s``: the application
    itself ends a trial that runs out of time (module docstring)."""
    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise EvaluationError(f"timeout must be a positive number of seconds, got {timeout_s}")
    try:
        flight = dataclasses.replace(config.flight, mission_timeout_s=float(timeout_s))
    except ValueError as error:
        raise EvaluationError(f"timeout: {error}") from None
    return dataclasses.replace(config, flight=flight)


# --------------------------------------------------------------------------------------------
# One trial (in a worker process)

def fly_trial(config, trial: Trial) -> dict:
    """Fly ``trial`` with ``config`` (its time limit already set, :func:`trial_config`) and
    return its record (:func:`trial_record`); a trial that raises is recorded too, as an
    ``error`` with its traceback (:func:`error_record`), and the run goes on."""
    started = time.perf_counter()
    try:
        summary = simulated.run(config, trial.mission())
    except Exception:  # noqa: BLE001 - any failure is this trial's result, not the run's end
        return error_record(trial, traceback.format_exc(),
                            timeout_s=config.flight.mission_timeout_s,
                            wall_s=time.perf_counter() - started)
    return trial_record(trial, summary, timeout_s=config.flight.mission_timeout_s,
                        wall_s=time.perf_counter() - started)


def trial_record(trial: Trial, summary: dict, *, timeout_s: float,
                 wall_s: float | None = None) -> dict:
    """The plain-number record of a flown trial: what it was, its time limit, its
    :func:`outcome`, whether it :func:`ended_early`, and the summary's numbers (``wall_s``: the
    flight's wall time)."""
    record = {**dataclasses.asdict(trial), "timeout_s": timeout_s, "outcome": outcome(summary),
              "ended_early": ended_early(summary),
              "time_to_goal_s": time_to_goal(summary)}
    record.update({key: summary.get(key) for key in _SUMMARY_KEYS})
    record["wall_s"] = wall_s
    return record


def error_record(trial: Trial, trace: str, *, timeout_s: float,
                 wall_s: float | None = None) -> dict:
    """The record of a trial that raised: outcome ``error``, the exception's last line as
    ``error`` and the whole ``traceback``; no flight numbers."""
    return {**dataclasses.asdict(trial), "timeout_s": timeout_s, "outcome": "error",
            "ended_early": False, "time_to_goal_s": None, **dict.fromkeys(_SUMMARY_KEYS),
            "wall_s": wall_s, "error": trace.strip().splitlines()[-1], "traceback": trace}


#: The flight summary's numbers a trial's record keeps.
_SUMMARY_KEYS = ("start", "reached_goal", "collisions", "floor_contact", "failsafes",
                 "final_state", "flight_time_s", "navigation_time_s", "path_length_m",
                 "min_clearance_m", "closest_to_goal_m", "vins_resets", "position_error_m",
                 "position_error_split", "backoffs",
                 "vins_correction_m", "landing_glide_m", "depth_fallbacks",
                 "camera_frames_dropped", "camera_frames_lost", "frame_age_ms")


def outcome(summary: dict) -> str:
    """``collision`` if any, else ``success`` if the goal was reached, else ``timeout``
    (module docstring). The time limit is the application's mission timeout: a goal reached is
    a goal reached within it."""
    if summary["collisions"]:
        return "collision"
    return "success" if summary["reached_goal"] else "timeout"


def ended_early(summary: dict) -> bool:
    """Whether a trial that neither collided nor reached its goal ended before its time limit:
    no "mission timeout" failsafe (another failsafe, an abort, or an unconfirmed landing)."""
    return outcome(summary) == "timeout" and MISSION_TIMEOUT not in summary["failsafes"]


def time_to_goal(summary: dict) -> float | None:
    """Simulated seconds from the switch to Offboard (the transition out of ENTERING_OFFBOARD,
    to the offset swing or to navigating: the swing is the flight's time too) to "goal
    reached", None if not reached."""
    transitions = summary.get("transitions", [])
    offboard = simulated.offboard_switch_time(transitions)
    reached = next((t["t"] for t in transitions if t["reason"] == GOAL_STOP_REASON), None)
    if offboard is None or reached is None:
        return None
    return reached - offboard


# --------------------------------------------------------------------------------------------
# Many trials, in parallel

class ProgressBar:
    """The trials done of the total, their outcomes so far, the trials in flight, the last
    one, and the elapsed time and ETA, drawn by tqdm: a bar redrawn in place on a terminal,
    one line per update elsewhere (a log, where redrawing would pile the updates onto one
    line)."""

    def __init__(self, total: int, stream: TextIO | None = None):
        self.total, self.done, self.workers = total, 0, 1
        self.stream = sys.stderr if stream is None else stream
        self.counts = dict.fromkeys(OUTCOMES, 0)
        self.started = time.monotonic()
        self._tty = getattr(self.stream, "isatty", lambda: False)()
        self._bar: tqdm | None = None

    def start(self, workers: int, where: str) -> None:
        self.workers = workers
        self._line(f"{self.total} trials on {where}")
        if self._tty:
            self._bar = tqdm(total=self.total, file=self.stream, unit="trial",
                             dynamic_ncols=True)

    def update(self, record: dict) -> None:
        self.done += 1
        self.counts[record["outcome"]] += 1
        running = min(self.workers, self.total - self.done)
        counts = " ".join(f"{name} {n}" for name, n in self.counts.items())
        last = f"{record['world']} pair {record['pair']} {record['depth']} #{record['index']}"
        status = f"{counts}, {running} running; last: {last} {record['outcome']}"
        if self._bar is not None:
            self._bar.set_postfix_str(status, refresh=False)
            self._bar.update(1)
        else:
            meter = tqdm.format_meter(self.done, self.total, time.monotonic() - self.started,
                                      unit="trial", ascii=True)
            self._line(f"{meter}  {status}")

    def finish(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def _line(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()


def run_trials(config, trials: list[Trial], *, workers: int | None = None,
               cluster: str | None = None, progress: ProgressBar | None = None,
               provenance: dict | None = None,
               on_record: Callable[[dict], None] | None = None) -> list[dict]:
    """Fly ``trials`` on ``cluster`` (a Ray address) or in up to ``workers`` local processes
    (default: the CPU count; :func:`~companion.tools.eval.executor.open_executor`) and return
    their records in the order of ``trials``, each with ``provenance``'s keys added and handed
    to ``on_record`` as it completes. A trial that raises is an ``error`` record
    (:func:`fly_trial`); a worker process that dies locally, or a task lost on the cluster
    after its retries, stops the run (trials not started are cancelled) with an
    :class:`~companion.tools.eval.executor.ExecutorError` (an EvaluationError)."""
    if not trials:
        return []
    runner = executor.open_executor(cluster, workers, len(trials))
    if progress is not None:
        progress.start(runner.workers, runner.where)
    records: list[dict | None] = [None] * len(trials)
    try:
        for k, record in runner.run(fly_trial, config, trials):
            record = {**record, **(provenance or {})}
            records[k] = record
            if on_record is not None:
                on_record(record)
            if progress is not None:
                progress.update(record)
    finally:
        if progress is not None:
            progress.finish()
    return records


def evaluate_navigation(config, *, worlds: Iterable[str], pairs: Iterable[int] | None = None,
                        trials: int = TRIALS, seed: int = 0, timeout_s: float = TIMEOUT_S,
                        tracks: str = "tracker",
                        workers: int | None = None, cluster: str | None = None,
                        progress: TextIO | None = None,
                        done: Iterable[dict] = (),
                        on_record: Callable[[dict], None] | None = None
                        ) -> tuple[dict, list[dict]]:
    """Plan (:func:`plan_trials`), fly (:func:`run_trials`) and count (:func:`summarise`):
    ``(result, records)``; a :class:`ProgressBar` on the ``progress`` stream if given.

    ``done``: records of this evaluation flown before (a run resumed, ``--resume``). Their
    trials are not flown again; they must come from the same code and config as this run
    (:func:`check_provenance`), and they join the records returned, in the order of the plan.
    Every record carries the code's revision and the config's hash (:mod:`provenance`).
    ``tracks``: the VINS's feature tracks (:class:`Trial`); EvaluationError for a source the
    config's profile cannot fly, before any trial starts."""
    try:
        simulated.check_track_source(config, tracks)
    except simulated.SimError as error:
        raise EvaluationError(str(error)) from None
    planned = plan_trials(worlds, pairs, trials, seed, tracks)
    flown = trial_config(config, timeout_s)
    stamp = provenance.stamp(flown)
    done = list(done)
    check_provenance([*done, {**stamp, "tracks": tracks}])
    finished = {trial_key(r) for r in done}
    if len(finished) < len(done):
        raise EvaluationError("a trial is recorded more than once in the records resumed")
    keys = [trial_key(dataclasses.asdict(t)) for t in planned]
    foreign = finished - set(keys)
    if foreign:
        raise EvaluationError(f"{describe_trial(min(foreign))} was flown but is not in this run's "
                              "plan; resume with the options the run was started with")
    pending = [t for t, key in zip(planned, keys) if key not in finished]
    bar = None if progress is None else ProgressBar(len(pending), progress)
    new = run_trials(flown, pending, workers=workers, cluster=cluster, progress=bar,
                     provenance=stamp, on_record=on_record)
    by_trial = {trial_key(r): r for r in done + new}
    records = merge_records([by_trial[key] for key in keys])
    return summarise(records), records


# --------------------------------------------------------------------------------------------
# Summaries

def summarise(records: list[dict]) -> dict:
    """The JSON result: ``{source: {world: count}}`` (:func:`count`), sources in the order
    of :data:`DEPTH_SOURCES`, worlds in the order they were flown."""
    worlds = list(dict.fromkeys(r["world"] for r in records))
    return {source: {world: count([r for r in records
                                   if r["depth"] == source and r["world"] == world])
                     for world in worlds}
            for source in DEPTH_SOURCES}


def count(records: list[dict]) -> dict:
    """Trials, each outcome's count, the mean flight time and speed of the successes, the
    least clearance, and the median and worst VINS error at the end of navigation (module
    docstring; None where no trial has the number)."""
    successes = [r for r in records if r["outcome"] == "success"]
    clearances = finite_values(records, "min_clearance_m")
    vins_errors = finite_values(records, "position_error_m")
    return {"trials": len(records),
            **{name: sum(r["outcome"] == name for r in records) for name in OUTCOMES},
            "mean_time_s": mean_or_none([r["flight_time_s"] for r in successes]),
            "mean_speed_mps": mean_or_none([r["path_length_m"] / r["navigation_time_s"]
                                            for r in successes
                                            if (r.get("navigation_time_s") or 0) > 0]),
            "least_clearance_m": min(clearances, default=None),
            "vins_error_median_m": float(np.median(vins_errors)) if vins_errors else None,
            "vins_error_worst_m": max(vins_errors, default=None)}


def finite_values(records: list[dict], key: str) -> list[float]:
    """The finite values of ``key`` in ``records`` (records of trials that raised, or from
    before the key was kept, have none)."""
    return [r[key] for r in records if finite(r.get(key))]


def finite(value) -> bool:
    """Is ``value`` a finite number (a record's number that was kept and means something)?"""
    return isinstance(value, (int, float)) and math.isfinite(value)


# --------------------------------------------------------------------------------------------
# Runs flown in parts, merged

#: What a record must hold to be merged, counted and reported.
RECORD_KEYS = ("world", "pair", "depth", "index", "seed", "timeout_s", "outcome",
               "ended_early", "flight_time_s", "path_length_m")


def read_runs(paths: Iterable[Path]) -> list[dict]:
    """The records of the ``--runs`` files at ``paths`` as one evaluation
    (:func:`merge_records`): an evaluation flown in parts, say one seed per run, reported as
    if flown at once. EvaluationError naming the file and line of a record that cannot be
    read, or naming what keeps the parts from making one evaluation."""
    records = []
    for path in paths:
        records += read_records(Path(path))
    return merge_records(records)


def read_records(path: Path) -> list[dict]:
    """The trial records of one ``--runs`` file, each checked as :func:`read_runs` says;
    EvaluationError for a file without any."""
    trials = [parse_record(line, f"{path}:{n}") for n, line in numbered_lines(path)]
    if not trials:
        raise EvaluationError(f"{path}: no trial records (is it an 'eval nav --runs' file?)")
    return trials


def parse_record(line: str, where: str) -> dict:
    """One trial's record from a line of a ``--runs`` file, checked as :func:`read_runs`
    says (``where``: its file and line, for the error)."""
    record = parse_object(line, where, "trial record")
    missing = [key for key in RECORD_KEYS if key not in record]
    if missing:
        raise EvaluationError(f"{where}: trial record without {', '.join(missing)}")
    for key, allowed in (("world", WORLD_NAMES), ("depth", tuple(DEPTH_SOURCES)),
                         ("outcome", OUTCOMES)):
        if record[key] not in allowed:
            raise EvaluationError(f"{where}: {key} {record[key]!r} is not one of "
                                  f"{', '.join(allowed)}")
    for key in ("pair", "index", "seed"):
        if type(record[key]) is not int or record[key] < 0:
            raise EvaluationError(f"{where}: {key} must be a non-negative integer, "
                                  f"got {record[key]!r}")
    if type(record["timeout_s"]) not in (int, float) or not record["timeout_s"] > 0:
        raise EvaluationError(f"{where}: timeout_s must be a positive number of seconds, "
                              f"got {record['timeout_s']!r}")
    for key in FLIGHT_NUMBERS:
        value = record.get(key)
        if value is not None and type(value) not in (int, float):
            raise EvaluationError(f"{where}: {key} must be a number or null, got {value!r}")
    if record["outcome"] == "success":
        unflown = [key for key in ("flight_time_s", "path_length_m") if record[key] is None]
        if unflown:
            raise EvaluationError(f"{where}: a success without {', '.join(unflown)}")
    return record


#: The numbers of a record that the reports read (null where a trial has none, as one that
#: raised).
FLIGHT_NUMBERS = ("flight_time_s", "path_length_m", "navigation_time_s", "time_to_goal_s",
                  "min_clearance_m", "position_error_m")


def merge_records(records: list[dict]) -> list[dict]:
    """``records`` of one or more runs as one evaluation's: in the order one run flies them
    (:func:`plan_trials`: world, pair, seed, depth source; the worlds in the order they first
    appear) with ``index`` the rank of the seed among its pair's, so the parts ``--seed S
    --trials 1`` for S = 0..4 merge into the records of ``--seed 0 --trials 5``.
    EvaluationError when a trial is in two records, when the parts flew different time
    limits, or when a seed of a pair was flown on one depth source only (the comparison is
    paired)."""
    refuse_repeated_trials(records)
    check_provenance(records)
    trials = dict.fromkeys(trial_key(r) for r in records)  # in record order: the first named
    refuse_mixed_time_limits(records, "merge")
    for world, pair, depth, seed in trials:
        other = next(d for d in DEPTH_SOURCES if d != depth)
        if (world, pair, other, seed) not in trials:
            raise EvaluationError(f"{describe_trial((world, pair, depth, seed))} has no "
                                  f"{other} flight of the same seed (the comparison is paired)")
    worlds = list(dict.fromkeys(r["world"] for r in records))
    ordered = sorted(records, key=lambda r: (worlds.index(r["world"]), r["pair"], r["seed"],
                                             list(DEPTH_SOURCES).index(r["depth"])))
    seeds = collections.defaultdict(list)
    for record in ordered:
        seeds[record["world"], record["pair"], record["depth"]].append(record["seed"])
    return [{**r, "index": seeds[r["world"], r["pair"], r["depth"]].index(r["seed"])}
            for r in ordered]


def refuse_repeated_trials(records: Iterable[dict]) -> None:
    """EvaluationError naming the first trial that is in more than one of ``records``."""
    trials = collections.Counter(trial_key(r) for r in records)
    twice = [key for key, n in trials.items() if n > 1]
    if twice:
        raise EvaluationError(f"{describe_trial(twice[0])} is in more than one record")


def refuse_mixed_time_limits(records: Iterable[dict], verb: str) -> float:
    """The one time limit ``records`` were flown to; EvaluationError naming them when they
    were flown to several (an outcome depends on the limit), telling the user to ``verb``
    runs of one ``--timeout``."""
    limits = sorted({r["timeout_s"] for r in records})
    if len(limits) > 1:
        raise EvaluationError("the runs flew different time limits ("
                              + ", ".join(f"{t:g} s" for t in limits) + f"); {verb} runs of "
                              "one --timeout")
    return limits[0]


def check_provenance(records: Iterable[dict]) -> None:
    """EvaluationError unless ``records`` all come from one revision of the code, one config,
    one set of library versions and one source of feature tracks (their ``revision``,
    ``config_hash``, ``libraries`` and ``tracks``; records from before these were kept lack
    them, and merge only with each other, a record without ``tracks`` counting as the
    tracker's)."""
    provenance = _provenance(records)
    for key, what in (("revision", "code revisions"), ("config_hash", "configs"),
                      ("libraries", "library versions"), ("tracks", "track sources")):
        if len(provenance[key]) > 1:
            raise EvaluationError(f"the records come from different {what} "
                                  f"({', '.join(provenance[key])}); one evaluation is flown "
                                  "by one code and config")


def _provenance(records: Iterable[dict]) -> dict[str, list[str]]:
    """The distinct ``revision``, ``config_hash``, ``libraries`` and ``tracks`` values of
    ``records``, in order: "none recorded" for records from before the first three were
    kept, "tracker" for those from before ``tracks`` was."""
    records = list(records)
    missing = {"revision": "none recorded", "config_hash": "none recorded",
               "libraries": "none recorded", "tracks": "tracker"}
    return {key: list(dict.fromkeys(str(r.get(key, default)) for r in records))
            for key, default in missing.items()}


def trial_key(record: dict) -> tuple:
    """What identifies a trial across runs: (world, pair, depth source, seed)."""
    return record["world"], record["pair"], record["depth"], record["seed"]


def describe_trial(key: tuple) -> str:
    world, pair, depth, seed = key
    return f"{world} pair {pair} {depth} seed {seed}"


# --------------------------------------------------------------------------------------------
# Report

def format_markdown(result: dict, records: list[dict]) -> str:
    """Markdown: a heading with the trials per pair, their seeds and time limit (read off
    ``records``), then one row per world and depth source with the counts, the success rate,
    the timeouts that ended early, the successes' mean flight time, path length and speed,
    the least clearance and the VINS error at the end of navigation; with more than one
    world, a row of all of them per depth source."""
    lines = [
        f"## Navigation in simulated flights ({_flown(records)})",
        "",
        "GT: planning on the renderer's true depth; estimated: on the network rescaled with "
        "the VINS map. Success: the goal reached without a collision within the time; "
        "collision: any collision; timeout: neither (of which *ended early*: stopped by a "
        "failsafe or landed away from the goal before the time ran out); error: the trial "
        "raised (its record holds the traceback). Mean flight time (take-off to landed), "
        "path length and speed (path over navigation time) over the successes; least true "
        "clearance and VINS error when navigation ended (median / worst) over all trials.",
        "",
        "| world | depth | trials | success | collision | timeout | error | ended early | "
        "success rate | mean flight s | mean path m | mean speed m/s | least clearance m | "
        "VINS error at end m |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for source, worlds in result.items():
        for world, numbers in worlds.items():
            lines.append(_row(world, source, numbers, [
                r for r in records if r["depth"] == source and r["world"] == world]))
        if len(worlds) > 1:
            flown = [r for r in records if r["depth"] == source]
            lines.append(_row("**all**", source, count(flown), flown))
    return "\n".join(lines)


def _flown(records: list[dict]) -> str:
    """"5 per start/goal pair and depth source, seeds 0..4, 120 s to reach the goal"."""
    if not records:
        return "no trials"
    per_pair = collections.Counter((r["world"], r["pair"], r["depth"]) for r in records)
    fewest, most = min(per_pair.values()), max(per_pair.values())
    trials = str(most) if fewest == most else f"{fewest} to {most}"
    seeds = sorted({r["seed"] for r in records})
    if len(seeds) == 1:
        seeds_text = f"seed {seeds[0]}"
    elif seeds == list(range(seeds[0], seeds[-1] + 1)):
        seeds_text = f"seeds {seeds[0]}..{seeds[-1]}"
    else:
        seeds_text = "seeds " + ", ".join(map(str, seeds))
    limits = " or ".join(f"{t:g}" for t in sorted({r["timeout_s"] for r in records}))
    sources = [source for source in _provenance(records)["tracks"] if source != "tracker"]
    return (f"{trials} per start/goal pair and depth source, {seeds_text}, "
            f"{limits} s to reach the goal"
            + "".join(f", the VINS on {source} tracks" for source in sources))


def _row(world: str, source: str, numbers: dict, records: list[dict]) -> str:
    early = sum(r["ended_early"] for r in records)
    path = mean_or_none([r["path_length_m"] for r in records if r["outcome"] == "success"])
    rate = numbers["success"] / numbers["trials"] if numbers["trials"] else None
    cells = [world, SOURCE_NAMES[source], numbers["trials"], *(numbers[o] for o in OUTCOMES),
             early, show(rate, ".0%"), show(numbers["mean_time_s"], ".1f"), show(path, ".1f"),
             show(numbers["mean_speed_mps"], ".2f"), show(numbers["least_clearance_m"], ".2f"),
             f"{show(numbers['vins_error_median_m'], '.2f')} / "
             f"{show(numbers['vins_error_worst_m'], '.2f')}"]
    return "| " + " | ".join(str(c) for c in cells) + " |"


# --------------------------------------------------------------------------------------------
# Plot

#: Colours of the outcomes: green, red, grey, purple.
_COLOURS = {"success": "tab:green", "collision": "tab:red", "timeout": "tab:gray",
            "error": "tab:purple"}


def plot_navigation(result: dict, records: list[dict], out: Path) -> Path:
    """Draw :func:`navigation_figure` as a PNG at ``out`` (parent folders created).
    ValueError for a name that does not end in .png, :class:`~companion.tools.plot.
    MissingExtra` without matplotlib."""
    return plot.save(navigation_figure(result, records), out)


def navigation_figure(result: dict, records: list[dict]):
    """The matplotlib Figure of the outcomes: per world, a bar per depth source stacking its
    counts of each outcome (successes at the bottom, each segment labelled with its count),
    the mean flight time of its successes above it; the caption says what was flown
    (:func:`_flown`) and by which code and config (the records' revision and config hash)."""
    bars = [(world, source) for world in next(iter(result.values()), {}) for source in result]
    x = np.array([k + k // len(result) for k in range(len(bars))], dtype=float)  # a gap a world
    figure = plot.new_figure(max(6.5, 2.5 + 0.75 * len(bars)), 5.0,
                             f"Flown: {_flown(records)}; {_made_by(records)}.")
    axes = figure.add_subplot()
    bottom = np.zeros(len(bars))
    for name in OUTCOMES:
        counts = np.array([result[source][world][name] for world, source in bars])
        container = axes.bar(x, counts, 0.8, bottom=bottom, color=_COLOURS[name], label=name)
        axes.bar_label(container, [str(n) if n else "" for n in counts], label_type="center",
                       color="white", fontsize=9)
        bottom += counts
    for at, top, (world, source) in zip(x, bottom, bars):
        mean = result[source][world]["mean_time_s"]
        axes.annotate("no success" if mean is None else f"{mean:.0f} s", (at, top),
                      xytext=(0, 3), textcoords="offset points", ha="center", fontsize=8)
    _label_bars(axes, x, bars, len(result))
    axes.set(ylabel="trials", ylim=(0, max([1.0, *bottom]) * 1.12),
             title="Navigation outcomes per world and depth source: higher success is "
                   "better\n(above each bar: the mean flight time, take-off to landed, of "
                   "its successes)")
    axes.title.set_fontsize(10)
    axes.yaxis.get_major_locator().set_params(integer=True)
    axes.legend(title="outcome", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return figure


def _label_bars(axes, x: np.ndarray, bars: list[tuple[str, str]], sources: int) -> None:
    """Each bar's depth source under it, each world's name under its bars."""
    axes.set_xticks(x, [SOURCE_NAMES[source] for _, source in bars])
    centres = x.reshape(-1, sources).mean(axis=1)
    axes.set_xticks(centres, [world for world, _ in bars[::sources]], minor=True)
    axes.tick_params(axis="x", which="minor", length=0, pad=18, labelsize=11)


def _made_by(records: list[dict]) -> str:
    """"code revision 1a2b...; config hash 3c4d..." of ``records`` (their provenance; the
    libraries' versions, which the records keep too, would crowd a caption)."""
    provenance = _provenance(records)
    return (f"code revision {', '.join(provenance['revision'])}; "
            f"config hash {', '.join(provenance['config_hash'])}")

