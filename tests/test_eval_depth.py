"""``companion eval depth``'s statistics of how the planner reads the metric depth: true over
estimated depth for the confident pixels and the rescaling's two tails."""

import numpy as np

from autonomy.depth.rescale import RescaleOptions
from autonomy.messages import DepthDiagnostics, MetricDepth
from autonomy.vins import VinsOptions
from companion.tools.eval.depth import (
    RATIO_STRIDE, DepthEvalOptions, DepthTrace, _record_ratios, ratio_percentiles,
)

DIAGNOSTICS = DepthDiagnostics(20, 20, 0.0, "poly1", 0.0)


def test_each_class_gets_its_own_pixels_true_over_estimated_where_the_truth_has_a_surface():
    """A frame of 4 columns: confident at 4 m (truly 3.6 m), the near tail at 1 m (truly
    1 m), the far tail at 8 m (truly 6 m, or no surface in its lower half) and a sky beyond
    range: the far tail's ratio is 0.75, read from the pixels with a surface only."""
    shape = (64, 64)
    depth = np.empty(shape, np.float32)
    confidence = np.full(shape, 0.1, np.float32)
    truth = np.empty(shape, np.float32)
    depth[:, :16], confidence[:, :16], truth[:, :16] = 4.0, 1.0, 3.6
    depth[:, 16:32], truth[:, 16:32] = 1.0, 1.0
    depth[:, 32:48], truth[:, 32:48] = 8.0, 6.0
    truth[32:, 32:48] = np.nan  # no surface: left out
    depth[:, 48:], truth[:, 48:] = 40.0, 40.0
    trace = DepthTrace()
    result = MetricDepth(0.0, depth, confidence, False, DIAGNOSTICS)
    _record_ratios(trace, result, truth, DepthEvalOptions(VinsOptions(), RescaleOptions()))
    scores = {name: ratio_percentiles(ratios) for name, ratios in trace.ratios.items()}
    assert scores["in_range"]["p1"] == scores["in_range"]["p50"] == np.float32(3.6) / 4.0
    assert scores["near_tail"]["p5"] == 1.0
    assert scores["far_tail"]["p1"] == scores["far_tail"]["p50"] == 0.75
    assert scores["far_tail"]["pixels"] == len(range(0, 32 * 16, RATIO_STRIDE))
    assert scores["in_range"]["pixels"] == len(range(0, 64 * 16, RATIO_STRIDE))


def test_a_class_without_pixels_has_no_percentiles():
    assert ratio_percentiles([]) == {"pixels": 0, "p1": None, "p5": None, "p50": None}
    assert ratio_percentiles([np.empty(0)])["p50"] is None
