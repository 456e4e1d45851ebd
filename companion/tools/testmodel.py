"""A tiny, real ONNX model with a depth network's interface, for tests and the benchmark.

It is not a depth network: three convolutions with fixed positive weights, so its output
grows with the brightness of the input, which lets a test follow an image through the whole
pipeline. Built in memory with the ``onnx`` helper API; nothing is downloaded.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
#: IR version 8 (ONNX 1.10+) so that older onnxruntime builds, as on a Jetson, load it too.
IR_VERSION = 8
#: (output channels, input channels, kernel size) of the three convolutions.
LAYERS = ((8, 3, 3), (8, 8, 3), (1, 8, 1))
#: Bias of the first convolution: above 27 x 0.15 x 2.12, the most a normalised image (values
#: >= -2.12) can pull a sum of 27 weights <= 0.15 below zero, so no ReLU ever clips.
FIRST_BIAS = 9.0


def build_test_model(*, fixed_size: tuple[int, int] | None = None,
                     output_rank: int = 3, seed: int = 0) -> bytes:
    """The serialised test model: input "image" (1, 3, H, W) float32, output "depth".

    ``H`` and ``W`` are symbolic, or fixed to ``fixed_size`` = (h, w). The output is
    (1, H, W) for ``output_rank=3`` (like the Depth Anything V2 exports) or (1, 1, H, W) for
    ``output_rank=4``: ``softplus(conv1x1(relu(conv3x3(relu(conv3x3(image))))))`` with weights
    drawn uniformly from [0.05, 0.15] by a numpy RNG seeded with ``seed``, the first layer's
    biases :data:`FIRST_BIAS` and the others' zero. All weights are positive and the first
    layer's output positive for any ImageNet-normalised image, so the output is positive and
    strictly increasing in every input pixel it sees: a brighter image gives a larger output.
    """
    if output_rank not in (3, 4):
        raise ValueError(f"output_rank must be 3 or 4, got {output_rank}")
    height, width = fixed_size if fixed_size is not None else ("height", "width")
    rng = np.random.default_rng(seed)
    weights, nodes, x = [], [], "image"
    for i, (out_channels, in_channels, kernel) in enumerate(LAYERS):
        w = rng.uniform(0.05, 0.15, (out_channels, in_channels, kernel, kernel))
        weights.append(numpy_helper.from_array(w.astype(np.float32), f"w{i}"))
        bias = np.full(out_channels, FIRST_BIAS if i == 0 else 0.0, np.float32)
        weights.append(numpy_helper.from_array(bias, f"b{i}"))
        pad = kernel // 2
        nodes.append(helper.make_node("Conv", [x, f"w{i}", f"b{i}"], [f"conv{i}"],
                                      pads=[pad] * 4))
        activation = "Relu" if i < len(LAYERS) - 1 else "Softplus"
        x = f"act{i}" if i < len(LAYERS) - 1 else "depth4"
        nodes.append(helper.make_node(activation, [f"conv{i}"], [x]))
    output_shape = [1, 1, height, width]
    if output_rank == 3:
        weights.append(numpy_helper.from_array(np.array([1], np.int64), "channel_axis"))
        nodes.append(helper.make_node("Squeeze", [x, "channel_axis"], ["depth"]))
        output_shape = [1, height, width]
    else:
        nodes[-1].output[0] = "depth"
    graph = helper.make_graph(
        nodes, "depth_test_model",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, height, width])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, output_shape)],
        initializer=weights,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="companion.tools.testmodel")
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString()
