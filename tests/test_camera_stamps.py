"""Frame stamps read off the camera's frame grid (drivers/camera/stamps.py)."""

import math

import numpy as np
import pytest

from drivers.camera.stamps import LEAST_FRAMES, RESTART_AFTER, WINDOW_FRAMES, GridStamps

RATE_HZ = 30.0
#: The camera's crystal against the host's clock: 80 ppm slow, a straight line over the window.
DRIFT = 80e-6
JITTER_S = 1e-3  # the realistic simulator's timestamp_jitter_ms


def grid_flight(frames: int, seed: int, start_s: float = 1234.5, first_counter: int = 7,
                drift: float = DRIFT):
    """Counters (1 % of frames lost: gaps) and the true exposure times on a grid whose period
    is ``drift`` longer on the host's clock than the camera's, and the stamps a host took on
    arrival: those times plus the simulator's jitter (1 ms, clipped at a quarter period)."""
    rng = np.random.default_rng(seed)
    kept = rng.random(frames) > 0.01
    counters = first_counter + np.flatnonzero(kept)
    exposed = start_s + (1.0 + drift) / RATE_HZ * counters
    jitter = np.clip(rng.normal(0.0, JITTER_S, len(counters)), -0.25 / RATE_HZ, 0.25 / RATE_HZ)
    return counters, exposed, exposed + jitter


def stamped(stamps: GridStamps, counters, arrived) -> np.ndarray:
    return np.array([stamps.stamp(float(t), int(n)) for n, t in zip(counters, arrived)])


@pytest.mark.parametrize("seed, drift", [(0, DRIFT), (1, DRIFT), (2, 1e-3)])
def test_grid_stamps_take_out_most_of_the_jitter(seed, drift):
    # at 1000 ppm the nominal period would be 2.5 ms off at a window's end: the period is fitted
    counters, exposed, arrived = grid_flight(900, seed, drift=drift)
    out = stamped(GridStamps.for_rate(RATE_HZ), counters, arrived)
    assert np.array_equal(out[:LEAST_FRAMES], arrived[:LEAST_FRAMES])  # before the fit holds
    settled = slice(WINDOW_FRAMES, None)
    raw_rms = np.sqrt(np.mean((arrived[settled] - exposed[settled]) ** 2))
    grid_rms = np.sqrt(np.mean((out[settled] - exposed[settled]) ** 2))
    # a line's end over N points keeps about sqrt(4 / N) of the jitter: 0.16 at 150 frames
    assert grid_rms < 0.25 * raw_rms
    # no lag or lead: the settled errors' mean is that of about five independent windows
    assert abs(np.mean(out[settled] - exposed[settled])) < 0.2 * JITTER_S
    assert np.all(np.diff(out) > 0)


def test_a_stalled_frame_gets_its_exposure_time_and_leaves_the_fit_alone():
    counters, exposed, arrived = grid_flight(400, seed=3)
    late = 300
    arrived[late] += 0.040  # held up 40 ms on the host
    stamps = GridStamps.for_rate(RATE_HZ)
    out = stamped(stamps, counters, arrived)
    assert abs(out[late] - exposed[late]) < 0.5e-3
    after = slice(late + 1, None)
    assert np.max(np.abs(out[after] - exposed[after])) < 0.6e-3
    assert stamps.restarts == 0


def test_a_stepped_clock_restarts_the_fit_and_then_follows_the_new_grid(caplog):
    counters, exposed, arrived = grid_flight(600, seed=4)
    step = 300
    exposed[step:] += 0.050  # the host's view of the camera's clock jumps by 50 ms
    arrived[step:] += 0.050
    stamps = GridStamps.for_rate(RATE_HZ)
    out = stamped(stamps, counters, arrived)
    assert stamps.restarts == 1
    assert "5 frames in a row over 8.3 ms off the grid" in caplog.text
    # the frames before the restart keep the old line: when the step was not yet known
    assert np.allclose(out[step:step + RESTART_AFTER - 1] - exposed[step:step + RESTART_AFTER - 1],
                       -0.050, atol=1e-3)
    restarted = step + RESTART_AFTER - 1
    assert np.array_equal(out[restarted:restarted + LEAST_FRAMES],
                          arrived[restarted:restarted + LEAST_FRAMES])
    settled = slice(restarted + WINDOW_FRAMES, None)
    assert np.sqrt(np.mean((out[settled] - exposed[settled]) ** 2)) < 0.25 * JITTER_S


def test_a_counter_that_goes_back_starts_a_new_grid(caplog):
    first, _, arrived_first = grid_flight(200, seed=5)
    second, exposed, arrived = grid_flight(400, seed=6, start_s=1300.0, first_counter=0)
    stamps = GridStamps.for_rate(RATE_HZ)
    stamped(stamps, first, arrived_first)
    out = stamped(stamps, second, arrived)  # the driver restarted its stream from 0
    assert stamps.restarts == 1
    assert f"frame 0 numbered before frame {first[-1]}" in caplog.text
    assert np.array_equal(out[:LEAST_FRAMES], arrived[:LEAST_FRAMES])
    settled = slice(WINDOW_FRAMES, None)
    assert np.sqrt(np.mean((out[settled] - exposed[settled]) ** 2)) < 0.25 * JITTER_S


def test_frames_off_the_grid_pass_through_and_leave_the_fit_alone():
    counters, exposed, arrived = grid_flight(300, seed=7)
    stamps = GridStamps.for_rate(RATE_HZ)
    stamped(stamps, counters[:200], arrived[:200])
    last = int(counters[199])
    assert stamps.stamp(55.0, None) == 55.0  # a camera with no counter
    assert stamps.stamp(float(arrived[199]) + 0.3, last) == float(arrived[199]) + 0.3  # stale
    assert math.isnan(stamps.stamp(math.nan, last + 1))
    assert stamps.stamp(math.inf, last + 1) == math.inf
    reference = GridStamps.for_rate(RATE_HZ)
    stamped(reference, counters[:200], arrived[:200])
    assert np.array_equal(stamped(stamps, counters[200:], arrived[200:]),
                          stamped(reference, counters[200:], arrived[200:]))
    assert stamps.restarts == 0


@pytest.mark.parametrize("arguments, named", [
    ((LEAST_FRAMES - 1, 0.01, 5), "window"),
    ((WINDOW_FRAMES, 0.0, 5), "max_residual_s"),
    ((WINDOW_FRAMES, math.nan, 5), "max_residual_s"),
    ((WINDOW_FRAMES, 0.01, 0), "restart_after"),
])
def test_bad_settings_are_refused_by_name(arguments, named):
    with pytest.raises(ValueError, match=named):
        GridStamps(*arguments)


@pytest.mark.parametrize("rate", [0.0, -30.0, math.nan])
def test_a_bad_frame_rate_is_refused(rate):
    with pytest.raises(ValueError, match="frame rate"):
        GridStamps.for_rate(rate)
