"""The depth network's speed on a GPU: DA-V2 Small's architecture through the product's runner.

    python benchmarks/depth_gpu.py MODELS_DIR [--repeats 30]

``MODELS_DIR`` holds models written by ``benchmarks/depth_anything_architecture.py``:
``da2s_518x686.onnx`` (required) and, where present, ``da2s_518x686_fp16.onnx``,
``da2s_392x518.onnx`` and ``da2s_266x350.onnx``. Each is timed by
``companion.tools.depth_bench.run_depth_benchmark`` (the code of ``companion depth bench``,
which this runs without the CLI, whose imports a GPU machine may lack): the 518 model on the
CUDA and CPU execution providers, the others on CUDA. Then the model is opened with the
default ``providers`` (TensorRT, CUDA, CPU) to show which one runs it, and, where PyTorch
with CUDA is installed, the same network is timed in PyTorch eager for reference (medians of
50 after 10 warm-ups, float32 and float16). Needs onnxruntime-gpu. Prints one JSON object.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from autonomy.depth.network import DepthNetwork, NetworkError, NetworkOptions
from autonomy.depth.rescale import RescaleOptions
from autonomy.depth.stage import DepthStageOptions
from companion.tools.depth_bench import run_depth_benchmark

#: (file, providers timed) in order.
MODELS = (("da2s_518x686.onnx", ("cuda", "cpu")), ("da2s_518x686_fp16.onnx", ("cuda",)),
          ("da2s_392x518.onnx", ("cuda",)), ("da2s_266x350.onnx", ("cuda",)))


def bench(path: Path, providers: tuple[str, ...], repeats: int) -> dict:
    try:
        return run_depth_benchmark(NetworkOptions(model=str(path), providers=providers),
                                   RescaleOptions(), DepthStageOptions(), repeats=repeats)
    except NetworkError as error:
        return {"error": str(error)}


def torch_eager_ms(size=(518, 686)) -> dict | str:
    """PyTorch eager on the same network, per dtype, or why it could not run."""
    try:
        import torch
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from depth_anything_architecture import build_model, depth_only
        if not torch.cuda.is_available():
            return "no CUDA device"
    except ImportError as error:
        return f"not run: {error}"
    result = {}
    for dtype in (torch.float32, torch.float16):
        model = depth_only(build_model(0)).to("cuda", dtype)
        image = torch.zeros((1, 3, *size), device="cuda", dtype=dtype)
        times = []
        with torch.no_grad():
            for _ in range(60):
                torch.cuda.synchronize()
                start = time.perf_counter()
                model(image)
                torch.cuda.synchronize()
                times.append((time.perf_counter() - start) * 1e3)
        result[str(dtype).removeprefix("torch.")] = round(statistics.median(times[10:]), 3)
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("models", type=Path, help="folder of the exported models")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per measurement")
    args = parser.parse_args()
    if not (args.models / MODELS[0][0]).is_file():
        parser.error(f"{args.models / MODELS[0][0]} is missing: write it with "
                     "benchmarks/depth_anything_architecture.py")
    result = {name: bench(args.models / name, providers, args.repeats)
              for name, providers in MODELS if (args.models / name).is_file()}
    try:
        opened = DepthNetwork.open(NetworkOptions(model=str(args.models / MODELS[0][0])))
        result["default_providers_run_on"] = opened.provider
    except NetworkError as error:
        result["default_providers_run_on"] = f"error: {error}"
    result["torch_eager_ms_518x686"] = torch_eager_ms()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
