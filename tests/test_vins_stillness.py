"""Standing still and the zero-velocity update's test (autonomy/vins/stillness.py): what
makes a keyframe stand still, and each thing that refuses it (features moving, or moved and
back, the body turning, too short a stretch, too few shared features, switched off)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from autonomy.geometry import rot_z
from autonomy.vins import Tracks, VinsOptions
from autonomy.vins.stillness import ZeroVelocityDetector, median_flow_px

FOCAL_PX = 400.0
FEATURES = 60


def tracks(shift_px: float = 0.0, count: int = FEATURES, frame: int = 0) -> Tracks:
    """``count`` features spread over the image, all moved ``shift_px`` along x."""
    rng = np.random.default_rng(0)
    normalised = rng.uniform(-0.6, 0.6, (count, 2)) + [shift_px / FOCAL_PX, 0.0]
    return Tracks(frame, np.arange(count), normalised * FOCAL_PX + [320.0, 240.0], normalised,
                  np.full(count, 10))


def detector(**options) -> ZeroVelocityDetector:
    """Keyframes every 0.1 s from t = 0 to 0.5 s, standing at yaw 0 seeing :func:`tracks`."""
    found = ZeroVelocityDetector(dataclasses.replace(VinsOptions(), **options), FOCAL_PX)
    for t in np.arange(0.0, 0.51, 0.1):
        found.add(float(t), np.eye(3), tracks())
    return found


def test_the_median_flow_is_of_the_shared_features_in_undistorted_pixels():
    moved = tracks(3.0)
    moved.normalised[:10] += 1.0  # a few tracks slid far: the median ignores them
    assert median_flow_px(moved, tracks(), FOCAL_PX, 20) == pytest.approx(3.0)
    assert median_flow_px(tracks(count=10), tracks(), FOCAL_PX, 20) == math.inf


def test_a_keyframe_standing_still_for_the_window_is_still():
    assert detector().still(0.6, np.eye(3), tracks(0.5))


@pytest.mark.parametrize("why, R_W_B, now", [
    ("features moved 2 px", np.eye(3), tracks(2.0)),
    ("turned at 0.1 rad/s", rot_z(0.05), tracks()),
    ("shares too few features", np.eye(3), tracks(count=20)),
])
def test_a_keyframe_that_is_not_still_gets_no_prior(why, R_W_B, now):
    assert not detector().still(0.6, R_W_B, now), why


def test_moved_away_and_back_within_the_window_is_not_still():
    """Each end alike, a keyframe between them 3 px off and turned 0.1 rad: judged against
    every keyframe of the stretch, not its first alone."""
    found = detector()
    found.keyframes[3] = (found.keyframes[3][0], np.eye(3), tracks(3.0))
    assert not found.still(0.6, np.eye(3), tracks())
    found = detector()
    found.keyframes[3] = (found.keyframes[3][0], rot_z(0.1), tracks())
    assert not found.still(0.6, np.eye(3), tracks())


def test_no_prior_before_the_window_has_passed_or_when_switched_off():
    fresh = ZeroVelocityDetector(VinsOptions(), FOCAL_PX)
    fresh.add(0.0, np.eye(3), tracks())
    assert not fresh.still(0.3, np.eye(3), tracks())
    assert fresh.still(0.5, np.eye(3), tracks())
    assert not detector(zero_velocity_update=False).still(0.6, np.eye(3), tracks())


def test_the_stretch_judged_is_since_the_keyframe_a_window_before():
    """Features drifting 0.3 px per 0.1 s: still over 0.2 s, not over the 0.5 s window."""
    found = ZeroVelocityDetector(VinsOptions(), FOCAL_PX)
    for k, t in enumerate(np.arange(0.0, 1.01, 0.1)):
        found.add(float(t), np.eye(3), tracks(0.3 * k))
    assert len(found.keyframes) <= 7  # older than the window needs: dropped
    assert not found.still(1.1, np.eye(3), tracks(3.3))
    short = ZeroVelocityDetector(VinsOptions(zero_velocity_window_s=0.2), FOCAL_PX)
    for k, t in enumerate(np.arange(0.0, 1.01, 0.1)):
        short.add(float(t), np.eye(3), tracks(0.3 * k))
    assert short.still(1.1, np.eye(3), tracks(3.3))
