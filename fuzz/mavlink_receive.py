#!/usr/bin/env python3
"""Fuzz the companion's MAVLink receive path: a hostile PX4 against a real autopilot driver.

    python fuzz/mavlink_receive.py [libFuzzer options] [CORPUS_DIR ...]

Each input is one session. A real :class:`~drivers.mavlink.autopilot.Autopilot` opens a real
link (``pty``: a pseudo-terminal, so the bytes go through the driver's own stream reader,
pymavlink's parser, the dispatch and every handler) and runs its own poll task on a
``SimClock``. On the terminal's other side a hostile PX4 reads what the companion sends and
writes what the input says, step by step:

- a message the driver handles (HEARTBEAT, HIGHRES_IMU, TIMESYNC, COMMAND_ACK, ODOMETRY,
  PARAM_VALUE, RC_CHANNELS, STATUSTEXT, ...), a ground station's COMMAND_LONG/COMMAND_INT to
  the companion (the operator's go), or one it ignores; every field drawn from the input:
  NaN, ±inf, float32 extremes, denormals, integer extremes, PX4's clock now, any value;
  from PX4's ids or another's, the next sequence number or any, sometimes a byte flipped;
- an answer to the companion's latest TIMESYNC request or command (so the time offset gets
  an estimate and IMU samples flow), with a hostile or a plausible value;
- raw bytes, or an unknown message id;
- a wait (PX4 silent: link loss and reconnection).

The invariant, checked after every step: the poll task never ends and nothing escapes it;
every IMU sample taken is finite (time, gyro, accel, three of each) and later than the one
before, its pressure None or one a barometer reads; the TIMESYNC offset and round trip are
None or finite; the vehicle state is None or finite with a unit quaternion; the measured IMU
rate, the last IMU time and home are finite; the RC channels are at most 18, each a pulse
width under 65535 or None (the value 65535 says "unused"). Every handler error must be the one
the driver documents (a PARAM_VALUE of a type that does not fit 4 bytes).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import re
import struct
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from fuzz import harness  # noqa: E402

if __name__ == "__main__":
    harness.require_atheris()

with harness.instrumented(__name__ == "__main__"):
    import numpy as np

    from autonomy.messages import PRESSURE_RANGE_PA
    from drivers.clock import SimClock
    from drivers.mavlink.autopilot import Autopilot, MavlinkOptions
    from drivers.mavlink.link import mavlink

TARGET = "mavlink_receive"
#: Steps of one session at most.
MAX_STEPS = 64
#: PX4's ids and the companion's (MavlinkOptions' defaults).
PX4_IDS, COMPANION_IDS = (1, 1), (1, 191)
#: PX4's boot time is the companion's clock less this (what TIMESYNC must find).
TRUE_OFFSET_S = 1000.0
#: What a hostile PX4 sends: every message the driver handles, commands addressed to the
#: companion, and a few it ignores.
MESSAGES = {name: mavlink.mavlink_map[getattr(mavlink, f"MAVLINK_MSG_ID_{name}")] for name in (
    "HEARTBEAT", "HIGHRES_IMU", "TIMESYNC", "COMMAND_ACK", "EXTENDED_SYS_STATE", "ODOMETRY",
    "LOCAL_POSITION_NED", "ATTITUDE_QUATERNION", "HOME_POSITION", "STATUSTEXT", "RC_CHANNELS",
    "PARAM_VALUE", "COMMAND_LONG", "COMMAND_INT", "SYS_STATUS", "ATTITUDE")}
_CLASSES = list(MESSAGES.values())
#: Edge values of a float field (float32 on the wire unless the field is a double).
FLOATS = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, -1.0, 0.5, 9.80665, 3.4028235e38,
          -3.4028235e38, 1.4e-45, 1e30)
#: struct codes of integer fields: (smallest, largest).
INTS = {"b": (-2**7, 2**7 - 1), "B": (0, 2**8 - 1), "h": (-2**15, 2**15 - 1),
        "H": (0, 2**16 - 1), "i": (-2**31, 2**31 - 1), "I": (0, 2**32 - 1),
        "q": (-2**63, 2**63 - 1), "Q": (0, 2**64 - 1)}
#: Time fields and their units per second: "now" on PX4's clock is a value they may take.
CLOCK_FIELDS = {"time_usec": 1e6, "time_boot_ms": 1e3, "tc1": 1e9, "ts1": 1e9}
#: Id fields, which take the ids of the two ends more often than any other value.
ID_FIELDS = {"target_system": (0, 1, 42), "target_component": (0, 1, 191)}
#: A wait lasts up to this long, in steps no longer than WAIT_STEP_S (under the driver's
#: DEAF_POLL_GAP_S, so that a wait is PX4's silence and not a stalled loop).
MAX_WAIT_S, WAIT_STEP_S = 2.0, 0.05


class Px4:
    """The hostile PX4 on the terminal's other side: writes frames, reads what the companion
    sends (its TIMESYNC requests and commands, to answer them)."""

    def __init__(self, path: str, clock: SimClock, fdp):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self.clock, self.fdp = clock, fdp
        self.parser = mavlink.MAVLink(None)
        self.seq = 0
        self.timesync_ts1: int | None = None  # the companion's latest request
        self.command: int | None = None  # the companion's latest COMMAND_LONG

    def close(self) -> None:
        os.close(self.fd)

    def write(self, data: bytes) -> None:
        """Bytes onto the wire; what the terminal cannot take now is lost, as on a wire."""
        with contextlib.suppress(BlockingIOError):
            os.write(self.fd, data)

    def read(self) -> None:
        """Take in what the companion sent since the last read."""
        while True:
            try:
                data = os.read(self.fd, 4096)
            except BlockingIOError:
                return
            for message in self.parser.parse_buffer(data) or ():
                if message.get_type() == "TIMESYNC" and message.tc1 == 0:
                    self.timesync_ts1 = message.ts1
                elif message.get_type() == "COMMAND_LONG":
                    self.command = message.command

    def send(self, cls, fixed: dict | None = None, msgid: int | None = None) -> None:
        """A message of class ``cls``, its fields drawn from the input except ``fixed``."""
        fdp = self.fdp
        payload = _payload(fdp, cls, fixed or {}, self.clock.now() - TRUE_OFFSET_S)
        if fdp.ConsumeBool():
            self.seq = (self.seq + 1) % 256
        else:
            self.seq = fdp.ConsumeIntInRange(0, 255)
        source = PX4_IDS if fdp.ConsumeIntInRange(0, 7) else (fdp.ConsumeIntInRange(0, 255),
                                                             fdp.ConsumeIntInRange(0, 255))
        data = bytearray(_frame(cls.id if msgid is None else msgid, cls.crc_extra, payload,
                                self.seq, source))
        if fdp.ConsumeIntInRange(0, 7) == 0:
            data[fdp.ConsumeIntInRange(0, len(data) - 1)] ^= fdp.ConsumeIntInRange(1, 255)
        self.write(bytes(data))


def _frame(msgid: int, crc_extra: int, payload: bytes, seq: int, source) -> bytes:
    """A MAVLink 2 frame, its payload's trailing zeros cut as the spec says."""
    payload = payload.rstrip(b"\0") or b"\0"
    header = struct.pack("<BBBBBBHB", len(payload), 0, 0, seq, *source, msgid & 0xFFFF,
                         msgid >> 16)
    crc = mavlink.x25crc(header + payload + bytes([crc_extra])).crc
    return b"\xfd" + header + payload + struct.pack("<H", crc)


