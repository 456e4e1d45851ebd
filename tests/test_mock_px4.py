"""The mock PX4 over real MAVLink: a pymavlink client on a loopback UDP socket (or a pty) talks
to MockPx4 flying the real Quadrotor, stepped here in lockstep so simulated time is exact."""

import math
import socket

import numpy as np
import pytest

from drivers.mavlink import px4_protocol
from drivers.mavlink.link import mavlink, open_link
from drivers.mavlink.signing import signing_timestamp
from drivers.sim.baro import AirData, isa_pressure, pressure_altitude
from drivers.sim.mock_px4 import MockPx4, Px4Options, check_parameter
from drivers.sim.quadrotor import Quadrotor

DT = 0.005  # 200 Hz physics, the IMU rate
KEY = bytes(range(100, 132))


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Bench:
    """Vehicle + mock PX4 on one end of a link, a ground-station client on the other."""

    def __init__(self, options=None, *, url=None, obstacle_clearance=None, parameters=None):
        port = free_udp_port()
        self.server = open_link(url or f"udpin://127.0.0.1:{port}")
        client_url = (f"serial://{self.server.pty_path}:57600" if self.server.pty_path
                      else f"udpout://127.0.0.1:{port}")
        self.client = open_link(client_url, source_system=255, source_component=190)
        self.vehicle = Quadrotor(obstacle_clearance=obstacle_clearance)
        self.px4 = MockPx4(self.server, self.vehicle, options or Px4Options(),
                           parameters=parameters)
        self.received = []
        self.client.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                       0, 0, 0)

    def close(self):
        self.client.close()
        self.server.close()

    @property
    def time(self):
        return self.vehicle.state.time

    def run(self, seconds, each_tick=None):
        """Fly ``seconds`` of simulated time; return the client's messages of that span."""
        start = len(self.received)
        for _ in range(int(round(seconds / DT))):
            truth = self.vehicle.step(DT)
            self.px4.update(self.time, truth.angular_velocity, truth.specific_force)
            if each_tick is not None:
                each_tick()
            self.received += self.client.receive_pending()
        return self.received[start:]

    def command(self, command, *params, link=None):
        """Send COMMAND_LONG; return the COMMAND_ACK's result (None if none came)."""
        params = list(params) + [0.0] * (7 - len(params))
        (link or self.client).mav.command_long_send(1, 1, command, 0, *params)
        acks = [m for m in self.run(0.02) if m.get_type() == "COMMAND_ACK"
                and m.command == command]
        return acks[-1].result if acks else None

    def set_mode(self, mode: px4_protocol.Px4Mode):
        return self.command(mavlink.MAV_CMD_DO_SET_MODE,
                            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode.main, mode.sub)

    def arm(self):
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def send_velocity(self, v_ned, frame=mavlink.MAV_FRAME_LOCAL_NED, yaw=0.0):
        """A velocity setpoint with an absolute yaw (NED heading), or a zero yaw rate if None."""
        type_mask = (px4_protocol.TYPE_MASK_VELOCITY_YAW if yaw is not None
                     else px4_protocol.TYPE_MASK_VELOCITY_YAW_RATE)
        self.client.mav.set_position_target_local_ned_send(
            0, 1, 1, frame, type_mask, 0, 0, 0, *v_ned, 0, 0, 0, yaw or 0.0, 0.0)

    def send_vision(self, x: float, y: float, z: float, quality: int = 100) -> None:
        """External vision: one ODOMETRY at NED ``(x, y, z)`` of ``quality`` (-1 failed, 0
        unknown, 100 best)."""
        self.client.mav.odometry_send(
            int(self.time * 1e6), mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD,
            x, y, z, [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [math.nan] + [0] * 20,
            [math.nan] + [0] * 20, 0, mavlink.MAV_ESTIMATOR_TYPE_VIO, quality)

    def stream_velocity(self, v_ned, seconds, rate_hz=20, **kwargs):
        every = int(round(1 / (rate_hz * DT)))
        ticks = iter(range(10**9))
        return self.run(seconds, lambda: next(ticks) % every == 0
                        and self.send_velocity(v_ned, **kwargs))

    def last(self, kind):
        found = self.all(kind)
        return found[-1] if found else None

    def all(self, kind, messages=None):
        return [m for m in (self.received if messages is None else messages)
                if m.get_type() == kind]

    def prearm_ok(self, seconds=0.25):
        """Whether the SYS_STATUS of the next ``seconds`` says arming is possible."""
        status = self.all("SYS_STATUS", self.run(seconds))[-1]
        return bool(status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK)

    def texts(self, messages=None):
        return [m.text for m in (messages or self.received) if m.get_type() == "STATUSTEXT"]


@pytest.fixture
def bench():
    b = Bench()
    yield b
    b.close()


def test_heartbeat_shows_a_px4_quadrotor_in_hold(bench):
    bench.run(1.1)
    heartbeat = bench.last("HEARTBEAT")
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert heartbeat.type == mavlink.MAV_TYPE_QUADROTOR
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert heartbeat.system_status == mavlink.MAV_STATE_STANDBY
    assert px4_protocol.Px4Mode.from_custom_mode(heartbeat.custom_mode).name == "AUTO.LOITER"
    assert heartbeat.custom_mode == (4 << 16) | (3 << 24)
    assert heartbeat.get_srcSystem() == 1 and heartbeat.get_srcComponent() == 1
    for kind in ("SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION", "LOCAL_POSITION_NED",
                 "ATTITUDE", "ATTITUDE_QUATERNION", "ODOMETRY", "HIGHRES_IMU", "TIMESYNC",
                 "RC_CHANNELS"):
        assert bench.last(kind) is not None, kind
    assert bench.last("EXTENDED_SYS_STATE").landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_arming_is_acknowledged_and_shown_in_the_heartbeat(bench):
    assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED
    bench.run(1.1)
    heartbeat = bench.last("HEARTBEAT")
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert heartbeat.system_status == mavlink.MAV_STATE_ACTIVE
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED
    assert not bench.vehicle.armed


def test_unknown_commands_are_unsupported_and_bad_arm_params_too(bench):
    assert bench.command(mavlink.MAV_CMD_DO_SET_SERVO, 1, 1500) == mavlink.MAV_RESULT_UNSUPPORTED
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 3) == mavlink.MAV_RESULT_UNSUPPORTED
    assert bench.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 42, 0) == \
        mavlink.MAV_RESULT_TEMPORARILY_REJECTED


