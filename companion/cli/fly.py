"""``companion fly``: fly the real vehicle (the systemd service's command)."""

from __future__ import annotations

import argparse
import json
import sys

from companion.cli import common
from companion.config import Config


def add_commands(commands: argparse._SubParsersAction) -> None:
    fly = commands.add_parser(
        "fly", parents=[common.configured_parser()],
        help="fly the real vehicle (the systemd service's command)",
        description="Connect to the flight controller ([mavlink] url), the camera ([camera] "
                    "driver) and the depth network ([depth_network] model), wait disarmed for "
                    "the operator's go ([go]), then fly the mission: [flight] waypoints, or "
                    "--goal. Stops, holds and lands on any failure and on SIGTERM. See "
                    "docs/operations.md.")
    fly.add_argument("--goal", dest="goals", type=common.point, action="append", default=[],
                     metavar="X,Y,Z",
                     help="waypoint in metres in PX4's local frame (x east, y north, z up); "
                          "repeatable, the last is the goal; replaces [flight] waypoints")
    fly.add_argument("--check", action="store_true",
                     help="open the network, the camera and the link, run every preflight check "
                          "(camera rate and exposure, MAVLink signing, IMU rate, TIMESYNC, PX4 "
                          "parameters), print a pass/fail table and exit without arming")
    common.add_record_flags(fly)
    common.add_json_flag(fly, instead_of="the summary table")
    fly.set_defaults(command=_fly)

    go = commands.add_parser(
        "go", parents=[common.configured_parser()],
        help="give the running `companion fly` the operator's go (arm and fly)",
        description="Tell the application on this vehicle, waiting disarmed in awaiting_go, "
                    "to arm and fly: a datagram on [go] socket. Ground stations give the same "
                    "go with MAV_CMD_MISSION_START, an RC switch with [go] rc_channel.")
    go.set_defaults(command=_go)


def _fly(args: argparse.Namespace, config: Config) -> int:
    if args.check:
        return _check(args, config)
    from autonomy.depth.network import NetworkError
    from companion.launch import real
    from companion.flight.app import format_flight
    from companion.flight.go import GoError
    from companion.recording.live import LiveViewError
    from companion.recording.storage import RecordingError
    from drivers.camera.base import CameraError

    waypoints = args.goals or config.flight.waypoint_points()
    try:
        summary = real.run(config, waypoints, record=common.recording_wanted(args, config),
                           live=args.live)
    except (real.FlyError, NetworkError, CameraError, GoError, RecordingError, LiveViewError,
            ValueError, OSError) as error:
        print(f"fly: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(summary) if args.json else format_flight(summary))
    return common.EXIT_OK if summary["final_state"] == "landed" and summary["reached_goal"] \
        else common.EXIT_FAILED


def _go(args: argparse.Namespace, config: Config) -> int:
    from companion.flight.go import send_go

    path = config.go.socket
    if not path:
        print("go: [go] socket is empty: this vehicle takes the go by MAVLink or RC only",
              file=sys.stderr)
        return common.EXIT_FAILED
    try:
        send_go(path)
    except OSError as error:
        print(f"go: nobody listens on {path} ({error.strerror or error}): is `companion fly` "
              "running and waiting for the go? (systemctl status companion)", file=sys.stderr)
        return common.EXIT_FAILED
    print(f"go sent to {path}")
    return common.EXIT_OK


def _check(args: argparse.Namespace, config: Config) -> int:
    import asyncio
    import dataclasses

    from companion.launch.check import format_checks, run_checks

    results = asyncio.run(run_checks(config))
    if args.json:
        print(json.dumps([dataclasses.asdict(r) for r in results]))
    else:
        print(format_checks(results))
    return common.EXIT_OK if all(r.ok for r in results) else common.EXIT_FAILED
