"""The ``companion`` command line: a thin shell over library calls, one module per command
group; :func:`main` builds the parser, loads the effective config once and dispatches."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from companion import __version__
from companion.cli import (bench, common, config_commands, depth, devices, fly, log, replay,
                           signing, sim)
from companion.cli import eval as eval_commands
from companion.config import LOG_LEVELS


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as done:  # --help, --version, or a usage error argparse has printed
        return done.code
    if args.command is None:
        args.help_of.print_help(sys.stderr)
        return common.EXIT_USAGE
    config = common.load_effective_config(args)
    if config is None:
        return common.EXIT_USAGE
    common.start_logging(args, config)
    return args.command(args, config)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Flight application for a PX4 drone's companion computer.")
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    parser.add_argument("--log-level", choices=LOG_LEVELS,
                        help="lowest severity logged to stderr (default: [log] level of the "
                             "config, INFO unless set)")
    commands = common.add_command_group(parser)
    for group in (config_commands, bench, sim, eval_commands, depth, devices, fly, log,
                  replay, signing):
        group.add_commands(commands)
    return parser
