"""``companion fly --check``: every preflight check on the real devices, then exit, disarmed.

Opens what ``companion fly`` opens (the depth network, the camera with its calibration, the
link to PX4 with its signing key), watches them for a few seconds, reads the PX4 parameters
docs/operations.md requires, and returns one :class:`CheckResult` per check. It never arms
and never sends a setpoint: an operator runs it on the bench, propellers off or on, before the
first flight and after any change.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import Callable

from autonomy.depth.network import DepthNetwork, NetworkError
from drivers.camera.base import CameraError
from drivers.camera.calibration import resolve
from drivers.camera.drivers import open_camera
from drivers.clock import MonotonicClock
from drivers.mavlink.autopilot import Autopilot
from drivers.mavlink.signing import SigningKeyError

#: A measured rate at least this fraction of the configured one passes.
RATE_FRACTION = 0.9
#: Longest wait for PX4's first HEARTBEAT, seconds.
LINK_WAIT_S = 5.0
#: Longest wait for the parameters, seconds.
PARAMETER_WAIT_S = 5.0


@dataclass(frozen=True)
class CheckResult:
    name: str
    ok: bool
    detail: str


@dataclass(frozen=True)
class ParameterRule:
    """What docs/operations.md, "PX4 parameters", asks of one parameter."""

    holds: Callable[[float], bool]
    expected: str


PX4_PARAMETERS = {
    "EKF2_EV_CTRL": ParameterRule(lambda v: int(v) != 0,
                                  "non-zero, so EKF2 fuses the companion's odometry"),
    "EKF2_EV_QMIN": ParameterRule(lambda v: int(v) >= 1,
                                  "at least 1, so odometry the companion marks failed "
                                  "(quality -1: VINS lost or blind) is not fused"),
    "EKF2_HGT_REF": ParameterRule(lambda v: int(v) == 3, "3 (Vision): height from the odometry"),
    "COM_OF_LOSS_T": ParameterRule(lambda v: 0.0 < v <= 1.0,
                                   "at most 1 s, so a dead companion is noticed quickly"),
    # 4 Land mode, 5 Hold mode: unchanged from the COM_OBL_ACT era to now (commander_params.c)
    "COM_OBL_RC_ACT": ParameterRule(lambda v: int(v) in (4, 5), "4 (Land) or 5 (Hold)"),
}


async def run_checks(config, *, listen_s: float = 3.0) -> list[CheckResult]:
    """All the checks, each independent of the others' outcome."""
    clock = MonotonicClock()
    results = [await asyncio.to_thread(_check_network, config)]
    results += await _check_camera(config, clock, listen_s)
    results += await _check_link(config, clock, listen_s)
    return results


def format_checks(results: list[CheckResult]) -> str:
    width = max(len(r.name) for r in results)
    return "\n".join(f"{'PASS' if r.ok else 'FAIL'}  {r.name:<{width}}  {r.detail}"
                     for r in results)


def _check_network(config) -> CheckResult:
    if not config.depth_network.model:
        return CheckResult("depth network", False, "[depth_network] model is empty")
    try:
        network = DepthNetwork.open(config.depth_network,
                                    (config.camera.height, config.camera.width))
    except (NetworkError, ValueError, OSError) as error:
        return CheckResult("depth network", False, str(error))
    return CheckResult("depth network", True, f"{config.depth_network.model} on "
                                              f"{network.provider}")


async def _check_camera(config, clock, listen_s: float) -> list[CheckResult]:
    camera = config.camera
    try:
        async with open_camera(config, clock) as driver:
            calibration = resolve(camera, getattr(driver, "camera_model", None))
            frames = await _count_frames(driver, clock, listen_s)
            lost = getattr(driver, "lost", 0)
    except CameraError as error:
        return [CheckResult("camera", False, str(error))]
    rate = frames / listen_s
    lens = calibration.model
    return [
        CheckResult("camera", True, f"{driver.name}: {camera.width}x{camera.height}"),
        CheckResult("camera rate", rate >= RATE_FRACTION * camera.rate_hz and lost == 0,
                    f"{rate:.1f} Hz measured, {camera.rate_hz:g} Hz configured, "
                    f"{lost} frames lost by the device"),
        CheckResult("camera calibration", True,
                    f"{calibration.source}: {lens.distortion} lens, fx {lens.pinhole.fx:.1f}, "
                    f"time offset {calibration.time_offset_s * 1e3:.1f} ms"),
        _exposure(driver, config),
    ]


