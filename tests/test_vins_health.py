"""The VINS health monitor: the state the application acts on, each with the reason a pilot
reads, and VINS options that contradict each other refused where they are made."""

from dataclasses import replace

import pytest

from autonomy.options import OptionError
from autonomy.vins.health import HealthInputs, HealthState, assess
from autonomy.vins.options import VinsOptions

OPTIONS = VinsOptions()
GOOD = HealthInputs(tracked=120, landmarks=60, parallax_px=4.0, speed=1.0, gyro_bias=0.01,
                    accel_bias=0.05, resets=0, update_ms=12.0, moved=True, starved_s=0.0,
                    since_reset_s=30.0)


def test_defaults_are_the_documented_limits():
    o = OPTIONS
    assert (o.min_tracked_ok, o.min_tracked_lost, o.min_landmarks_ok) == (40, 10, 15)
    assert (o.lost_after_s, o.degraded_after_reset_s, o.max_update_ms) == (0.5, 1.0, 50.0)


def test_everything_in_bounds_is_ok_and_carries_the_figures():
    health = assess(GOOD, OPTIONS)
    assert health.state is HealthState.OK and health.reason == ""
    assert (health.tracked, health.landmarks, health.parallax_px, health.speed) == (
        120, 60, 4.0, 1.0)
    assert (health.gyro_bias, health.accel_bias, health.resets, health.update_ms) == (
        0.01, 0.05, 0, 12.0)


def test_starved_for_lost_after_s_is_lost_saying_so():
    health = assess(replace(GOOD, tracked=3, starved_s=0.5), OPTIONS)
    assert health.state is HealthState.LOST
    assert "only 3 features tracked for 0.50 s" in health.reason


def test_starved_briefly_is_only_degraded():
    health = assess(replace(GOOD, tracked=3, starved_s=0.45), OPTIONS)
    assert health.state is HealthState.DEGRADED
    assert "3 features tracked (< 40)" in health.reason


def test_lost_wins_over_every_other_problem():
    worst = replace(GOOD, tracked=0, landmarks=0, since_reset_s=0.0, update_ms=500.0,
                    starved_s=2.0)
    assert assess(worst, OPTIONS).state is HealthState.LOST


@pytest.mark.parametrize("change, says", [
    ({"tracked": 39}, "39 features tracked (< 40)"),
    ({"landmarks": 14}, "14 landmarks (< 15)"),
    ({"since_reset_s": 0.25}, "reset 0.25 s ago"),
    ({"update_ms": 80.0}, "update took 80 ms (> 50)"),
])
def test_each_weakness_is_degraded_and_named(change, says):
    health = assess(replace(GOOD, **change), OPTIONS)
    assert health.state is HealthState.DEGRADED
    assert health.reason == says


@pytest.mark.parametrize("change", [
    {"tracked": 40}, {"landmarks": 15}, {"since_reset_s": 1.0}, {"update_ms": 50.0},
    {"update_ms": None},
])
def test_each_limit_itself_is_still_ok(change):
    assert assess(replace(GOOD, **change), OPTIONS).state is HealthState.OK


def test_several_weaknesses_are_all_named():
    health = assess(replace(GOOD, tracked=20, update_ms=90.0), OPTIONS)
    assert health.state is HealthState.DEGRADED
    assert "20 features tracked" in health.reason and "update took 90 ms" in health.reason


def test_standing_still_without_landmarks_is_not_degraded():
    """Before the vehicle moves nothing can be triangulated; that is not a weakness."""
    health = assess(replace(GOOD, moved=False, landmarks=0, speed=0.0), OPTIONS)
    assert health.state is HealthState.OK


def test_the_limits_come_from_the_options():
    strict = VinsOptions(min_tracked_ok=150, min_tracked_lost=10)
    assert assess(GOOD, strict).state is HealthState.DEGRADED
    assert assess(replace(GOOD, tracked=3, starved_s=0.3),
                  VinsOptions(lost_after_s=0.25)).state is HealthState.LOST


# ------------------------------------------------------------------ options


@pytest.mark.parametrize("values, key", [
    ({"min_depth": 5.0, "max_depth": 5.0}, "max_depth"),
    ({"min_depth": 10.0, "max_depth": 2.0}, "max_depth"),
    ({"keyframe_min_interval_s": 0.2, "keyframe_interval_s": 0.1}, "keyframe_min_interval_s"),
    ({"min_tracked_lost": 50, "min_tracked_ok": 40}, "min_tracked_lost"),
])
def test_contradicting_options_are_refused_naming_the_key(values, key):
    with pytest.raises(OptionError) as error:
        VinsOptions(**values)
    assert error.value.key == key
    assert str(error.value).startswith(f"{key}: ")


@pytest.mark.parametrize("values", [
    {"keyframe_min_interval_s": 0.1, "keyframe_interval_s": 0.1},
    {"min_tracked_lost": 40, "min_tracked_ok": 40},
    {"min_depth": 0.5, "max_depth": 0.6},
])
def test_equal_limits_where_allowed_are_accepted(values):
    VinsOptions(**values)


@pytest.mark.parametrize("values, key", [
    ({"smoother_lag_s": 0.0}, "smoother_lag_s"),
    ({"min_observations": 1}, "min_observations"),
    ({"lost_after_s": -1.0}, "lost_after_s"),
    ({"mounting_rotation_sigma_deg": 0.0}, "mounting_rotation_sigma_deg"),
    ({"mounting_rotation_sigma_deg": 20.0}, "mounting_rotation_sigma_deg"),
    ({"imu_bias_walk_scale": 0.0}, "imu_bias_walk_scale"),
    ({"imu_bias_walk_scale": 200.0}, "imu_bias_walk_scale"),
])
def test_out_of_range_options_are_refused_naming_the_key(values, key):
    with pytest.raises(OptionError, match=f"^{key}: "):
        VinsOptions(**values)
