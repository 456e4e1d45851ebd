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
        description="Connect to the flight controller ([mavlink] url), the camera ([v4l2]) and "
                    "the depth network ([depth_network] model), then fly the mission: "
                    "[flight] waypoints, or --goal. Stops, holds and lands on any failure and "
                    "on SIGTERM. See docs/operations.md.")
    fly.add_argument("--goal", dest="goals", type=common.point, action="append", default=[],
                     metavar="X,Y,Z",
                     help="waypoint in metres in PX4's local frame (x east, y north, z up); "
                          "repeatable, the last is the goal; replaces [flight] waypoints")
    common.add_json_flag(fly, instead_of="the summary table")
    fly.set_defaults(command=_fly)


def _fly(args: argparse.Namespace, config: Config) -> int:
    from autonomy.depth.network import NetworkError
    from companion.launch import real
    from companion.flight.app import format_flight
    from drivers.camera.v4l2 import CameraError

    waypoints = args.goals or config.flight.waypoint_points()
    try:
        summary = real.run(config, waypoints)
    except (real.FlyError, NetworkError, CameraError, ValueError, OSError) as error:
        print(f"fly: {error}", file=sys.stderr)
        return common.EXIT_FAILED
    print(json.dumps(summary) if args.json else format_flight(summary))
    return common.EXIT_OK if summary["final_state"] == "landed" and summary["reached_goal"] \
        else common.EXIT_FAILED