def _payload(fdp, cls, fixed: dict, px4_now: float) -> bytes:
    """``cls``'s wire payload, every field but ``fixed`` drawn from the input: either all of
    them hostile, or all plausible but one (so that the message passes the driver's first
    checks and the hostile value reaches the code behind them)."""
    items = re.findall(r"(\d*)([a-zA-Z])", cls.unpacker.format)
    fields = list(zip(cls.ordered_fieldnames, items))
    hostile = fdp.ConsumeIntInRange(0, len(fields)) if fdp.ConsumeBool() else None
    parts = []
    for index, (name, (count, code)) in enumerate(fields):
        count = int(count or 1)
        if name in fixed:
            parts.append(struct.pack("<" + code, fixed[name]))
        elif code == "s":
            parts.append(fdp.ConsumeBytes(count).ljust(count, b"\0"))
        elif hostile is None or index == hostile:
            parts += [_hostile(fdp, code) for _ in range(count)]
        else:
            parts.append(_plausible(fdp, cls, name, count, code, px4_now))
    return b"".join(parts)


def _hostile(fdp, code: str) -> bytes:
    """One value of struct type ``code``, packed: an edge value (NaN, ±inf, float32's
    extremes, a denormal; an integer type's extremes, 0) or any value of the type."""
    if code in "fd":
        pick = fdp.ConsumeIntInRange(0, len(FLOATS))
        if pick < len(FLOATS):
            return struct.pack("<" + code, FLOATS[pick])
        size = struct.calcsize(code)
        return fdp.ConsumeBytes(size).ljust(size, b"\0")
    low, high = INTS[code]
    value = fdp.PickValueInList([low, high, 0])
    pick = fdp.ConsumeIntInRange(0, 3)
    if pick:  # a small value (an enum, an id, a count), a byte, any value of the type
        value = fdp.ConsumeIntInRange(*((0, 20), (0, 255), (low, high))[pick - 1])
    return struct.pack("<" + code, min(value, high))


