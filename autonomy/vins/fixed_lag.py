"""A fixed-lag smoother on GTSAM's iSAM2 that eliminates chosen variables last, and kinds of
variable early.

It does what GTSAM's ``IncrementalFixedLagSmoother`` does
(``gtsam_unstable/nonlinear/IncrementalFixedLagSmoother.cpp``): each variable carries a
timestamp; at every update the variables older than ``lag`` before the newest timestamp are
eliminated first (ordering constraint group 0, so they are leaves of the Bayes tree) and then
marginalised out, leaving a linear marginal factor on their neighbours.

What it adds is the end of the elimination ordering (the last group, of its own): the caller
names the variables eliminated last: the newest keyframe's pose, velocity and IMU bias, and, in
the VINS, the camera mounting every landmark shares and the gauge hold's pose, the other key of
the marginal it asks for (:mod:`autonomy.vins.backend`). The reason is GTSAM's Cholesky
(``gtsam/base/cholesky.cpp``, ``choleskyPartial``): after factoring
a clique's frontal block ``A = RᵀR`` it calls the system indeterminate when the last two
diagonal entries of ``R`` differ by 12 binary exponents or more (about 4096x, information
1.7e7x), a test meant to catch rank deficiency. In a visual-inertial window the absolute
position and yaw (the gauge, fixed only by the first keyframe's prior) are held ever more
weakly as the flight goes on, while the IMU and the landmarks tie the keyframes to each other
strongly. After 35-40 m a clique that ends on a variable held only through the gauge, after
one tied to it, fails the test, though the window is well posed and QR factors it
(docs/vins.md, "The rebuilds"). The likely reason the newest keyframe's variables cure it:
every variable of the window is tied to them, so, eliminated last, they join the separators
of the cliques below, where each pose and velocity is then held relative to the newest pose,
as strongly as its links; and the root ends on two alike pivots (two axes of one position,
velocity or bias). Measured, not proven: no refusal on any of the 35 recordings tried, where
the bias alone last, the first version, still met two in mid-window; none either on the 30 of
the presets' seeds table with the VINS's gauge hold's pose last too. The solution is the same
for any ordering.

The caller may also name kinds of variable eliminated early (a group of their own: after those
marginalised, before the rest of the window): the landmarks, in a visual-inertial window. Left
to GTSAM's constrained COLAMD among the keyframes, they ended in the Bayes tree's root (89 of its
variables in the median on a mine flight), which every marginal starts from: the newest
keyframe's marginal took about 10 ms, more than the update. Eliminated first, each landmark is a
leaf whose separator is the keyframes that saw it (bundle adjustment's Schur complement), the
root holds keyframes alone (6 variables in the median, counted before the hold's pose was last
too), and the same marginal took 1.1 ms, and takes 0.3 ms now that every key it asks for is
eliminated last; a keyframe takes up to about 1 ms more in the median (docs/vins.md,
"Landmarks eliminated first").

The window can be kept open (:attr:`FixedLagSmoother.kept_from`): every variable stamped at or
after a time stays however old it grows, until the caller lets it go; the next update then
marginalises all that the lag leaves behind. What it is for: a keyframe filed at a wrong camera
time offset can be moved while it is in the window, not once it is in the marginal
(:meth:`autonomy.vins.estimator.Vins._keep_window_open`).

Every update re-eliminates the whole window (``extraReelimKeys``) so that the constraint
groups order all of it; a new keyframe sees most of the window's landmarks, so iSAM2 would
re-eliminate nearly all of it anyway (docs/benchmarks.md, "VINS back-end").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Iterable, Mapping

import gtsam

#: The elimination ordering's constraint groups: marginalised, eliminated early, the rest,
#: eliminated last.
_MARGINALISED, _EARLY, _WINDOW, _LAST = 0, 1, 2, 3

#: Told of every update after it is solved, before the marginalisation: the factors added, the
#: (re)stamps of their variables, the slots removed, the slots the new factors took, and the
#: window's estimate. An evaluation's log of the factors
#: (``companion/tools/eval/vio_bound.py``); nothing listens in flight.
UpdateListener = Callable[[gtsam.NonlinearFactorGraph, Mapping[int, float], Collection[int],
                           list[int], gtsam.Values], None]


def _none(key: int) -> bool:
    """No variable is eliminated early."""
    return False


class FixedLagSmoother:
    """iSAM2 over the variables of the last ``lag`` seconds (module docstring)."""

    def __init__(self, lag: float, params: gtsam.ISAM2Params,
                 listener: UpdateListener | None = None,
                 eliminated_early: Callable[[int], bool] = _none):
        """``eliminated_early``: whether a variable (its key) is of a kind eliminated right
        after those marginalised (module docstring); asked at every update."""
        if not lag > 0.0:
            raise ValueError(f"the smoother's lag must be positive, got {lag}")
        self.lag = float(lag)
        self.listener = listener
        self._isam = gtsam.ISAM2(params)
        self._stamps: dict[int, float] = {}
        self._last: frozenset[int] = frozenset()
        self._eliminated_early = eliminated_early
        #: variables stamped at or after this time are not marginalised (None: the lag alone)
        self.kept_from: float | None = None

    def cutoff(self, newest: float) -> float:
        """The update at ``newest`` marginalises the variables stamped before this time: the
        lag's, or :attr:`kept_from` when that is earlier."""
        cutoff = newest - self.lag
        return cutoff if self.kept_from is None else min(cutoff, self.kept_from)

    def update(self, graph: gtsam.NonlinearFactorGraph | None = None,
               values: gtsam.Values | None = None, stamps: Mapping[int, float] | None = None,
               eliminate_last: Collection[int] | None = None,
               remove: Collection[int] = (), slide: bool = True) -> list[int]:
        """Add ``graph`` with the new variables ``values``, (re)stamp the variables in
        ``stamps`` (seconds), remove the factors at the iSAM2 slots ``remove``, solve, and
        marginalise every variable older than the lag (or :attr:`kept_from`).
        ``eliminate_last`` are the keys eliminated last from now on (they must be in the
        window); without them, those named before, until they are marginalised. Returns the
        slots of ``graph``'s factors, in order. A factor removed in the update that
        marginalises its variables never enters their marginal. ``slide=False``: this update
        marginalises nothing (one that moves the window's stamps, not one that adds to it)."""
        graph = gtsam.NonlinearFactorGraph() if graph is None else graph
        values = gtsam.Values() if values is None else values
        stamps = dict(stamps or {})
        last = self._last if eliminate_last is None else frozenset(eliminate_last)
        unknown = [key for key in last if key not in stamps and key not in self._stamps]
        if unknown:
            raise ValueError("keys to eliminate last have no timestamp in the window: "
                             + ", ".join(gtsam.Symbol(key).string() for key in unknown))
        if not stamps and not self._stamps:
            raise ValueError("the smoother holds no variable yet: the first update must stamp "
                             "its new variables")
        self._stamps.update(stamps)
        self._last = last
        cutoff = self.cutoff(max(self._stamps.values())) if slide else -math.inf
        old = [key for key, t in self._stamps.items() if t < cutoff]
        params = gtsam.ISAM2UpdateParams()
        params.constrainedKeys = self._groups(old)
        # one set of the few new keys, not a GTSAM look-up per key of the window
        new = set(values.keys())
        params.extraReelimKeys = _key_list(key for key in self._stamps if key not in new)
        if remove:
            params.removeFactorIndices = list(remove)
        slots = list(self._isam.update(graph, values, params).getNewFactorsIndices())
        if self.listener is not None:
            self.listener(graph, stamps, remove, slots, self._isam.calculateEstimate())
        if old:
            self._isam.marginalizeLeaves(_key_list(old))
            for key in old:
                del self._stamps[key]
            self._last = self._last.difference(old)
        return slots

    def _groups(self, old: list[int]) -> gtsam.KeyGroupMap:
        """The ordering constraint: ``old`` first, then those eliminated early, then the window,
        then the last keys. Group numbers are renumbered 0, 1, ... over the groups in use:
        GTSAM's constrained COLAMD refused groups 1 and 2, or 0 and 2, on two variables
        ("variables that are not involved in the factor graph")."""
        early = self._eliminated_early
        wanted = {key: _EARLY if early(key) else _WINDOW for key in self._stamps}
        wanted.update(dict.fromkeys(self._last, _LAST))
        wanted.update(dict.fromkeys(old, _MARGINALISED))
        renumber = {group: rank for rank, group in enumerate(sorted(set(wanted.values())))}
        groups = gtsam.KeyGroupMap()
        for key, group in wanted.items():
            groups.insert2(key, renumber[group])
        return groups

    def params(self) -> gtsam.ISAM2Params:
        return self._isam.params()

    def calculateEstimate(self) -> gtsam.Values:  # noqa: N802 (GTSAM's smoother interface)
        return self._isam.calculateEstimate()

    def marginalCovariance(self, key: int):  # noqa: N802 (GTSAM's smoother interface)
        return self._isam.marginalCovariance(key)

    def jointMarginalCovariance(self, keys: list[int]) -> gtsam.JointMarginal:  # noqa: N802
        return self._isam.jointMarginalCovariance(keys)


def _key_list(keys: Iterable[int]) -> gtsam.KeyList:
    key_list = gtsam.KeyList()
    for key in keys:
        key_list.push_back(key)
    return key_list
