"""The depth path's speed, behind ``companion depth bench``: the network runtime per preset,
input size and execution provider, and the metric depth stage without the network.

The network is timed in its three steps: ``preprocess_ms`` (colour order, resize,
normalisation), ``inference_ms`` (onnxruntime) and ``postprocess_ms`` (upsampling to the
camera); ``total_ms`` is the median of the three in a row. With no user model the numbers are
the small generated test model's (:mod:`companion.tools.testmodel`): they measure the pre- and
post-processing honestly, but its inference is a few convolutions, not a depth network's.
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import onnxruntime

from autonomy.depth.network import PROVIDERS, DepthNetwork, NetworkOptions, choose_providers
from autonomy.depth.rescale import RescaleOptions
from autonomy.depth.stage import DepthStageOptions, MetricDepthStage
from autonomy.messages import RelativeDepth, SparseMap
from companion.tools.bench import BenchmarkError, interleaved_medians_ms, synthetic_scene

#: (preset, input size) pairs the test model is timed at: the defaults, and smaller DA-V2
#: inputs a user picks for speed.
TEST_MODEL_SIZES = (("depth_anything_v2", 518), ("depth_anything_v2", 392),
                    ("depth_anything_v2", 266), ("midas_v21_small", 256))

#: Anchors per frame in the stage timing: the VINS's landmark budget (vins.max_landmarks).
STAGE_ANCHORS = 80


def run_depth_benchmark(network: NetworkOptions, rescale: RescaleOptions,
                        stage: DepthStageOptions, *, shape: tuple[int, int] = (480, 640),
                        repeats: int = 20) -> dict:
    """Time the network runtime and the stage on ``shape`` (height, width) frames.

    Every provider of ``network.providers`` that onnxruntime offers here is timed alone: the
    test model at :data:`TEST_MODEL_SIZES`, and the user's model (``network.model``, when set)
    at its configured preset and size. ``stage_ms`` is :meth:`MetricDepthStage.process` on a
    synthetic frame with :data:`STAGE_ANCHORS` tracked landmarks.
    """
    available = onnxruntime.get_available_providers()
    providers = choose_providers(network.providers, available)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        test_model = _write_test_model(Path(folder))
        for provider in providers:
            for preset, size in TEST_MODEL_SIZES:
                options = dataclasses.replace(network, model=str(test_model), sha256="",
                                              preset=preset, input_size=size)
                rows.append(_time_network("test", options, provider, shape, repeats))
            if network.model:
                rows.append(_time_network("user", network, provider, shape, repeats))
    return {"image": list(shape), "providers_available": available, "inference": rows,
            "stage_anchors": STAGE_ANCHORS,
            "stage_ms": round(_time_stage(rescale, stage, shape, repeats), 4)}


def _write_test_model(folder: Path) -> Path:
    # Imported here: building the model needs the onnx package, which nothing else at run
    # time does.
    from companion.tools.testmodel import build_test_model

    path = folder / "test_model.onnx"
    path.write_bytes(build_test_model())
    return path


def _time_network(model: str, options: NetworkOptions, provider: str,
                  shape: tuple[int, int], repeats: int) -> dict:
    """One row of the table: the model opened on ``provider`` alone, each step timed."""
    short = next(name for name, full in PROVIDERS.items() if full == provider)
    options = dataclasses.replace(options, providers=(short,))
    network = DepthNetwork.open(options, camera_size=shape)
    image = np.random.default_rng(0).integers(0, 256, (*shape, 3), dtype=np.uint8)
    tensor = network.preprocess(image)
    output = network.run(tensor)
    pre, infer, post, total = interleaved_medians_ms(
        [lambda: network.preprocess(image), lambda: network.run(tensor),
         lambda: network.postprocess(output, shape), lambda: network(image)], repeats)
    return {"model": model, "path": options.model if model == "user" else None,
            "preset": options.preset, "input": list(tensor.shape[2:]),
            "provider": network.provider, "preprocess_ms": round(pre, 4),
            "inference_ms": round(infer, 4), "postprocess_ms": round(post, 4),
            "total_ms": round(total, 4)}


def _time_stage(rescale: RescaleOptions, options: DepthStageOptions,
                shape: tuple[int, int], repeats: int) -> float:
    scene = synthetic_scene(shape, STAGE_ANCHORS)
    z = scene.anchor_depth
    points = np.column_stack([np.zeros((len(z), 2)), z])
    sparse = SparseMap(0.0, np.arange(len(z)), points, 0.02 * z, scene.anchor_pixels,
                       np.ones(len(z), dtype=bool))
    stage = MetricDepthStage(rescale, options)
    frame = RelativeDepth(0.0, scene.relative_disparity)
    if not stage.process(frame, sparse).ok:
        raise BenchmarkError("the stage found no fit on the benchmark scene")
    stage_ms, = interleaved_medians_ms([lambda: stage.process(frame, sparse)], repeats)
    return stage_ms


def format_depth_table(result: dict) -> str:
    """The benchmark result as a table a person reads."""
    height, width = result["image"]
    lines = [f"depth benchmark: {height}x{width} camera images (medians, ms)",
             f"{'model':<6}{'preset':<19}{'input':>9}  {'provider':<27}{'pre':>8}{'infer':>9}"
             f"{'post':>8}{'total':>9}"]
    for row in result["inference"]:
        h, w = row["input"]
        lines.append(f"{row['model']:<6}{row['preset']:<19}{f'{h}x{w}':>9}  "
                     f"{row['provider']:<27}{row['preprocess_ms']:>8.2f}"
                     f"{row['inference_ms']:>9.2f}{row['postprocess_ms']:>8.2f}"
                     f"{row['total_ms']:>9.2f}")
    lines.append(f"stage without the network ({result['stage_anchors']} anchors): "
                 f"{result['stage_ms']:.2f} ms")
    return "\n".join(lines)
