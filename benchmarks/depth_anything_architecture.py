"""Write an ONNX model with Depth Anything V2 Small's architecture and random weights, to time
the real network's inference where its weights are not at hand (they are never downloaded).

    python benchmarks/depth_anything_architecture.py OUT.onnx [--size 518x686] [--fp16]

Needs PyTorch and Hugging Face transformers (``pip install -e '.[export]'``); the product does
not. The model is transformers' ``DepthAnythingForDepthEstimation`` in the configuration of
``depth-anything/Depth-Anything-V2-Small-hf``: a DINOv2 ViT-S/14 encoder (12 layers, width
384, 6 heads) whose layers 3, 6, 9 and 12 feed a DPT head (neck widths 48, 96, 192, 384,
fusion width 64) -- 24.8 M parameters, as the paper's network. Inference time does not depend
on the weights' values, so the numbers ``companion depth bench --model OUT.onnx`` gives with
it are the real network's (its depth is noise). The input is fixed to ``--size`` (height x
width, multiples of 14; 518x686 is the ``depth_anything_v2`` preset's size for 480x640
images), as a TensorRT engine wants; ``--fp16`` stores weights and input in half precision.
Prints one JSON object: the file, its size, the parameter count and the opset.
"""

import argparse
import json
import sys
from pathlib import Path

#: The ViT-S/14 encoder of Depth-Anything-V2-Small-hf (its config.json).
ENCODER = {"image_size": 518, "hidden_size": 384, "num_attention_heads": 6,
           "num_hidden_layers": 12, "patch_size": 14, "mlp_ratio": 4,
           "out_indices": [3, 6, 9, 12], "reshape_hidden_states": False,
           "apply_layernorm": True}

OPSET = 17


def image_size(text: str) -> tuple[int, int]:
    height, _, width = text.partition("x")
    try:
        size = int(height), int(width)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not HEIGHTxWIDTH") from None
    if min(size) <= 0 or size[0] % 14 or size[1] % 14:
        raise argparse.ArgumentTypeError(f"{text!r}: both sides must be positive multiples "
                                         "of the patch size, 14")
    return size


def build_model(seed: int):
    """DepthAnythingForDepthEstimation in DA-V2 Small's configuration, weights seeded."""
    import torch
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    torch.manual_seed(seed)
    config = DepthAnythingConfig(backbone_config=Dinov2Config(**ENCODER),
                                 neck_hidden_sizes=[48, 96, 192, 384], fusion_hidden_size=64,
                                 head_hidden_size=32, reassemble_hidden_size=384,
                                 depth_estimation_type="relative")
    return DepthAnythingForDepthEstimation(config).eval()


def depth_only(model):
    """The model's ``predicted_depth`` alone, (1, h, w): one image in, one depth image out."""
    import torch

    class DepthOnly(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, pixel_values):
            return self.model(pixel_values=pixel_values).predicted_depth

    return DepthOnly().eval()


def export(path: Path, size: tuple[int, int], fp16: bool, seed: int) -> dict:
    import torch

    model = build_model(seed)
    parameters = sum(p.numel() for p in model.parameters())
    dtype = torch.float16 if fp16 else torch.float32
    wrapped = depth_only(model).to(dtype)
    example = torch.zeros((1, 3, *size), dtype=dtype)
    with torch.no_grad():
        torch.onnx.export(wrapped, (example,), str(path), input_names=["pixel_values"],
                          output_names=["predicted_depth"], opset_version=OPSET,
                          dynamo=False)
    return {"file": str(path), "bytes": path.stat().st_size, "parameters": parameters,
            "input": [1, 3, *size], "dtype": "float16" if fp16 else "float32", "opset": OPSET}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the ONNX file to write")
    parser.add_argument("--size", type=image_size, default=(518, 686), metavar="HxW",
                        help="fixed input height x width (default: 518x686)")
    parser.add_argument("--fp16", action="store_true", help="half-precision weights and input")
    parser.add_argument("--seed", type=int, default=0, help="weights' random seed")
    args = parser.parse_args()
    try:
        import torch  # noqa: F401
        import transformers  # noqa: F401
    except ImportError as error:
        print(f"{error.name} is missing: install the export extra, "
              "pip install -e '.[export]'", file=sys.stderr)
        return 2
    print(json.dumps(export(args.out, args.size, args.fp16, args.seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
