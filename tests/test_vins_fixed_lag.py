"""The fixed-lag smoother (:mod:`autonomy.vins.fixed_lag`): GTSAM's fixed-lag smoother's
estimates and marginalisation, with the variable eliminated last chosen so that GTSAM's
Cholesky does not refuse a window whose gauge has faded. That it does not in flight is
tested on the recorded 40 s flights (tests/test_vins_depth_acceptance.py: the mine's window
was rebuilt 36.9 s in with GTSAM's smoother)."""

import math

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, L, X

from autonomy.vins.fixed_lag import FixedLagSmoother
from tests.bayes_tree import root_frontals

LAG = 1.0
STEP = 0.1


def isam2_params() -> gtsam.ISAM2Params:
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(0.05)
    params.relinearizeSkip = 1
    return params


def fly_a_pose_chain(smoother, steps: int, odometry_sigma: float = 0.01, seed: int = 0):
    """A chain of poses, one every STEP seconds, tied by noisy odometry (sigma in metres and
    radians), beside a chain of bias-like variables tied by a random walk; only the first of
    each has a prior. Yields the index after each update."""
    rng = np.random.default_rng(seed)
    sigma = gtsam.noiseModel.Isotropic.Sigma
    step = gtsam.Pose3(gtsam.Rot3.Yaw(0.05), np.array([0.5, 0.0, 0.0]))
    odometry, walk = sigma(6, odometry_sigma), sigma(3, 1e-3)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(X(0), gtsam.Pose3(), sigma(6, 1e-3)))
    graph.add(gtsam.PriorFactorPoint3(B(0), np.zeros(3), sigma(3, 1e-2)))
    values.insert(X(0), gtsam.Pose3())
    values.insert(B(0), np.zeros(3))
    update(smoother, graph, values, {X(0): 0.0, B(0): 0.0}, [X(0), B(0)])
    truth = gtsam.Pose3()
    for k in range(1, steps + 1):
        truth = truth.compose(step)
        measured = step.compose(gtsam.Pose3.Expmap(rng.normal(0.0, odometry_sigma, 6)))
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), measured, odometry))
        graph.add(gtsam.BetweenFactorPoint3(B(k - 1), B(k), np.zeros(3), walk))
        values.insert(X(k), truth.compose(gtsam.Pose3.Expmap(rng.normal(0.0, 1e-3, 6))))
        values.insert(B(k), np.zeros(3))
        update(smoother, graph, values, {X(k): k * STEP, B(k): k * STEP}, [X(k), B(k)])
        yield k


def update(smoother, graph, values, stamps, last):
    if isinstance(smoother, FixedLagSmoother):
        smoother.update(graph, values, stamps, eliminate_last=last)
    else:
        smoother.update(graph, values, stamps)


def test_it_estimates_and_marginalises_as_gtsams_fixed_lag_smoother():
    """The ordering changes how the window is factored, not what it solves: on a chain both
    smoothers can factor, every estimate agrees with GTSAM's own smoother, and what is older
    than the lag is gone from both."""
    ours = FixedLagSmoother(LAG, isam2_params())
    gtsams = gtsam.IncrementalFixedLagSmoother(LAG, isam2_params())
    for k, _ in zip(fly_a_pose_chain(ours, 40), fly_a_pose_chain(gtsams, 40)):
        a, b = ours.calculateEstimate(), gtsams.calculateEstimate()
        assert sorted(a.keys()) == sorted(b.keys())
        for key in a.keys():
            if gtsam.Symbol(key).chr() == ord("x"):
                assert a.atPose3(key).equals(b.atPose3(key), 1e-9), gtsam.Symbol(key).string()
        window = round(LAG / STEP)
        assert a.exists(X(max(k - window + 1, 0)))
        assert k <= window or not a.exists(X(k - window - 1))
    covariance = np.asarray(ours.marginalCovariance(X(40)))
    np.testing.assert_allclose(covariance, gtsams.marginalCovariance(X(40)), rtol=1e-6)


