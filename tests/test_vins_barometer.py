"""The barometer as a height in the smoother (autonomy/vins/barometer.py)."""

import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY, PinholeCamera, make_pose
from autonomy.messages import ImuSample
from autonomy.vins import VinsOptions
from autonomy.vins.backend import KeyframeState, PriorSigmas, SlidingWindowSmoother
from autonomy.vins import barometer
from autonomy.vins.barometer import MATCH_S, PressureHistory, usable_pressure
from autonomy.vins.estimator import Vins

from test_vins_smoother import IMU_DT, NOISE

#: The pressure at PX4 SITL's home, 488 m (drivers.sim.baro.isa_pressure).
HOME_PA = 95594.9
BAROMETER = dict(barometer_sigma_m=0.2, barometer_drift_m_per_sqrt_s=0.02)


def hovering(options: VinsOptions, bias_z: float, seconds: float = 8.0,
             start_height: float = 0.0, pressure_every: int = 1,
             seed: int = 0, step_pa: float = 0.0) -> SlidingWindowSmoother:
    """A smoother with no landmark, started at ``start_height``, fed keyframes every 0.1 s of
    a body hovering level, its accelerometer reading ``bias_z`` more than gravity (a bias it
    is not told of), and the barometer's pressure (2 Pa of noise, drawn apart from the IMU's)
    on every ``pressure_every``-th keyframe, ``step_pa`` more from 4 s on (a door opened)."""
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    rng, barometer_rng = np.random.default_rng(seed), np.random.default_rng(seed + 100)

    def pressure(k: int) -> float | None:
        step = step_pa if k >= 40 else 0.0
        return None if k % pressure_every else HOME_PA + step + barometer_rng.normal(0.0, 2.0)

    start = make_pose(np.eye(3), [0.0, 0.0, start_height])
    smoother.start(KeyframeState(0, 0.0, start, np.zeros(3), np.zeros(3), np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.005), 0.01, 0.02),
                   pressure_pa=pressure(0))
    for k in range(1, int(round(seconds / 0.1)) + 1):
        pim = smoother.preintegration()
        for _ in range(int(round(0.1 / IMU_DT))):
            accel = [0.0, 0.0, GRAVITY + bias_z] + rng.normal(0.0, 6.9e-4 / math.sqrt(IMU_DT), 3)
            pim.integrateMeasurement(accel, np.zeros(3), IMU_DT)
        smoother.add_keyframe(k * 0.1, pim, [], None, pressure_pa=pressure(k))
    return smoother


def hover_pim(smoother: SlidingWindowSmoother, seconds: float, bias_z: float = 0.05):
    """The hovering body's IMU over ``seconds``, noiseless."""
    pim = smoother.preintegration()
    for _ in range(int(round(seconds / IMU_DT))):
        pim.integrateMeasurement([0.0, 0.0, GRAVITY + bias_z], np.zeros(3), IMU_DT)
    return pim


def height(smoother: SlidingWindowSmoother) -> float:
    return float(smoother.latest.T_W_B[2, 3])


def test_the_barometer_keeps_a_hover_level_through_an_accelerometer_bias_it_finds():
    """0.05 m/s^2 the smoother does not know climbs 1.6 m in 8 s; the barometer holds the
    height, and the smoother learns the bias from it."""
    blind = hovering(VinsOptions(), 0.05)
    held = hovering(VinsOptions(**BAROMETER), 0.05)
    assert height(blind) > 1.0
    assert abs(height(held)) < 0.1
    assert held.latest.bias_a[2] == pytest.approx(0.05, abs=0.02)
    assert held.resets == 0
    # a barometer every third keyframe holds it too
    assert abs(height(hovering(VinsOptions(**BAROMETER), 0.05, pressure_every=3))) < 0.25


