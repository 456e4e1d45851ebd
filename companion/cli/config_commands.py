"""``companion config``: validate a configuration (``check``) or print the effective one
(``show``)."""

from __future__ import annotations

import argparse

from companion.cli import common
from companion.config import Config, dump_toml


def add_commands(commands: argparse._SubParsersAction) -> None:
    overrides = common.overrides_parser()
    group = commands.add_parser("config", help="validate or print a configuration",
                                description="Validate or print a TOML configuration.")
    actions = common.add_command_group(group)
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


def _config_check(args: argparse.Namespace, config: Config) -> int:
    print(f"{args.config_path}: ok")
    return common.EXIT_OK


def _config_show(args: argparse.Namespace, config: Config) -> int:
    print(dump_toml(config), end="")
    return common.EXIT_OK
