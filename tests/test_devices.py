"""`companion devices`: what this computer has, listed without a traceback whatever is missing."""

from __future__ import annotations

import json
import os
import sys

import pytest

from companion.cli import main
from drivers.camera.v4l2 import list_devices
from drivers.mavlink.ports import list_serial_ports


def test_devices_lists_every_kind_and_exits_0(capsys):
    assert main(["devices", "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert [section["heading"].split()[0] for section in listing] == [
        "V4L2", "RealSense", "OAK", "Serial"]
    for section in listing:
        assert section["error"] or isinstance(section["devices"], list)


def test_devices_prints_a_readable_listing(capsys):
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "V4L2 cameras ([camera] driver = \"v4l2\", [v4l2] device)" in out
    assert "Serial ports ([mavlink] url)" in out


def test_v4l2_listing_names_nodes_it_cannot_use(tmp_path):
    (tmp_path / "video0").write_bytes(b"")  # a node that answers no V4L2 ioctl
    (tmp_path / "ttyS0").write_bytes(b"")
    [device] = list_devices(str(tmp_path))
    assert device.address == str(tmp_path / "video0")
    assert device.description.startswith("not a V4L2 device")
    assert list_devices(str(tmp_path / "empty")) == []


def test_v4l2_listing_says_why_a_node_cannot_be_opened(tmp_path):
    node = tmp_path / "video3"
    node.write_bytes(b"")
    node.chmod(0)
    if os.access(node, os.R_OK):
        pytest.skip("running as root, which opens any node")
    [device] = list_devices(str(tmp_path))
    assert "cannot open" in device.description


def test_serial_listing_adds_the_jetson_uarts_with_the_url_to_use(tmp_path):
    (tmp_path / "ttyTHS1").write_bytes(b"")
    ports = {p.address: p for p in list_serial_ports(str(tmp_path))}
    jetson = ports[str(tmp_path / "ttyTHS1")]
    assert jetson.description == "on-board UART"
    assert jetson.modes == (f'[mavlink] url = "serial://{tmp_path}/ttyTHS1:921600" '
                            "(PX4: SER_TELn_BAUD)",)


class _LoadFails:
    """A meta path finder under which importing ``name`` fails as a wheel that misses a system
    library does: an ImportError from loading it, not a ModuleNotFoundError."""

    def __init__(self, name: str, message: str):
        self.name, self.message = name, message

    def find_spec(self, fullname, path=None, target=None):
        if fullname == self.name:
            raise ImportError(self.message)
        return None


def test_an_sdk_installed_but_not_loading_is_named_with_its_cause(monkeypatch, capsys):
    """pyrealsense2's wheel on a host without the system's libusb-1.0 (a fresh Debian): the
    listing gives the loader's own words, not "not installed", which would send the user to
    pip for nothing."""
    missing = "libusb-1.0.so.0: cannot open shared object file: No such file or directory"
    monkeypatch.delitem(sys.modules, "pyrealsense2", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_LoadFails("pyrealsense2", missing), *sys.meta_path])
    assert main(["devices", "--json"]) == 0
    realsense = next(section for section in json.loads(capsys.readouterr().out)
                     if section["heading"].startswith("RealSense"))
    assert realsense["error"] == f"pyrealsense2 is installed but does not load: {missing}"