@pytest.mark.parametrize("step_pa", [-48.0, 30.0])
def test_a_step_of_pressure_moves_the_offset_not_the_height(step_pa, monkeypatch):
    """A door opened at 4 s: 48 Pa down reads as a 4 m climb, 30 Pa up as a 2.5 m descent, in
    a moment. Taken as a climb the hover would end 4.6 m up or 3.4 m down; taken as a step
    (one), the offset takes it and the hover ends within 0.25 m (measured 0.24 m both ways:
    the height the barometer had at the step is kept, where without a step it ends 0.04 m
    off). A hover without a door has no step."""
    held = hovering(VinsOptions(**BAROMETER), 0.05, step_pa=step_pa)
    assert held.barometer_steps == 1 and held.resets == 0
    assert abs(height(held)) < 0.3
    assert hovering(VinsOptions(**BAROMETER), 0.05).barometer_steps == 0
    monkeypatch.setattr(barometer, "STEP_M", math.inf)  # every sample a climb
    dragged = hovering(VinsOptions(**BAROMETER), 0.05, step_pa=step_pa)
    assert abs(height(dragged)) > 2.0


def test_the_barometer_gives_height_changes_not_the_height():
    """The offset's chain starts wherever the VINS is: a smoother started 5 m up stays there
    through the same bias (the pressure's own height is 495 m)."""
    held = hovering(VinsOptions(**BAROMETER), 0.05, start_height=5.0)
    assert height(held) == pytest.approx(5.0, abs=0.1)
    assert height(hovering(VinsOptions(), 0.05, start_height=5.0)) > 6.0


def test_a_retimed_window_keeps_its_heights_and_goes_on():
    """Retiming moves the offsets with their keyframes: the window is solved again, as held,
    and the keyframes after it are held too."""
    smoother = hovering(VinsOptions(**BAROMETER), 0.05, seconds=6.0)
    window = smoother.window_keyframes
    times = [t - 0.018 for _, t in window]
    assert smoother.retime(times, [hover_pim(smoother, t1 - t0) for t0, t1
                                   in zip(times, times[1:])])
    assert abs(height(smoother)) < 0.1
    for k in range(1, 21):
        assert smoother.add_keyframe(times[-1] + 0.1 * k, hover_pim(smoother, 0.1), [], None,
                                     pressure_pa=HOME_PA)
    assert abs(height(smoother)) < 0.1 and smoother.resets == 0


def test_the_hold_leaves_the_height_to_the_barometer_only_while_it_has_samples():
    """Without samples in the window (landed, or under ``barometer_min_height_m``), the
    gauge hold keeps the height as it keeps the rest of the position."""
    smoother = hovering(VinsOptions(**BAROMETER), 0.0, seconds=3.0)
    assert smoother.gauge_keyframe is not None
    assert smoother._barometer_holds(smoother._window)
    for k in range(1, 31):
        smoother.add_keyframe(3.0 + 0.1 * k, hover_pim(smoother, 0.1), [], None)
    assert not smoother._barometer_holds(smoother._window)
    assert smoother.resets == 0


def test_each_sample_serves_the_keyframe_nearest_it_once():
    history = PressureHistory()
    for k in range(6):
        history.add(0.05 * k, 95000.0 + k)      # 0, 0.05, ..., 0.25 s
    assert history.take(0.12) == 95002.0        # 0.10 s is nearer than 0.15 s
    assert history.take(0.13) == 95003.0        # 0.10 s is used: the next one
    assert history.take(0.14) is None           # 0.20 s is 0.06 s away
    assert history.take(0.30) == 95005.0
    assert len(history) == 0
    assert history.take(0.35) is None
    history.add(1.0, 95000.0)
    assert history.take(1.0 + MATCH_S * 1.5) is None and len(history) == 0


def test_a_pressure_no_barometer_reads_is_left_out_and_counted():
    """A damaged recording's record: the IMU sample is used, its pressure is not."""
    assert usable_pressure(95000) == 95000.0
    for bad in (math.nan, 0.0, 2e5, "95000 Pa", None, [95000.0]):
        assert usable_pressure(bad) is None
    vins = Vins(PinholeCamera.from_hfov(64, 48, math.radians(90.0)), (), np.eye(4), NOISE,
                VinsOptions(**BAROMETER))
    vins.add_imu(ImuSample(0.0, np.zeros(3), np.array([0.0, 0.0, GRAVITY]), -5.0))
    vins.add_imu(ImuSample(0.005, np.zeros(3), np.array([0.0, 0.0, GRAVITY]), 95000.0))
    assert vins.refused_pressures == 1
