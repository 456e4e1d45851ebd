"""``companion log``: what a flight recording holds (``info``), and a recording cut short by a
crash or a power cut made a complete file again (``recover``); docs/recording.md."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    group = commands.add_parser("log", help="summarise or recover a flight recording",
                                description="Read the MCAP recordings the flight recorder "
                                            "writes (docs/recording.md).")
    actions = common.add_command_group(group)
    info = actions.add_parser(
        "info", help="summarise a recording",
        description="Summarise a recording: complete or truncated, its duration, each "
                    "channel's topic, schema and message count, the metadata, the messages "
                    "the recorder dropped and why, and the flight events and failsafes. A "
                    "truncated recording is summarised as far as it is readable. Exits 1 with "
                    "one line when FILE is missing or not MCAP.")
    info.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    common.add_json_flag(info, instead_of="the summary")
    info.set_defaults(command=_info, config_path=None, overrides=[])
    recover = actions.add_parser(
        "recover", help="rewrite a truncated recording as a complete one",
        description="Write every readable message of FILE (a recording cut short by a crash, "
                    "a power cut or a full disk: everything up to its last complete chunk) "
                    "into OUT, a new, complete MCAP file that Foxglove and replay open. Exits "
                    "1 with one line when FILE cannot be read or OUT exists or cannot be "
                    "written.")
    recover.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    recover.add_argument("out", type=Path, metavar="OUT", help="new file to write (.mcap)")
    common.add_json_flag(recover, instead_of="one line")
    recover.set_defaults(command=_recover, config_path=None, overrides=[])


def _info(args: argparse.Namespace, config: Config) -> int:
    from companion.recording import inspect

    try:
        summary = inspect.summarise(args.file)
    except inspect.InspectError as error:
        print(f"log info: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(summary) if args.json else inspect.format_summary(summary))
    return common.EXIT_OK


def _recover(args: argparse.Namespace, config: Config) -> int:
    from companion.recording import inspect

    try:
        result = inspect.recover(args.file, args.out)
    except inspect.InspectError as error:
        print(f"log recover: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    source = "complete" if result["complete"] else "truncated"
    print(json.dumps(result) if args.json else
          f"{args.out}: {result['messages']} messages from {args.file} ({source})")
    return common.EXIT_OK
