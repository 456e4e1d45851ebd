"""Issues 4 and 5's acceptance: the VINS, and the metric depth stage on its sparse maps, on a
40 s simulated flight in each world. One module, so that one worker records each flight once
(:func:`conftest.record_flight`) for both.

Each flight (seed 0) is 2 s still on the ground, a climb, then forward flight at 1 m/s along
the world's route.

- The VINS (``companion eval vio``'s library call, scored against the ground truth):
  trajectory error at most 1 % of the distance flown (after SE(3) alignment, so scale error
  counts), median landmark depth error at most 3 %, never LOST (no unrecovered divergence)
  and never rebuilt (the mine's window was, 36.9 s in, until the smoother ordered its
  elimination: :mod:`autonomy.vins.fixed_lag`).
- The depth path over the first 15 s as in flight (the VINS, the synthetic stand-in network on
  the rendered depth, the stage with the default monotone spline; ``companion eval depth``'s
  library call scores every frame against the rendered depth with the rescaler's metrics).
  What a user relies on: once the VINS has a map, nearly every frame has metric depth;
  rescaling with at most 80 VINS landmarks costs little beyond the network's own error (the
  floor any affine rescaling has, AbsRel after the best affine fit to the truth at every
  pixel); and near obstacles are almost never placed too far away.
"""

import pytest

from autonomy.depth.rescale import RescaleOptions
from autonomy.depth.synthetic import SyntheticNetwork
from autonomy.vins import VinsOptions
from companion.tools.eval.depth import DepthEvalOptions, evaluate_depth
from companion.tools.eval.vio import evaluate_vio

SECONDS = 40.0
DEPTH_FRAMES = 300  # 15 s at 20 Hz
WORLDS = ["mine", "sewer", "dome"]


@pytest.mark.parametrize("world", WORLDS)
def test_a_forty_second_flight_stays_within_one_percent_and_three_percent_depth(
        world, record_flight):
    result = evaluate_vio(record_flight(world, SECONDS), VinsOptions(), consistency=False)
    assert result["health"].get("LOST", 0) == 0, result["health"]
    assert result["resets"] == 0, result["rebuilds"]
    assert result["distance_m"] > 30.0
    assert result["ate_over_distance"] <= 0.01, result
    assert result["depth_rel_err_median"] <= 0.03, result


@pytest.mark.parametrize("world", WORLDS)
def test_the_stage_gives_metric_depth_on_a_flight_with_vins_sparse_maps(world, record_flight):
    network = SyntheticNetwork(seed=0)
    result = evaluate_depth(record_flight(world, SECONDS),
                            DepthEvalOptions(VinsOptions(), RescaleOptions()),
                            lambda frame, truth: network(truth), max_frames=DEPTH_FRAMES)
    assert result["frames"] == DEPTH_FRAMES
    assert result["rejected"] == {}
    with_map = DEPTH_FRAMES - result["no_fit"].get("no_sparse_map", 0)
    assert result["frames_with_depth"] >= 0.9 * with_map, result
    assert result["abs_rel"] <= 1.5 * result["network_affine_abs_rel"], result
    assert result["delta1"] >= 0.85, result
    assert result["overestimate_rate"] <= 0.02, result
