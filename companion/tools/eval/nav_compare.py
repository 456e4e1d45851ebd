"""Two navigation runs compared trial by trial, behind ``companion eval nav --compare``.

A change to the stack is judged on the trials both runs flew: the same world, start/goal pair,
depth source and seed (:func:`compare_runs`). Lockstep flights are deterministic on one machine
(docs/simulator.md, "Reproducible flights"), so a trial flown to the same numbers in both runs
(same outcome, flight time, path length and least clearance) was untouched by the change, and
every other difference is the change's. Flown on different machines, two runs may differ by
floating-point rounding alone; the count of identical trials shows which case a comparison is.

Per depth source, over the common trials: the successes and collisions of each run, the
trials that changed outcome, the trials flown identically, the least true clearance of each
run, and for the trials both runs brought to the goal the ratio after/before of their
navigation times (``time_to_goal_s``, Offboard to goal): median, range and count. A ratio
below 1 is a faster flight after the change.

Either run may be partial (an interrupted ``--runs`` file): only common trials are compared,
and the trials one run flew alone are counted, not compared.
"""

from __future__ import annotations

import collections
from pathlib import Path

import numpy as np

from companion.report import show
from companion.tools.eval import nav
from companion.tools.eval.vio import EvaluationError

#: The numbers two flights of one trial must share to count as the same flight.
SAME_FLIGHT_KEYS = ("outcome", "flight_time_s", "path_length_m", "min_clearance_m")


def read_run(path: Path) -> list[dict]:
    """The records of one ``--runs`` file, complete or interrupted: EvaluationError naming
    the file when one trial is in it twice or it mixes code revisions or configs."""
    records = nav.read_records(Path(path))
    try:
        nav.refuse_repeated_trials(records)
        nav.check_provenance(records)
    except EvaluationError as error:
        raise EvaluationError(f"{path}: {error}") from None
    return records


def compare_runs(before: list[dict], after: list[dict]) -> dict:
    """``{"trials_only_before", "trials_only_after", "sources": {source: {...}}}``, the
    comparison of the module docstring; ``sources`` in the order of
    :data:`~companion.tools.eval.nav.DEPTH_SOURCES`, those with no common trial left out."""
    earlier = {nav.trial_key(r): r for r in before}
    later = {nav.trial_key(r): r for r in after}
    common = [key for key in earlier if key in later]
    by_source = collections.defaultdict(list)
    for key in common:
        by_source[key[2]].append((earlier[key], later[key]))
    return {"trials_only_before": len(earlier) - len(common),
            "trials_only_after": len(later) - len(common),
            "sources": {source: _compare_source(by_source[source])
                        for source in nav.DEPTH_SOURCES if by_source[source]}}


def _compare_source(pairs: list[tuple[dict, dict]]) -> dict:
    def each_run(value_of) -> list:
        return [value_of([pair[k] for pair in pairs]) for k in (0, 1)]

    ratios = [a["time_to_goal_s"] / b["time_to_goal_s"] for b, a in pairs
              if b["outcome"] == a["outcome"] == "success"
              and _positive(b.get("time_to_goal_s")) and _positive(a.get("time_to_goal_s"))]
    return {
        "trials": len(pairs),
        "success": each_run(lambda records: _count(records, "success")),
        "collision": each_run(lambda records: _count(records, "collision")),
        "identical": sum(_same_flight(b, a) for b, a in pairs),
        "changed": [{"trial": nav.describe_trial(nav.trial_key(b)), "before": b["outcome"],
                     "after": a["outcome"]}
                    for b, a in pairs if b["outcome"] != a["outcome"]],
        "least_clearance_m": each_run(_least_clearance),
        "time_ratio": {"median": float(np.median(ratios)) if ratios else None,
                       "min": min(ratios, default=None), "max": max(ratios, default=None),
                       "trials": len(ratios)},
    }


def _positive(seconds) -> bool:
    return isinstance(seconds, (int, float)) and seconds > 0


def _count(records: list[dict], outcome: str) -> int:
    return sum(r["outcome"] == outcome for r in records)


def _same_flight(before: dict, after: dict) -> bool:
    return all(before.get(key) == after.get(key) for key in SAME_FLIGHT_KEYS)


def _least_clearance(records: list[dict]) -> float | None:
    return min((r["min_clearance_m"] for r in records if r.get("min_clearance_m") is not None),
               default=None)


def format_markdown(comparison: dict, before: str, after: str) -> str:
    """A heading naming the two runs, one row per depth source, and the changed outcomes."""
    lines = [
        f"## Navigation runs compared: {before} → {after}",
        "",
        "On the trials both runs flew (world, pair, depth source, seed); "
        f"{comparison['trials_only_before']} flown only before and "
        f"{comparison['trials_only_after']} only after are left out. Identical: the same "
        "outcome, flight time, path length and least clearance. Time ratio: navigation time "
        "after over before, on the trials both runs brought to the goal (below 1: faster).",
        "",
        "| depth | trials | identical | success | collision | least clearance m | "
        "time ratio median | range | over |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    changes = []
    for source, numbers in comparison["sources"].items():
        ratio = numbers["time_ratio"]
        clearance = [show(c, ".2f") for c in numbers["least_clearance_m"]]
        cells = [nav.SOURCE_NAMES[source], numbers["trials"], numbers["identical"],
                 _arrow(numbers["success"]), _arrow(numbers["collision"]), _arrow(clearance),
                 show(ratio["median"], ".2f"),
                 f"{show(ratio['min'], '.2f')}–{show(ratio['max'], '.2f')}", ratio["trials"]]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
        changes += [f"- {c['trial']}: {c['before']} → {c['after']}" for c in numbers["changed"]]
    if changes:
        lines += ["", "Changed outcomes:", "", *changes]
    return "\n".join(lines)


def _arrow(values: list) -> str:
    return f"{values[0]} → {values[1]}"