def test_in_flight_disarm_needs_px4s_force_magic(bench):
    bench.arm()
    assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF) == mavlink.MAV_RESULT_ACCEPTED
    bench.run(2.0)
    assert not bench.vehicle.landed
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == \
        mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert "Disarming denied: not landed" in bench.texts()
    assert bench.vehicle.armed
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                         px4_protocol.FORCE_ARM_DISARM_MAGIC) == mavlink.MAV_RESULT_ACCEPTED
    assert not bench.vehicle.armed


def test_highres_imu_rate_follows_set_message_interval(bench):
    def rate(messages):
        stamps = [m.time_usec for m in messages if m.get_type() == "HIGHRES_IMU"]
        return (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-6)

    assert rate(bench.run(1.0)) == pytest.approx(50, rel=0.05)
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                         mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 5000) == mavlink.MAV_RESULT_ACCEPTED
    messages = bench.run(1.0)
    assert rate(messages) == pytest.approx(200, rel=0.02)
    imu = [m for m in messages if m.get_type() == "HIGHRES_IMU"][-1]
    # PX4 semantics: FRD body, specific force: at rest on the ground z reads -g
    assert imu.zacc == pytest.approx(-9.80665, abs=0.05)
    assert abs(imu.xacc) < 0.05 and abs(imu.ygyro) < 1e-3
    assert imu.fields_updated & 0b111111 == 0b111111
    assert imu.time_usec == pytest.approx(bench.time * 1e6, abs=DT * 1e6)
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                         mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, -1) == mavlink.MAV_RESULT_ACCEPTED
    assert not [m for m in bench.run(0.5) if m.get_type() == "HIGHRES_IMU"]


