"""A mock PX4 flight controller around the simulated quadrotor, speaking real MAVLink 2.

The flight-controller side of the link, close enough to PX4 (v1.14+) that MAVSDK, QGroundControl
or our own companion driver cannot tell the difference for what they use: heartbeat and
status streams (PX4's Onboard stream set, ATTITUDE and RC_CHANNELS included), the health and
armability bits of SYS_STATUS, commands with COMMAND_ACK, message intervals, HIGHRES_IMU at up
to the physics rate, a stand-in state estimate, TIMESYNC, offboard control with PX4's entry and
loss rules, take-off, land and hold, the parameter protocol over a table of the parameters the
mock honours, MAVLink 2 signing with PX4's key provisioning (SETUP_SIGNING). Each rule names
the PX4 source file it follows.

It never blocks: :meth:`MockPx4.update` is called once per physics tick with the IMU sample
of the step that just ended; it reads every pending byte, applies commands to the vehicle
and sends whatever streams are due at that time. Time is the simulator's (seconds since the
mock "booted"); PX4 boot time on the wire is that in µs/ms, as PX4 stamps ``hrt_absolute_time``.

Frames: the vehicle lives in world ENU with an FLU body; everything on the wire is local NED
and body FRD (PX4's), converted by :mod:`drivers.mavlink.frames`.

Ground truth goes to the stand-in estimator only: what leaves the mock is that estimate
(ground truth plus white noise, or shifted onto the companion's external-vision ODOMETRY while
it arrives), and IMU samples from the IMU model, as PX4 SITL's simulated sensors would give.
"""

from __future__ import annotations

import logging
import math
import struct
import zlib
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from autonomy.geometry import GRAVITY, quat_multiply, quat_to_rot, rot_to_quat, so3_exp, yaw_of
from autonomy.options import option, validate
from drivers.mavlink import px4_protocol
from drivers.mavlink.frames import (enu_to_ned, flu_to_frd, ned_to_enu,
                                    quat_enu_flu_to_ned_frd)
from drivers.mavlink.link import MavlinkLink, mavlink
from drivers.mavlink.parameters import decode_value, encode_value
from drivers.mavlink.signing import check_key_options, load_key
from drivers.sim.baro import AirData
from drivers.sim.quadrotor import ControlTarget, Quadrotor
from drivers.sim.trajectory import AxisState, VelocitySmoothing, max_speed_from_distance

log = logging.getLogger(__name__)

#: PX4 SITL's default home (the PX4 "Zurich" origin), degrees and metres AMSL.
HOME_LATITUDE_DEG, HOME_LONGITUDE_DEG, HOME_ALTITUDE_M = 47.397742, 8.545594, 488.0

#: Default stream rates in Hz before any MAV_CMD_SET_MESSAGE_INTERVAL: those of PX4's
#: Onboard MAVLink mode (MAV_X_MODE = Onboard, what a companion's link runs), for the messages
#: the mock has (mavlink_main.cpp, Mavlink::configure_streams_to_default,
#: MAVLINK_MODE_ONBOARD). HEARTBEAT is sent at 1 Hz whatever the mode.
DEFAULT_STREAM_RATES_HZ = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: 50.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 100.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 30.0,
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS: 20.0,
    mavlink.MAVLINK_MSG_ID_TIMESYNC: 10.0,
}

#: Seconds a rebooting flight controller is silent before it streams again: about what a
#: Pixracer (STM32F4) takes from reset through NuttX and PX4's start scripts to MAVLink.
BOOT_DURATION_S = 3.0

#: HIGHRES_IMU.fields_updated: xacc..zgyro (bits 0-5), always; abs_pressure, pressure_alt and
#: temperature (bits 9, 11, 12) when PX4 published air data since the last message
#: (src/modules/mavlink/streams/HIGHRES_IMU.hpp, ``_air_data_sub.update``).
HIGHRES_IMU_FIELDS = 0b111111
HIGHRES_IMU_AIR_DATA_FIELDS = (1 << 9) | (1 << 11) | (1 << 12)

#: PX4's AUTOPILOT_VERSION.capabilities (mavlink_main.cpp, send_autopilot_capabilities) less
#: what the mock does not serve (FTP, flight termination, fence and rally missions).
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2)

#: PX4 v1.15.0 as AUTOPILOT_VERSION.flight_sw_version packs it (major, minor, patch, type=255).
FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255

#: External-vision ODOMETRY older than this no longer feeds the estimate.
EXTERNAL_VISION_TIMEOUT = 0.5

#: The RC receiver the mock simulates: 16 channels (S.Bus, CRSF), centred until a test moves
#: them, full signal (RC_INPUT_RSSI_MAX, drivers/drv_rc_input.h). PX4 accepts pulses of
#: RC_INPUT_LOWEST_MIN_US..RC_INPUT_HIGHEST_MAX_US and sends unused channels as UINT16_MAX.
RC_CHANNEL_COUNT, RC_CHANNEL_CENTRE_US, RC_RSSI = 16, 1500, 100
RC_PULSE_RANGE_US = (500, 2500)
RC_CHANNELS_MAX = 18
RC_CHANNEL_UNUSED = 65535

#: The mock's health components (PX4's health_component_t) as SYS_STATUS bits, with whether
#: the mock has each: what MavlinkStreamSysStatus::send fills with fillOutComponent
#: (src/modules/mavlink/streams/SYS_STATUS.hpp, v1.14-v1.15).
SYS_STATUS_COMPONENTS = {
    mavlink.MAV_SYS_STATUS_SENSOR_BATTERY: True,
    mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS: False,
    mavlink.MAV_SYS_STATUS_OBSTACLE_AVOIDANCE: False,
    mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL: True,
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO: True,
    mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG: False,
    mavlink.MAV_SYS_STATUS_SENSOR_GPS: False,
    mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER: True,
    mavlink.MAV_SYS_STATUS_AHRS: True,  # local_position_estimate
    mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE: False,
    mavlink.MAV_SYS_STATUS_SENSOR_DIFFERENTIAL_PRESSURE: False,
}
#: ... and those of the *_extended fields (MAV_SYS_STATUS_SENSOR_EXTENDED): the parachute.
SYS_STATUS_EXTENDED_COMPONENTS = {mavlink.MAV_SYS_STATUS_RECOVERY_SYSTEM: False}

#: COM_OBL_RC_ACT values the mock flies (commander_params.c: 4 Land mode, 5 Hold mode).
OFFBOARD_LOSS_MODES = {4: px4_protocol.AUTO_LAND, 5: px4_protocol.AUTO_LOITER}
#: Px4Options.offboard_loss_action as COM_OBL_RC_ACT.
OFFBOARD_LOSS_ACTION_VALUES = {"hold": 5, "land": 4}
OFFBOARD_LOSS_ACTIONS = tuple(OFFBOARD_LOSS_ACTION_VALUES)