def test_a_window_kept_open_keeps_its_variables_until_let_go():
    """Kept from 0.5 s, a variable's own stamp: however long the chain grows, nothing stamped
    then or since leaves the window, and what came before leaves as the lag says; let go, the
    next update leaves the lag's window alone."""
    smoother = FixedLagSmoother(LAG, isam2_params())
    chain = fly_a_pose_chain(smoother, 40)
    for k in chain:
        if k == 10:
            smoother.kept_from = 5 * STEP  # X(5)'s stamp
        if k == 30:
            break
    estimate = smoother.calculateEstimate()
    assert not estimate.exists(X(4)) and not estimate.exists(B(4))
    assert all(estimate.exists(X(k)) and estimate.exists(B(k)) for k in range(5, 31))
    smoother.kept_from = None
    assert next(chain) == 31
    estimate = smoother.calculateEstimate()
    window = round(LAG / STEP)
    assert not estimate.exists(X(31 - window - 1))
    assert all(estimate.exists(X(k)) for k in range(31 - window + 1, 32))


def test_the_variable_to_eliminate_last_must_be_in_the_window():
    smoother = FixedLagSmoother(LAG, isam2_params())
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPoint3(B(0), np.zeros(3), gtsam.noiseModel.Unit.Create(3)))
    values.insert(B(0), np.zeros(3))
    with pytest.raises(ValueError, match="b7"):
        smoother.update(graph, values, {B(0): 0.0}, eliminate_last=[B(0), B(7)])


def test_a_first_update_without_timestamps_is_refused():
    with pytest.raises(ValueError, match="stamp"):
        FixedLagSmoother(LAG, isam2_params()).update()


def test_the_lag_must_be_positive():
    with pytest.raises(ValueError, match="lag"):
        FixedLagSmoother(0.0, isam2_params())


def test_gtsams_cholesky_refuses_or_factors_the_same_window_by_what_it_eliminates_last():
    """The library behaviour behind the smoother's rebuilds (docs/vins.md, the rebuilds):
    a variable held by information 1 (the gauge), linked by information 1e8 to another, and a
    gauge-free variable held by 1e8 beside them. Well posed, and QR factors it in any order;
    GTSAM's Cholesky refuses it when a gauge-held variable is eliminated last and factors it
    when the gauge-free one is. At 1e7 it factors it either way. If a GTSAM upgrade moves
    this, the test says so."""
    def graph(link: float) -> gtsam.GaussianFactorGraph:
        unit = gtsam.noiseModel.Unit.Create(1)
        graph = gtsam.GaussianFactorGraph()
        graph.add(X(1), np.eye(1), np.zeros(1), unit)
        graph.add(X(1), np.eye(1) * math.sqrt(link), X(2), -np.eye(1) * math.sqrt(link),
                  np.zeros(1), unit)
        graph.add(B(0), np.eye(1) * math.sqrt(link), np.zeros(1), unit)
        graph.add(X(2), np.eye(1), B(0), -np.eye(1), np.zeros(1), unit)
        return graph

    def factors(link: float, order: list, qr: bool = False) -> bool:
        try:
            if qr:
                graph(link).eliminateMultifrontal(gtsam.Ordering(order), gtsam.EliminateQR)
            else:  # GTSAM's default elimination: Cholesky
                graph(link).eliminateMultifrontal(gtsam.Ordering(order))
            return True
        except RuntimeError:
            return False

    gauge_last, gauge_free_last = [X(1), B(0), X(2)], [X(1), X(2), B(0)]
    assert not factors(1e8, gauge_last)
    assert factors(1e8, gauge_free_last)
    assert factors(1e8, gauge_last, qr=True)
    assert factors(1e7, gauge_last) and factors(1e7, gauge_free_last)


def chain_with_a_held_pose(hold: str, held: int = 5, steps: int = 30):
    """The pose chain of :func:`fly_a_pose_chain` with a tight prior added on pose ``held`` (a
    rigid 5 cm off its estimate) when it enters: ``hold`` is "never" (not added), "removed" (in
    the update that marginalises the pose) or "kept". Returns the smoother after ``steps``."""
    smoother, slot = FixedLagSmoother(LAG, isam2_params()), None
    chain = fly_a_pose_chain(smoother, steps)
    for k in chain:
        if k == held and hold != "never":
            moved = smoother.calculateEstimate().atPose3(X(held)).compose(
                gtsam.Pose3(gtsam.Rot3(), np.array([0.05, 0.0, 0.0])))
            graph = gtsam.NonlinearFactorGraph()
            graph.add(gtsam.PriorFactorPose3(X(held), moved, gtsam.noiseModel.Isotropic.Sigma(
                6, 1e-4)))
            slot = smoother.update(graph)[0]
        leaving = (k + 1) * STEP - LAG > held * STEP
        if hold == "removed" and slot is not None and leaving:
            smoother.update(remove=[slot])
            slot = None
    return smoother