def test_highres_imu_marks_air_data_in_the_first_message_after_it_and_repeats_it_after(bench):
    """PX4's HIGHRES_IMU.hpp: every message carries the last air data (zero before any),
    its fields (abs_pressure in hPa, pressure_alt, temperature: bits 9, 11, 12) marked
    updated only in the first message after the barometer published."""
    bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 5000)
    before = bench.all("HIGHRES_IMU", bench.run(0.1))[-1]
    assert before.abs_pressure == 0.0 and before.fields_updated == 0b111111
    pressure = isa_pressure(489.0)
    bench.px4.update(bench.time, air_data=AirData(pressure, pressure_altitude(pressure), 11.7))
    first, *later = bench.all("HIGHRES_IMU", bench.run(0.05))
    air_data_bits = (1 << 9) | (1 << 11) | (1 << 12)
    assert first.fields_updated == 0b111111 | air_data_bits
    assert first.abs_pressure == pytest.approx(pressure / 100.0)
    assert first.pressure_alt == pytest.approx(pressure_altitude(pressure))
    assert first.temperature == pytest.approx(11.7)
    assert later and all(m.fields_updated == 0b111111 for m in later)
    assert all(m.abs_pressure == first.abs_pressure for m in later)


def test_request_message_sends_autopilot_version_with_capabilities(bench):
    assert bench.command(mavlink.MAV_CMD_REQUEST_MESSAGE,
                         mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == mavlink.MAV_RESULT_ACCEPTED
    version = bench.last("AUTOPILOT_VERSION")
    for capability in (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2,
                       mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED,
                       mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
                       mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT):
        assert version.capabilities & capability
    assert bench.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 9999) == mavlink.MAV_RESULT_DENIED


def test_offboard_needs_one_setpoint_younger_than_com_of_loss_t(bench):
    """offboardCheck.cpp: offboard is available while the last setpoint is less than
    COM_OF_LOSS_T old; one setpoint is enough (MAVSDK's example starts right after one)."""
    bench.arm()
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    bench.send_velocity((0, 0, 0))
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    bench.run(1.0)  # no more setpoints: lost after COM_OF_LOSS_T, the failsafe holds
    assert bench.px4.mode == px4_protocol.AUTO_LOITER
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED


def test_offboard_signal_time_is_the_com_of_loss_t_parameter():
    bench = Bench(parameters={"COM_OF_LOSS_T": 0.0})  # PX4: offboard can never be entered
    try:
        bench.send_velocity((0, 0, 0))
        assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    finally:
        bench.close()


def test_disarmed_in_offboard_without_setpoints_the_mode_stays_and_arming_is_refused(bench):
    """No failsafe acts while disarmed (failsafe/framework.cpp); the offboard mode's
    requirement then fails the arming check, and SYS_STATUS's prearm bit says so."""
    assert bench.prearm_ok()
    bench.send_velocity((0, 0, 0))
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    assert bench.prearm_ok()
    bench.run(1.0)
    assert bench.px4.mode == px4_protocol.OFFBOARD
    assert not bench.prearm_ok()
    assert bench.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert "Arming denied: no offboard signal" in bench.texts()


def test_sys_status_reports_health_as_px4_does(bench):
    """SYS_STATUS.hpp: health set for every component without a failure, present and enabled
    for those the vehicle has; the prearm bit in health only."""
    status = bench.all("SYS_STATUS", bench.run(0.25))[-1]
    has = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
           | mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER | mavlink.MAV_SYS_STATUS_AHRS
           | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY)
    assert status.onboard_control_sensors_present == has
    assert status.onboard_control_sensors_enabled == has
    health = status.onboard_control_sensors_health
    assert health & has == has and health & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert not status.onboard_control_sensors_present & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert status.onboard_control_sensors_health_extended == mavlink.MAV_SYS_STATUS_RECOVERY_SYSTEM


def test_attitude_streams_at_the_onboard_rate_as_euler_angles_in_ned(bench):
    messages = bench.all("ATTITUDE", bench.run(1.0))
    assert len(messages) == pytest.approx(100, abs=2)  # PX4's Onboard mode: 100 Hz
    attitude = messages[-1]
    # the vehicle starts facing east (ENU yaw 0): heading +90 degrees from north in NED
    assert attitude.yaw == pytest.approx(math.pi / 2, abs=0.02)
    assert abs(attitude.roll) < 0.02 and abs(attitude.pitch) < 0.02
    assert attitude.time_boot_ms == pytest.approx(bench.time * 1e3, abs=DT * 1e3)


