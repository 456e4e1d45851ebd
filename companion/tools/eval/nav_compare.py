"""Two navigation runs compared trial by trial, behind ``companion eval nav --compare``.

A change to the stack is judged on the trials both runs flew: the same world, start/goal pair,
depth source and seed (:func:`compare_runs`). Lockstep flights are deterministic on one machine
(docs/simulator.md, "Reproducible flights"), so a trial flown to the same numbers in both runs
(:data:`SAME_FLIGHT_KEYS`: outcome, times, path length, least clearance, VINS error) was
untouched by the change, and every other difference is the change's. Flown on different
machines, two runs may differ by floating-point rounding alone; the count of identical trials
shows which case a comparison is. A trial that raised is never identical: it flew nothing.

Per depth source, over the common trials: each run's numbers as ``eval nav`` counts them
(:func:`companion.tools.eval.nav.count`: successes, collisions, mean speed, least clearance,
VINS error at the end), the trials that changed outcome, the trials flown identically, and for
the trials both runs brought to the goal the ratio after/before of their times to the goal
(``time_to_goal_s``, Offboard to goal): median, range and count. A ratio below 1 is a faster
flight after the change. And the VINS at the end of navigation, as issue 24 judges it
(:func:`_vins_at_the_end`): each run's worst error, the trials over :data:`FAR_M`, the paths
the VINS made long (``position_error_split.scale`` above 1) and the median ``|scale - 1|``;
and the trials that ended nearer and farther after the change, with the median change and
how sure it is (:func:`_paired_change`).

Flights are chaotic: one that changes at all lands anywhere within its spread, so a count of
nearer trials is judged against a coin: the exact two-sided sign test's p, the chance of a
split at least as uneven if the change did nothing. And every trial of a seed flies that seed's
vehicle and its draw of the sensors' noise (``SimOptions.vehicle_for``, ``noise_for``), so the
trials of one seed are one draw, not independent ones: the change is also counted per seed (the
median change of its trials), and an arm is judged over seeds (docs/vins.md, "The take-off's
window kept open").

Either run may be partial (an interrupted ``--runs`` file): only common trials are compared,
and the trials one run flew alone are counted, not compared. Runs with no trial in common, or
flown to different time limits (an outcome depends on the limit), are not compared.

An arm weighed over more seeds than one session flies is several pairs of runs, each pair
flown by one code revision on one host (a host redraws flights; docs/vins.md, "The height wave
flown level where it cannot swing"): each pair is matched on its own trials and the trials of
all pairs are pooled (``also`` of :func:`compare_runs`), a trial in two pairs refused.
"""

from __future__ import annotations

import collections
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.stats import binomtest

from companion.report import show
from companion.tools.eval import nav
from companion.tools.eval.vio import EvaluationError

#: The numbers two flights of one trial must share to count as the same flight.
SAME_FLIGHT_KEYS = ("outcome", "time_to_goal_s", "navigation_time_s", "flight_time_s",
                    "path_length_m", "min_clearance_m", "position_error_m")
#: The numbers of :func:`~companion.tools.eval.nav.count` a comparison gives for each run.
COMPARED_COUNTS = ("success", "collision", "mean_speed_mps", "least_clearance_m",
                   "vins_error_median_m")
#: A VINS error at the end of navigation beyond this is a miss of issue 24's worst, metres.
FAR_M = 1.0


def read_run(path: Path) -> list[dict]:
    """The records of one ``--runs`` file, complete or interrupted: EvaluationError naming
    the file when one trial is in it twice or it mixes code revisions, configs or library
    versions."""
    records = nav.read_records(Path(path))
    try:
        nav.refuse_repeated_trials(records)
        nav.check_provenance(records)
    except EvaluationError as error:
        raise EvaluationError(f"{path}: {error}") from None
    return records


