"""What several command groups share: argument types, flags, parent parsers, exit codes, the
effective configuration and the printing of results."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Callable

from autonomy.navigation.mission import parse_point
from autonomy.options import OptionError
from companion.config import SIMULATOR_DEFAULTS, Config, ConfigError, load_config

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

EXIT_OK = 0
EXIT_FAILED = 1  # the command ran and could not do its job
EXIT_USAGE = 2  # argparse's status for bad arguments; a bad config is a bad argument too


def overrides_parser() -> argparse.ArgumentParser:
    """The parent parser of every command that reads a config: ``--set``."""
    overrides = argparse.ArgumentParser(add_help=False)
    overrides.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override one config value, e.g. --set rescale.kappa=1e5 or "
             "--set rescale.method=poly1 (a TOML value; a bare word is a string); repeatable, "
             "the last one wins")
    return overrides


def configured_parser(simulator: bool = False) -> argparse.ArgumentParser:
    """The parent parser of the commands that take the config file as an option: ``--set``
    and ``--config``. ``simulator``: the command's defaults are
    :data:`~companion.config.SIMULATOR_DEFAULTS` (the realistic vehicle), under the file."""
    configured = argparse.ArgumentParser(add_help=False, parents=[overrides_parser()])
    defaults = SIMULATOR_DEFAULTS if simulator else ()
    configured.add_argument(
        "--config", dest="config_path", metavar="FILE",
        help="TOML config file over the defaults (default: none; the defaults are the "
             "realistic simulated vehicle, config/sim-realistic.toml's settings: --config "
             "config/sim.toml flies the ideal profile)" if simulator else
             "TOML config file (default: none, all defaults)")
    configured.set_defaults(config_defaults=defaults)
    return configured


def add_command_group(parser: argparse.ArgumentParser) -> argparse._SubParsersAction:
    """Subcommands of ``parser``; given none, the command prints ``parser``'s help."""
    parser.set_defaults(command=None, help_of=parser)
    return parser.add_subparsers(title="commands", metavar="COMMAND")


def load_effective_config(args: argparse.Namespace) -> Config | None:
    """The effective configuration of ``args``: the file, then the ``--set`` overrides. None,
    after one line on stderr, when it is bad, so every command reports a bad config the same
    way: exit status 2, never a traceback."""
    try:
        return load_config(args.config_path, args.overrides,
                           getattr(args, "config_defaults", ()))
    except ConfigError as error:
        print(error, file=sys.stderr)
        return None


def start_logging(args: argparse.Namespace, config: Config) -> None:
    """Log to stderr from ``--log-level``, else the config's [log] level."""
    logging.basicConfig(level=args.log_level or config.log.level, stream=sys.stderr,
                        format=LOG_FORMAT)


def report(command: str, args: argparse.Namespace, result: dict, text: str,
           *files: tuple[Path | None, Callable[[Path], object]]) -> int:
    """Print an evaluation's ``result`` (``--json``) or Markdown report ``text``, then write
    ``--markdown`` and each of ``files`` (path or None, writer): exit 1 with one line when
    one cannot be written (the result is printed already)."""
    print(json.dumps(result) if args.json else text)
    try:
        if args.markdown is not None:
            args.markdown.parent.mkdir(parents=True, exist_ok=True)
            args.markdown.write_text(text + "\n")
        for path, write in files:
            if path is not None:
                write(path)
    except OSError as error:
        print(f"{command}: {error}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def print_progress(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def point(text: str) -> tuple[float, float, float]:
    """``x,y,z`` metres -> a finite 3-tuple (:func:`autonomy.navigation.mission.parse_point`)."""
    try:
        return parse_point(text)
    except OptionError:
        raise argparse.ArgumentTypeError(
            f"expected X,Y,Z in metres, e.g. 10,-4,1.5; got {text!r}") from None


def add_json_flag(parser: argparse.ArgumentParser, instead_of: str) -> None:
    parser.add_argument("--json", action="store_true",
                        help=f"print the result as one JSON object instead of {instead_of}")


def add_record_flags(parser: argparse.ArgumentParser) -> None:
    """``--no-record`` and ``--live [HOST:PORT]`` (docs/recording.md)."""
    parser.add_argument("--no-record", dest="record", action="store_false",
                        help="write no flight recording (default: record as [recorder] says, "
                             "docs/recording.md)")
    parser.add_argument("--live", nargs="?", const="127.0.0.1:8765", default=None,
                        metavar="HOST:PORT",
                        help="serve the recorder's topics to Foxglove over WebSocket while "
                             "flying (default address: %(const)s)")


def recording_wanted(args: argparse.Namespace, config) -> bool:
    """Record unless ``--no-record`` or ``[recorder] enabled = false``."""
    return args.record and config.recorder.enabled


def png_path(text: str) -> Path:
    """A path ending in .png, for a plot that can be drawn: a usage error before a long run,
    not after it, for another name or when matplotlib (the ``plots`` extra) is missing."""
    from companion.tools import plot

    try:
        path = plot.png_path(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    missing = plot.missing_extra()
    if missing is not None:
        raise argparse.ArgumentTypeError(missing)
    return path


def float_above(minimum: float, wording: str, *, inclusive: bool):
    """An argparse type: a finite number above ``minimum`` (or equal to it, ``inclusive``),
    else a usage error in ``wording``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value >= minimum if inclusive else value > minimum)):
            raise argparse.ArgumentTypeError(f"expected a {wording} number, got {text!r}")
        return value
    return parse


positive_float = float_above(0.0, "positive", inclusive=False)
non_negative_float = float_above(0.0, "non-negative", inclusive=True)


def integer_at_least(minimum: int, wording: str):
    """An argparse type: an integer >= ``minimum``, else a usage error in ``wording``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected a {wording} integer, got {text!r}")
        return value
    return parse


positive_int = integer_at_least(1, "positive")
non_negative_int = integer_at_least(0, "non-negative")


def image_size(text: str) -> tuple[int, int]:
    """``480x640`` -> ``(480, 640)``: height first, as in a numpy shape."""
    parts = text.lower().split("x")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"expected HEIGHTxWIDTH, e.g. 480x640; got {text!r}")
    height, width = (positive_int(part) for part in parts)
    return height, width