def test_rc_channels_stream_the_receiver_as_px4_forwards_it(bench):
    messages = bench.all("RC_CHANNELS", bench.run(1.0))
    assert len(messages) == pytest.approx(20, abs=1)  # PX4's Onboard mode: 20 Hz
    rc = messages[-1]
    assert (rc.chancount, rc.rssi) == (16, 100)
    assert [getattr(rc, f"chan{i}_raw") for i in range(1, 19)] == [1500] * 16 + [65535] * 2
    bench.px4.set_rc_channel(7, 2000)
    rc = bench.all("RC_CHANNELS", bench.run(0.1))[-1]
    assert rc.chan7_raw == 2000 and rc.chan6_raw == 1500
    for channel, pulse in ((0, 1500), (17, 1500), (1, 2600), (1, 1500.0), (True, 1500)):
        with pytest.raises(ValueError, match="RC"):
            bench.px4.set_rc_channel(channel, pulse)


def test_offboard_after_streaming_flies_the_velocity_in_ned(bench):
    bench.arm()
    bench.stream_velocity((1.0, 0.0, -0.5), 1.2)
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_ACCEPTED
    bench.stream_velocity((1.0, 0.0, -0.5), 3.0)
    bench.run(1.1)
    assert px4_protocol.Px4Mode.from_custom_mode(bench.last("HEARTBEAT").custom_mode) \
        == px4_protocol.OFFBOARD
    position = bench.last("LOCAL_POSITION_NED")
    assert position.x > 1.5 and position.z < -0.8 and abs(position.y) < 0.2  # north and up
    assert bench.vehicle.state.position[1] > 1.5  # north is the world's +y (ENU)


def test_body_ned_velocity_is_rotated_by_the_attitude(bench):
    bench.arm()
    body = {"frame": mavlink.MAV_FRAME_BODY_NED, "yaw": None}
    bench.stream_velocity((1.0, 0.0, -0.5), 1.2, **body)
    bench.set_mode(px4_protocol.OFFBOARD)
    bench.stream_velocity((1.0, 0.0, -0.5), 3.0, **body)
    x, y, z = bench.vehicle.state.position
    assert x > 1.5 and abs(y) < 0.2 and z > 0.5  # yaw 0 faces east: body forward is +x ENU


@pytest.mark.parametrize("action, mode", [("hold", px4_protocol.AUTO_LOITER),
                                          ("land", px4_protocol.AUTO_LAND)])
def test_offboard_loss_failsafe_after_com_of_loss_t(action, mode):
    bench = Bench(Px4Options(offboard_loss_action=action, disarm_after_land=0.5))
    try:
        bench.arm()
        bench.stream_velocity((0.0, 0.0, -1.0), 1.2)
        bench.set_mode(px4_protocol.OFFBOARD)
        bench.stream_velocity((0.0, 0.0, -1.0), 1.0)
        bench.run(0.9)
        assert bench.px4.mode == px4_protocol.OFFBOARD
        bench.run(0.2)
        assert bench.px4.mode == mode
        assert any("offboard lost" in text for text in bench.texts())
        if action == "land":
            bench.run(6.0)
            assert bench.vehicle.landed and not bench.vehicle.armed
    finally:
        bench.close()


def test_a_vehicle_flown_down_onto_the_floor_in_offboard_is_disarmed_as_in_land():
    """Commander's auto-disarm (Commander.cpp, handleAutoDisarm) holds in every mode once the
    vehicle has taken off since arming: Offboard setpoints flown into the floor end with the
    motors off COM_DISARM_LAND seconds after the touch-down, the mode kept. Armed on the
    ground and not yet taken off, it stays armed."""
    bench = Bench(Px4Options(disarm_after_land=0.5))
    try:
        bench.arm()
        bench.stream_velocity((0.0, 0.0, 0.5), 1.2)  # on the ground, pushed down
        bench.set_mode(px4_protocol.OFFBOARD)
        bench.stream_velocity((0.0, 0.0, 0.5), 1.0)
        assert bench.vehicle.landed and bench.vehicle.armed  # never took off
        bench.stream_velocity((0.0, 0.0, -1.0), 1.5)  # up 1.5 m
        assert not bench.vehicle.landed and bench.vehicle.armed
        for _ in range(60):  # down into the floor, to the touch-down
            bench.stream_velocity((0.0, 0.0, 1.0), 0.1)
            if bench.vehicle.landed:
                break
        assert bench.vehicle.landed and bench.vehicle.armed  # not yet the delay
        bench.stream_velocity((0.0, 0.0, 1.0), 0.3)
        assert bench.vehicle.armed
        bench.stream_velocity((0.0, 0.0, 1.0), 0.3)
        assert not bench.vehicle.armed and bench.px4.mode == px4_protocol.OFFBOARD
        assert "Disarmed by landing" in bench.texts()
        bench.arm()  # armed again on the ground: not taken off since this arming
        bench.run(1.0)
        assert bench.vehicle.landed and bench.vehicle.armed
    finally:
        bench.close()