#: The parameters the mock serves, all INT32 or REAL32 as in PX4. Those the mock honours:
#: COM_OF_LOSS_T, COM_OBL_RC_ACT, COM_DISARM_LAND, MIS_TAKEOFF_ALT, MPC_TKO_SPEED,
#: MPC_TKO_RAMP_T, MPC_ACC_UP_MAX, MPC_JERK_AUTO, MPC_LAND_SPEED, EKF2_EV_CTRL (bits 0 and 1:
#: horizontal and vertical vision position), EKF2_EV_QMIN (odometry of a lower quality is not
#: fused); the others are what docs/operations.md asks an operator to set, held at a correctly
#: configured vehicle's values, for `companion fly --check` to read. MAV_SYS_ID and MAV_COMP_ID
#: are read once at boot, as PX4 reads them (mavlink_main.cpp, the Mavlink constructor).
PARAMETER_TYPES = {
    "COM_DISARM_LAND": mavlink.MAV_PARAM_TYPE_REAL32,
    "COM_OBL_RC_ACT": mavlink.MAV_PARAM_TYPE_INT32,
    "COM_OF_LOSS_T": mavlink.MAV_PARAM_TYPE_REAL32,
    "EKF2_EV_CTRL": mavlink.MAV_PARAM_TYPE_INT32,
    "EKF2_EV_DELAY": mavlink.MAV_PARAM_TYPE_REAL32,
    "EKF2_EV_QMIN": mavlink.MAV_PARAM_TYPE_INT32,
    "EKF2_GPS_CTRL": mavlink.MAV_PARAM_TYPE_INT32,
    "EKF2_HGT_REF": mavlink.MAV_PARAM_TYPE_INT32,
    "MAV_1_CONFIG": mavlink.MAV_PARAM_TYPE_INT32,
    "MAV_1_FORWARD": mavlink.MAV_PARAM_TYPE_INT32,
    "MAV_1_MODE": mavlink.MAV_PARAM_TYPE_INT32,
    "MAV_COMP_ID": mavlink.MAV_PARAM_TYPE_INT32,
    "MAV_SYS_ID": mavlink.MAV_PARAM_TYPE_INT32,
    "MIS_TAKEOFF_ALT": mavlink.MAV_PARAM_TYPE_REAL32,
    "MPC_ACC_UP_MAX": mavlink.MAV_PARAM_TYPE_REAL32,
    "MPC_JERK_AUTO": mavlink.MAV_PARAM_TYPE_REAL32,
    "MPC_LAND_SPEED": mavlink.MAV_PARAM_TYPE_REAL32,
    "MPC_TKO_RAMP_T": mavlink.MAV_PARAM_TYPE_REAL32,
    "MPC_TKO_SPEED": mavlink.MAV_PARAM_TYPE_REAL32,
    "SER_TEL2_BAUD": mavlink.MAV_PARAM_TYPE_INT32,
}
#: The take-off's limits (trajectory.py), which divide or bound and so must be positive; PX4's
#: parameter metadata sets their least values at 0.1 or more. MPC_TKO_RAMP_T may be 0: no ramp.
POSITIVE_PARAMETERS = ("MPC_ACC_UP_MAX", "MPC_JERK_AUTO", "MPC_TKO_SPEED")
#: PX4 sends its parameters by index in name order (the generated parameter table is sorted).
PARAMETER_NAMES = tuple(sorted(PARAMETER_TYPES))
#: PARAM_VALUE's name for the hash PX4 sends first on PARAM_REQUEST_LIST, and its index:
#: PX4 sets param_index = -1, which the uint16 field carries as 65535.
HASH_PARAM, HASH_PARAM_INDEX = "_HASH_CHECK", 65535


@dataclass(frozen=True)
class Px4Options:
    """The mock flight controller's settings; PX4 parameter names in brackets."""

    system_id: int = option(1, ge=1, le=255, doc="MAVLink system id [MAV_SYS_ID]")
    component_id: int = option(1, ge=1, le=255, doc="MAVLink component id [MAV_COMP_ID]")
    offboard_loss_timeout: float = option(
        1.0, gt=0.0, le=60.0,
        doc="seconds a setpoint keeps offboard available: entry needs one this recent, and "
            "the offboard-loss failsafe follows when none is [COM_OF_LOSS_T]")
    offboard_loss_action: str = option(
        "hold", choices=OFFBOARD_LOSS_ACTIONS,
        doc="mode the offboard-loss failsafe switches to: hold (AUTO.LOITER) or land "
            "(AUTO.LAND) [COM_OBL_RC_ACT 5 / 4]")
    takeoff_altitude: float = option(
        2.5, gt=0.0, le=100.0, doc="take-off height above home, metres [MIS_TAKEOFF_ALT]")
    takeoff_speed: float = option(1.5, gt=0.0, le=10.0,
                                  doc="climb rate of take-off, m/s [MPC_TKO_SPEED]")
    takeoff_ramp_time: float = option(
        3.0, ge=0.0, le=5.0,
        doc="time the take-off takes to reach its climb rate: its acceleration is at most "
            "takeoff_speed / takeoff_ramp_time; 0: no ramp, s [MPC_TKO_RAMP_T]")
    climb_accel_max: float = option(
        4.0, gt=0.0, le=15.0, doc="largest upward acceleration of auto modes, m/s^2 "
                                  "[MPC_ACC_UP_MAX]")
    auto_jerk_max: float = option(
        4.0, gt=0.0, le=80.0, doc="largest jerk of auto modes' trajectories, m/s^3 "
                                  "[MPC_JERK_AUTO]")
    # PX4's own take-off (trajectory.py); the step remains for the flights measured with it
    # (docs/vins.md, "The take-off as PX4 flies it").
    smooth_takeoff: bool = option(
        True, doc="climb as PX4 does, smoothed to MPC_TKO_SPEED within MPC_TKO_RAMP_T, "
                   "MPC_ACC_UP_MAX and MPC_JERK_AUTO (FlightTaskAuto); false: a step to "
                   "MPC_TKO_SPEED, stopped by the position hold at the height")
    land_speed: float = option(0.7, gt=0.0, le=5.0,
                               doc="descent rate of Land, m/s [MPC_LAND_SPEED]")
    disarm_after_land: float = option(
        2.0, ge=0.0, le=60.0,
        doc="seconds on the ground after landing before auto-disarm; 0: never "
            "[COM_DISARM_LAND]")
    imu_rate_hz: float = option(
        50.0, gt=0.0, le=1000.0,
        doc="HIGHRES_IMU rate before any SET_MESSAGE_INTERVAL, Hz (capped by the physics rate)")
    position_noise: float = option(
        0.02, ge=0.0, le=10.0,
        doc="white noise (1 sigma, metres) of the stand-in estimator's position")
    velocity_noise: float = option(
        0.02, ge=0.0, le=10.0,
        doc="white noise (1 sigma, m/s) of the stand-in estimator's velocity")
    attitude_noise: float = option(
        0.002, ge=0.0, le=1.0,
        doc="white noise (1 sigma, radians per axis) of the stand-in estimator's attitude")
    signing_key_file: str = option(
        "", doc="file holding the MAVLink 2 signing key PX4 boots with, 64 hex digits (PX4 "
                "keeps it on its SD card, /mavlink/mavlink-signing-key.bin); found as [mavlink] "
                "signing_key_file is. Empty (and no signing_key): no key, PX4 signs nothing and "
                "accepts everything until a SETUP_SIGNING gives it one")
    signing_key: str = option(
        "", doc="the key PX4 boots with, itself, as 64 hex digits (tests); not with "
                "signing_key_file. With a key, unsigned messages are ignored except PX4's "
                "allowlist")

    def __post_init__(self) -> None:
        validate(self)
        check_key_options(self)


def default_parameters(options: Px4Options) -> dict[str, int | float]:
    """The parameter table of a vehicle configured as docs/operations.md asks (PX4 v1.14
    names and values), the options standing in for the parameters they name."""
    return {
        "COM_DISARM_LAND": options.disarm_after_land,
        "COM_OBL_RC_ACT": OFFBOARD_LOSS_ACTION_VALUES[options.offboard_loss_action],
        "COM_OF_LOSS_T": options.offboard_loss_timeout,
        "EKF2_EV_CTRL": 15,     # fuse vision horizontal and vertical position, velocity, yaw
        "EKF2_EV_DELAY": 0.0,   # ms: the mock's vision fusion has no delay
        "EKF2_EV_QMIN": 1,      # odometry the companion marks failed (quality -1) not fused
        "EKF2_GPS_CTRL": 0,     # no GNSS: the mock has none
        "EKF2_HGT_REF": 3,      # Vision
        "MAV_1_CONFIG": 102,    # TELEM 2
        "MAV_1_FORWARD": 1,
        "MAV_1_MODE": 2,        # Onboard
        "MAV_COMP_ID": options.component_id,
        "MAV_SYS_ID": options.system_id,
        "MIS_TAKEOFF_ALT": options.takeoff_altitude,
        "MPC_ACC_UP_MAX": options.climb_accel_max,
        "MPC_JERK_AUTO": options.auto_jerk_max,
        "MPC_LAND_SPEED": options.land_speed,
        "MPC_TKO_RAMP_T": options.takeoff_ramp_time,
        "MPC_TKO_SPEED": options.takeoff_speed,
        "SER_TEL2_BAUD": 921600,
    }