def compare_runs(before: list[dict], after: list[dict],
                 also: Sequence[tuple[list[dict], list[dict]]] = ()) -> dict:
    """``{"timeout_s", "trials_only_before", "trials_only_after", "sources": {source:
    {...}}}``, the comparison of the module docstring; ``sources`` in the order of
    :data:`~companion.tools.eval.nav.DEPTH_SOURCES`, those with no common trial left out.
    ``also``: further (before, after) pairs of runs, each matched on its own trials, all
    pooled. EvaluationError when a pair has no trial in both runs, a trial is in two pairs,
    or the runs flew different time limits."""
    runs = [(before, after), *also]
    trials, only_before, only_after = {}, 0, 0
    for pair in runs:
        earlier, later = ({nav.trial_key(r): r for r in run} for run in pair)
        common = [key for key in earlier if key in later]
        if not common:
            raise EvaluationError("no trial is in both runs (other worlds, pairs or seeds?)")
        twice = next((key for key in common if key in trials), None)
        if twice is not None:
            raise EvaluationError(f"{nav.describe_trial(twice)} is in two of the pairs "
                                  "compared; pool pairs of other trials")
        trials.update((key, (earlier[key], later[key])) for key in common)
        only_before += len(earlier) - len(common)
        only_after += len(later) - len(common)
    timeout_s = nav.refuse_mixed_time_limits(
        [record for pair in runs for run in pair for record in run], "compare")
    by_source = collections.defaultdict(list)
    for key, pair in trials.items():
        by_source[key[2]].append(pair)
    return {"timeout_s": timeout_s, "trials_only_before": only_before,
            "trials_only_after": only_after,
            "sources": {source: _compare_source(by_source[source])
                        for source in nav.DEPTH_SOURCES if by_source[source]}}


def _compare_source(pairs: list[tuple[dict, dict]]) -> dict:
    counts = [nav.count([pair[k] for pair in pairs]) for k in (0, 1)]
    ratios = [a["time_to_goal_s"] / b["time_to_goal_s"] for b, a in pairs
              if b["outcome"] == a["outcome"] == "success"
              and _positive(b.get("time_to_goal_s")) and _positive(a.get("time_to_goal_s"))]
    return {
        "trials": len(pairs),
        **{key: [c[key] for c in counts] for key in COMPARED_COUNTS},
        "identical": sum(_same_flight(b, a) for b, a in pairs),
        "changed": [{"trial": nav.describe_trial(nav.trial_key(b)), "before": b["outcome"],
                     "after": a["outcome"]}
                    for b, a in pairs if b["outcome"] != a["outcome"]],
        "time_ratio": {"median": float(np.median(ratios)) if ratios else None,
                       "min": min(ratios, default=None), "max": max(ratios, default=None),
                       "trials": len(ratios)},
        "vins_at_end": _vins_at_the_end(pairs),
    }


def _vins_at_the_end(pairs: list[tuple[dict, dict]]) -> dict:
    """Per run (before, after): the worst VINS error at the end of navigation, the trials
    over :data:`FAR_M`, the trials whose path the VINS made long and the median |scale - 1|
    in percent (None where no trial has the number); and :func:`_paired_change` of the
    trials with an error in both runs."""
    runs = []
    for k in (0, 1):
        errors = nav.finite_values([pair[k] for pair in pairs], "position_error_m")
        scales = [scale for scale in (_scale(pair[k]) for pair in pairs) if scale is not None]
        runs.append({"worst_m": max(errors, default=None),
                     "over_far": sum(error > FAR_M for error in errors),
                     "long": sum(scale > 1.0 for scale in scales),
                     "scale_off_median_pct": (float(np.median(np.abs(np.subtract(scales, 1.0))))
                                              * 100.0 if scales else None)})
    both = [pair for pair in pairs if all(nav.finite(record.get("position_error_m"))
                                          for record in pair)]
    return {**{key: [run[key] for run in runs] for key in runs[0]}, **_paired_change(both)}


def _paired_change(pairs: list[tuple[dict, dict]]) -> dict:
    """Of trials with a VINS error at the end in both runs: how many ended nearer and farther
    after; the exact two-sided sign test's p of that split (ties left out; None without a
    change); the median of the changes (after - before, metres; None without trials); and
    the seeds whose trials' median change is below and above zero."""
    changes = [a["position_error_m"] - b["position_error_m"] for b, a in pairs]
    nearer, farther = sum(c < 0 for c in changes), sum(c > 0 for c in changes)
    by_seed = collections.defaultdict(list)
    for (before, _), change in zip(pairs, changes):
        by_seed[before["seed"]].append(change)
    seed_medians = [float(np.median(c)) for c in by_seed.values()]
    return {"nearer": nearer, "farther": farther,
            "sign_test_p": (binomtest(nearer, nearer + farther).pvalue
                            if nearer + farther else None),
            "change_median_m": float(np.median(changes)) if changes else None,
            "seeds_nearer": sum(m < 0 for m in seed_medians),
            "seeds_farther": sum(m > 0 for m in seed_medians)}


