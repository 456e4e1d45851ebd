"""Depth metrics against hand-computed values."""

import math
import warnings

import numpy as np
import pytest

from autonomy.depth.metrics import (
    DepthMetrics,
    abs_rel,
    delta1,
    evaluate,
    overestimate_rate,
    rmse,
)

# Ground truth 1, 2, 4 m; predictions 2, 2, 2 m. Errors +1, 0, -2 m.
GT = np.array([[1.0, 2.0, 4.0]], dtype=np.float32)
PRED = np.array([[2.0, 2.0, 2.0]], dtype=np.float32)


def test_abs_rel_divides_by_ground_truth_by_default():
    # (1/1 + 0/2 + 2/4) / 3 = 1.5 / 3
    assert abs_rel(PRED, GT) == pytest.approx(0.5)


def test_abs_rel_pred_denominator_is_the_papers_formula():
    gt = np.array([1.0, 4.0])
    pred = np.array([2.0, 2.0])
    assert abs_rel(pred, gt, denominator="gt") == pytest.approx((1 / 1 + 2 / 4) / 2)
    assert abs_rel(pred, gt, denominator="pred") == pytest.approx((1 / 2 + 2 / 2) / 2)


def test_abs_rel_rejects_unknown_denominator():
    with pytest.raises(ValueError, match="denominator"):
        abs_rel(PRED, GT, denominator="mean")


def test_delta1_counts_ratios_below_threshold():
    # ratios max(z/z*, z*/z): 2, 1, 2 -> one of three below 1.25
    assert delta1(PRED, GT) == pytest.approx(1 / 3)
    assert delta1(PRED, GT, threshold=2.5) == pytest.approx(1.0)


def test_delta1_ratio_exactly_at_threshold_is_not_counted():
    assert delta1(np.array([1.25, 1.0]), np.array([1.0, 1.25])) == 0.0


def test_rmse():
    # sqrt((1 + 0 + 4) / 3)
    assert rmse(PRED, GT) == pytest.approx(math.sqrt(5 / 3))


def test_mask_restricts_pixels():
    mask = np.array([[False, True, True]])
    assert abs_rel(PRED, GT, mask=mask) == pytest.approx((0 + 0.5) / 2)
    assert rmse(PRED, GT, mask=mask) == pytest.approx(math.sqrt(4 / 2))
    assert evaluate(PRED, GT, mask=mask).valid_pixels == 2


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 0.0, -1.0])
@pytest.mark.parametrize("where", ["pred", "gt"])
def test_invalid_pixels_are_excluded(bad, where):
    gt = np.array([2.0, 3.0], dtype=np.float32)
    pred = np.array([2.0, 30.0], dtype=np.float32)
    if where == "pred":
        pred[1] = bad
    else:
        gt[1] = bad
    assert abs_rel(pred, gt) == 0.0
    assert rmse(pred, gt) == 0.0
    assert delta1(pred, gt) == 1.0
    assert evaluate(pred, gt).valid_pixels == 1


def test_no_valid_pixels_gives_nan_without_warnings():
    gt = np.full((2, 2), np.nan, dtype=np.float32)
    pred = np.ones((2, 2), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = evaluate(pred, gt)
        assert math.isnan(abs_rel(pred, gt, denominator="pred"))
        assert math.isnan(delta1(pred, gt))
        assert math.isnan(rmse(pred, gt))
        assert math.isnan(overestimate_rate(pred, gt))
    assert math.isnan(result.abs_rel)
    assert math.isnan(result.delta1)
    assert math.isnan(result.rmse)
    assert math.isnan(result.overestimate_rate)
    assert result.valid_pixels == 0
    assert result.near_pixels == 0


def test_empty_images_give_nan():
    empty = np.zeros((0, 0), dtype=np.float32)
    assert math.isnan(abs_rel(empty, empty))


def test_shape_mismatch_names_both_shapes():
    with pytest.raises(ValueError, match=r"\(2, 3\).*\(3, 2\)"):
        evaluate(np.ones((2, 3)), np.ones((3, 2)))


def test_mask_shape_mismatch_is_rejected():
    with pytest.raises(ValueError, match="mask"):
        rmse(PRED, GT, mask=np.ones((3, 1), dtype=bool))


def test_overestimate_rate_counts_only_near_ground_truth():
    gt = np.array([1.0, 2.0, 4.0, 10.0])
    pred = np.array([2.0, 2.0, 4.0, 50.0])  # 1 m seen at 2 m; the 10 m pixel is not near
    assert overestimate_rate(pred, gt) == pytest.approx(1 / 3)
    assert overestimate_rate(pred, gt, near=20.0) == pytest.approx(2 / 4)


def test_overestimate_rate_ignores_underestimates():
    gt = np.array([2.0, 2.0])
    pred = np.array([0.5, 2.0])
    assert overestimate_rate(pred, gt) == 0.0


def test_overestimate_exactly_at_margin_is_not_counted():
    gt = np.array([2.0, 2.0])
    pred = np.array([2.5, 2.5 + 1e-6])  # (1 + 0.25) * 2 = 2.5 exactly
    assert overestimate_rate(pred, gt) == pytest.approx(0.5)


def test_overestimate_rate_is_nan_without_near_pixels():
    assert math.isnan(overestimate_rate(np.array([9.0]), np.array([8.0])))


@pytest.mark.parametrize("kwargs", [{"near": 0.0}, {"margin": -0.1}, {"near": float("nan")}])
def test_overestimate_rate_rejects_bad_parameters(kwargs):
    with pytest.raises(ValueError):
        overestimate_rate(PRED, GT, **kwargs)


def test_delta1_rejects_threshold_not_above_one():
    with pytest.raises(ValueError, match="threshold"):
        delta1(PRED, GT, threshold=1.0)


def test_evaluate_matches_the_single_metrics():
    gt = np.array([1.0, 2.0, 4.0, 10.0], dtype=np.float32)
    pred = np.array([2.0, 2.0, 2.0, 11.0], dtype=np.float32)
    result = evaluate(pred, gt, denominator="pred")
    assert result == DepthMetrics(
        abs_rel=abs_rel(pred, gt, denominator="pred"),
        delta1=delta1(pred, gt),
        rmse=rmse(pred, gt),
        overestimate_rate=overestimate_rate(pred, gt),
        valid_pixels=4,
        near_pixels=3,
    )
    assert result.overestimate_rate == pytest.approx(1 / 3)


def test_as_dict_lists_every_metric():
    assert evaluate(PRED, GT).as_dict() == {
        "abs_rel": pytest.approx(0.5),
        "delta1": pytest.approx(1 / 3),
        "rmse": pytest.approx(math.sqrt(5 / 3)),
        "overestimate_rate": pytest.approx(1 / 3),
        "valid_pixels": 3,
        "near_pixels": 3,
    }