def test_a_factor_removed_before_its_variable_is_marginalised_leaves_no_trace():
    """The gauge hold's prior (autonomy/vins/backend.py) never enters a marginal: removed
    before its pose leaves the window, the window later solves as if it had never been (but
    for the linearisation point the pull left, 1 mm of its 5 cm); kept, it is marginalised
    into the window and holds it 5 cm off, and tighter, for good."""
    never, removed, kept = (chain_with_a_held_pose(hold) for hold in ("never", "removed", "kept"))
    last = X(30)

    def offset(smoother) -> float:
        return float(np.linalg.norm(never.calculateEstimate().atPose3(last).between(
            smoother.calculateEstimate().atPose3(last)).translation()))

    assert offset(removed) < 0.002 and offset(kept) > 0.045
    np.testing.assert_allclose(removed.marginalCovariance(last), never.marginalCovariance(last),
                               rtol=0.01, atol=1e-6)
    assert np.all(np.diag(kept.marginalCovariance(last)) < 0.9 * np.diag(
        never.marginalCovariance(last)))


def is_point(key: int) -> bool:
    return gtsam.Symbol(key).chr() == ord("l")


def map_a_corridor(smoother: FixedLagSmoother, steps: int = 30, per_step: int = 3,
                   seen_for: int = 4) -> FixedLagSmoother:
    """A chain of positions ``X(k)`` one every STEP seconds, and ``per_step`` points made at
    each, each seen from it and the ``seen_for - 1`` positions after: bundle adjustment's
    shape in three dimensions, the newest position eliminated last. Returns the smoother."""
    rng = np.random.default_rng(1)
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    for k in range(steps):
        graph, values, stamps = gtsam.NonlinearFactorGraph(), gtsam.Values(), {X(k): k * STEP}
        values.insert(X(k), np.array([k, 0.0, 0.0]))
        if k == 0:
            graph.add(gtsam.PriorFactorPoint3(X(0), np.zeros(3), noise))
        else:
            graph.add(gtsam.BetweenFactorPoint3(X(k - 1), X(k), np.array([1.0, 0.0, 0.0])
                                                + rng.normal(0.0, 0.1, 3), noise))
        for j in range(per_step * max(0, k - seen_for + 1), per_step * (k + 1)):
            made_at, point = divmod(j, per_step)
            where = np.array([made_at + 0.5, point, 3.0])
            if made_at == k:
                values.insert(L(j), where)
            graph.add(gtsam.BetweenFactorPoint3(X(k), L(j), where - (k, 0.0, 0.0)
                                                + rng.normal(0.0, 0.1, 3), noise))
            stamps[L(j)] = k * STEP
        smoother.update(graph, values, stamps, eliminate_last=[X(k)])
    return smoother


def test_points_eliminated_early_leave_the_root_to_the_chain_and_the_answer_unchanged():
    """Eliminated where GTSAM's constrained COLAMD puts them, points end in the Bayes tree's
    root, which every marginal starts from (on a flight, 89 of its variables, and a marginal
    took twice the update); eliminated early, the root holds positions alone. The estimate
    and the newest position's marginal are the same either way."""
    as_colamd = map_a_corridor(FixedLagSmoother(LAG, isam2_params()))
    early = map_a_corridor(FixedLagSmoother(LAG, isam2_params(), eliminated_early=is_point))
    assert any(name.startswith("l") for name in root_frontals(as_colamd))
    assert all(name.startswith("x") for name in root_frontals(early))
    newest = X(29)
    np.testing.assert_allclose(early.calculateEstimate().atPoint3(newest),
                               as_colamd.calculateEstimate().atPoint3(newest), atol=1e-9)
    np.testing.assert_allclose(early.marginalCovariance(newest),
                               as_colamd.marginalCovariance(newest), rtol=1e-9, atol=1e-12)