def check_parameter(name: str, value) -> int | float:
    """``value`` as parameter ``name`` holds it (int for INT32, float32 for REAL32); ValueError
    for an unknown name, a non-integer INT32, a non-finite REAL32, a take-off limit that is
    not positive (:data:`POSITIVE_PARAMETERS`; a negative MPC_TKO_RAMP_T), or a COM_OBL_RC_ACT
    the mock cannot fly."""
    if name not in PARAMETER_TYPES:
        raise ValueError(f"unknown parameter {name!r}; the mock has {', '.join(PARAMETER_NAMES)}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if (name in POSITIVE_PARAMETERS and number <= 0.0) or (name == "MPC_TKO_RAMP_T"
                                                            and number < 0.0):
        raise ValueError(f"{name} {number:g}: the mock cannot take off with it (PX4's own "
                         "range excludes it)")
    if PARAMETER_TYPES[name] == mavlink.MAV_PARAM_TYPE_REAL32:
        return decode_value(encode_value(number, mavlink.MAV_PARAM_TYPE_REAL32),
                            mavlink.MAV_PARAM_TYPE_REAL32)  # a float32, as PX4 holds it
    if not number.is_integer() or isinstance(value, bool):
        raise ValueError(f"{name} is an integer parameter, got {value!r}")
    if name == "COM_OBL_RC_ACT" and int(number) not in OFFBOARD_LOSS_MODES:
        raise ValueError(f"COM_OBL_RC_ACT {int(number)}: the mock flies only 4 (Land) and "
                         "5 (Hold)")
    return int(number)


@dataclass(frozen=True)
class OffboardSetpoint:
    """An accepted SET_POSITION_TARGET_LOCAL_NED in the world frame (ENU), NaN = ignored."""

    time: float
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    yaw: float
    yaw_rate: float


@dataclass(frozen=True)
class Estimate:
    """The stand-in estimator's output in the world frame (ENU, FLU body)."""

    position: np.ndarray
    velocity: np.ndarray
    q_W_B: np.ndarray
    angular_velocity_B: np.ndarray


