"""PX4's MAVLink conventions: custom flight modes, the unsigned-message allowlist, type masks.

Sources (PX4-Autopilot):
- ``src/modules/commander/px4_custom_mode.h``: ``union px4_custom_mode { struct { uint16_t
  reserved; uint8_t main_mode; uint8_t sub_mode; }; uint32_t data; }`` — on PX4's
  little-endian targets the main mode is bits 16-23 of HEARTBEAT.custom_mode and the sub
  mode bits 24-31; the low 16 bits are zero.
- ``src/modules/mavlink/mavlink_sign_control.cpp`` (``accept_unsigned``, PX4 v1.18 and
  main since PR #26894): with a key, only HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and COLLISION
  are accepted unsigned; without one, everything.
- ``src/modules/mavlink/mavlink_receiver.cpp`` (handle_message_set_position_target_local_ned):
  MAV_FRAME_LOCAL_NED and MAV_FRAME_BODY_NED only; a bit set in type_mask means "ignore".
- ``src/modules/commander/Commander.cpp``: param2 = 21196 on MAV_CMD_COMPONENT_ARM_DISARM
  forces the action; for commands from outside (MAVLink) it skips the landed check on
  disarm but never the preflight checks on arm.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from drivers.mavlink.link import mavlink


class MainMode(IntEnum):
    """PX4_CUSTOM_MAIN_MODE."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class AutoSubMode(IntEnum):
    """PX4_CUSTOM_SUB_MODE_AUTO (sub modes of MainMode.AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    RTGS = 7
    FOLLOW_TARGET = 8
    PRECLAND = 9


@dataclass(frozen=True)
class Px4Mode:
    """A PX4 flight mode: main mode and, for AUTO, a sub mode (0 otherwise)."""

    main: MainMode
    sub: int = 0

    @property
    def custom_mode(self) -> int:
        """HEARTBEAT.custom_mode as PX4 packs it: main << 16 | sub << 24."""
        return (int(self.main) << 16) | (int(self.sub) << 24)

    @property
    def name(self) -> str:
        """The name QGroundControl and MAVSDK use: 'OFFBOARD', 'AUTO.LOITER', ..."""
        if self.main == MainMode.AUTO:
            return f"AUTO.{AutoSubMode(self.sub).name}"
        return self.main.name

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> "Px4Mode":
        """Unpack HEARTBEAT.custom_mode; ValueError for bits PX4 never sets."""
        if not 0 <= custom_mode < 2**32 or custom_mode & 0xFFFF:
            raise ValueError(f"custom_mode {custom_mode:#x} is not a PX4 mode "
                             "(low 16 bits must be zero)")
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        return cls.from_numbers(main, sub)

    @classmethod
    def from_numbers(cls, main: int, sub: int = 0) -> "Px4Mode":
        """From MAV_CMD_DO_SET_MODE's param2 (main) and param3 (sub); ValueError if unknown."""
        try:
            main_mode = MainMode(int(main))
        except ValueError:
            raise ValueError(f"unknown PX4 main mode {main}") from None
        if main_mode != MainMode.AUTO:
            return cls(main_mode, 0)
        try:
            return cls(main_mode, AutoSubMode(int(sub)))
        except ValueError:
            raise ValueError(f"unknown PX4 AUTO sub mode {sub}") from None

    @classmethod
    def from_name(cls, name: str) -> "Px4Mode":
        """From a name like 'OFFBOARD' or 'AUTO.LAND'; ValueError listing the known names."""
        main, _, sub = name.upper().partition(".")
        try:
            if main == "AUTO":
                return cls(MainMode.AUTO, AutoSubMode[sub])
            if sub:
                raise KeyError(name)
            return cls(MainMode[main], 0)
        except KeyError:
            known = [m.name for m in MainMode if m != MainMode.AUTO]
            known += [f"AUTO.{s.name}" for s in AutoSubMode]
            raise ValueError(f"unknown PX4 mode {name!r}; known: {', '.join(known)}") from None

    def __str__(self) -> str:
        return self.name


MANUAL = Px4Mode(MainMode.MANUAL)
ALTCTL = Px4Mode(MainMode.ALTCTL)
POSCTL = Px4Mode(MainMode.POSCTL)
ACRO = Px4Mode(MainMode.ACRO)
OFFBOARD = Px4Mode(MainMode.OFFBOARD)
STABILIZED = Px4Mode(MainMode.STABILIZED)
AUTO_READY = Px4Mode(MainMode.AUTO, AutoSubMode.READY)
AUTO_TAKEOFF = Px4Mode(MainMode.AUTO, AutoSubMode.TAKEOFF)
AUTO_LOITER = Px4Mode(MainMode.AUTO, AutoSubMode.LOITER)  # "Hold" in QGroundControl/MAVSDK
AUTO_MISSION = Px4Mode(MainMode.AUTO, AutoSubMode.MISSION)
AUTO_RTL = Px4Mode(MainMode.AUTO, AutoSubMode.RTL)
AUTO_LAND = Px4Mode(MainMode.AUTO, AutoSubMode.LAND)

#: MAV_CMD_COMPONENT_ARM_DISARM param2 that forces arming/disarming (Commander.cpp).
FORCE_ARM_DISARM_MAGIC = 21196

#: Messages PX4 accepts unsigned while it has a key (mavlink_sign_control.cpp,
#: ``unsigned_messages``: HEARTBEAT "for link discovery", the rest as the MAVLink spec says).
UNSIGNED_MESSAGE_IDS = frozenset({
    mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
    mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
    mavlink.MAVLINK_MSG_ID_COLLISION,
})


def accept_unsigned(message_id: int) -> bool:
    """PX4's rule for an unsigned message while it has a signing key."""
    return message_id in UNSIGNED_MESSAGE_IDS


#: Frames PX4 accepts in SET_POSITION_TARGET_LOCAL_NED (mavlink_receiver.cpp).
SUPPORTED_SETPOINT_FRAMES = frozenset({mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_NED})

# POSITION_TARGET_TYPEMASK bits: a set bit means "ignore this field".
IGNORE_POSITION = (mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE)
IGNORE_VELOCITY = (mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
                   | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE)
IGNORE_ACCELERATION = (mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
                       | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
                       | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE)
FORCE_SET = mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET
IGNORE_YAW = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
IGNORE_YAW_RATE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

#: type_mask for a velocity-only setpoint with a yaw rate (what MAVSDK's set_velocity_body
#: sends) and with an absolute yaw (set_velocity_ned).
TYPE_MASK_VELOCITY_YAW_RATE = IGNORE_POSITION | IGNORE_ACCELERATION | IGNORE_YAW
#: ... and with an acceleration feed-forward (PX4's PositionControl adds it to the output of
#: its velocity loop).
TYPE_MASK_VELOCITY_ACCELERATION_YAW_RATE = IGNORE_POSITION | IGNORE_YAW
TYPE_MASK_VELOCITY_YAW = IGNORE_POSITION | IGNORE_ACCELERATION | IGNORE_YAW_RATE
#: type_mask for a position setpoint with an absolute yaw.
TYPE_MASK_POSITION_YAW = IGNORE_VELOCITY | IGNORE_ACCELERATION | IGNORE_YAW_RATE