async def _count_frames(driver, clock, listen_s: float) -> int:
    end, frames = clock.now() + listen_s, 0
    while clock.now() < end:
        await driver.next_frame()
        frames += 1
    return frames


def _exposure(driver, config) -> CheckResult:
    exposure = getattr(driver, "exposure_us", None)
    if exposure is None:
        return CheckResult("camera exposure", True, f"not reported by the {config.camera.driver} "
                                                    "driver")
    period_us = 1e6 / config.camera.rate_hz
    return CheckResult("camera exposure", exposure < period_us,
                       f"at most {exposure:.0f} us (a frame lasts {period_us:.0f} us)")


async def _check_link(config, clock, listen_s: float) -> list[CheckResult]:
    try:
        autopilot = Autopilot.open(config.mavlink, clock)
    except SigningKeyError as error:
        return [CheckResult("MAVLink signing", False, str(error))]
    except (OSError, ValueError) as error:
        return [CheckResult("MAVLink link", False, str(error))]
    task = asyncio.create_task(autopilot.run())
    try:
        if not await _until(lambda: autopilot.connected, LINK_WAIT_S):
            return [CheckResult("MAVLink link", False,
                                f"no HEARTBEAT from PX4 on {config.mavlink.url} in "
                                f"{LINK_WAIT_S:g} s: {autopilot.link_problem}"),
                    _signing(autopilot)]
        await asyncio.sleep(listen_s)
        return [CheckResult("MAVLink link", True, f"PX4 on {config.mavlink.url}"),
                _signing(autopilot),
                CheckResult("TIMESYNC", autopilot.time_synced,
                            "answered" if autopilot.time_synced else "no answer from PX4"),
                _imu_rate(autopilot, config),
                *_rc_switch(autopilot, config),
                *await _parameters(autopilot)]
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        autopilot.close()


def _signing(autopilot) -> CheckResult:
    """Signing must be on (else any sender can command the vehicle, the operator's go
    included) and PX4's messages must verify with the key."""
    signing = autopilot.signing
    if not signing["on"]:
        return CheckResult("MAVLink signing", False,
                           "off: whoever can send MAVLink to the vehicle can command it, the "
                           "operator's go included; set [mavlink] signing_key_file "
                           "(docs/operations.md, MAVLink signing)")
    ignored = (f"{signing['unsigned']} unsigned and {signing['bad_signature']} badly signed "
               "messages ignored")
    if not autopilot.connected:
        return CheckResult("MAVLink signing", False, f"on, but nothing from PX4 verified with "
                                                     f"the key; {ignored}")
    return CheckResult("MAVLink signing", True, f"on: PX4's messages verify with the key; "
                                                f"{ignored}")


def _imu_rate(autopilot, config) -> CheckResult:
    wanted = config.mavlink.imu_rate_hz
    return CheckResult("IMU rate", autopilot.imu_rate_hz >= RATE_FRACTION * wanted,
                       f"{autopilot.imu_rate_hz:.0f} Hz HIGHRES_IMU, {wanted:g} Hz asked")


def _rc_switch(autopilot, config) -> list[CheckResult]:
    channel = config.go.rc_channel
    if not channel:
        return []
    values = autopilot.rc_channels_us
    if values is None or len(values) < channel:
        return [CheckResult("RC go switch", False,
                            f"no RC_CHANNELS with channel {channel} from PX4")]
    pulse = values[channel - 1]
    if pulse is None:
        return [CheckResult("RC go switch", False,
                            f"channel {channel} reported unused by the receiver")]
    return [CheckResult("RC go switch", True, f"channel {channel} at {pulse} us")]


async def _parameters(autopilot) -> list[CheckResult]:
    values = await autopilot.read_parameters(tuple(PX4_PARAMETERS), PARAMETER_WAIT_S)
    results = []
    for name, rule in PX4_PARAMETERS.items():
        value = values.get(name)
        if value is None:
            results.append(CheckResult(name, False, "not read from PX4"))
        else:
            results.append(CheckResult(name, rule.holds(value), f"{value:g}; {rule.expected}"))
    return results


async def _until(condition, timeout_s: float) -> bool:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not condition():
        if loop.time() >= end:
            return False
        await asyncio.sleep(0.02)
    return True
