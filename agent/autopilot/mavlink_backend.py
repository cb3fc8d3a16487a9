"""The pymavlink backend: ArduPilot (ArduCopter first), PX4 and generic MAVLink autopilots.

Identity: by default the agent speaks as the *vehicle's own system id* with component
``MAV_COMP_ID_ONBOARD_COMPUTER`` (191), the way companion computers do, so it never takes a system
id that another vehicle (1..250) or a ground station (usually 255) uses. Before the vehicle's first
heartbeat arrives (needed only for ``udpout:`` links, where the vehicle must hear us first) it uses
``target_system`` or 254. It sends its own HEARTBEAT at 1 Hz (MAV_TYPE_ONBOARD_CONTROLLER,
MAV_AUTOPILOT_INVALID). Pass ``source_system`` to force another id.

Threading: see :mod:`agent.autopilot.mavlink_link` (a reader thread feeds state and hands messages
to asyncio queues with ``call_soon_threadsafe``; nothing here blocks the event loop).

The full message mapping, retry rules and stream setup are in ``docs/autopilot-backends.md``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Sequence
from typing import Any

from agent.autopilot import mavlink_mission
from agent.autopilot.base import (
    CommandRefused,
    CommandTimeout,
    FenceSpec,
    LinkLost,
    MissionPoint,
    Telemetry,
)
from agent.autopilot.flavoured import FlavouredAutopilot, positive
from agent.autopilot.flavours import Flavour, flavour_for
from agent.autopilot.mavlink_link import MavlinkLink, mavlink, mission_result_name
from agent.autopilot.mavlink_router import MavlinkRouter
from agent.autopilot.mavlink_streams import StreamKeeper
from agent.autopilot.mavlink_telemetry import MavlinkTelemetry
from agent.autopilot.vehicle_state import VehicleState

log = logging.getLogger(__name__)

__all__ = ["MavlinkAutopilot", "decode_mode"]

POSITION_TARGET_TYPE_MASK = 0x0DF8  # use x/y/z only: ignore velocity, acceleration, yaw, yaw rate


def decode_mode(autopilot: int, mav_type: int, base_mode: int, custom_mode: int) -> str:
    """The upper-case mode name of a HEARTBEAT (ArduPilot custom modes, PX4 main/sub modes)."""
    return flavour_for(autopilot).decode_mode(mav_type, base_mode, custom_mode)


class MavlinkAutopilot(FlavouredAutopilot):
    """An :class:`Autopilot` over a pymavlink connection (serial, UDP or TCP), MAVLink 2.

    Firmware differences (ArduPilot, PX4) come from :attr:`flavour`, picked from the heartbeat.
    Its parts: the link (:mod:`~agent.autopilot.mavlink_link`), the telemetry decoder
    (:mod:`~agent.autopilot.mavlink_telemetry`) into the shared vehicle state, the stream keeper
    (:mod:`~agent.autopilot.mavlink_streams`) and the mission protocol
    (:mod:`~agent.autopilot.mavlink_mission`); this class turns commands into MAVLink.

    Args:
        connection: ``/dev/ttyAMA0:921600``, ``/dev/serial0,921600``, ``udpin:0.0.0.0:14550``,
            ``udpout:192.168.1.10:14550``, ``tcp:127.0.0.1:5760``.
        target_system: the vehicle's system id; None takes the first autopilot heartbeat seen.
        source_system: our system id; None = the vehicle's (companion-computer convention).
        source_component: our component id, default MAV_COMP_ID_ONBOARD_COMPUTER (191).
        heartbeat_timeout_s: heartbeat silence after which commands raise :class:`LinkLost`.
        command_timeout_s / command_retries: per-send ACK wait and number of sends.
        telemetry_hz: rate asked for position, attitude, HUD, landed state and mission progress.
        local_offset_targets: use MAV_FRAME_LOCAL_OFFSET_NED for :meth:`go_by`; None = when the
            vehicle's AUTOPILOT_VERSION advertises SET_POSITION_TARGET_LOCAL_NED.
        tlog_path: append every MAVLink message received and sent to this .tlog file (MAVProxy format).
        mavlink_out: extra ground-station endpoints sharing the link (``udp:HOST:PORT``, ``udpin:``,
            ``tcpin:``), routed by target; what they command counts as the pilot's
            (agent/autopilot/mavlink_router.py).
        signing_key: MAVLink 2 signing secret (32 bytes, 64 hex digits or a passphrase); when set,
            every frame we send is signed and unsigned frames from the vehicle are dropped unless
            ``allow_unsigned`` (RADIO_STATUS is always accepted).
    """

    def __init__(
        self,
        connection: str,
        *,
        target_system: int | None = None,
        source_system: int | None = None,
        source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER,
        heartbeat_timeout_s: float = 3.0,
        command_timeout_s: float = 1.5,
        command_retries: int = 5,
        telemetry_hz: float = 10.0,
        local_offset_targets: bool | None = None,
        signing_key: bytes | str | None = None,
        allow_unsigned: bool = False,
        tlog_path: str | None = None,
        mavlink_out: Sequence[str] = (),
    ) -> None:
        if telemetry_hz <= 0:
            raise ValueError("telemetry_hz must be positive")
        self.connection = connection
        self.telemetry_hz = telemetry_hz
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.command_timeout_s = command_timeout_s
        self.command_retries = command_retries
        self._local_offset_option = local_offset_targets
        self._state = VehicleState()
        self._decoder = MavlinkTelemetry(self._state)
        self._link = MavlinkLink(
            connection,
            target_system=target_system,
            source_system=source_system,
            source_component=source_component,
            heartbeat_timeout_s=heartbeat_timeout_s,
            command_timeout_s=command_timeout_s,
            command_retries=command_retries,
            on_message=self._decoder.on_message,
            on_tick=self._on_tick,
            on_link_restored=self._on_link_restored,
            signing_key=signing_key,
            allow_unsigned=allow_unsigned,
            tlog_path=tlog_path,
        )
        if mavlink_out:
            # Raises RouterConfigError (a ValueError naming the endpoint) for a bad string now.
            self._link.router = MavlinkRouter(mavlink_out, self._link.send_raw, self._link.own_ids)
        self._streams = StreamKeeper(self._link, self._state, telemetry_hz)
        self._pending_speed: float | None = None  # set_speed in a mode that refuses it
        self._leg_speed: float | None = None  # PX4: the last speed asked for, sent with each reposition
        self._connected = False
        self._closed = False

    # ================================================================== lifecycle

    async def connect(self, timeout: float = 30.0) -> None:
        if self._connected:
            return
        loop = asyncio.get_running_loop()
        started = time.monotonic()
        await loop.run_in_executor(None, self._link.open)
        self._link.start()
        while not self._link.vehicle_found.is_set():
            if time.monotonic() - started > timeout:
                await self.close()
                raise LinkLost(f"no autopilot heartbeat on {self.connection} within {timeout:.0f} s")
            await asyncio.sleep(0.05)
        self._connected = True
        await self._streams.setup()

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._connected = False
        await asyncio.get_running_loop().run_in_executor(None, self._link.stop)

    @property
    def flavour(self) -> Flavour:
        """The vehicle's firmware conventions, from its heartbeat (ArduPilot until one is seen)."""
        vehicle = self._link.vehicle
        return flavour_for(vehicle.autopilot if vehicle is not None else None)

    @property
    def link(self) -> MavlinkLink:
        """The underlying link (for tools and tests: raw sends, subscriptions)."""
        return self._link

    def _on_tick(self) -> None:  # reader thread, every 0.5 s
        self._streams.on_tick()

    def _on_link_restored(self) -> None:  # reader thread
        self._streams.on_link_restored()

    # ================================================================== telemetry

    def telemetry(self) -> Telemetry:
        texts = [t.text for t in self._link.status_texts()]
        return self._state.snapshot(texts, self._link.last_heartbeat_monotonic)

    # ================================================================== modes

    def _mode_now(self) -> str:
        return self._state.mode_now()

    async def set_mode(self, name: str) -> None:
        """Switch flight mode by name (ArduPilot custom mode / PX4 main+sub mode); waits for the ACK."""
        name = name.upper()
        self._pilot.movable(f"mode {name}")
        what = f"mode {name}"
        vehicle = self._link.vehicle
        flavour = self.flavour
        mav_type = vehicle.mav_type if vehicle is not None else 2
        params, custom, raw = self._mode_request(name, mav_type)
        before = self._pilot.expect(raw)
        try:
            await self._link.command(what, mavlink.MAV_CMD_DO_SET_MODE, params)
        except CommandRefused as exc:
            if "UNSUPPORTED" not in exc.reason:
                self._pilot.refused(raw, before)
                raise
            await self._set_mode_legacy(what, name, custom)
            return
        self._set_leg_active(False)
        if flavour.guided_mode is not None:
            # Accepted: the mode has changed, though the next heartbeat may be up to 1 s away.
            # Later decisions (send the speed now? switch to GUIDED first?) need it at once.
            self._state.show_mode(name)

    async def _set_mode_legacy(self, what: str, name: str, custom: int) -> None:
        """SET_MODE message for autopilots without MAV_CMD_DO_SET_MODE; confirmed by the heartbeat."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        deadline = time.monotonic() + self.command_timeout_s * self.command_retries
        while time.monotonic() < deadline:
            self._link.send(mavlink.MAVLink_set_mode_message(self._link.target_system, base, custom))
            for _ in range(5):
                await asyncio.sleep(0.1)
                self._link.ensure_link(what)
                if self._mode_now() == name:
                    return
        raise CommandTimeout(what, self.command_timeout_s * self.command_retries)

    async def _ensure_mode(self, name: str) -> None:
        if self._mode_now() != name:
            await self.set_mode(name)

    # ================================================================== commands

    async def arm(self, deadline_s: float = 60.0) -> None:
        self._pilot.movable("arm")

        async def attempt() -> None:
            if self.flavour.guided_mode is not None:
                await self._ensure_mode(self.flavour.guided_mode)
            await self._link.command("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1,))

        await self._arm_retrying(deadline_s, attempt)

    async def disarm(self) -> None:
        self._pilot.movable("disarm")
        await self._link.command("disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0,))

    async def takeoff(self, alt_rel_m: float) -> None:
        self._pilot.movable("takeoff")
        positive("takeoff altitude", alt_rel_m)
        flavour = self.flavour
        if flavour.guided_mode is not None:
            await self._ensure_mode(flavour.guided_mode)
        params = flavour.takeoff_params(alt_rel_m, self.telemetry())
        if flavour.guided_mode is None:
            self._pilot.expect("TAKEOFF")  # PX4 takes off in its own mode, then holds by itself
        await self._link.command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, params, already=self._taking_off)
        self._set_leg_active(False)

    def _taking_off(self) -> bool:
        """The vehicle left the ground (a takeoff re-sent after a lost ACK is refused then)."""
        t = self.telemetry()
        return t.armed and not t.landed

    async def set_speed(self, speed_mps: float) -> None:
        """Change the cruise speed now if the mode takes it, else with the next position target.

        ArduCopter accepts DO_CHANGE_SPEED only in AUTO, GUIDED and RTL (BRAKE, LOITER, LAND
        refuse it with MAV_RESULT_FAILED), so in a hold the speed is kept and sent right after
        the next goto's target.
        """
        self._leg_speed = positive("speed", speed_mps)
        if not self.flavour.speed_accepted_in(self._mode_now()):
            self._link.ensure_link("set speed")
            log.info(
                "mode %s takes no speed change; %.1f m/s goes with the next target",
                self._mode_now(),
                speed_mps,
            )
            self._pending_speed = speed_mps
            return
        await self._change_speed(speed_mps)

    async def _change_speed(self, speed_mps: float) -> None:
        self._pilot.movable("set speed")
        # param1 1 = ground speed, param3 -1 = throttle unchanged
        await self._link.command("set speed", mavlink.MAV_CMD_DO_CHANGE_SPEED, (1, speed_mps, -1))
        self._pending_speed = None

    async def _speed_after_target(self, speed_mps: float | None) -> None:
        """Send the leg's speed *after* its position target (or a speed kept from a hold).

        ArduCopter resets the horizontal speed to WPNAV_SPEED when a GUIDED position target
        starts its waypoint controller (the first target after takeoff or after entering
        GUIDED), so a speed sent before that target is lost.
        """
        speed = speed_mps if speed_mps is not None else self._pending_speed
        if speed is not None:
            await self._change_speed(speed)

    def _check_target(self, what: str, *values: float) -> None:
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{what}: non-finite target {values!r}")
        self._link.ensure_link(what)
        if not self.telemetry().armed:
            raise CommandRefused(what, "vehicle is disarmed")

    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        self._pilot.movable("goto")
        self._check_target("goto", lat, lon, alt_rel_m)
        flavour = self.flavour
        if flavour.guided_mode is None:  # PX4: DO_REPOSITION, the speed in param1
            await self._reposition_leg(lat, lon, alt_rel_m, speed_mps)
            return
        await self._ensure_mode(flavour.guided_mode)
        # Not acknowledged by ArduPilot: the queue watches the position.
        self._link.send(
            _position_target(self._link, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, lat, lon, alt_rel_m)
        )
        await self._speed_after_target(speed_mps)

    def supports_local_offset(self) -> bool:
        if self._local_offset_option is not None:
            return self._local_offset_option
        caps = self._decoder.capabilities
        return (
            self.flavour.guided_mode is not None
            and caps is not None
            and bool(caps & mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)
        )

    async def go_by(self, north_m: float, east_m: float, up_m: float, speed_mps: float | None = None) -> None:
        self._pilot.movable("go_by")
        if not self.supports_local_offset():
            await super().go_by(north_m, east_m, up_m, speed_mps)
            return
        self._check_target("go_by", north_m, east_m, up_m)
        await self._ensure_mode(self.flavour.guided_mode or "GUIDED")
        # MAV_FRAME_LOCAL_OFFSET_NED: x/y/z relative to the vehicle's position when received, z down.
        self._link.send(
            _position_target(self._link, mavlink.MAV_FRAME_LOCAL_OFFSET_NED, north_m, east_m, -up_m)
        )
        await self._speed_after_target(speed_mps)

    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        self._pilot.movable("land")
        await self._land_point(lat, lon)  # ArduCopter ignores NAV_LAND's lat/lon: there in GUIDED, then LAND
        try:
            await self.set_mode("LAND")
        except CommandRefused as exc:
            if "no such" not in exc.reason:
                raise
            self._pilot.expect("LAND")
            await self._link.command("land", mavlink.MAV_CMD_NAV_LAND, ())

    def ensure_link(self, what: str) -> None:
        self._link.ensure_link(what)

    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        self._pilot.movable("rtl")
        flavour = self.flavour
        alt_rel_m = self._return_alt(alt_rel_m)
        if alt_rel_m is not None:
            # The return altitude layer: ArduCopter RTL_ALT in cm, PX4 RTL_RETURN_ALT in m.
            try:
                await self.set_param(flavour.return_alt_param, flavour.return_alt_value(alt_rel_m))
            except (CommandRefused, CommandTimeout) as exc:  # a return must not fail for its altitude
                log.warning("return altitude %.1f m not set (%s); returning at the vehicle's", alt_rel_m, exc)
        await self.set_mode("RTL")

    async def hold(self) -> None:
        """Stop where the vehicle is: ArduPilot BRAKE (LOITER if refused); PX4 its own pause.

        PX4 flies a goto (DO_REPOSITION) in Hold already, so switching to Hold would change
        nothing; a DO_REPOSITION without position, altitude or yaw (:meth:`Flavour.pause_params`)
        makes it brake and hold where it comes to rest. Asked again (collision holds repeat every
        2 s) it re-aims at the stopping point from where the vehicle is then; from speed it is asked
        again once slowed (:meth:`_pause`), as PX4 brakes past its point and would fly back.
        """
        self._pilot.movable("hold")
        pause = self._pause_now()
        if pause is not None:

            async def send() -> None:
                self._pilot.expect("LOITER")  # PX4's pause holds in Hold
                await self._link.command(
                    "hold", mavlink.MAV_CMD_DO_REPOSITION, pause, int_frame=mavlink.MAV_FRAME_GLOBAL
                )

            await self._pause(send)
            return
        await self._hold_in_modes(self.set_mode)

    async def _reposition(
        self, what: str, lat: float, lon: float, alt_amsl: float, speed: float | None
    ) -> None:
        """MAV_CMD_DO_REPOSITION as COMMAND_INT (PX4 ignores the frame: z is AMSL)."""
        params = self.flavour.reposition_params(lat, lon, alt_amsl, speed)
        self._pilot.expect("LOITER")  # PX4 flies a reposition in Hold (CHANGE_MODE)
        await self._link.command(
            what, mavlink.MAV_CMD_DO_REPOSITION, params, int_frame=mavlink.MAV_FRAME_GLOBAL
        )

    # ================================================================== fence, mission, params

    async def get_param(self, name: str) -> float:
        """Read one autopilot parameter (PX4 integers decoded from their bytes)."""
        self._link.param_codec = self.flavour
        return await self._link.get_param(name)

    async def set_param(self, name: str, value: float) -> float:
        """Write one autopilot parameter; returns the value the vehicle echoed."""
        self._link.param_codec = self.flavour
        return await self._link.set_param(name, value)

    async def _upload(self, items: list[mavlink_mission.Item], mission_type: int, what: str) -> int:
        """The mission protocol's upload with this backend's per-item timeout and retries."""
        return await mavlink_mission.upload(
            self._link,
            items,
            mission_type,
            what=what,
            item_timeout_s=self.command_timeout_s,
            retries=self.command_retries,
        )

    async def upload_fence(self, fence: FenceSpec) -> bool:
        items = mavlink_mission.fence_items(fence)
        flavour = self.flavour
        params = flavour.fence_params(fence, bool(items))  # ValueError on an unknown breach action
        try:
            result = await self._upload(items, mavlink.MAV_MISSION_TYPE_FENCE, "fence upload")
        except CommandTimeout:
            log.warning("fence upload unanswered: the vehicle does not take fences")
            return False
        if result != mavlink.MAV_MISSION_ACCEPTED:
            log.warning("fence upload rejected: %s", mission_result_name(result))
            return False
        return await self._fence_parameters(params)

    async def upload_mission(self, points: list[MissionPoint]) -> None:
        home = self.telemetry() if self.flavour.mission_home_item else None
        items = mavlink_mission.mission_items(points, home)
        result = await self._upload(items, mavlink.MAV_MISSION_TYPE_MISSION, "mission upload")
        if result != mavlink.MAV_MISSION_ACCEPTED:
            reason = await self._link.refusal_reason(mission_result_name(result), time.monotonic() - 2.0)
            raise CommandRefused("mission upload", reason)
        self._state.mission_uploaded(0 if home is None else 1)

    async def start_mission(self) -> None:
        self._pilot.movable("mission start")
        tel = self.telemetry()
        await self.set_mode("AUTO")
        if self.flavour.mission_home_item and tel.armed and tel.landed:
            # ArduCopter on the ground needs MISSION_START to begin an AUTO mission.
            await self._link.command("mission start", mavlink.MAV_CMD_MISSION_START, (0, 0))


def _position_target(link: MavlinkLink, frame: int, x: float, y: float, z: float) -> Any:
    """SET_POSITION_TARGET_GLOBAL_INT (x/y lat/lon in degrees) or _LOCAL_NED (x/y/z in metres, NED):
    position only, never the Z-ignore bit."""
    if frame == mavlink.MAV_FRAME_LOCAL_OFFSET_NED:
        return mavlink.MAVLink_set_position_target_local_ned_message(
            link.time_boot_ms(),
            link.target_system,
            link.target_component,
            frame,
            POSITION_TARGET_TYPE_MASK,
            x,
            y,
            z,
            *(0,) * 8,
        )
    return mavlink.MAVLink_set_position_target_global_int_message(
        link.time_boot_ms(),
        link.target_system,
        link.target_component,
        frame,
        POSITION_TARGET_TYPE_MASK,
        round(x * 1e7),
        round(y * 1e7),
        z,
        *(0,) * 8,
    )