def test_unsupported_frames_are_rejected_and_do_not_move_the_vehicle(bench):
    bench.arm()
    start = bench.vehicle.state.position
    messages = bench.stream_velocity((1.0, 0.0, -1.0), 1.2, frame=mavlink.MAV_FRAME_LOCAL_ENU)
    assert any("coordinate frame 4" in text
               for text in bench.texts(messages))
    assert bench.set_mode(px4_protocol.OFFBOARD) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert np.linalg.norm(bench.vehicle.state.position - start) < 0.01


def test_takeoff_climbs_to_the_takeoff_altitude_then_holds_and_land_disarms(bench):
    bench.arm()
    assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan,
                         math.nan) == mavlink.MAV_RESULT_ACCEPTED
    bench.run(6.0)  # PX4's smoothed climb, the default: over 4 s (below)
    assert bench.px4.mode == px4_protocol.AUTO_LOITER
    assert bench.vehicle.state.position[2] == pytest.approx(2.5, abs=0.3)
    assert bench.last("EXTENDED_SYS_STATE").landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    assert bench.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
    bench.run(2.0)
    assert -bench.vehicle.state.velocity[2] == pytest.approx(0.7, abs=0.1)  # MPC_LAND_SPEED
    bench.run(4.0)
    assert bench.vehicle.landed and not bench.vehicle.armed


def smoothed_takeoff_rates(parameters=None, seconds=6.0) -> np.ndarray:
    """The vertical speed, every tick, of a smoothed take-off to MIS_TAKEOFF_ALT (2.5 m)."""
    bench = Bench(Px4Options(), parameters=parameters)
    try:
        bench.arm()
        assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan,
                             math.nan, math.nan) == mavlink.MAV_RESULT_ACCEPTED
        climb = []
        bench.run(seconds, each_tick=lambda: climb.append(
            (bench.px4.mode, bench.vehicle.state.velocity[2])))
        assert bench.px4.mode == px4_protocol.AUTO_LOITER
        assert bench.vehicle.state.position[2] == pytest.approx(2.5, abs=0.15)
    finally:
        bench.close()
    return np.array([v for mode, v in climb if mode == px4_protocol.AUTO_TAKEOFF])


def test_a_smoothed_takeoff_climbs_as_px4s():
    """PX4's take-off is a smoothed climb (FlightTaskAuto.cpp, _updateTrajConstraints): at most
    MPC_TKO_SPEED, and an acceleration of at most MPC_TKO_SPEED / MPC_TKO_RAMP_T = 0.5 m/s²
    (1.5 m/s over 3 s) up and down, so the climb stops without a jolt."""
    rates = smoothed_takeoff_rates()
    assert 1.0 < rates.max() < 1.5  # 2.5 m does not leave room to reach 1.5 m/s at 0.5 m/s²
    assert np.abs(np.diff(rates) / DT).max() < 0.5 * 1.2  # the vehicle lags its setpoint
    assert len(rates) * DT > 4.0  # a velocity step climbs 2.5 m in under 2 s


def test_the_step_takeoff_climbs_at_the_takeoff_speed_at_once():
    """``smooth_takeoff = false``, the take-off the earlier measurements flew: a velocity step
    to MPC_TKO_SPEED (1.5 m/s), stopped by the position hold at the height."""
    bench = Bench(Px4Options(smooth_takeoff=False))
    try:
        bench.arm()
        assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan,
                             math.nan, math.nan) == mavlink.MAV_RESULT_ACCEPTED
        bench.run(1.0)
        assert bench.vehicle.state.velocity[2] == pytest.approx(1.5, abs=0.1)
        bench.run(2.0)
        assert bench.px4.mode == px4_protocol.AUTO_LOITER
    finally:
        bench.close()


