"""The ``companion`` command line: a thin shell over library calls.

Every command works on the effective configuration, which :func:`main` loads once (the file,
then ``--set`` overrides) before dispatching, so a bad config is reported the same way by
every command: one line on stderr and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Sequence

from companion import __version__
from companion.config import LOG_LEVELS, Config, ConfigError, dump_toml, load_config

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran and could not do its job
EXIT_USAGE = 2  # argparse's status for bad arguments; a bad config is a bad argument too


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, --version, or a usage error argparse has printed
        return done.code
    if args.command is None:
        args.help_of.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        config = load_config(args.config_path, args.overrides)
    except ConfigError as error:
        print(error, file=sys.stderr)
        return EXIT_USAGE
    logging.basicConfig(level=args.log_level or config.log.level, stream=sys.stderr,
                        format=LOG_FORMAT)
    return args.command(args, config)


def _config_check(args: argparse.Namespace, config: Config) -> int:
    print(f"{args.config_path}: ok")
    return EXIT_OK


def _config_show(args: argparse.Namespace, config: Config) -> int:
    print(dump_toml(config), end="")
    return EXIT_OK


def _bench_rescale(args: argparse.Namespace, config: Config) -> int:
    # Imported here: the benchmark pulls in the whole rescaler, which no other command needs.
    from companion import bench

    try:
        result = bench.run_rescale_benchmark(config.rescale, anchors=args.anchors,
                                             shape=args.size, repeats=args.repeats)
    except bench.BenchmarkError as error:
        print(f"bench rescale: {error}", file=sys.stderr)
        return EXIT_FAILED
    print(json.dumps(result) if args.json else bench.format_rescale_table(result))
    return EXIT_OK


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Flight application for a PX4 drone's companion computer.")
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="lowest severity logged to stderr (default: [log] level of the "
                             "config, INFO unless set)")
    commands = _add_command_group(parser)
    overrides = argparse.ArgumentParser(add_help=False)
    overrides.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override one config value, e.g. --set rescale.kappa=1e5 or "
             "--set rescale.method=poly1 (a TOML value; a bare word is a string); repeatable, "
             "the last one wins")
    _add_config_commands(commands, overrides)
    _add_bench_commands(commands, overrides)
    return parser


def _add_command_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Subcommands of ``parser``; given none, the command prints ``parser``'s help."""
    parser.set_defaults(command=None, help_of=parser)
    return parser.add_subparsers(title="commands", metavar="COMMAND")


def _add_config_commands(commands: argparse._SubParsersAction,
                         overrides: argparse.ArgumentParser) -> None:
    group = commands.add_parser("config", help="validate or print a configuration",
                                description="Validate or print a TOML configuration.")
    actions = _add_command_group(group)
    check = actions.add_parser(
        "check", parents=[overrides], help="validate a config file",
        description="Validate a config file and its overrides: print 'FILE: ok' and exit 0, "
                    "or print what is wrong and where, and exit 2.")
    check.add_argument("config_path", metavar="FILE", help="TOML config file")
    check.set_defaults(command=_config_check)
    show = actions.add_parser(
        "show", parents=[overrides], help="print the effective config as TOML",
        description="Print the effective configuration as TOML, every key with its value: "
                    "the defaults, then FILE, then the overrides.")
    show.add_argument("config_path", metavar="FILE", nargs="?",
                      help="TOML config file (default: none, all defaults)")
    show.set_defaults(command=_config_show)


def _add_bench_commands(commands: argparse._SubParsersAction,
                        overrides: argparse.ArgumentParser) -> None:
    group = commands.add_parser("bench", help="measure the speed of the algorithms",
                                description="Measure the speed of the algorithms on "
                                            "synthetic input.")
    actions = _add_command_group(group)
    rescale = actions.add_parser(
        "rescale", parents=[overrides], help="time the depth rescaler",
        description="Time fitting the rescaling curve to sparse anchors and applying it to a "
                    "relative-disparity image, with the [rescale] options of the config. "
                    "Every method is timed, whatever rescale.method says; the result is "
                    "medians in milliseconds, with the direct per-pixel evaluation of the same "
                    "curve as the baseline.")
    rescale.add_argument("--config", dest="config_path", metavar="FILE",
                         help="TOML config file (default: none, all defaults)")
    rescale.add_argument("--json", action="store_true",
                         help="print the result as one JSON object instead of a table")
    rescale.add_argument("--repeats", type=_positive_int, default=30,
                         help="timed runs per measurement (default: %(default)s)")
    rescale.add_argument("--anchors", type=_positive_int, default=150,
                         help="sparse metric anchors per frame (default: %(default)s)")
    rescale.add_argument("--size", type=_image_size, default=(480, 640), metavar="HxW",
                         help="image height x width in pixels (default: 480x640)")
    rescale.set_defaults(command=_bench_rescale)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _image_size(text: str) -> tuple[int, int]:
    """``480x640`` -> ``(480, 640)``: height first, as in a numpy shape."""
    parts = text.lower().split("x")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH, e.g. 480x640; got {text!r}")
    height, width = (_positive_int(part) for part in parts)
    return height, width
