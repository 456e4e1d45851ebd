"""``companion signing``: MAVLink 2 signing keys: make one (``keygen``), give it to PX4
(``provision``); docs/operations.md, "MAVLink signing"."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from companion.cli import common
from companion.config import Config

#: Where the service unit's LoadCredential= takes the key from.
INSTALLED_KEY = "/etc/companion/mavlink-signing.key"


def add_commands(commands: argparse._SubParsersAction) -> None:
    group = commands.add_parser(
        "signing", help="make a MAVLink signing key, give it to PX4",
        description="MAVLink 2 signing: only holders of the vehicle's key can command it "
                    "(docs/operations.md, MAVLink signing).")
    actions = common.add_command_group(group)
    keygen = actions.add_parser(
        "keygen", help="write a new random key to a new file (mode 0600)",
        description="Write 32 random bytes as 64 hex digits to FILE, created readable by you "
                    "only; an existing FILE is never overwritten. Prints where to put it.")
    keygen.add_argument("key_file", type=Path, metavar="FILE", help="the key file to create")
    keygen.set_defaults(command=_keygen, config_path=None, overrides=[])
    provision = actions.add_parser(
        "provision", parents=[common.configured_parser()],
        help="give PX4 the config's key over the [mavlink] link",
        description="Send PX4 (disarmed, PX4 v1.18 or later) SETUP_SIGNING with the key of "
                    "[mavlink] signing_key_file and the current signing timestamp over the "
                    "[mavlink] link, then wait until PX4's HEARTBEAT verifies with the key. "
                    "The key travels in clear: use a wire (USB, the companion's UART), never "
                    "a radio. Stop the service first: it holds the link.")
    provision.add_argument("--current-key-file", metavar="FILE",
                           help="the key PX4 has now, when replacing it (PX4 takes a new key "
                                "only signed with its current one)")
    provision.add_argument("--timeout", type=common.positive_float, default=5.0,
                           metavar="SECONDS",
                           help="longest wait for each answer of PX4 (default: %(default)s)")
    provision.set_defaults(command=_provision)


def _keygen(args: argparse.Namespace, config: Config) -> int:
    from drivers.mavlink.signing import SigningKeyError, new_key, write_key_file

    try:
        path = write_key_file(args.key_file, new_key())
    except SigningKeyError as error:
        print(f"signing keygen: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(f"wrote a new MAVLink signing key to {path} (mode 0600). Next:\n"
          f"  1. install it where the service unit loads it from:\n"
          f"       sudo install -o root -g root -m 600 {path} {INSTALLED_KEY}\n"
          f"     (systemd/companion.service: LoadCredential=mavlink-signing.key:"
          f"{INSTALLED_KEY};\n"
          f"      the config's [mavlink] signing_key_file = \"mavlink-signing.key\" finds "
          f"the service's copy)\n"
          f"  2. give PX4 the key, disarmed, over a wire, the service stopped:\n"
          f"       sudo companion signing provision --config /etc/companion/flight.toml "
          f"--set mavlink.signing_key_file={INSTALLED_KEY}\n"
          f"  3. give the same key to every ground station that commands the vehicle\n"
          f"  then delete {path}, or keep it offline: whoever reads it can fly the vehicle")
    return common.EXIT_OK


def _provision(args: argparse.Namespace, config: Config) -> int:
    import asyncio

    from drivers.clock import MonotonicClock
    from drivers.mavlink.provision import ProvisionError, provision
    from drivers.mavlink.signing import load_key, read_key_file

    options = config.mavlink
    try:
        key = load_key(options)
        if key is None:
            raise ProvisionError("no key: set [mavlink] signing_key_file (`companion signing "
                                 "keygen FILE` makes one)")
        current = read_key_file(args.current_key_file) if args.current_key_file else None
        done = asyncio.run(provision(options, MonotonicClock(), key, current_key=current,
                                     timeout_s=args.timeout))
    except (ProvisionError, ValueError, OSError) as error:
        print(f"signing provision: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    px4 = f"PX4 (system {options.target_system} component {options.target_component})"
    if done.already:
        print(f"{px4} already signs with this key: nothing sent")
    else:
        print(f"{px4} took the key{' in place of its old one' if done.had_key else ''}: its "
              "HEARTBEAT verifies with it. From now on it signs everything it sends and "
              "ignores unsigned commands, on every link.")
    return common.EXIT_OK