def test_a_smoothed_takeoff_honours_its_ramp_time():
    """MPC_TKO_RAMP_T 1 s lets the take-off reach MPC_TKO_SPEED (1.5 m/s at 1.5 m/s²)."""
    rates = smoothed_takeoff_rates({"MPC_TKO_RAMP_T": 1.0}, seconds=4.0)
    assert rates.max() == pytest.approx(1.5, abs=0.1)


def test_signing_ignores_unsigned_commands_and_accepts_signed_ones():
    bench = Bench(Px4Options(signing_key=KEY.hex()))
    try:
        assert bench.arm() is None  # unsigned: ignored, no ACK
        assert not bench.vehicle.armed
        bench.client.setup_signing(KEY)
        assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED
        assert bench.vehicle.armed
        assert bench.last("COMMAND_ACK").get_signed()
    finally:
        bench.close()


def test_setup_signing_keys_px4_and_only_the_key_changes_it_again(bench):
    """PX4 v1.18's rules (mavlink_sign_control.cpp, check_for_signing): a keyless PX4 takes a
    key from anyone; then it signs, ignores unsigned commands and a new key unless signed with
    its key, refuses one while armed, and a signed blank key turns signing off."""
    def setup_signing(key):  # an all-zero key goes with timestamp 0: the blank key
        bench.client.mav.setup_signing_send(1, 1, list(key), signing_timestamp() if any(key)
                                            else 0)
        return bench.run(0.05)

    setup_signing(KEY)
    assert bench.px4.signing_key == KEY
    heartbeat = bench.all("HEARTBEAT", bench.run(1.0))[-1]
    assert heartbeat.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED
    assert bench.arm() is None  # unsigned: ignored, no ACK
    setup_signing(bytes(32))  # unsigned blank key: ignored too
    assert bench.px4.signing_key == KEY
    bench.client.setup_signing(KEY)
    assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED
    assert "MAVLink signing: rejected while armed" in bench.texts(setup_signing(bytes(32 * [1])))
    assert bench.px4.signing_key == KEY
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED
    setup_signing(bytes(32))  # signed with the key: signing off
    assert bench.px4.signing_key is None
    bench.client.stop_signing()
    assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED


def test_garbage_bytes_neither_crash_the_mock_nor_change_its_state(bench):
    bench.arm()
    rng = np.random.default_rng(7)
    before = (bench.px4.mode, bench.vehicle.armed, bench.px4.message_rate_hz(
        mavlink.MAVLINK_MSG_ID_HIGHRES_IMU))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        target = (bench.server.address.host, bench.server.address.port)
        for size in rng.integers(1, 300, size=200):
            raw.sendto(rng.integers(0, 256, size=size, dtype=np.uint8).tobytes(), target)
        # and frames that look like MAVLink 2 but are corrupt
        raw.sendto(bytes([0xFD, 33, 0, 0, 0, 255, 190, 76, 0, 0]) + bytes(40), target)
        bench.run(0.1)
    assert bench.server.bad_data_count > 0
    assert (bench.px4.mode, bench.vehicle.armed, bench.px4.message_rate_hz(
        mavlink.MAVLINK_MSG_ID_HIGHRES_IMU)) == before
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED


def test_timesync_is_answered_and_the_mock_uses_answers_to_its_own():
    bench = Bench()
    try:
        bench.run(0.5)
        bench.client.mav.timesync_send(0, 123456789)
        reply = [m for m in bench.run(0.02) if m.get_type() == "TIMESYNC" and m.tc1 != 0][-1]
        assert reply.ts1 == 123456789
        assert reply.tc1 == pytest.approx(bench.time * 1e9, abs=0.03e9)

        offset_ns = 5_000_000_000  # the client's clock runs 5 s ahead of the mock's boot time

        def answer():
            for m in bench.client.receive_pending():
                bench.received.append(m)
                if m.get_type() == "TIMESYNC" and m.tc1 == 0:
                    bench.client.mav.timesync_send(int(bench.time * 1e9) + offset_ns, m.ts1)
        bench.run(1.1, answer)
        assert bench.px4.timesync_offset_ns == pytest.approx(offset_ns, abs=0.01e9)

        # the timesync_stop fault: neither answers nor requests (a request the mock sent before
        # it, stamped earlier, may still arrive: loopback delivery can lag on a loaded host)
        bench.px4.suppressed_streams.add(mavlink.MAVLINK_MSG_ID_TIMESYNC)
        stopped_ns = bench.time * 1e9
        bench.client.mav.timesync_send(0, 987654321)
        assert not [m for m in bench.all("TIMESYNC", bench.run(1.0))
                    if m.tc1 != 0 or m.ts1 >= stopped_ns]
    finally:
        bench.close()


