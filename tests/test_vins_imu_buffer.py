"""The VINS IMU buffer: bad samples are refused with a reason, the zero-order-hold pieces cover
exactly the interval asked for, trimming keeps what is still needed, and propagation gives the
closed-form state for constant measurements (with the biases taken off)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from autonomy.geometry import GRAVITY, rot_z, so3_exp
from autonomy.messages import ImuSample
from autonomy.vins.imu_buffer import ImuBuffer, ImuPieces, NavState, Propagator, propagate

ZERO = np.zeros(3)
HOVER = np.array([0.0, 0.0, GRAVITY])


def buffer_of(times, gyro=ZERO, accel=HOVER) -> ImuBuffer:
    buffer = ImuBuffer()
    for t in times:
        buffer.add(ImuSample(float(t), np.asarray(gyro, float), np.asarray(accel, float)))
    return buffer


def at_rest(t: float = 0.0) -> NavState:
    return NavState(t, np.eye(3), np.zeros(3), np.zeros(3))


def constant(gyro, accel, duration: float, n: int) -> ImuPieces:
    return ImuPieces(np.tile(np.asarray(gyro, float), (n, 1)),
                     np.tile(np.asarray(accel, float), (n, 1)), np.full(n, duration / n))


# ------------------------------------------------------------------ bad samples


@pytest.mark.parametrize("gyro, accel", [
    ([math.nan, 0.0, 0.0], [0.0, 0.0, 9.8]),
    ([0.0, 0.0, 0.0], [0.0, math.inf, 9.8]),
])
def test_non_finite_values_are_refused_and_the_sample_is_not_kept(gyro, accel):
    buffer = buffer_of([0.0])
    with pytest.raises(ValueError, match="NaN or infinite"):
        buffer.add(ImuSample(0.005, np.array(gyro), np.array(accel)))
    assert len(buffer) == 1 and buffer.last_time == 0.0
    buffer.add(ImuSample(0.005, ZERO, HOVER))  # the bad one left no trace
    assert len(buffer) == 2


def test_a_non_finite_time_is_refused():
    with pytest.raises(ValueError, match="NaN or infinite"):
        ImuBuffer().add(ImuSample(math.nan, ZERO, HOVER))


@pytest.mark.parametrize("gyro, accel, counts", [
    (np.zeros(2), HOVER, "got 2 and 3"),
    (ZERO, np.zeros(4), "got 3 and 4"),
    (np.zeros((2, 3)), HOVER, "got 6 and 3"),
])
def test_wrong_shapes_are_refused_naming_the_sizes(gyro, accel, counts):
    buffer = ImuBuffer()
    with pytest.raises(ValueError, match="must have 3 values") as error:
        buffer.add(ImuSample(0.0, gyro, accel))
    assert counts in str(error.value)
    assert len(buffer) == 0


@pytest.mark.parametrize("t", [0.01, 0.005])
def test_a_time_not_after_the_last_is_refused(t):
    buffer = buffer_of([0.0, 0.01])
    with pytest.raises(ValueError, match="not after the previous one"):
        buffer.add(ImuSample(t, ZERO, HOVER))
    assert len(buffer) == 2 and buffer.last_time == 0.01


# ------------------------------------------------------------------ pieces


def test_pieces_are_cut_exactly_at_the_interval_ends():
    buffer = ImuBuffer()
    for k, t in enumerate([0.0, 0.1, 0.2, 0.3]):
        buffer.add(ImuSample(t, np.array([k, 0.0, 0.0]), np.array([0.0, k, 0.0])))
    pieces = buffer.pieces(0.05, 0.25)
    np.testing.assert_allclose(pieces.dt, [0.05, 0.1, 0.05], atol=1e-15)
    # Each piece carries the sample that holds over it: 0 from 0.05, 1 from 0.1, 2 from 0.2.
    np.testing.assert_array_equal(pieces.gyro[:, 0], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(pieces.accel[:, 1], [0.0, 1.0, 2.0])


def test_the_newest_sample_holds_until_the_time_asked_for():
    pieces = buffer_of([0.0, 0.1]).pieces(0.05, 0.4)
    np.testing.assert_allclose(pieces.dt, [0.05, 0.3], atol=1e-15)


def test_an_interval_on_sample_times_has_no_empty_pieces():
    pieces = buffer_of([0.0, 0.1, 0.2, 0.3]).pieces(0.1, 0.3)
    np.testing.assert_allclose(pieces.dt, [0.1, 0.1], atol=1e-15)
    assert (buffer_of([0.0, 0.1]).pieces(0.1, 0.1).dt.size == 0)


@settings(max_examples=100, deadline=None)
@given(gaps=st.lists(st.floats(1e-3, 0.05), min_size=1, max_size=30),
       start=st.floats(0.0, 1.0), length=st.floats(0.0, 1.0))
def test_pieces_sum_to_the_interval_and_start_at_its_beginning(gaps, start, length):
    times = np.concatenate([[0.0], np.cumsum(gaps)])
    buffer = buffer_of(times)
    t0 = start * times[-1]
    t1 = t0 + length * (times[-1] + 0.1 - t0)  # may run past the newest sample
    pieces = buffer.pieces(t0, t1)
    assert (pieces.dt > 0).all()
    assert pieces.dt.sum() == pytest.approx(t1 - t0, abs=1e-12)
    assert len(pieces.gyro) == len(pieces.accel) == len(pieces.dt)
    if t1 > t0:  # the first piece starts at t0: it ends at the first sample after t0 (or t1)
        later = times[times > t0]
        first_end = min(later[0], t1) if len(later) else t1
        assert pieces.dt[0] == pytest.approx(first_end - t0, abs=1e-12)


def test_pieces_need_a_sample_holding_at_the_start():
    with pytest.raises(ValueError, match="no IMU sample holds at t=0.05"):
        buffer_of([0.1, 0.2]).pieces(0.05, 0.15)
    with pytest.raises(ValueError, match="no IMU sample holds"):
        ImuBuffer().pieces(0.0, 0.1)


def test_pieces_refuse_an_interval_that_ends_before_it_starts():
    with pytest.raises(ValueError, match="ends before it starts"):
        buffer_of([0.0, 0.1]).pieces(0.08, 0.02)


# ------------------------------------------------------------------ trimming


def test_discard_before_keeps_the_sample_holding_at_that_time():
    buffer = buffer_of([0.0, 0.1, 0.2, 0.3])
    buffer.discard_before(0.15)
    assert buffer.first_time == 0.1 and len(buffer) == 3
    assert buffer.pieces(0.15, 0.3).dt.sum() == pytest.approx(0.15)


def test_discard_before_a_sample_time_keeps_that_sample():
    buffer = buffer_of([0.0, 0.1, 0.2, 0.3])
    buffer.discard_before(0.2)
    assert buffer.first_time == 0.2 and len(buffer) == 2


def test_discard_before_the_start_or_past_the_end_keeps_what_is_needed():
    buffer = buffer_of([0.0, 0.1, 0.2])
    buffer.discard_before(-1.0)
    assert len(buffer) == 3
    buffer.discard_before(5.0)
    assert len(buffer) == 1 and buffer.first_time == 0.2  # still holds at 5.0
    assert buffer.pieces(5.0, 5.5).dt.sum() == pytest.approx(0.5)


# ------------------------------------------------------------------ propagation


def test_free_fall_drops_by_half_g_t_squared():
    state = propagate(at_rest(1.0), constant(ZERO, ZERO, 2.0, 37), ZERO, ZERO)
    assert state.t == pytest.approx(3.0)
    np.testing.assert_allclose(state.position, [0.0, 0.0, -0.5 * GRAVITY * 4.0], atol=1e-10)
    np.testing.assert_allclose(state.velocity, [0.0, 0.0, -GRAVITY * 2.0], atol=1e-10)
    np.testing.assert_allclose(state.R_W_B, np.eye(3), atol=1e-15)


def test_hovering_stays_put_from_any_position_and_attitude():
    yaw = rot_z(0.7)
    start = NavState(0.0, yaw, np.array([1.0, 2.0, 3.0]), np.zeros(3))
    state = propagate(start, constant(ZERO, HOVER, 5.0, 100), ZERO, ZERO)
    np.testing.assert_allclose(state.position, [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(state.velocity, ZERO, atol=1e-12)
    np.testing.assert_allclose(state.R_W_B, yaw, atol=1e-12)


def test_constant_velocity_carries_on_in_a_straight_line():
    start = NavState(0.0, np.eye(3), np.zeros(3), np.array([1.0, -2.0, 0.5]))
    state = propagate(start, constant(ZERO, HOVER, 2.0, 10), ZERO, ZERO)
    np.testing.assert_allclose(state.position, [2.0, -4.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(state.velocity, [1.0, -2.0, 0.5], atol=1e-12)


def test_constant_acceleration_gives_the_parabola():
    a = np.array([0.5, -0.3, 0.2])
    state = propagate(at_rest(), constant(ZERO, HOVER + a, 3.0, 60), ZERO, ZERO)
    np.testing.assert_allclose(state.position, 0.5 * a * 9.0, atol=1e-10)
    np.testing.assert_allclose(state.velocity, a * 3.0, atol=1e-10)


def test_constant_yaw_rate_turns_by_rate_times_time():
    w, T = 0.8, 1.5
    state = propagate(at_rest(), constant([0.0, 0.0, w], HOVER, T, 300), ZERO, ZERO)
    np.testing.assert_allclose(state.R_W_B, rot_z(w * T), atol=1e-12)
    np.testing.assert_allclose(state.position, ZERO, atol=1e-12)  # accel along the yaw axis


def test_constant_rate_about_any_axis_gives_the_exponential():
    w = np.array([0.3, -0.5, 0.2])
    R0 = so3_exp(np.array([0.1, 0.2, -0.3]))
    state = propagate(NavState(0.0, R0, ZERO, ZERO), constant(w, HOVER, 2.0, 17), ZERO, ZERO)
    np.testing.assert_allclose(state.R_W_B, R0 @ so3_exp(w * 2.0), atol=1e-12)


def test_biases_are_subtracted_before_integrating():
    bias_g, bias_a = np.array([0.01, -0.02, 0.03]), np.array([0.1, 0.2, -0.3])
    w = np.array([0.0, 0.0, 0.8])
    biased = constant(w + bias_g, HOVER + bias_a, 1.5, 50)
    state = propagate(at_rest(), biased, bias_g, bias_a)
    # yaw about the vertical leaves the (vertical) specific force vertical: hover exactly
    np.testing.assert_allclose(state.R_W_B, rot_z(0.8 * 1.5), atol=1e-12)
    np.testing.assert_allclose(state.position, ZERO, atol=1e-12)
    np.testing.assert_allclose(state.velocity, ZERO, atol=1e-12)
    # ... and ignoring them would not
    unbiased = propagate(at_rest(), biased, ZERO, ZERO)
    assert np.linalg.norm(unbiased.position) > 0.1


def test_propagating_through_the_buffer_matches_the_closed_form_across_samples():
    """Pieces from an uneven buffer, cut mid-sample at both ends, integrate like one constant
    piece of the whole interval."""
    times = np.cumsum(np.r_[0.0, np.random.default_rng(3).uniform(0.002, 0.02, 80)])
    a = np.array([0.2, 0.1, -0.4])
    buffer = buffer_of(times, accel=HOVER + a)
    t0, t1 = times[3] + 0.001, times[-5] - 0.001
    state = propagate(at_rest(t0), buffer.pieces(t0, t1), ZERO, ZERO)
    T = t1 - t0
    assert state.t == pytest.approx(t1)
    np.testing.assert_allclose(state.position, 0.5 * a * T * T, atol=1e-10)


def _same_state(a: NavState, b: NavState) -> bool:
    return a.t == b.t and all(np.array_equal(x, y) for x, y in (
        (a.R_W_B, b.R_W_B), (a.position, b.position), (a.velocity, b.velocity)))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.0, 0.2), min_size=1, max_size=12), st.integers(0, 2**32 - 1))
def test_the_propagator_resumes_bit_for_bit_what_propagate_gives_from_scratch(ends, seed):
    """The odometry's repeated propagation from one keyframe state, to later and earlier times,
    with new samples arriving between the calls and a new start state midway: every answer
    is exactly the from-scratch one."""
    rng = np.random.default_rng(seed)
    buffer = ImuBuffer()
    t = 0.0
    for _ in range(5):
        buffer.add(ImuSample(t, rng.normal(0, 0.5, 3), rng.normal(0, 3, 3)))
        t += 0.005
    start = NavState(0.0, so3_exp(rng.normal(0, 1, 3)), rng.normal(0, 5, 3), rng.normal(0, 1, 3))
    bias_g, bias_a = rng.normal(0, 0.01, 3), rng.normal(0, 0.1, 3)
    propagator = Propagator()
    for k, extra in enumerate(ends):
        for _ in range(int(rng.integers(0, 4))):  # samples arrive between the calls
            buffer.add(ImuSample(t, rng.normal(0, 0.5, 3), rng.normal(0, 3, 3)))
            t += 0.005
        if k == len(ends) // 2:  # a new keyframe: a new start state
            start = NavState(0.0, start.R_W_B, start.position + 1.0, start.velocity)
        until = min(buffer.last_time, extra) if k % 3 == 2 else buffer.last_time + extra
        pieces = buffer.pieces(0.0, until)
        assert _same_state(propagator.propagate(start, pieces, bias_g, bias_a),
                           propagate(start, pieces, bias_g, bias_a))
