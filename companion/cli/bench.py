"""``companion bench``: the speed of the algorithms on synthetic input (``rescale``)."""

from __future__ import annotations

import argparse
import json
import sys

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    group = commands.add_parser("bench", help="measure the speed of the algorithms",
                                description="Measure the speed of the algorithms on "
                                            "synthetic input.")
    actions = common.add_command_group(group)
    rescale = actions.add_parser(
        "rescale", parents=[common.configured_parser()], help="time the depth rescaler",
        description="Time fitting the rescaling curve to sparse anchors and applying it to a "
                    "relative-disparity image, with the [rescale] options of the config. "
                    "Every method is timed, whatever rescale.method says; the result is "
                    "medians in milliseconds, with the direct per-pixel evaluation of the same "
                    "curve as the baseline.")
    common.add_json_flag(rescale, instead_of="a table")
    rescale.add_argument("--repeats", type=common.positive_int, default=30,
                         help="timed runs per measurement (default: %(default)s)")
    rescale.add_argument("--anchors", type=common.positive_int, default=150,
                         help="sparse metric anchors per frame (default: %(default)s)")
    rescale.add_argument("--size", type=common.image_size, default=(480, 640), metavar="HxW",
                         help="image height x width in pixels (default: 480x640)")
    rescale.set_defaults(command=_bench_rescale)


def _bench_rescale(args: argparse.Namespace, config: Config) -> int:
    # Imported here: the benchmark pulls in the whole rescaler, which no other command needs.
    from companion.tools import bench

    try:
        result = bench.run_rescale_benchmark(config.rescale, anchors=args.anchors,
                                             shape=args.size, repeats=args.repeats)
    except bench.BenchmarkError as error:
        print(f"bench rescale: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(result) if args.json else bench.format_rescale_table(result))
    return common.EXIT_OK