def test_pty_link_serves_the_same_px4():
    bench = Bench(url="pty")
    try:
        bench.run(0.1)
        heartbeat = bench.last("HEARTBEAT")
        assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
        assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED
    finally:
        bench.close()


def test_a_collision_ends_the_flight():
    def wall(points):  # a wall across the world at x = 2 m
        return 2.0 - np.asarray(points)[:, 0]
    bench = Bench(obstacle_clearance=wall)
    try:
        bench.arm()
        bench.stream_velocity((0.0, 2.0, -0.5), 1.2)  # NED east = ENU +x, towards the wall
        bench.set_mode(px4_protocol.OFFBOARD)
        bench.stream_velocity((0.0, 2.0, -0.5), 3.0)
        assert bench.vehicle.collision is not None and not bench.vehicle.armed
        assert any("Collision" in text for text in bench.texts())
        bench.run(1.0)
        assert bench.last("HEARTBEAT").system_status == mavlink.MAV_STATE_EMERGENCY
        assert bench.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    finally:
        bench.close()


def test_external_vision_odometry_moves_the_estimate_not_the_truth(bench):
    bench.run(0.5, lambda: bench.send_vision(3.0, 4.0, 0.0))
    position = bench.last("LOCAL_POSITION_NED")
    assert (position.x, position.y) == (pytest.approx(3.0, abs=0.1), pytest.approx(4.0, abs=0.1))
    assert np.linalg.norm(bench.vehicle.state.position) < 0.01


def test_options_reject_bad_values():
    with pytest.raises(ValueError, match="offboard_loss_action"):
        Px4Options(offboard_loss_action="terminate")
    with pytest.raises(ValueError, match="64 hex digits"):
        Px4Options(signing_key="abcd")
    with pytest.raises(ValueError, match="offboard_loss_timeout"):
        Px4Options(offboard_loss_timeout=0.0)


def test_commands_with_nan_where_a_number_is_needed_are_denied(bench):
    assert bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, math.nan, 5000) == \
        mavlink.MAV_RESULT_DENIED
    assert bench.command(mavlink.MAV_CMD_DO_SET_MODE, 1, math.nan, 0) == \
        mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert bench.px4.mode == px4_protocol.AUTO_LOITER


def test_serve_in_lockstep_runs_simulated_time_and_wakes_sleepers_on_it():
    import asyncio

    from drivers.clock import SimClock
    from drivers.sim.serve import serve

    clock = SimClock()
    woke_at = []

    async def main():
        async def sleeper():
            await clock.sleep(0.5)
            woke_at.append(clock.now())
        task = asyncio.create_task(sleeper())
        summary = await serve("pty", None, clock_mode="lockstep", duration=1.0, sim_clock=clock,
                              seed=3)
        await task
        return summary

    summary = asyncio.run(main())
    assert summary.steps == 200 and summary.sim_time == pytest.approx(1.0)
    assert summary.collision is None and summary.pty_path.startswith("/dev/")
    assert woke_at == [pytest.approx(0.5)]


def test_serve_rejects_bad_arguments():
    import asyncio

    from drivers.sim.serve import serve

    with pytest.raises(ValueError, match="clock_mode"):
        asyncio.run(serve("pty", None, clock_mode="fast"))
    with pytest.raises(ValueError, match="duration"):
        asyncio.run(serve("pty", None, duration=-1.0))
    with pytest.raises(ValueError, match="scheme"):
        asyncio.run(serve("udp://127.0.0.1:1", None, duration=1.0))


def test_serve_starts_the_vehicle_at_the_worlds_first_route():
    import asyncio

    from drivers.sim.serve import serve
    from drivers.sim.world import build_world

    world = build_world("dome", seed=0)
    served = []
    summary = asyncio.run(serve("pty", world, clock_mode="lockstep", duration=0.1,
                                on_ready=served.append))
    assert summary.collision is None
    assert served[0].vehicle.state.position[:2] == pytest.approx(world.routes[0].start[:2])