def _plausible(fdp, cls, name: str, count: int, code: str, px4_now: float) -> bytes:
    """``count`` values PX4 could send in field ``name``, packed: its clock now in a time
    field, the ends' ids, a value of the field's enum, a unit quaternion, small numbers."""
    if name == "q":
        return struct.pack("<4f", *_unit_quaternion(fdp))
    enum = mavlink.enums.get(cls.fieldenums_by_name.get(name))
    values = []
    for _ in range(count):
        if code in "fd":
            values.append(fdp.ConsumeFloatInRange(-20.0, 20.0))
        elif name in CLOCK_FIELDS:
            values.append(round(px4_now * CLOCK_FIELDS[name]) + fdp.ConsumeIntInRange(-3, 3))
        elif name in ID_FIELDS:
            values.append(fdp.PickValueInList(list(ID_FIELDS[name])))
        else:
            values.append(fdp.PickValueInList(list(enum)) if enum else
                          fdp.ConsumeIntInRange(0, 20))
    low, high = INTS.get(code, (-math.inf, math.inf))
    return struct.pack(f"<{count}{code}", *(min(max(v, low), high) for v in values))


def _unit_quaternion(fdp) -> np.ndarray:
    """A unit quaternion (float32 on the wire, as PX4 sends it) drawn from the input."""
    q = np.array([fdp.ConsumeFloatInRange(-1.0, 1.0) for _ in range(4)]) + (1e-3, 0, 0, 0)
    return q / np.linalg.norm(q)


# ---------------------------------------------------------------- what a step does


def _send_message(fdp, px4: Px4) -> None:
    px4.send(_CLASSES[fdp.ConsumeIntInRange(0, len(_CLASSES) - 1)])


def _answer_timesync(fdp, px4: Px4) -> None:
    """PX4's answer to the latest request: its clock now, or any value."""
    if px4.timesync_ts1 is not None:
        fixed = {"ts1": px4.timesync_ts1}
        if fdp.ConsumeBool():
            fixed["tc1"] = round((px4.clock.now() - TRUE_OFFSET_S) * 1e9)
        px4.send(MESSAGES["TIMESYNC"], fixed)


def _answer_command(fdp, px4: Px4) -> None:
    if px4.command is not None:
        px4.send(MESSAGES["COMMAND_ACK"], {"command": px4.command})


def _send_imu_burst(fdp, px4: Px4) -> None:
    """Up to 20 HIGHRES_IMU at once (a link that delivers them in bursts), PX4 times one
    period apart from now (or any values), every other field drawn."""
    start = round((px4.clock.now() - TRUE_OFFSET_S) * 1e6)
    period = fdp.PickValueInList([5000, 4000, 1, fdp.ConsumeIntInRange(0, 10**6)])
    for k in range(fdp.ConsumeIntInRange(1, 20)):
        fixed = {"time_usec": max(0, start + k * period)} if fdp.ConsumeIntInRange(0, 7) else {}
        px4.send(MESSAGES["HIGHRES_IMU"], fixed)


def _send_raw(fdp, px4: Px4) -> None:
    px4.write(fdp.ConsumeBytes(fdp.ConsumeIntInRange(1, 300)))


def _send_unknown(fdp, px4: Px4) -> None:
    px4.send(MESSAGES["ATTITUDE"], msgid=fdp.ConsumeIntInRange(0, 2**24 - 1))


STEPS = (_send_message, _send_message, _send_message, _answer_timesync, _answer_command,
         _send_imu_burst, _send_raw, _send_unknown)


async def _advance(clock: SimClock, seconds: float) -> None:
    """Let ``seconds`` pass on the clock, the driver polling at least every WAIT_STEP_S."""
    end = clock.now() + seconds
    while True:
        clock.advance_to(min(end, clock.now() + WAIT_STEP_S))
        for _ in range(3):  # the poll task wakes, polls and sleeps again
            await asyncio.sleep(0)
        if clock.now() >= end:
            return


# ---------------------------------------------------------------- the invariant


