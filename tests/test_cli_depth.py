"""``companion depth bench`` and ``companion eval depth`` as a user runs them."""

from __future__ import annotations

import json
import shutil

import pytest

from companion.cli import main
from companion.tools.testmodel import build_test_model


@pytest.fixture(scope="module")
def test_model(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "depth.onnx"
    path.write_bytes(build_test_model())
    return path


def _json_of(capsys, *argv) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_depth_bench_times_every_preset_size_on_the_cpu_and_the_stage(capsys):
    result = _json_of(capsys, "depth", "bench", "--json", "--repeats", "2")
    rows = result["inference"]
    assert [(r["preset"], r["input"]) for r in rows] == [
        ("depth_anything_v2", [518, 686]), ("depth_anything_v2", [392, 518]),
        ("depth_anything_v2", [266, 350]), ("midas_v21_small", [192, 256])]
    assert {r["provider"] for r in rows} == {"CPUExecutionProvider"}
    assert {r["model"] for r in rows} == {"test"}
    for row in rows:
        assert 0 < row["preprocess_ms"] and 0 < row["inference_ms"] and 0 < row["total_ms"]
    assert result["image"] == [480, 640] and result["stage_ms"] > 0


def test_depth_bench_times_the_users_model_at_its_configured_size(capsys, test_model):
    result = _json_of(capsys, "depth", "bench", "--json", "--repeats", "1", "--size",
                      "240x320", "--model", str(test_model),
                      "--set", "depth_network.input_size=266")
    user = [r for r in result["inference"] if r["model"] == "user"]
    assert len(user) == 1
    assert user[0]["path"] == str(test_model) and user[0]["input"] == [266, 350]


def test_depth_bench_with_a_missing_model_fails_in_one_line(capsys, tmp_path):
    assert main(["depth", "bench", "--model", str(tmp_path / "none.onnx")]) == 1
    error = capsys.readouterr().err.strip()
    assert error.startswith("depth bench: cannot read the depth model")
    assert len(error.splitlines()) == 1


def test_depth_bench_with_no_wanted_provider_available_fails_in_one_line(capsys):
    assert main(["depth", "bench", "--set", "depth_network.providers=['tensorrt']"]) == 1
    assert "depth bench:" in capsys.readouterr().err


def test_eval_depth_on_a_dataset_without_depth_says_so(capsys, tmp_path):
    from tests.test_eval_vio import _write_dataset

    _write_dataset(tmp_path)
    shutil.rmtree(tmp_path / "mav0" / "depth0")
    assert main(["eval", "depth", str(tmp_path)]) == 1
    assert "no mav0/depth0 stream" in capsys.readouterr().err


def test_eval_depth_with_a_broken_model_fails_before_any_frame(capsys, tmp_path):
    from tests.test_eval_vio import _write_dataset

    _write_dataset(tmp_path)
    garbage = tmp_path / "model.onnx"
    garbage.write_bytes(b"not a model")
    assert main(["eval", "depth", str(tmp_path), "--set",
                 f"depth_network.model={json.dumps(str(garbage))}"]) == 1
    assert "eval depth: onnxruntime cannot load the depth model" in capsys.readouterr().err