class MockPx4:
    """The flight controller: MAVLink in and out, modes and failsafes, targets to the vehicle.

    ``parameters`` overrides entries of :func:`default_parameters` (a misconfigured vehicle
    for a test); ValueError for one :func:`check_parameter` refuses, or for MAV_SYS_ID and
    MAV_COMP_ID, which come from ``options`` as the link's ids do.
    """

    def __init__(self, link: MavlinkLink, vehicle: Quadrotor, options: Px4Options | None = None,
                 *, rng: np.random.Generator | None = None, physics_rate_hz: float = 200.0,
                 parameters: Mapping[str, float] | None = None):
        self.link = link
        self.vehicle = vehicle
        self.options = options or Px4Options()
        self.parameters = self._parameter_table(parameters or {})
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self._min_interval = 1.0 / physics_rate_hz  # the physics tick: streams and link reads
        #: The signing key PX4 has now (None: none, signing off).
        self.signing_key: bytes | None = None
        self._use_key(load_key(self.options))
        self.time = float(vehicle.state.time)
        self._rc_pulses_us = [RC_CHANNEL_CENTRE_US] * RC_CHANNEL_COUNT
        self._collision_reported = False
        self._statustext_id = 0
        self._builders: dict | None = None
        #: Streams held back (a fault injected by the simulator: e.g. an IMU gap); TIMESYNC
        #: held back stops its answers too.
        self.suppressed_streams: set[int] = set()
        #: How HIGHRES_IMU reaches the link (a fault injected by the simulator): None in
        #: order, once; "repeat" each twice; "reorder" in swapped pairs.
        self.imu_delivery: str | None = None
        self._held_imu = None
        self._imu = (np.zeros(3), np.array([0.0, 0.0, GRAVITY]))
        self._boot_at = 0.0
        self._booting_until: float | None = None
        self._power_on()

    def _power_on(self) -> None:
        """The state PX4 boots into: disarmed in Hold, its default stream rates, no offboard
        setpoint, no TIMESYNC estimate, home where the vehicle stands."""
        self.mode = px4_protocol.AUTO_LOITER
        self._intervals: dict[int, float | None] = {}
        self._next_due = {}
        for message_id, rate in DEFAULT_STREAM_RATES_HZ.items():
            self._set_rate(message_id, rate)
        self._set_rate(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, self.options.imu_rate_hz)
        self._setpoint: OffboardSetpoint | None = None
        self._hold_position: np.ndarray | None = None
        self._hold_yaw = 0.0
        self._takeoff_height = self.parameters["MIS_TAKEOFF_ALT"]
        self._takeoff: tuple[VelocitySmoothing, float] | None = None  # the climb, its last tick
        self._landed_since: float | None = None
        self._taken_off = False  # since arming (Commander's _have_taken_off_since_arming)
        self._ev_offset = np.zeros(3)
        self._ev_time: float | None = None
        self._timesync_sent_ns: int | None = None
        self.timesync_offset_ns: int | None = None
        #: The last air data and whether a HIGHRES_IMU has carried it yet: PX4 sends the last
        #: values in every message (zero before the first), marked updated in the first after
        #: they were published.
        self._air_data = AirData(0.0, 0.0, 0.0)
        self._air_data_fresh = False
        self._home = np.array(self.vehicle.state.position, dtype=float)
        self.estimate = self._estimate()
        self._enter_hold()

    def _parameter_table(self, overrides: Mapping[str, float]) -> dict[str, int | float]:
        fixed = {"MAV_SYS_ID", "MAV_COMP_ID"} & set(overrides)
        if fixed:
            raise ValueError(f"{', '.join(sorted(fixed))}: set Px4Options.system_id / "
                             "component_id, which the link speaks as")
        table = default_parameters(self.options)
        table.update(overrides)
        return {name: check_parameter(name, value) for name, value in table.items()}

    def set_rc_channel(self, channel: int, pulse_us: int) -> None:
        """Move RC ``channel`` (1-based) of the simulated receiver to ``pulse_us``; RC_CHANNELS
        carries it from the next message on. ValueError for a channel the receiver does not
        have or a pulse PX4's RC input would reject."""
        if not _integer_in(channel, 1, RC_CHANNEL_COUNT):
            raise ValueError(f"RC channel must be an integer 1..{RC_CHANNEL_COUNT}, "
                             f"got {channel!r}")
        if not _integer_in(pulse_us, *RC_PULSE_RANGE_US):
            raise ValueError("RC pulse must be an integer {}..{} us, got {!r}".format(
                *RC_PULSE_RANGE_US, pulse_us))
        self._rc_pulses_us[channel - 1] = pulse_us

    # ---------------------------------------------------------------- the tick

    def update(self, t: float, gyro_B=None, accel_B=None, air_data: AirData | None = None
               ) -> None:
        """One physics tick at time ``t`` (s since boot), with the IMU sample (FLU) ending at t
        and the barometer's sample when it took one in the tick."""
        self.time = float(t)
        if gyro_B is not None and accel_B is not None:
            self._imu = (np.asarray(gyro_B, dtype=float), np.asarray(accel_B, dtype=float))
        if air_data is not None:
            self._air_data, self._air_data_fresh = air_data, True
        if self._booting_until is not None and not self._booted():
            return
        self.estimate = self._estimate()
        for message in self.link.receive_pending():
            self._handle(message)
        self._check_collision()
        self._fly()
        self._send_due_streams()

    # ---------------------------------------------------------------- reboot

    def reboot(self, boot_duration_s: float = BOOT_DURATION_S) -> None:
        """Restart, as after a brown-out or a watchdog reset: the motors stop at once (in the
        air, the vehicle falls), nothing is read or sent for ``boot_duration_s``, then PX4
        comes up as at power-on (:meth:`_power_on`) with its boot time from zero. Parameters
        and the signing key survive, as PX4 keeps them in flash or on its SD card."""
        if self.vehicle.armed:
            self.vehicle.disarm()
        self._booting_until = self.time + boot_duration_s
        self._held_imu = None
        log.warning("PX4 rebooting at t=%.3f", self.time)

    def _booted(self) -> bool:
        """While booting, whatever reaches the board is lost; when done, power on."""
        self.link.receive_pending()
        if self.time < self._booting_until:
            return False
        self._booting_until, self._boot_at = None, self.time
        self._power_on()
        return True

    # ---------------------------------------------------------------- estimator

    def _estimate(self) -> Estimate:
        state = self.vehicle.state
        if self._ev_time is not None and self.time - self._ev_time > EXTERNAL_VISION_TIMEOUT:
            self._ev_time = None  # offset kept: the estimate stays where vision left it
        noise = self._rng.standard_normal(9)
        rotation_noise = rot_to_quat(so3_exp(noise[6:9] * self.options.attitude_noise))
        return Estimate(
            position=np.asarray(state.position) + self._ev_offset
            + noise[0:3] * self.options.position_noise,
            velocity=np.asarray(state.velocity) + noise[3:6] * self.options.velocity_noise,
            q_W_B=quat_multiply(np.asarray(state.q_W_B), rotation_noise),
            angular_velocity_B=self._imu[0],
        )

    def _to_vehicle_frame(self, position: np.ndarray) -> np.ndarray:
        """A position in the estimator's frame as the vehicle (ground truth) sees it."""
        return position - self._ev_offset

    def _handle_odometry(self, message) -> None:
        """External vision: the position axes EKF2_EV_CTRL fuses (bit 0 horizontal, bit 1
        vertical) follow it; with neither, it is ignored as EKF2 ignores it. A sample whose
        quality is below EKF2_EV_QMIN (when that is above 0) is not fused, as if it had not
        come (EKF2's quality_sufficient, src/modules/ekf2/EKF/aid_sources/external_vision/
        ev_control.cpp), so vision times out after EXTERNAL_VISION_TIMEOUT."""
        if message.frame_id not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD):
            self._statustext(mavlink.MAV_SEVERITY_WARNING,
                             f"ODOMETRY frame {message.frame_id} unsupported")
            return
        position = ned_to_enu((message.x, message.y, message.z))
        ev_ctrl = self.parameters["EKF2_EV_CTRL"]
        fused = np.array([ev_ctrl & 1, ev_ctrl & 1, ev_ctrl & 2], dtype=bool)
        minimum_quality = self.parameters["EKF2_EV_QMIN"]
        if not np.all(np.isfinite(position)) or not fused.any() \
                or (minimum_quality > 0 and message.quality < minimum_quality):
            return
        offset = position - np.asarray(self.vehicle.state.position)
        self._ev_offset = np.where(fused, offset, self._ev_offset)
        self._ev_time = self.time

    @property
    def external_vision_active(self) -> bool:
        return self._ev_time is not None

    # ---------------------------------------------------------------- incoming

    def _handle(self, message) -> None:
        kind = message.get_type()
        handler = {
            "COMMAND_LONG": self._handle_command_long,
            "COMMAND_INT": self._handle_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self._handle_setpoint,
            "TIMESYNC": self._handle_timesync,
            "ODOMETRY": self._handle_odometry,
            "PARAM_REQUEST_READ": self._handle_param_request_read,
            "PARAM_REQUEST_LIST": self._handle_param_request_list,
            "PARAM_SET": self._handle_param_set,
            "SETUP_SIGNING": self._handle_setup_signing,
        }.get(kind)
        if handler is None:
            return
        try:
            handler(message)
        except (ValueError, TypeError, OverflowError) as error:
            # A well-framed message with nonsense in it (NaN where an integer belongs, ...)
            log.warning("ignored %s: %s", kind, error)

    def _for_me(self, message, *, any_system: bool = True) -> bool:
        """Addressed to us, or to every component; to every system too unless ``any_system``
        is False (the parameter protocol wants our system id: mavlink_parameters.cpp)."""
        systems = (0, self.options.system_id) if any_system else (self.options.system_id,)
        return (message.target_system in systems
                and message.target_component in (0, self.options.component_id))

    def _handle_command_long(self, message) -> None:
        if not self._for_me(message):
            return
        params = (message.param1, message.param2, message.param3, message.param4,
                  message.param5, message.param6, message.param7)
        self._command(message, message.command, params)

    def _handle_command_int(self, message) -> None:
        if not self._for_me(message):
            return
        params = (message.param1, message.param2, message.param3, message.param4,
                  float(message.x), float(message.y), message.z)
        self._command(message, message.command, params)

    def _command(self, message, command: int, params) -> None:
        handler = {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            mavlink.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink.MAV_CMD_NAV_LAND: lambda p: self._change_mode(px4_protocol.AUTO_LAND),
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            mavlink.MAV_CMD_REQUEST_MESSAGE: lambda p: self._cmd_request_message(int(p[0])),
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: lambda p: self._cmd_request_message(
                mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
        }.get(command)
        try:
            result = mavlink.MAV_RESULT_UNSUPPORTED if handler is None else handler(params)
        except ValueError as error:  # e.g. NaN where the command needs a number
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Command {command} denied: {error}")
            result = mavlink.MAV_RESULT_DENIED
        ack = self.link.mav.command_ack_encode(command, result, 0, 0,
                                               message.get_srcSystem(),
                                               message.get_srcComponent())
        self.link.send(ack)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE and result == mavlink.MAV_RESULT_ACCEPTED:
            self._send_message(int(params[0]))
        if (command == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL
                and result == mavlink.MAV_RESULT_ACCEPTED):
            self._send_message_interval(int(params[0]))
        if (command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
                and result == mavlink.MAV_RESULT_ACCEPTED):
            self._send_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)

    def _cmd_arm_disarm(self, params) -> int:
        action = _round(params[0])
        # MAVSDK sends NaN for unused params; anything but the magic number is "not forced"
        forced = math.isfinite(params[1]) \
            and _round(params[1]) == px4_protocol.FORCE_ARM_DISARM_MAGIC
        if action == 1:
            return self._arm()
        if action == 0:
            return self._disarm(forced)
        self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                         f"Unsupported ARM_DISARM param: {params[0]:.3f}")
        return mavlink.MAV_RESULT_UNSUPPORTED

    def arming_denial(self) -> str | None:
        """Why arming would be refused now (the failing check, as PX4 words it), None when the
        checks pass: what SYS_STATUS's MAV_SYS_STATUS_PREARM_CHECK bit reports."""
        if self.vehicle.collision is not None:
            return "vehicle crashed"
        if self.mode == px4_protocol.OFFBOARD and not self._offboard_signal_ok():
            return "no offboard signal"
        return None

    def _arm(self) -> int:
        # Commands from MAVLink always run the preflight checks, forced or not (Commander.cpp).
        if self.vehicle.armed:
            return mavlink.MAV_RESULT_ACCEPTED
        denial = self.arming_denial()
        if denial is not None:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, f"Arming denied: {denial}")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self.vehicle.arm()
        self._home = np.array(self.estimate.position)
        self._landed_since = None
        self._taken_off = False
        self._takeoff = None  # a take-off armed into starts from rest
        if self.mode == px4_protocol.AUTO_LOITER:
            self._enter_hold()
        self._statustext(mavlink.MAV_SEVERITY_INFO, "Armed by external command")
        return mavlink.MAV_RESULT_ACCEPTED

    def force_disarm(self, reason: str) -> int:
        """Stop the motors, in the air too, as a forced disarm (param2 21196) does: PX4
        skips its landed check for it (commander/Commander.cpp, ``Commander::disarm``)."""
        return self._disarm(True, reason)

    def _disarm(self, forced: bool, reason: str = "external command") -> int:
        if not self.vehicle.armed:
            return mavlink.MAV_RESULT_ACCEPTED
        if not forced and not self.vehicle.landed:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, "Disarming denied: not landed")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        self.vehicle.disarm()
        self._statustext(mavlink.MAV_SEVERITY_INFO, f"Disarmed by {reason}")
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_set_mode(self, params) -> int:
        base_mode = _round(params[0])
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mavlink.MAV_RESULT_UNSUPPORTED
        try:
            mode = px4_protocol.Px4Mode.from_numbers(_round(params[1]), _round(params[2]))
        except ValueError as error:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, str(error))
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        return self._change_mode(mode)

    def _cmd_takeoff(self, params) -> int:
        altitude_amsl = params[6]
        if math.isfinite(altitude_amsl):
            self._takeoff_height = max(0.5, altitude_amsl - HOME_ALTITUDE_M)
        else:
            self._takeoff_height = self.parameters["MIS_TAKEOFF_ALT"]
        return self._change_mode(px4_protocol.AUTO_TAKEOFF)

    SUPPORTED_MODES = (px4_protocol.OFFBOARD, px4_protocol.AUTO_LOITER, px4_protocol.AUTO_LAND,
                       px4_protocol.AUTO_TAKEOFF)

    def _change_mode(self, mode: px4_protocol.Px4Mode) -> int:
        """PX4's mode-change rules as far as the mock flies them; rejected: TEMPORARILY_REJECTED."""
        if mode not in self.SUPPORTED_MODES:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                             f"Switching to {mode.name} is not supported here")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode == px4_protocol.OFFBOARD and not self._offboard_signal_ok():
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                             "Switching to Offboard is currently not available")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        if mode != self.mode:
            self._set_mode(mode)
        return mavlink.MAV_RESULT_ACCEPTED

    def _set_mode(self, mode: px4_protocol.Px4Mode) -> None:
        self.mode = mode
        self._takeoff = None  # a take-off begins afresh
        if mode == px4_protocol.AUTO_LOITER:
            self._enter_hold()
        log.info("mode %s at t=%.3f", mode.name, self.time)

    def _cmd_set_message_interval(self, params) -> int:
        message_id, interval_us = _round(params[0]), _round(params[1])
        if message_id not in DEFAULT_STREAM_RATES_HZ:
            return mavlink.MAV_RESULT_DENIED
        if interval_us == 0:
            rate = DEFAULT_STREAM_RATES_HZ[message_id]
            if message_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
                rate = self.options.imu_rate_hz
        elif interval_us < 0:
            rate = 0.0
        else:
            rate = 1e6 / interval_us
        self._set_rate(message_id, rate)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, params) -> int:
        return (mavlink.MAV_RESULT_ACCEPTED if _round(params[0]) in DEFAULT_STREAM_RATES_HZ
                else mavlink.MAV_RESULT_DENIED)

    def _cmd_request_message(self, message_id: int) -> int:
        return (mavlink.MAV_RESULT_ACCEPTED if message_id in self._message_builders()
                else mavlink.MAV_RESULT_DENIED)

    def _set_rate(self, message_id: int, rate_hz: float) -> None:
        """Stream at ``rate_hz`` (0: off), no faster than the physics tick."""
        if rate_hz <= 0.0:
            self._intervals[message_id] = None
            return
        self._intervals[message_id] = max(1.0 / rate_hz, self._min_interval)
        self._next_due[message_id] = self.time

    def message_rate_hz(self, message_id: int) -> float:
        """The rate a stream is sent at now (0 when off)."""
        interval = self._intervals.get(message_id)
        return 0.0 if interval is None else 1.0 / interval

    def _handle_setpoint(self, message) -> None:
        """SET_POSITION_TARGET_LOCAL_NED as mavlink_receiver.cpp takes it."""
        if not self._for_me(message):
            return
        setpoint = self._decode_setpoint(message)
        if setpoint is not None:
            self._setpoint = setpoint

    def _decode_setpoint(self, message) -> OffboardSetpoint | None:
        mask = message.type_mask
        frame = message.coordinate_frame
        if frame not in px4_protocol.SUPPORTED_SETPOINT_FRAMES:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                             f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported")
            return None
        position = _masked((message.x, message.y, message.z), mask, px4_protocol.IGNORE_POSITION)
        velocity = _masked((message.vx, message.vy, message.vz), mask, px4_protocol.IGNORE_VELOCITY)
        acceleration = _masked((message.afx, message.afy, message.afz), mask,
                               px4_protocol.IGNORE_ACCELERATION)
        if frame == mavlink.MAV_FRAME_BODY_NED:
            R_NED_FRD = quat_to_rot(quat_enu_flu_to_ned_frd(self.estimate.q_W_B))
            position = np.full(3, np.nan)
            velocity = _rotate_body(R_NED_FRD, velocity)
            acceleration = _rotate_body(R_NED_FRD, acceleration)
        has_acceleration = bool(np.isfinite(acceleration).any())
        if has_acceleration and mask & px4_protocol.FORCE_SET:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                             "SET_POSITION_TARGET_LOCAL_NED force not supported")
            return None
        if not (np.isfinite(position).any() or np.isfinite(velocity).any() or has_acceleration):
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, "SET_POSITION_TARGET_LOCAL_NED invalid")
            return None
        yaw_ned = math.nan if mask & px4_protocol.IGNORE_YAW else float(message.yaw)
        yaw_rate_ned = math.nan if mask & px4_protocol.IGNORE_YAW_RATE else float(message.yaw_rate)
        return OffboardSetpoint(
            time=self.time,
            position=ned_to_enu(position),
            velocity=ned_to_enu(velocity),
            acceleration=ned_to_enu(acceleration),
            yaw=math.pi / 2 - yaw_ned,    # NED heading (from north, clockwise) -> ENU yaw
            yaw_rate=-yaw_rate_ned,       # about down -> about up
        )

    def _offboard_signal_ok(self) -> bool:
        """PX4's one condition for offboard, to enter it and to stay in it: an accepted
        setpoint arrived less than COM_OF_LOSS_T ago. No stream of any length or rate is asked
        for: a single setpoint makes offboard available
        (src/modules/commander/HealthAndArmingChecks/checks/offboardCheck.cpp,
        OffboardChecks::checkAndReport: ``now < offboard_control_mode.timestamp +
        COM_OF_LOSS_T``; mavlink_receiver.cpp stamps offboard_control_mode on every accepted
        SET_POSITION_TARGET_LOCAL_NED). COM_OF_LOSS_T = 0 makes offboard unavailable."""
        return (self._setpoint is not None
                and self.time < self._setpoint.time + self.parameters["COM_OF_LOSS_T"])

    def _handle_timesync(self, message) -> None:
        """Answer requests (tc1 == 0) with our boot time; use answers to our own requests.

        PX4 stamps its answer as its receiver handles the request and sends it at once
        (src/modules/mavlink/mavlink_timesync.cpp, ``MavlinkTimesync::handle_message``:
        ``rsync.tc1 = now * 1000ULL`` with ``now = hrt_absolute_time()``), so only the link's
        delays, about equal both ways, lie between the companion's send and its receipt, as
        the NTP midpoint it takes assumes. This mock reads the link once a physics tick: in
        lockstep a request, sent just after one tick, is handled at the next, while the answer
        reaches the companion at once. Stamped at the tick, the answer would put the
        companion's estimate of our clock half a tick (2.5 ms at 200 Hz) off, and every IMU
        sample would reach its VINS that much early against the camera: about 1 % of path
        scale in a simulated flight with exact sensors (docs/vins.md, "The mock's clock half a
        tick off"). So the answer is stamped at the middle of the tick it waited, where equal
        legs put it."""
        if mavlink.MAVLINK_MSG_ID_TIMESYNC in self.suppressed_streams:
            return
        now_ns = self._boot_ns()
        if message.tc1 == 0:
            answered_ns = now_ns - int(round(self._min_interval * 0.5e9))
            self.link.send(self.link.mav.timesync_encode(answered_ns, message.ts1))
        elif message.ts1 == self._timesync_sent_ns:
            # offset = remote - local, with the remote stamp taken halfway through the round trip
            self.timesync_offset_ns = (2 * message.tc1 - message.ts1 - now_ns) // 2

    # ---------------------------------------------------------------- signing
    # PX4 v1.18 (main since PR #26894 "align signing with MAVLink spec"): the key's presence
    # switches signing on, on every link, USB included; there is no MAV_SIGN_CFG any more.

    def _use_key(self, key: bytes | None, initial_timestamp: int | None = None) -> None:
        """Sign with ``key`` and refuse unsigned messages outside PX4's allowlist, or, for
        None, sign nothing and accept everything (mavlink_sign_control.cpp,
        ``_update_signing_state`` and ``accept_unsigned``)."""
        self.signing_key = key
        if key is None:
            self.link.stop_signing()
        else:
            self.link.setup_signing(key, accept_unsigned=px4_protocol.accept_unsigned,
                                    initial_timestamp=initial_timestamp)

    def _handle_setup_signing(self, message) -> None:
        """A new key (mavlink_sign_control.cpp, ``check_for_signing``). It got here past the
        link's signature check: unsigned while PX4 has no key, else signed with the key it has
        (SETUP_SIGNING is not on the allowlist), so only a holder of the key can change it.
        Refused while armed (PR #26894's armed guard; the STATUSTEXT as QGroundControl issue
        #14250 quotes it). A blank key (all zero, timestamp 0) clears the key; any other
        replaces key and timestamp. The target ids are not looked at, as check_for_signing
        does not."""
        if self.vehicle.armed:
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                             "MAVLink signing: rejected while armed")
            return
        key = bytes(message.secret_key)
        if any(key) or message.initial_timestamp:
            log.info("signing key set by SETUP_SIGNING from system %d",
                     message.get_srcSystem())
            self._use_key(key, message.initial_timestamp)
        else:
            self._use_key(None)

    # ---------------------------------------------------------------- parameters
    # MavlinkParametersManager::handle_message and send_param, mavlink_parameters.cpp.

    def _handle_param_request_read(self, message) -> None:
        """One parameter by index (``param_index`` >= 0; an unknown index is answered with a
        STATUSTEXT) or by name (an unknown name is not answered at all, as in PX4)."""
        if not self._for_me(message, any_system=False):
            return
        index = message.param_index
        if index >= len(PARAMETER_NAMES):
            self._statustext(mavlink.MAV_SEVERITY_INFO, f"[pm] unknown param ID: {index}")
        elif index >= 0:
            self._send_parameter(PARAMETER_NAMES[index])
        elif message.param_id == HASH_PARAM:
            self._send_parameter_hash()
        elif message.param_id in self.parameters:
            self._send_parameter(message.param_id)

    def _handle_param_request_list(self, message) -> None:
        """The hash of the table first, then every parameter in index order (PX4 spreads them
        over its next sends; the mock sends them at once)."""
        if not self._for_me(message, any_system=False):
            return
        self._send_parameter_hash()
        for name in PARAMETER_NAMES:
            self._send_parameter(name)

    def _handle_param_set(self, message) -> None:
        """Set and answer with the parameter's PARAM_VALUE. As PX4's param_set, the four bytes
        are taken as the parameter's own type whatever ``param_type`` says. A value the mock
        cannot honour is refused with a STATUSTEXT and answered with the value kept."""
        name = message.param_id
        if not self._for_me(message, any_system=False) or name == HASH_PARAM:
            return
        if name not in self.parameters:
            self._statustext(mavlink.MAV_SEVERITY_INFO, f"[pm] unknown param: {name}")
            return
        try:
            self.set_parameter(name, decode_value(message.param_value, PARAMETER_TYPES[name]))
        except ValueError as error:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"[pm] {error}")
        self._send_parameter(name)

    def set_parameter(self, name: str, value: float) -> None:
        """Set parameter ``name`` as PARAM_SET does (ValueError as :func:`check_parameter`);
        the behaviour follows from the next tick."""
        self.parameters[name] = check_parameter(name, value)

    def _send_parameter(self, name: str) -> None:
        param_type = PARAMETER_TYPES[name]
        self.link.send(self.link.mav.param_value_encode(
            name.encode(), encode_value(self.parameters[name], param_type), param_type,
            len(PARAMETER_NAMES), PARAMETER_NAMES.index(name)))

    def _send_parameter_hash(self) -> None:
        """``_HASH_CHECK``: a CRC-32 over every name and value, in the manner of PX4's
        param_hash_check (lib/parameters/parameters.cpp), not bit for bit: a ground station
        only compares it with the hash of its cached copy."""
        crc = 0
        for name in PARAMETER_NAMES:
            value = encode_value(self.parameters[name], PARAMETER_TYPES[name])
            crc = zlib.crc32(struct.pack("<f", value), zlib.crc32(name.encode(), crc))
        self.link.send(self.link.mav.param_value_encode(
            HASH_PARAM.encode(), encode_value(crc, mavlink.MAV_PARAM_TYPE_UINT32),
            mavlink.MAV_PARAM_TYPE_UINT32, len(PARAMETER_NAMES), HASH_PARAM_INDEX))

    # ---------------------------------------------------------------- flying

    def _check_collision(self) -> None:
        collision = self.vehicle.collision
        if collision is None or self._collision_reported:
            return
        self._collision_reported = True
        if self.vehicle.armed:
            self.vehicle.disarm()
        self._statustext(mavlink.MAV_SEVERITY_EMERGENCY,
                         f"Collision at t={collision.time:.2f}s: flight ended, disarmed")
        log.warning("collision at t=%.3f position %s", collision.time, collision.position)

    def _fly(self) -> None:
        if self.mode == px4_protocol.OFFBOARD:
            self._fly_offboard()
        elif self.mode == px4_protocol.AUTO_TAKEOFF:
            self._fly_takeoff()
        elif self.mode == px4_protocol.AUTO_LAND:
            self._fly_land()
        else:
            self._fly_hold()
        self._auto_disarm()

    def _fly_offboard(self) -> None:
        """Follow the setpoint while the offboard signal holds (:meth:`_offboard_signal_ok`);
        when it is lost, armed, the failsafe switches to COM_OBL_RC_ACT's mode. Disarmed, PX4
        takes no failsafe action (failsafe/framework.cpp, FailsafeBase::getSelectedAction:
        ``if (!state.armed) action = None``): the mode stays and arming is refused."""
        if self._offboard_signal_ok():
            self.vehicle.set_target(self._offboard_target(self._setpoint))
            return
        if not self.vehicle.armed:
            self._fly_hold()
            return
        mode = OFFBOARD_LOSS_MODES[self.parameters["COM_OBL_RC_ACT"]]
        self._statustext(mavlink.MAV_SEVERITY_CRITICAL,
                         f"Failsafe activated: offboard lost, switching to {mode.name}")
        self._set_mode(mode)
        self._fly()

    def _offboard_target(self, setpoint: OffboardSetpoint) -> ControlTarget:
        """PX4's per-axis rule (PositionControl): a position axis is tracked with the velocity as
        feed-forward; an axis with only a velocity tracks that velocity; an axis with neither
        holds where it is. The vehicle's controller takes whole vectors, so a velocity-only axis
        of a mixed setpoint becomes "stay at the current position plus that feed-forward",
        re-anchored every tick, which gives the same velocity setpoint."""
        position = self._to_vehicle_frame(setpoint.position)
        velocity, acceleration = setpoint.velocity, setpoint.acceleration
        yaw = None if math.isnan(setpoint.yaw) else setpoint.yaw
        yaw_rate = None if math.isnan(setpoint.yaw_rate) else setpoint.yaw_rate
        acceleration_ff = np.nan_to_num(acceleration)
        if np.isnan(position).all() and np.isfinite(velocity).all():
            return ControlTarget(velocity=velocity, acceleration=acceleration_ff,
                                 yaw=yaw, yaw_rate=yaw_rate)
        here = np.asarray(self.vehicle.state.position)
        free_axes = np.isnan(position)
        velocity_ff = np.where(np.isnan(velocity), 0.0, velocity)
        velocity_ff = np.where(free_axes & np.isnan(velocity) & np.isfinite(acceleration),
                               self.vehicle.state.velocity, velocity_ff)
        return ControlTarget(position=np.where(free_axes, here, position), velocity=velocity_ff,
                             acceleration=acceleration_ff, yaw=yaw, yaw_rate=yaw_rate)

    def _enter_hold(self) -> None:
        self._hold_position = np.array(self.estimate.position)
        self._hold_yaw = yaw_of(quat_to_rot(self.estimate.q_W_B))

    def _fly_hold(self) -> None:
        if self.vehicle.landed:
            # PX4's land detector keeps a landed vehicle at idle in Hold: never lift off because
            # the estimate's noise put the hold point a few centimetres above the ground.
            self._fly_land()
            return
        self.vehicle.set_target(ControlTarget(
            position=self._to_vehicle_frame(self._hold_position),
            velocity=np.zeros(3), yaw=self._hold_yaw))

    def _fly_takeoff(self) -> None:
        if not self.vehicle.armed:
            return
        goal = np.array([self._hold_position[0], self._hold_position[1],
                         self._home[2] + self._takeoff_height])
        height = float(self.estimate.position[2])
        if height >= goal[2] - 0.1:
            self._set_mode(px4_protocol.AUTO_LOITER)
            self._hold_position = goal
            self._fly_hold()
            return
        if not self.options.smooth_takeoff:
            self._climb(self.parameters["MPC_TKO_SPEED"])
            return
        climb = self._smoothed_climb(height, goal[2])
        self.vehicle.set_target(ControlTarget(velocity=np.array([0.0, 0.0, climb.v]),
                                              acceleration=np.array([0.0, 0.0, climb.a]),
                                              yaw=self._hold_yaw))

    def _smoothed_climb(self, height: float, goal_height: float) -> AxisState:
        """This tick's vertical setpoint of PX4's take-off (trajectory.py: FlightTaskAuto's
        PositionSmoothing under the take-off's limits, the trajectory's height held at the
        vehicle's), from rest when the take-off began. PX4 applies those limits below
        MPC_LAND_ALT1 (10 m by default) and the auto modes' above it; the mock applies them
        all the way up. The limits are read when the take-off begins (PX4 reads them every
        step: a PARAM_SET during a climb acts from the next take-off here)."""
        p = self.parameters
        if self._takeoff is None:
            speed, ramp = p["MPC_TKO_SPEED"], p["MPC_TKO_RAMP_T"]
            accel = min(p["MPC_ACC_UP_MAX"], speed / ramp) if ramp > 0.0 else p["MPC_ACC_UP_MAX"]
            self._takeoff = (VelocitySmoothing(p["MPC_JERK_AUTO"], accel, speed,
                                               AxisState(x=height)), self.time)
        smoothing, last = self._takeoff
        smoothing.force_position(height)
        wanted = min(smoothing.max_vel, max_speed_from_distance(
            smoothing.max_jerk, smoothing.max_accel, goal_height - height))
        state = smoothing.update_traj(self.time - last)
        smoothing.update_durations(wanted)
        self._takeoff = (smoothing, self.time)
        return state

    def _fly_land(self) -> None:
        self._climb(-self.parameters["MPC_LAND_SPEED"])

    def _climb(self, rate: float) -> None:
        """Straight up (down for a negative rate) at ``rate`` m/s, holding the heading."""
        self.vehicle.set_target(ControlTarget(velocity=np.array([0.0, 0.0, rate]),
                                              yaw=self._hold_yaw))

    def _auto_disarm(self) -> None:
        """Disarm COM_DISARM_LAND seconds after touching down, once taken off since arming, in
        any mode (a mission not yet finished aside, which the mock does not fly); a value not
        above 0 turns it off (Commander.cpp, handleAutoDisarm: ``_param_com_disarm_land.get()
        > 0 && _have_taken_off_since_arming``). Offboard setpoints flown into the floor end
        so, as in Land."""
        self._taken_off |= self.vehicle.armed and not self.vehicle.landed
        delay = self.parameters["COM_DISARM_LAND"]
        if (not self.vehicle.armed or not self.vehicle.landed or delay <= 0.0
                or not self._taken_off):
            self._landed_since = None
            return
        if self._landed_since is None:
            self._landed_since = self.time
        if self.time - self._landed_since >= delay:
            self._disarm(forced=True, reason="landing")
            if self.mode == px4_protocol.AUTO_LAND:
                self._set_mode(px4_protocol.AUTO_LOITER)

    # ---------------------------------------------------------------- outgoing

    def _boot_ns(self) -> int:
        return int(round((self.time - self._boot_at) * 1e9))

    def _boot_ms(self) -> int:
        return int(round((self.time - self._boot_at) * 1e3))

    def _send_due_streams(self) -> None:
        for message_id, interval in self._intervals.items():
            if interval is None:
                continue
            due = self._next_due.get(message_id, self.time)
            if self.time + 1e-9 < due:
                continue
            # keep the phase while on time; after a stall, restart from now (no burst)
            next_due = due + interval
            self._next_due[message_id] = next_due if next_due > self.time else self.time + interval
            if message_id in self.suppressed_streams:
                continue
            if message_id == mavlink.MAVLINK_MSG_ID_TIMESYNC:
                self._send_timesync_request()
            else:
                self._send_message(message_id)

    def _send_timesync_request(self) -> None:
        self._timesync_sent_ns = self._boot_ns()
        self.link.send(self.link.mav.timesync_encode(0, self._timesync_sent_ns))

    def _message_builders(self) -> dict:
        if self._builders is not None:
            return self._builders
        self._builders = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self._extended_sys_state,
            mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self._autopilot_version,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: self._home_position,
            mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: self._highres_imu,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self._attitude_quaternion,
            mavlink.MAVLINK_MSG_ID_RC_CHANNELS: self._rc_channels,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position_ned,
            mavlink.MAVLINK_MSG_ID_ODOMETRY: self._odometry,
        }
        return self._builders

    def _send_message(self, message_id: int) -> None:
        builder = self._message_builders().get(message_id)
        if builder is None:
            return
        if message_id == mavlink.MAVLINK_MSG_ID_HIGHRES_IMU:
            self._send_imu(builder())
        else:
            self.link.send(builder())

    def _send_imu(self, message) -> None:
        """HIGHRES_IMU as :attr:`imu_delivery` says: each twice, or held back to follow the
        next (a swapped pair), or in order."""
        if self.imu_delivery == "reorder" and self._held_imu is None:
            self._held_imu = message
            return
        self.link.send(message)
        if self.imu_delivery == "repeat":
            self.link.send(message)
        if self._held_imu is not None:
            self.link.send(self._held_imu)
            self._held_imu = None

    def _send_message_interval(self, message_id: int) -> None:
        interval = self._intervals.get(message_id)
        interval_us = -1 if interval is None else int(round(interval * 1e6))
        self.link.send(self.link.mav.message_interval_encode(message_id, interval_us))

    def _statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT, split into 50-byte chunks sharing an id when longer (MAVLink 2)."""
        log.info("STATUSTEXT %s", text)
        data = text.encode()
        chunks = [data[i:i + 50] for i in range(0, len(data), 50)] or [b""]
        if len(chunks) == 1:
            self.link.send(self.link.mav.statustext_encode(severity, chunks[0]))
            return
        self._statustext_id = self._statustext_id % 65535 + 1
        for seq, chunk in enumerate(chunks):
            self.link.send(self.link.mav.statustext_encode(severity, chunk,
                                                           self._statustext_id, seq))

    def _heartbeat(self):
        base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.vehicle.armed:
            base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        # every mode the mock flies (AUTO.*, OFFBOARD) is auto + guided + stabilised, as PX4's
        # get_mavlink_navigation_mode() reports them (mavlink_main.cpp)
        base_mode |= (mavlink.MAV_MODE_FLAG_AUTO_ENABLED | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
                      | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED)
        if self.vehicle.collision is not None:
            status = mavlink.MAV_STATE_EMERGENCY
        elif self.vehicle.armed:
            status = mavlink.MAV_STATE_ACTIVE
        else:
            status = mavlink.MAV_STATE_STANDBY
        return self.link.mav.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base_mode,
            self.mode.custom_mode, status)

    def _sys_status(self):
        """SYS_STATUS as PX4 v1.14-v1.15 fills it from its health report
        (src/modules/mavlink/streams/SYS_STATUS.hpp, MavlinkStreamSysStatus::send): the
        components of :data:`SYS_STATUS_COMPONENTS` (none failing on the mock), and
        MAV_SYS_STATUS_PREARM_CHECK in the health field only, set while arming is possible
        in the current mode (``health_report.can_arm_mode_flags & (1 << nav_state)``). That
        bit is all MAVSDK reads for ``Telemetry.health().is_armable``
        (telemetry_impl.cpp, TelemetryImpl::process_sys_status)."""
        present, enabled, health = _component_bits(SYS_STATUS_COMPONENTS)
        extended = _component_bits(SYS_STATUS_EXTENDED_COMPONENTS)
        if self.arming_denial() is None:
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        bad_data = min(self.link.bad_data_count, 65535)
        return self.link.mav.sys_status_encode(present, enabled, health, 250, 16200, 500, 90,
                                               0, bad_data, 0, 0, 0, 0, *extended)

    def _landed_state(self) -> int:
        """PX4's land detector: landed whenever disarmed, in the air too
        (MulticopterLandDetector.cpp, ``_get_landed_state``: ``return !_armed ||
        _maybe_landed_hysteresis.get_state()``). PX4 passes it through its landed hysteresis
        (LandDetector.cpp, ``LNDMC_TRIG_TIME / 3``, 0.33 s); the mock says it at once, which
        only brings the word sooner after a disarm in the air."""
        if self.vehicle.landed or not self.vehicle.armed:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == px4_protocol.AUTO_TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == px4_protocol.AUTO_LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _extended_sys_state(self):
        return self.link.mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED,
                                                       self._landed_state())

    def _autopilot_version(self):
        return self.link.mav.autopilot_version_encode(
            CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0,
            self.options.system_id)

    def _home_position(self):
        x, y, z = enu_to_ned(self._home)
        return self.link.mav.home_position_encode(
            int(HOME_LATITUDE_DEG * 1e7), int(HOME_LONGITUDE_DEG * 1e7),
            int(HOME_ALTITUDE_M * 1e3), x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
            self._boot_ns() // 1000)

    def _highres_imu(self):
        """HIGHRES_IMU as PX4 fills it (src/modules/mavlink/streams/HIGHRES_IMU.hpp): the IMU
        sample; the last air data (``abs_pressure`` in hPa, ``pressure_alt``,
        ``temperature``), marked updated once; no magnetometer, no differential pressure."""
        gyro, accel = flu_to_frd(self._imu[0]), flu_to_frd(self._imu[1])
        air, fields = self._air_data, HIGHRES_IMU_FIELDS
        if self._air_data_fresh:
            fields |= HIGHRES_IMU_AIR_DATA_FIELDS
            self._air_data_fresh = False
        return self.link.mav.highres_imu_encode(
            self._boot_ns() // 1000, *accel, *gyro, 0.0, 0.0, 0.0, air.pressure_pa * 0.01, 0.0,
            air.altitude_m, air.temperature_c, fields)

    def _attitude(self):
        """ATTITUDE: the estimate's roll, pitch and yaw (NED/FRD) as PX4's matrix::Eulerf of
        the attitude quaternion, body rates FRD (src/modules/mavlink/streams/ATTITUDE.hpp)."""
        roll, pitch, yaw = _euler_zyx(quat_to_rot(quat_enu_flu_to_ned_frd(self.estimate.q_W_B)))
        rates = flu_to_frd(self.estimate.angular_velocity_B)
        return self.link.mav.attitude_encode(self._boot_ms(), roll, pitch, yaw, *rates)

    def _rc_channels(self):
        """RC_CHANNELS as PX4 sends its RC input (src/modules/mavlink/streams/RC_CHANNELS.hpp):
        ``chancount`` the receiver's channel count, channels past it UINT16_MAX, ``rssi``
        the input's RSSI (PX4's 0-100 scale, passed through)."""
        pulses = self._rc_pulses_us
        unused = [RC_CHANNEL_UNUSED] * (RC_CHANNELS_MAX - len(pulses))
        return self.link.mav.rc_channels_encode(self._boot_ms(), len(pulses), *pulses, *unused,
                                                RC_RSSI)

    def _attitude_quaternion(self):
        q = quat_enu_flu_to_ned_frd(self.estimate.q_W_B)
        rates = flu_to_frd(self.estimate.angular_velocity_B)
        return self.link.mav.attitude_quaternion_encode(self._boot_ms(), *q, *rates)

    def _local_position_ned(self):
        return self.link.mav.local_position_ned_encode(
            self._boot_ms(), *enu_to_ned(self.estimate.position),
            *enu_to_ned(self.estimate.velocity))

    def _odometry(self):
        q = quat_enu_flu_to_ned_frd(self.estimate.q_W_B)
        rates = flu_to_frd(self.estimate.angular_velocity_B)
        nan_covariance = [math.nan] + [0.0] * 20
        return self.link.mav.odometry_encode(
            self._boot_ns() // 1000, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_NED,
            *enu_to_ned(self.estimate.position), q, *enu_to_ned(self.estimate.velocity),
            *rates, nan_covariance, nan_covariance, 0, mavlink.MAV_ESTIMATOR_TYPE_NAIVE, 100)


def _integer_in(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _component_bits(components: Mapping[int, bool]) -> tuple[int, int, int]:
    """(present, enabled, health) as SYS_STATUS.hpp's fillOutComponent sets them for
    components none of which reports an error or warning: health set for every one, present
    for those the vehicle has, enabled for those present (or unhealthy)."""
    present = sum(bit for bit, has in components.items() if has)
    return present, present, sum(components)


def _euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (Z-Y-X) of a rotation matrix as PX4's matrix::Euler(Dcm) computes them
    (src/lib/matrix/matrix/Euler.hpp): at +-90 degrees pitch, roll 0 and yaw the rest."""
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(abs(pitch) - math.pi / 2) < 1e-3:
        sign = math.copysign(1.0, pitch)
        return 0.0, pitch, math.atan2(sign * R[1, 2], sign * R[0, 2])
    return math.atan2(R[2, 1], R[2, 2]), pitch, math.atan2(R[1, 0], R[0, 0])


def _round(value: float) -> int:
    """A float parameter that encodes an integer, rounded half away from zero as PX4's
    ``lroundf``; ValueError for NaN or infinity."""
    if not math.isfinite(value):
        raise ValueError(f"parameter {value} is not a finite number")
    return int(math.copysign(math.floor(abs(value) + 0.5), value))


def _masked(values, type_mask: int, bits: int) -> np.ndarray:
    """The three components of one field, NaN where type_mask says ignore (x, y, z bits)."""
    out = np.array(values, dtype=float)
    axis_bits = [b for b in (1, 2, 4, 8, 16, 32, 64, 128, 256) if b & bits]
    for i, bit in enumerate(axis_bits):
        if type_mask & bit:
            out[i] = np.nan
    return out


def _rotate_body(R_NED_FRD: np.ndarray, v_FRD: np.ndarray) -> np.ndarray:
    """A body-frame (FRD) vector into NED as mavlink_receiver.cpp does for MAV_FRAME_BODY_NED:
    if any axis is ignored the whole vector is ignored (NaN), else it is rotated."""
    if np.isnan(v_FRD).any():
        return np.full(3, np.nan)
    return R_NED_FRD @ v_FRD
