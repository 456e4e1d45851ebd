"""Issue 4's acceptance: the VINS on 40 s simulated flights in each world.

Each flight (seed 0) is 2 s still on the ground, a climb, then forward flight at 1 m/s along
the world's route; ``companion eval vio``'s library call scores it against the ground truth.
The goal: trajectory error at most 1 % of the distance flown (after SE(3) alignment, so scale
error counts), median landmark depth error at most 3 %, and never LOST (no unrecovered
divergence).
"""

import pytest

from autonomy.vins import VinsOptions
from companion.tools.eval.vio import evaluate_vio

SECONDS = 40.0


@pytest.mark.parametrize("world", ["mine", "sewer", "dome"])
def test_a_forty_second_flight_stays_within_one_percent_and_three_percent_depth(
        world, record_flight):
    result = evaluate_vio(record_flight(world, SECONDS), VinsOptions())
    assert result["health"].get("LOST", 0) == 0, result["health"]
    assert result["distance_m"] > 30.0
    assert result["ate_over_distance"] <= 0.01, result
    assert result["depth_rel_err_median"] <= 0.03, result
