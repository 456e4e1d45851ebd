"""The sliding-window smoother and its resets: position and yaw are unobservable, and once the
window's information on them has faded iSAM2's Cholesky fails (a reset); the loose keyframe
priors (``keyframe_prior_position_sigma``, off by default: docs/vins.md) keep it."""

import math

import numpy as np

from autonomy.geometry import GRAVITY, PinholeCamera
from autonomy.vins import ImuNoise, VinsOptions
from autonomy.vins.backend import KeyframeState, PriorSigmas, SlidingWindowSmoother

#: The estimator's noise model of the simulated vehicle's IMU (config/sim.toml [vins_imu]).
NOISE = ImuNoise(4.8869e-05, 6.865e-04, 1.9393e-05, 3e-3)
IMU_DT = 0.005


def resets_turning_in_place_unseeing(options: VinsOptions, seconds: float = 20.0,
                                     keyframe_interval: float = 0.05, seed: int = 0) -> int:
    """Resets of a smoother fed keyframes with no landmark while the IMU turns in place at
    0.5 rad/s, as over a corner: the keyframes come fast (the front-end's parallax is the
    rotation's) and nothing but the IMU joins them."""
    smoother = SlidingWindowSmoother(PinholeCamera.from_hfov(640, 480, math.radians(90.0)),
                                     np.eye(4), NOISE, options)
    smoother.start(KeyframeState(0, 0.0, np.eye(4), np.zeros(3), np.zeros(3), np.zeros(3)),
                   PriorSigmas.with_bias_priors(options, (0.017, 0.017, 0.005), 0.01, 0.02))
    rng = np.random.default_rng(seed)
    steps = int(round(keyframe_interval / IMU_DT))
    for k in range(1, int(round(seconds / keyframe_interval)) + 1):
        pim = smoother.preintegration()
        for _ in range(steps):
            gyro = np.array([0.0, 0.0, 0.5]) + rng.normal(0.0, 4.9e-5 / math.sqrt(IMU_DT), 3)
            accel = np.array([0.0, 0.0, GRAVITY]) + rng.normal(0.0, 6.9e-4 / math.sqrt(IMU_DT),
                                                               3)
            pim.integrateMeasurement(accel, gyro, IMU_DT)
        smoother.add_keyframe(k * keyframe_interval, pim, [], None)
    return smoother.resets


def test_with_the_loose_keyframe_priors_a_window_without_landmarks_stays_well_posed():
    assert resets_turning_in_place_unseeing(VinsOptions(keyframe_prior_position_sigma=0.1,
                                                        keyframe_prior_rotation_sigma=0.05)) == 0


def test_without_them_the_same_window_is_rebuilt():
    """What the priors are for: the same IMU-only window meets an indeterminate linear system
    within 20 s when nothing refreshes its absolute pose information."""
    assert resets_turning_in_place_unseeing(VinsOptions()) >= 1