def _scale(record: dict) -> float | None:
    """The VINS's path over the truth's at the end of navigation, None when not kept."""
    scale = (record.get("position_error_split") or {}).get("scale")
    return scale if nav.finite(scale) else None


def _positive(seconds) -> bool:
    return nav.finite(seconds) and seconds > 0


def _same_flight(before: dict, after: dict) -> bool:
    return before["outcome"] != "error" and all(before.get(key) == after.get(key)
                                                for key in SAME_FLIGHT_KEYS)


def format_markdown(comparison: dict, runs: Sequence[tuple[str, str]]) -> str:
    """A heading naming the pairs of runs (before, after), one row per depth source, and the
    changed outcomes."""
    lines = [
        f"## Navigation runs compared: {'; '.join(f'{b} → {a}' for b, a in runs)}",
        "",
        f"On the trials both runs flew (world, pair, depth source, seed; "
        f"{comparison['timeout_s']:g} s to reach the goal); "
        f"{comparison['trials_only_before']} flown only before and "
        f"{comparison['trials_only_after']} only after are left out. Each cell: before → "
        "after. Identical: the same outcome, times, path length, least clearance and VINS "
        "error. Speed: path over navigation time, the successes. Time-to-goal ratio: after "
        "over before, on the trials both runs brought to the goal (below 1: faster).",
        "",
        "| depth | trials | identical | success | collision | mean speed m/s | "
        "least clearance m | VINS error at end m (median) | time-to-goal ratio median | "
        "range | over |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    changes, vins_rows = [], []
    for source, numbers in comparison["sources"].items():
        ratio = numbers["time_ratio"]
        cells = [nav.SOURCE_NAMES[source], numbers["trials"], numbers["identical"],
                 _arrow(numbers["success"], "d"), _arrow(numbers["collision"], "d"),
                 _arrow(numbers["mean_speed_mps"], ".2f"),
                 _arrow(numbers["least_clearance_m"], ".2f"),
                 _arrow(numbers["vins_error_median_m"], ".2f"), show(ratio["median"], ".2f"),
                 f"{show(ratio['min'], '.2f')}–{show(ratio['max'], '.2f')}", ratio["trials"]]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
        vins_rows.append(_vins_row(nav.SOURCE_NAMES[source], numbers))
        changes += [f"- {c['trial']}: {c['before']} → {c['after']}" for c in numbers["changed"]]
    lines += [
        "",
        f"The VINS at the end of navigation: worst error; trials over {FAR_M:g} m; nearer and "
        "farther after, of the trials with an error in both runs, with the sign test's p "
        "(two-sided: the chance of a split at least as uneven if the change did nothing) and "
        "the median change (after − before); the seeds nearer and farther (a seed's trials "
        "share its vehicle and noise: the median change of each); paths the VINS made long "
        "(scale above 1); the median of |scale − 1|.",
        "",
        f"| depth | median m | worst m | over {FAR_M:g} m | nearer | farther | sign test p | "
        "median change m | seeds nearer | seeds farther | long | "
        "median \\|scale − 1\\| % |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        *vins_rows,
    ]
    if changes:
        lines += ["", "Changed outcomes:", "", *changes]
    return "\n".join(lines)


def _vins_row(name: str, numbers: dict) -> str:
    end = numbers["vins_at_end"]
    cells = [name, _arrow(numbers["vins_error_median_m"], ".2f"), _arrow(end["worst_m"], ".2f"),
             _arrow(end["over_far"], "d"), end["nearer"], end["farther"],
             show(end["sign_test_p"], ".2g"), show(end["change_median_m"], "+.2f"),
             end["seeds_nearer"], end["seeds_farther"], _arrow(end["long"], "d"),
             _arrow(end["scale_off_median_pct"], ".2f")]
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _arrow(values: list, spec: str) -> str:
    return " → ".join(show(value, spec) for value in values)
