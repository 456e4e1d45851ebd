"""What the VINS's own factors allow: a batch over every factor its smoother was given.

The fixed-lag smoother (``autonomy/vins/fixed_lag.py``) keeps 1.5 s of keyframes and folds
what leaves the window into a linear marginal, linearised once, at the estimate of that
moment. :class:`FactorLog` keeps every factor the smoother was given (the same IMU
preintegrations, reprojections, priors, noise models and gates), and :func:`batch_positions`
solves them again by Levenberg-Marquardt with nothing marginalised:

- the *causal batch*: at a keyframe, the estimate from every factor up to that keyframe,
  the best the factors allow an estimator that flies on them (what a smoother with an
  unbounded window and exact relinearisation would report then);
- the *whole-flight batch*: every factor of the flight at once, later ones correcting earlier
  keyframes, the best any smoother of these factors can do after the flight.

Where the causal batch beats the fixed-lag smoother, the window or its marginalisation loses
information; where the whole-flight batch misses too, the factors themselves (the tracks,
the IMU's model) carry the error, and no smoother fixes it (docs/vins.md, "What the factors
allow").

The gauge hold's priors (``backend.py``) are left out: several position priors held at
their estimates would pin distances, so the scale. The batches keep the start's prior alone.
A run whose smoother was rebuilt is not bounded: the rebuild's priors pin the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from autonomy.trajectory import align_umeyama, ate_rmse, path_length
from companion.report import finite_or_none

#: The causal batch is solved at every this many keyframes (and the last): a solve grows with
#: the flight to about a second for 40 s, so at every keyframe it would take minutes.
BOUND_EVERY = 5
#: The Levenberg-Marquardt iterations of each batch; each starts from the last one's solution
#: or the smoother's estimate, a few iterations from its optimum.
BATCH_ITERATIONS = 30


def _is_pose(key: int) -> bool:
    return chr(gtsam.Symbol(key).chr()) == "x"


class FactorLog:
    """Every factor a smoother was given (an ``UpdateListener``: ``record``), each variable's
    first stamp, and each variable's latest estimate while it was in the window."""

    def __init__(self) -> None:
        self.factors: list[gtsam.NonlinearFactor] = []
        self.removed: set[int] = set()  # indices into factors
        self.stamps: dict[int, float] = {}
        self.estimates = gtsam.Values()
        self._at_slot: dict[int, int] = {}

    def record(self, graph, stamps, removed, slots, estimate) -> None:
        """Keep one update's factors, stamps and the ``estimate`` after it."""
        for slot in removed:
            self.removed.add(self._at_slot[slot])
        for position, slot in enumerate(slots):
            self._at_slot[slot] = len(self.factors)
            self.factors.append(graph.at(position))
        for key, t in stamps.items():
            self.stamps.setdefault(key, float(t))
        self.estimates.insert_or_assign(estimate)

    def drop_slot(self, slot: int | None) -> None:
        """Leave out the factor now at ``slot`` (the gauge hold's last prior, never removed)."""
        if slot is not None:
            self.removed.add(self._at_slot[slot])

    def kept(self) -> list[tuple[float, gtsam.NonlinearFactor]]:
        """The factors not removed, each with the time it could first be used (its newest
        variable's first stamp), in that order."""
        timed = [(max(self.stamps[key] for key in factor.keys()), index, factor)
                 for index, factor in enumerate(self.factors) if index not in self.removed]
        return [(t, factor) for t, _, factor in sorted(timed, key=lambda item: item[:2])]


@dataclass(frozen=True)
class BoundedKeyframes:
    """The positions of the sampled keyframes at times ``t`` by each estimator."""

    t: np.ndarray
    fixed_lag: np.ndarray
    causal_batch: np.ndarray
    whole_flight_batch: np.ndarray


def batch_positions(log: FactorLog, fixed_lag: dict[float, np.ndarray],
                    every: int) -> BoundedKeyframes:
    """Solve the causal batch at every ``every``-th keyframe of ``fixed_lag`` (the smoother's
    newest keyframe position by keyframe time; and at the last), then the whole flight's.
    Each solve starts from the one before, and a variable it has not solved yet from the
    smoother's estimate (a variable no factor of the batch touches is carried along
    unchanged)."""
    poses = sorted((t, key) for key, t in log.stamps.items()
                   if _is_pose(key) and t in fixed_lag)
    chosen = poses[::every] + ([poses[-1]] if (len(poses) - 1) % every else [])
    factors = log.kept()
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(BATCH_ITERATIONS)
    graph, current, used = gtsam.NonlinearFactorGraph(), gtsam.Values(log.estimates), 0
    causal = []
    for t, key in chosen:
        while used < len(factors) and factors[used][0] <= t:
            graph.add(factors[used][1])
            used += 1
        current = gtsam.LevenbergMarquardtOptimizer(graph, current, params).optimize()
        causal.append(current.atPose3(key).translation())
    for _, factor in factors[used:]:
        graph.add(factor)
    whole = gtsam.LevenbergMarquardtOptimizer(graph, current, params).optimize()
    return BoundedKeyframes(np.array([t for t, _ in chosen]),
                            np.array([fixed_lag[t] for t, _ in chosen]), np.array(causal),
                            np.array([whole.atPose3(key).translation() for _, key in chosen]))


def bound_report(keyframes: BoundedKeyframes, true_positions: np.ndarray) -> dict:
    """Each estimator's ATE over the true distance (SE(3) alignment) and scale (its size
    over the truth's, Sim(3)), on the same keyframes, as ``eval vio`` scores the frames."""
    distance = path_length(true_positions)
    report = {"keyframes": len(keyframes.t), "distance_m": distance}
    for name in ("fixed_lag", "causal_batch", "whole_flight_batch"):
        estimated = getattr(keyframes, name)
        scale = align_umeyama(estimated, true_positions, with_scale=True).s
        report[name] = {
            "ate_over_distance": finite_or_none(ate_rmse(estimated, true_positions) / distance),
            "scale": finite_or_none(1.0 / scale) if scale > 0.0 else None}
    return report
