"""Issue 5's acceptance: the metric depth stage on simulated flights, with VINS sparse maps.

The first 15 s of each world's 40 s flight (seed 0; 2 s still on the ground, a climb, then
forward flight) run through the whole depth path as in flight: the VINS, the synthetic
stand-in network on the rendered depth, and the stage with the default monotone spline;
``companion eval depth``'s library call scores every frame against the rendered depth with
the rescaler's metrics. What a user relies on: once the VINS has a map, nearly every frame has
metric depth; rescaling with at most 80 VINS landmarks costs little beyond the network's own
error (the floor any affine rescaling has, AbsRel after the best affine fit to the truth at
every pixel); and near obstacles are almost never placed too far away.
"""

import pytest

from autonomy.depth.rescale import RescaleOptions
from autonomy.depth.synthetic import SyntheticNetwork
from autonomy.vins import VinsOptions
from companion.tools.eval.depth import DepthEvalOptions, evaluate_depth

SECONDS = 40.0  # the VINS acceptance test's flights, recorded once per session
FRAMES = 300  # 15 s at 20 Hz


@pytest.mark.parametrize("world", ["mine", "sewer", "dome"])
def test_the_stage_gives_metric_depth_on_a_flight_with_vins_sparse_maps(world, record_flight):
    network = SyntheticNetwork(seed=0)
    result = evaluate_depth(record_flight(world, SECONDS),
                            DepthEvalOptions(VinsOptions(), RescaleOptions()),
                            lambda frame, truth: network(truth), max_frames=FRAMES)
    assert result["frames"] == FRAMES
    assert result["rejected"] == {}
    with_map = FRAMES - result["no_fit"].get("no_sparse_map", 0)
    assert result["frames_with_depth"] >= 0.9 * with_map, result
    assert result["abs_rel"] <= 1.5 * result["network_affine_abs_rel"], result
    assert result["delta1"] >= 0.85, result
    assert result["overestimate_rate"] <= 0.02, result
