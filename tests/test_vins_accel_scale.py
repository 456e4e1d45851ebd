"""The accelerometer's z sensitivity read at rest (autonomy/vins/accel_scale.py): its share of
the specific force's excess over gravity, divided out of the z axis alone; bad inputs refused.
The estimator's use of it is in tests/test_vins_estimator.py."""

import math

import numpy as np
import pytest

from autonomy.geometry import GRAVITY
from autonomy.vins import VinsOptions
from autonomy.vins.accel_scale import RestAccelScale


def test_the_share_of_the_excess_over_gravity_is_the_z_sensitivity_error():
    # a z axis 1 % long, no bias: read whole with share 1, at 0.7 of itself with 0.7
    assert RestAccelScale.from_rest(1.01 * GRAVITY, 1.0).error == pytest.approx(0.01)
    assert RestAccelScale.from_rest(1.01 * GRAVITY, 0.7).error == pytest.approx(0.007)
    assert RestAccelScale.from_rest(0.995 * GRAVITY, 1.0).error == pytest.approx(-0.005)
    assert RestAccelScale.from_rest(1.01 * GRAVITY, 0.0).error == 0.0


def test_the_z_axis_alone_is_divided_by_its_read_sensitivity():
    scale = RestAccelScale(0.02)
    force = np.array([0.3, -0.2, 1.02 * 9.0])
    corrected = scale.correct(force)
    np.testing.assert_allclose(corrected, [0.3, -0.2, 9.0])
    np.testing.assert_array_equal(force, [0.3, -0.2, 1.02 * 9.0])  # the caller's untouched
    # at rest, a vehicle whose z reads 1 % long with share 1 reads gravity again
    at_rest = RestAccelScale.from_rest(1.01 * GRAVITY, 1.0).correct([0.0, 0.0, 1.01 * GRAVITY])
    assert at_rest[2] == pytest.approx(GRAVITY)
    # a window of samples, row by row
    np.testing.assert_allclose(scale.correct(np.tile(force, (4, 1))), np.tile(corrected, (4, 1)))


@pytest.mark.parametrize("norm, share, message", [
    (math.nan, 0.7, "accel_norm must be a positive number"),
    (0.0, 0.7, "accel_norm must be a positive number"),
    (-9.8, 0.7, "accel_norm must be a positive number"),
    (GRAVITY, 1.5, r"share must be in \[0, 1\]"),
    (GRAVITY, -0.1, r"share must be in \[0, 1\]"),
])
def test_a_bad_rest_reading_or_share_is_refused(norm, share, message):
    with pytest.raises(ValueError, match=message):
        RestAccelScale.from_rest(norm, share)


@pytest.mark.parametrize("share", [-0.1, 1.01, math.nan])
def test_a_share_outside_zero_to_one_is_refused_by_the_options(share):
    with pytest.raises(ValueError, match="rest_accel_scale_share"):
        VinsOptions(rest_accel_scale_share=share)
