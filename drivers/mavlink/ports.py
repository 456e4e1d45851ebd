"""The serial ports a flight controller may be on, for ``companion devices``.

pyserial's ``list_ports`` finds USB adapters and flight controllers on USB (``ttyACM*``,
``ttyUSB*``, with their USB ids) and on-board UARTs it knows; the Jetson's own UARTs
(``ttyTHS*``: the Orin's 40-pin header and its carrier boards' TELEM connectors) are added
by name, since pyserial does not look for them.
"""

from __future__ import annotations

from pathlib import Path

from serial.tools import list_ports

from drivers.camera.base import DeviceInfo

#: Serial nodes pyserial does not enumerate but a companion's flight controller is often on.
EXTRA_PATTERNS = ("ttyTHS*",)
#: What a user sets: the MAVLink URL form and the baud rates PX4's TELEM ports are set to.
URL_HINT = "[mavlink] url = \"serial://{device}:921600\" (PX4: SER_TELn_BAUD)"


def list_serial_ports(dev: str = "/dev") -> list[DeviceInfo]:
    """Every serial port found, with pyserial's description and USB ids where it has them."""
    found = {port.device: _describe(port) for port in list_ports.comports()}
    for pattern in EXTRA_PATTERNS:
        for node in sorted(Path(dev).glob(pattern)):
            found.setdefault(str(node), "on-board UART")
    return [DeviceInfo("serial", device, description, (URL_HINT.format(device=device),))
            for device, description in sorted(found.items())]


def _describe(port) -> str:
    parts = [p for p in (port.description, port.manufacturer) if p and p != "n/a"]
    if port.vid is not None:
        parts.append(f"USB {port.vid:04x}:{port.pid:04x}")
    return ", ".join(parts) or "serial port"
