"""PX4 parameters over MAVLink's parameter protocol, read by name from the companion.

PX4 puts every value into the float ``param_value`` of PARAM_VALUE *bytewise*: an INT32
parameter's four bytes are copied into the float, not converted
(``src/modules/mavlink/mavlink_parameters.cpp``, ``MavlinkParametersManager::send_param``:
``param_get(param, &msg.param_value)`` and ``param_type`` INT32 or REAL32), and its
AUTOPILOT_VERSION says so with ``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``
(``mavlink_main.cpp``, ``Mavlink::send_autopilot_capabilities``). Read as a plain float, an
INT32 of 3 is 4.2e-45; :func:`decode_value` turns it back into 3, :func:`encode_value` is the
inverse (the mock PX4 uses it to answer).

:class:`ParameterReader` asks for named parameters with PARAM_REQUEST_READ (``param_index``
-1: by name), re-asks those that have not come back every ``retry_interval_s``, and returns
what arrived within the timeout. It sends through the link owner's sender and never reads the
link itself: the owner of the receive loop (the :class:`~drivers.mavlink.autopilot.Autopilot`,
whose ``read_parameters`` delegates here) hands it every PARAM_VALUE through
:meth:`ParameterReader.on_param_value`.
"""

from __future__ import annotations

import asyncio
import math
import struct
from typing import Callable, Iterable

from drivers.clock import Clock
from drivers.mavlink.link import mavlink

#: PARAM_*.param_id is char[16], without a terminating NUL when all 16 are used.
PARAM_ID_LENGTH = 16

#: Little-endian layout of each MAV_PARAM_TYPE that fits the 4 bytes of ``param_value``;
#: a shorter type occupies the low bytes (MAVLink parameter protocol, bytewise encoding).
_LAYOUTS = {
    mavlink.MAV_PARAM_TYPE_UINT8: "<B",
    mavlink.MAV_PARAM_TYPE_INT8: "<b",
    mavlink.MAV_PARAM_TYPE_UINT16: "<H",
    mavlink.MAV_PARAM_TYPE_INT16: "<h",
    mavlink.MAV_PARAM_TYPE_UINT32: "<I",
    mavlink.MAV_PARAM_TYPE_INT32: "<i",
    mavlink.MAV_PARAM_TYPE_REAL32: "<f",
}


def _layout(param_type: int) -> str:
    try:
        return _LAYOUTS[param_type]
    except KeyError:
        raise ValueError(f"MAV_PARAM_TYPE {param_type} does not fit a 4-byte param_value "
                         "(PX4 sends only INT32 and REAL32)") from None


def encode_value(value: int | float, param_type: int) -> float:
    """``value`` as the ``param_value`` float that carries it bytewise. ValueError for a type
    that does not fit 4 bytes or a value out of the type's range."""
    layout = _layout(param_type)
    if layout != "<f" and (isinstance(value, bool) or not float(value).is_integer()):
        raise ValueError(f"MAV_PARAM_TYPE {param_type} holds integers, got {value!r}")
    try:
        raw = struct.pack(layout, value if layout == "<f" else int(value))
    except struct.error as error:
        raise ValueError(f"{value!r} does not fit MAV_PARAM_TYPE {param_type}: {error}") from None
    return struct.unpack("<f", raw.ljust(4, b"\0"))[0]


def decode_value(param_value: float, param_type: int) -> int | float:
    """The value a bytewise-encoded ``param_value`` carries: an int for the integer types, a
    float for REAL32. ValueError for a type that does not fit 4 bytes."""
    layout = _layout(param_type)
    raw = struct.pack("<f", param_value)
    return struct.unpack(layout, raw[:struct.calcsize(layout)])[0]


def check_name(name) -> str:
    """``name`` if it can be a parameter id (1 to 16 printable ASCII characters), else
    ValueError saying why."""
    if not isinstance(name, str) or not 1 <= len(name) <= PARAM_ID_LENGTH:
        raise ValueError(f"a PX4 parameter name is 1 to {PARAM_ID_LENGTH} characters, "
                         f"got {name!r}")
    if not (name.isascii() and name.isprintable()):
        raise ValueError(f"a PX4 parameter name is printable ASCII, got {name!r}")
    return name


class ParameterReader:
    """Reads named parameters of one MAVLink component (PX4's autopilot by default).

    ``send`` writes a message on the link: a :class:`~drivers.mavlink.link.MavlinkLink`'s
    ``send``, or the Autopilot's locked sender (pymavlink's sequence numbers are not
    thread-safe). Values are kept as they arrive, with their arrival time on ``clock``.
    """

    def __init__(self, send: Callable, clock: Clock, target_system: int = 1,
                 target_component: int = 1, *, retry_interval_s: float = 0.5):
        if not (math.isfinite(retry_interval_s) and retry_interval_s > 0.0):
            raise ValueError(f"retry_interval_s must be positive seconds, got "
                             f"{retry_interval_s!r}")
        self._send = send
        self._clock = clock
        self._target = (target_system, target_component)
        self.retry_interval_s = retry_interval_s
        #: name -> (value, arrival time): the newest PARAM_VALUE of each parameter.
        self.values: dict[str, tuple[int | float, float]] = {}
        self._waiters: list[asyncio.Future] = []

    def on_param_value(self, message, now: float | None = None) -> None:
        """Keep a PARAM_VALUE from the target (others are ignored); ValueError for a
        ``param_type`` that cannot be decoded."""
        if (message.get_srcSystem(), message.get_srcComponent()) != self._target:
            return
        value = decode_value(message.param_value, message.param_type)
        self.values[message.param_id] = (value, self._clock.now() if now is None else now)
        for waiter in self._waiters:
            if not waiter.done():
                waiter.set_result(None)
        self._waiters.clear()

    async def read(self, names: Iterable[str], timeout_s: float) -> dict[str, int | float]:
        """The values of ``names`` that arrive within ``timeout_s`` (seconds on the clock),
        in the order asked; a parameter the target does not answer for is absent. Only values
        that arrive after the call count. ValueError for a bad name or timeout."""
        wanted = list(dict.fromkeys(check_name(name) for name in names))
        if not (math.isfinite(timeout_s) and timeout_s > 0.0):
            raise ValueError(f"timeout_s must be positive seconds, got {timeout_s!r}")
        start = self._clock.now()
        deadline, next_request = start + timeout_s, -math.inf
        while True:
            found = {name: self.values[name][0] for name in wanted
                     if name in self.values and self.values[name][1] >= start}
            now = self._clock.now()
            missing = [name for name in wanted if name not in found]
            if not missing or now >= deadline:
                return found
            if now >= next_request:
                self._request(missing)
                next_request = now + self.retry_interval_s
            await self._next_value(until=min(next_request, deadline))

    def _request(self, names: list[str]) -> None:
        for name in names:
            self._send(mavlink.MAVLink_param_request_read_message(*self._target, name.encode(),
                                                                  -1))

    async def _next_value(self, until: float) -> None:
        """Return at the next PARAM_VALUE or at time ``until`` on the clock."""
        arrived = asyncio.get_running_loop().create_future()
        self._waiters.append(arrived)
        sleeper = asyncio.ensure_future(self._sleep_until(until))
        try:
            await asyncio.wait({arrived, sleeper}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            sleeper.cancel()
            if arrived in self._waiters:
                self._waiters.remove(arrived)

    async def _sleep_until(self, t: float) -> None:
        # measured when the task starts, not when it is made: a SimClock may have moved since
        await self._clock.sleep(t - self._clock.now())