class HandlerErrors(logging.Handler):
    """Collects the driver's "ignored MESSAGE: Error: text" warnings."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.found: list[tuple] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.msg.startswith("ignored %s"):
            self.found.append(record.args)


class Invariant:
    """What must hold of the driver after every step (module docstring)."""

    def __init__(self, autopilot: Autopilot, task: asyncio.Task, errors: HandlerErrors):
        self.autopilot, self.task, self.errors = autopilot, task, errors
        self.last_imu_t = -math.inf

    def check(self) -> None:
        if self.task.done():
            self.task.result()  # raises what escaped
            raise AssertionError("the poll task returned")
        autopilot = self.autopilot
        for sample in autopilot.take_imu():
            self._check_sample(sample)
        for name, value in (("timesync offset", autopilot.timesync.offset),
                            ("timesync rtt", autopilot.timesync.rtt),
                            ("last IMU time", autopilot.last_imu_t),
                            ("home altitude", autopilot.home_altitude_amsl)):
            assert value is None or math.isfinite(value), f"{name} is {value}"
        assert math.isfinite(autopilot.imu_rate_hz) and autopilot.imu_rate_hz >= 0.0
        assert autopilot.home_position_L is None or np.isfinite(autopilot.home_position_L).all()
        self._check_state(autopilot.state)
        self._check_rc(autopilot.rc_channels_us)
        for args in self.errors.found:
            assert args[:2] == ("PARAM_VALUE", "ValueError"), f"handler error {args}"

    def _check_sample(self, sample) -> None:
        assert math.isfinite(sample.t), f"IMU sample at t={sample.t}"
        assert sample.t > self.last_imu_t, f"IMU sample at {sample.t} after {self.last_imu_t}"
        for vector in (sample.gyro, sample.accel):
            assert vector.shape == (3,) and np.isfinite(vector).all(), f"IMU sample {sample}"
        low, high = PRESSURE_RANGE_PA
        assert sample.pressure_pa is None or low <= sample.pressure_pa <= high, \
            f"IMU sample {sample}"
        self.last_imu_t = sample.t

    @staticmethod
    def _check_state(state) -> None:
        if state is None:
            return
        assert math.isfinite(state.t), f"state at t={state.t}"
        for vector in (state.position_L, state.q_L_B):
            assert np.isfinite(vector).all(), f"state {state}"
        assert abs(np.linalg.norm(state.q_L_B) - 1.0) < 1e-6, f"state quaternion {state.q_L_B}"

    @staticmethod
    def _check_rc(channels) -> None:
        if channels is None:
            return
        assert len(channels) <= 18 and all(c is None or 0 <= c < 2**16 - 1
                                           for c in channels), channels


# ---------------------------------------------------------------- one session


async def _session(data: bytes) -> list[str]:
    fdp = harness.atheris.FuzzedDataProvider(data)
    clock = SimClock(TRUE_OFFSET_S + fdp.ConsumeIntInRange(0, 100))
    autopilot = Autopilot.open(MavlinkOptions(url="pty"), clock)
    go = fdp.ConsumeBool()
    autopilot.on_go = lambda source: go
    px4 = Px4(autopilot.link.pty_path, clock, fdp)
    errors = HandlerErrors()
    logging.getLogger("drivers.mavlink.autopilot").addHandler(errors)
    task = asyncio.ensure_future(autopilot.run())
    invariant = Invariant(autopilot, task, errors)
    try:
        for _ in range(MAX_STEPS):
            if not fdp.remaining_bytes():
                break
            pick = fdp.ConsumeIntInRange(0, len(STEPS))
            if pick < len(STEPS):
                STEPS[pick](fdp, px4)
                await _advance(clock, autopilot.options.poll_interval_s)
            else:
                await _advance(clock, fdp.ConsumeFloatInRange(0.0, MAX_WAIT_S))
            px4.read()
            invariant.check()
        return [f"{key}={value}" for key, value in sorted(autopilot.stats().items())]
    finally:
        logging.getLogger("drivers.mavlink.autopilot").removeHandler(errors)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        autopilot.close()
        px4.close()


_LOOP = asyncio.new_event_loop()


def run(data: bytes) -> list[str]:
    """One session driven by ``data``, checking the invariant after every step (module
    docstring); what the driver counted: its ``stats()``, as ``name=count``."""
    return _LOOP.run_until_complete(_session(data))


def test_one_input(data: bytes) -> None:
    """libFuzzer's entry point: :func:`run`."""
    run(data)


if __name__ == "__main__":
    harness.fuzz(test_one_input)
