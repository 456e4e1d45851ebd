"""``companion depth``: the depth network runtime and the metric depth stage (``bench``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    group = commands.add_parser("depth", help="the depth network and the metric depth stage",
                                description="The depth network runtime and the metric depth "
                                            "stage.")
    actions = common.add_command_group(group)
    bench = actions.add_parser(
        "bench", parents=[common.configured_parser()],
        help="time the depth network and the stage",
        description="Time the depth network runtime (pre-processing, inference, "
                    "post-processing) per preset and input size on every execution provider "
                    "of [depth_network] providers that onnxruntime offers here, with a small "
                    "generated test model and, with --model or [depth_network] model, the "
                    "user's model; and the metric depth stage without the network. Medians "
                    "in milliseconds.")
    bench.add_argument("--model", metavar="FILE",
                       help="the user's ONNX depth model (default: [depth_network] model)")
    common.add_json_flag(bench, instead_of="a table")
    bench.add_argument("--repeats", type=common.positive_int, default=20,
                       help="timed runs per measurement (default: %(default)s)")
    bench.add_argument("--size", type=common.image_size, default=(480, 640), metavar="HxW",
                       help="camera image height x width in pixels (default: 480x640)")
    bench.set_defaults(command=_depth_bench)


def _depth_bench(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.tools import bench, depth_bench

    network = config.depth_network
    if args.model is not None:
        network = dataclasses.replace(network, model=args.model, sha256="")
    try:
        result = depth_bench.run_depth_benchmark(network, config.rescale, config.depth,
                                                 shape=args.size, repeats=args.repeats)
    except (NetworkError, bench.BenchmarkError) as error:
        print(f"depth bench: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(result) if args.json else depth_bench.format_depth_table(result))
    return common.EXIT_OK
