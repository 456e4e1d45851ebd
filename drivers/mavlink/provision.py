"""Giving PX4 the signing key: SETUP_SIGNING over a link to it, then proof that it signs with it.

PX4 v1.18 and later (``src/modules/mavlink/mavlink_sign_control.cpp``, ``check_for_signing``,
as reworked by PR #26894) takes a key from a SETUP_SIGNING message that passed its signature
check: any one while it has no key, one signed with its current key once it has one; none while
armed. It keeps the key and ``initial_timestamp`` in ``/mavlink/mavlink-signing-key.bin`` on its
SD card and from then on signs everything it sends, on every link (USB too), and refuses what is
unsigned or wrongly signed but HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and COLLISION. It sends no
acknowledgement: the proof is PX4's next HEARTBEAT verifying under the new key. (PX4 before
v1.18 has no MAVLink signing; the MAV_SIGN_CFG parameter of PX4's main branch from late 2025 to
March 2026 never reached a release.)

The message carries the key in clear: send it over a wire (USB, the companion's UART), never a
radio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.clock import Clock
from drivers.mavlink.link import MavlinkLink, mavlink, open_link
from drivers.mavlink.signing import signing_timestamp

#: Seconds between two looks at the link.
POLL_S = 0.01
#: Seconds between our HEARTBEATs (PX4 on UDP learns where we are from them).
HEARTBEAT_S = 1.0


class ProvisionError(RuntimeError):
    """PX4 did not take the key; the message says why and what to do."""


@dataclass(frozen=True)
class Provisioned:
    """What provisioning found: ``had_key``, PX4 signed before (the key was rotated);
    ``already``, it signed with this very key, so nothing was sent."""

    had_key: bool
    already: bool


async def provision(options, clock: Clock, key: bytes, *, current_key: bytes | None = None,
                    timeout_s: float = 5.0) -> Provisioned:
    """Give PX4 at ``options`` (a ``[mavlink]`` table: url, our ids, PX4's) the signing
    ``key``, signing the SETUP_SIGNING with ``current_key`` when PX4 already has a key (a
    rotation); waits at most ``timeout_s`` for each answer. :class:`ProvisionError` when PX4
    is silent, armed, keyed with another key than ``current_key``, or does not take it."""
    link = open_link(options.url, source_system=options.system_id,
                     source_component=options.component_id)
    try:
        session = _Session(link, clock, options, timeout_s)
        return await session.provision(key, current_key)
    finally:
        link.close()


class _Session:
    """One provisioning over an open link: PX4's heartbeats awaited, our own sent."""

    def __init__(self, link: MavlinkLink, clock: Clock, options, timeout_s: float):
        self.link, self.clock, self.options, self.timeout_s = link, clock, options, timeout_s
        self.px4 = (options.target_system, options.target_component)
        self.texts: list[str] = []
        self._next_heartbeat = -math.inf

    async def provision(self, key: bytes, current_key: bytes | None) -> Provisioned:
        first = await self._heartbeat()
        if first is None:
            raise ProvisionError(f"no HEARTBEAT from PX4 (system {self.px4[0]} component "
                                 f"{self.px4[1]}): "
                                 + self.link.describe_silence(self.timeout_s, self.link.traffic))
        if first.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
            raise ProvisionError("PX4 is armed, and refuses a new key while armed: land and "
                                 "disarm first")
        # signed at all (pymavlink's get_signed() says "verified", which needs a key)
        had_key = bool(first.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED)
        if had_key:
            if await self._verifies(key):
                return Provisioned(had_key=True, already=True)
            await self._sign_as_px4(current_key)
        self._send_setup_signing(key)
        if not await self._verifies(key):
            said = f" (PX4 said: {'; '.join(self.texts)})" if self.texts else ""
            raise ProvisionError(f"PX4 did not take the key: no HEARTBEAT of it verified with "
                                 f"the key in {self.timeout_s:g} s{said}; MAVLink signing needs "
                                 "PX4 v1.18 or later")
        return Provisioned(had_key=had_key, already=False)

    async def _sign_as_px4(self, current_key: bytes | None) -> None:
        """Sign from now on with PX4's present key, which a new one must be signed with."""
        if current_key is None:
            raise ProvisionError("PX4 already signs with another key: give that key with "
                                 "--current-key-file to replace it, or delete "
                                 "/mavlink/mavlink-signing-key.bin from PX4's SD card and "
                                 "reboot it")
        if not await self._verifies(current_key):
            raise ProvisionError("PX4 signs with neither this key nor the one of "
                                 "--current-key-file: find its key, or delete "
                                 "/mavlink/mavlink-signing-key.bin from its SD card and "
                                 "reboot it")

    def _send_setup_signing(self, key: bytes) -> None:
        self.link.send(self.link.mav.setup_signing_encode(
            self.px4[0], self.px4[1], list(key), signing_timestamp()))

    async def _verifies(self, key: bytes) -> bool:
        """Whether a HEARTBEAT of PX4 passes the signature check with ``key`` (which our link
        then keeps signing with) within the timeout."""
        self.link.setup_signing(key)
        return await self._heartbeat() is not None

    async def _heartbeat(self):
        """PX4's next HEARTBEAT that this link accepts, None after the timeout; our own
        HEARTBEATs go out meanwhile, PX4's STATUSTEXTs are kept."""
        deadline = self.clock.now() + self.timeout_s
        while self.clock.now() < deadline:
            self._send_heartbeat()
            for message in self.link.receive_pending():
                source = (message.get_srcSystem(), message.get_srcComponent())
                if source != self.px4:
                    continue
                if message.get_type() == "HEARTBEAT":
                    return message
                if message.get_type() == "STATUSTEXT":
                    self.texts.append(message.text)
            await self.clock.sleep(POLL_S)
        return None

    def _send_heartbeat(self) -> None:
        now = self.clock.now()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + HEARTBEAT_S
            self.link.send(self.link.mav.heartbeat_encode(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                mavlink.MAV_STATE_STANDBY))
