"""``companion devices``: the cameras and serial ports this computer has, to fill in a config."""

from __future__ import annotations

import argparse
import dataclasses
import json

from companion.cli import common
from companion.config import Config

#: (heading, module, function) of each kind of device, listed in this order.
SOURCES = (
    ("V4L2 cameras ([camera] driver = \"v4l2\", [v4l2] device)", "drivers.camera.v4l2",
     "list_devices"),
    ("RealSense cameras ([camera] driver = \"realsense\", [realsense] serial)",
     "drivers.camera.realsense", "list_devices"),
    ("OAK cameras ([camera] driver = \"oak\", [oak] device_id)", "drivers.camera.oak",
     "list_devices"),
    ("Serial ports ([mavlink] url)", "drivers.mavlink.ports", "list_serial_ports"),
)


def add_commands(commands: argparse._SubParsersAction) -> None:
    devices = commands.add_parser(
        "devices", parents=[common.overrides_parser()],
        help="list the cameras and serial ports found, with what each supports",
        description="List V4L2 cameras, RealSense and OAK devices (when their extras are "
                    "installed) and serial ports, with the config keys that select each. "
                    "Always exits 0: finding nothing is an answer.")
    common.add_json_flag(devices, instead_of="the listing")
    devices.set_defaults(command=_devices, config_path=None)


def _devices(args: argparse.Namespace, config: Config) -> int:
    listing = [_list(heading, module, function) for heading, module, function in SOURCES]
    if args.json:
        print(json.dumps(listing))
        return common.EXIT_OK
    for section in listing:
        print(section["heading"])
        if section["error"]:
            print(f"  ({section['error']})")
        elif not section["devices"]:
            print("  none found")
        for device in section["devices"]:
            print(f"  {device['address']}  {device['description']}")
            for mode in device["modes"]:
                print(f"      {mode}")
    return common.EXIT_OK


def _list(heading: str, module: str, function: str) -> dict:
    """One kind's devices, or the one-line reason it cannot be listed (an SDK not installed,
    a daemon not answering); never an exception."""
    import importlib

    from drivers.camera.base import CameraError

    try:
        found = getattr(importlib.import_module(module), function)()
        return {"heading": heading, "devices": [dataclasses.asdict(d) for d in found],
                "error": ""}
    except (CameraError, OSError, RuntimeError) as error:
        return {"heading": heading, "devices": [], "error": str(error)}