def test_a_reboot_stops_the_motors_goes_silent_then_boots_from_zero_keeping_its_parameters(
        bench):
    """A brown-out in the air: the motors stop at once, nothing is read or sent while the
    board boots (BOOT_DURATION_S), then PX4 streams again disarmed in Hold, its boot time
    from zero, at its default rates (the companion's IMU rate request is gone), its
    parameters kept."""
    from drivers.sim.mock_px4 import BOOT_DURATION_S

    bench.arm()
    bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
    bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU,
                  5000)
    bench.client.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.7, mavlink.MAV_PARAM_TYPE_REAL32)
    bench.run(3.0)
    height = bench.vehicle.state.position[2]
    assert height > 1.0
    bench.px4.reboot()
    assert not bench.vehicle.armed
    silent = bench.run(BOOT_DURATION_S - 0.1)
    assert silent == [] and bench.vehicle.state.position[2] < height  # falling
    assert bench.arm() is None  # a booting board answers nothing
    messages = bench.run(1.2)
    heartbeat = bench.all("HEARTBEAT", messages)[-1]
    assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert bench.px4.mode == px4_protocol.AUTO_LOITER
    stamps = [m.time_usec * 1e-6 for m in bench.all("HIGHRES_IMU", messages)]
    assert 0.0 <= stamps[0] < 0.1 and stamps[-1] < 1.3  # from zero again
    assert (len(stamps) - 1) / (stamps[-1] - stamps[0]) == pytest.approx(50, rel=0.1)
    assert bench.px4.parameters["COM_OF_LOSS_T"] == pytest.approx(0.7)


@pytest.mark.parametrize("delivery, order", [
    ("repeat", lambda stamps: all(b - a in (0, 5000) for a, b in zip(stamps, stamps[1:]))),
    ("reorder", lambda stamps: sorted(stamps) == sorted(set(stamps))
     and sum(b < a for a, b in zip(stamps, stamps[1:])) >= len(stamps) // 2 - 1),
])
def test_imu_delivery_faults_repeat_or_swap_the_stamps_px4_sends(bench, delivery, order):
    bench.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIGHRES_IMU,
                  5000)
    bench.px4.imu_delivery = delivery
    stamps = [m.time_usec for m in bench.all("HIGHRES_IMU", bench.run(0.5))]
    assert len(stamps) > 50 and order(stamps), stamps[:12]
    if delivery == "repeat":
        assert len(stamps) == 2 * len(set(stamps))


@pytest.mark.parametrize("name, value", [("MPC_JERK_AUTO", 0.0), ("MPC_ACC_UP_MAX", -1.0),
                                         ("MPC_TKO_SPEED", 0.0), ("MPC_TKO_RAMP_T", -0.5)])
def test_take_off_limits_the_mock_cannot_fly_are_refused(name, value):
    with pytest.raises(ValueError, match="cannot take off"):
        check_parameter(name, value)


def test_a_takeoff_without_a_ramp_accelerates_past_the_ramps_limit():
    """MPC_TKO_RAMP_T 0 is PX4's "no ramp": the acceleration is bounded by MPC_ACC_UP_MAX
    (4 m/s²) and the jerk alone, not by the ramp's 0.5 m/s²."""
    assert check_parameter("MPC_TKO_RAMP_T", 0.0) == 0.0
    rates = smoothed_takeoff_rates({"MPC_TKO_RAMP_T": 0.0}, seconds=8.0)
    assert np.abs(np.diff(rates) / DT).max() > 1.0


def test_a_takeoff_armed_into_again_starts_from_rest():
    """Disarmed mid-climb (a forced disarm: the vehicle falls) and armed again in the same
    mode, the climb starts from rest, not where the interrupted one had got to."""
    bench = Bench(Px4Options())
    try:
        bench.arm()
        bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan,
                      math.nan)
        bench.run(1.5)
        assert bench.vehicle.state.velocity[2] > 0.4
        bench.px4.force_disarm("test")
        bench.run(3.0)
        assert bench.vehicle.landed
        assert bench.px4.mode == px4_protocol.AUTO_TAKEOFF
        assert bench.arm() == mavlink.MAV_RESULT_ACCEPTED
        bench.run(0.5)
        assert 0.0 <= bench.vehicle.state.velocity[2] < 0.5 * 0.5 + 0.05
    finally:
        bench.close()
