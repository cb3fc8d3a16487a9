"""The MAVSDK backend, meant for PX4 (``--autopilot-backend mavsdk``).

Built on the ``mavsdk`` package **4.x**, the native ctypes binding of the MAVSDK C++ library (no
``mavsdk_server`` process, no gRPC: ``System(mavsdk_server_address=...)`` of mavsdk<4 is gone). The
library runs its own threads: telemetry arrives as plugin callbacks on those threads and is copied
into a :class:`Telemetry` under a lock; blocking plugin calls (arm, takeoff, uploads) run in the
default executor and are bounded with :func:`asyncio.wait_for`, so nothing blocks the event loop.

Connection URLs are MAVSDK's (``udpin://0.0.0.0:14540``, ``udpout://host:port``,
``tcpout://host:port``, ``tcpin://0.0.0.0:port``, ``serial:///dev/ttyAMA0:921600``); the
pymavlink-style strings the other backend takes (``tcp:host:port``, ``udpin:0.0.0.0:14540``,
``/dev/ttyAMA0:921600``) and the deprecated ``udp://:14540`` / ``tcp://host:port`` are translated.

What differs per firmware comes from the vehicle's :class:`~agent.autopilot.flavours.Flavour`,
shared with the pymavlink backend. Mapping: arm → ``Action.arm`` (retried on refusal until the
deadline), takeoff → ``MAV_CMD_NAV_TAKEOFF`` with the flavour's params (PX4: AMSL), goto → PX4
``DO_REPOSITION`` with the speed in param1 (ArduPilot: GUIDED + ``Action.goto_location``), hold → PX4's
pause, ``DO_REPOSITION`` without position (``Action.hold`` only switches to Hold, which a PX4 goto is
already flown in), land → ``Action.land`` (after a goto when lat/lon are given), RTL →
``Action.return_to_launch`` after the return altitude, speed → ``Action.set_current_speed``, fence →
``Geofence.upload_geofence`` + the flavour's parameters, mission → ``MissionRaw``. Raw commands
(modes, take-off, repositions) go through the ``MavlinkDirect`` plugin with our own ACK wait; it
also feeds the heartbeat clock and the mode name.

Its parts: the link (:mod:`~agent.autopilot.mavsdk_link`: the plugins, bounded calls, raw commands)
and the telemetry feed (:mod:`~agent.autopilot.mavsdk_telemetry`) into the vehicle state both
backends keep (:mod:`~agent.autopilot.vehicle_state`); this class turns commands into plugin calls.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Awaitable
from typing import Any

from agent.autopilot.base import CommandRefused, CommandTimeout, FenceSpec, MissionPoint, Telemetry
from agent.autopilot.flavoured import FlavouredAutopilot, positive
from agent.autopilot.flavours import Flavour, flavour_for
from agent.autopilot.flavours.base import base_altitude_amsl
from agent.autopilot.mavlink_link import mavlink
from agent.autopilot.mavsdk_link import MavsdkLink, to_mavsdk_url
from agent.autopilot.mavsdk_telemetry import MavsdkTelemetry
from agent.autopilot.vehicle_state import VehicleState

log = logging.getLogger(__name__)

__all__ = ["MavsdkAutopilot", "to_mavsdk_url"]


class MavsdkAutopilot(FlavouredAutopilot):
    """An :class:`Autopilot` over MAVSDK (PX4 first; ArduPilot basics work too).

    Args:
        connection: a MAVSDK URL or a pymavlink-style string (see :func:`to_mavsdk_url`).
        heartbeat_timeout_s: heartbeat silence after which commands raise :class:`LinkLost`.
        command_timeout_s: bound on one MAVSDK call (MAVSDK retries internally).
        telemetry_hz: rate asked for position, velocity, attitude and landed state.
        companion: identify as a companion computer (component 191) rather than a ground station.
    """

    def __init__(
        self,
        connection: str,
        *,
        heartbeat_timeout_s: float = 3.0,
        command_timeout_s: float = 10.0,
        telemetry_hz: float = 10.0,
        companion: bool = True,
    ) -> None:
        self.connection = connection
        self.url = to_mavsdk_url(connection)
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.command_timeout_s = command_timeout_s
        self.telemetry_hz = telemetry_hz
        self.companion = companion
        self._state = VehicleState()
        self._link = MavsdkLink(
            self.url,
            self._state.lock,
            heartbeat_timeout_s=heartbeat_timeout_s,
            command_timeout_s=command_timeout_s,
        )
        self._feed = MavsdkTelemetry(self._state, self._link)
        self._leg_speed: float | None = None  # PX4: the last speed asked for, sent with each reposition
        self._param_is_int: dict[str, bool] = {}

    # ================================================================== lifecycle

    async def connect(self, timeout: float = 30.0) -> None:
        await self._link.open(timeout, self.companion)
        self._feed.subscribe()
        await self._link.set_rates(self.telemetry_hz)

    async def close(self) -> None:
        await self._link.close()

    def telemetry(self) -> Telemetry:
        return self._state.snapshot(self._link.status_texts(), self._link.last_hb)

    @property
    def flavour(self) -> Flavour:
        """The vehicle's firmware conventions, from MAVSDK's autopilot type and each heartbeat."""
        return flavour_for(self._link.autopilot_type)

    def ensure_link(self, what: str) -> None:
        self._link.ensure_link(what)

    async def _into_mode(self, raw: str, command: Awaitable[Any]) -> Any:
        """Run ``command``, which puts the vehicle in ``raw``: told to the pilot gate first, so the
        heartbeat that shows it is ours; withdrawn when the vehicle refuses."""
        before = self._pilot.expect(raw)
        try:
            return await command
        except CommandRefused:
            self._pilot.refused(raw, before)
            raise

    async def _set_mode(self, name: str) -> None:
        """MAV_CMD_DO_SET_MODE by name, encoded by the flavour (a no-op when already in it)."""
        self._pilot.movable(f"mode {name}")
        if self.telemetry().mode == name:
            return
        params, _custom, raw = self._mode_request(name, mavlink.MAV_TYPE_QUADROTOR)
        await self._into_mode(
            raw, self._link.direct_command(f"mode {name}", mavlink.MAV_CMD_DO_SET_MODE, params)
        )
        self._set_leg_active(False)

    # ================================================================== commands

    async def arm(self, deadline_s: float = 60.0) -> None:
        self._pilot.movable("arm")

        async def attempt() -> None:
            if self.flavour.guided_mode is not None:
                await self._set_mode(self.flavour.guided_mode)
            await self._link.call("arm", self._link.action.arm)

        await self._arm_retrying(deadline_s, attempt)

    async def disarm(self) -> None:
        self._pilot.movable("disarm")
        await self._link.call("disarm", self._link.action.disarm)

    async def takeoff(self, alt_rel_m: float) -> None:
        positive("takeoff altitude", alt_rel_m)
        flavour = self.flavour
        if flavour.guided_mode is not None:
            # MAVSDK's ArduPilot takeoff sends NAV_TAKEOFF without switching mode; ArduCopter needs GUIDED.
            await self._set_mode(flavour.guided_mode)
        self._pilot.movable("takeoff")
        params = flavour.takeoff_params(alt_rel_m, self.telemetry())
        command = self._link.direct_command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, params)
        if flavour.guided_mode is None:
            await self._into_mode("TAKEOFF", command)  # PX4 takes off in its own mode, then holds
        else:
            await command
        self._set_leg_active(False)

    async def set_speed(self, speed_mps: float) -> None:
        positive("speed", speed_mps)
        self._pilot.movable("set speed")
        self._leg_speed = speed_mps
        await self._link.call("set speed", self._link.action.set_current_speed, speed_mps)

    async def _reposition(
        self, what: str, lat: float, lon: float, alt_amsl: float, speed: float | None
    ) -> None:
        self._pilot.movable(what)
        params = self.flavour.reposition_params(lat, lon, alt_amsl, speed)
        command = self._link.direct_command(
            what, mavlink.MAV_CMD_DO_REPOSITION, params, int_frame=mavlink.MAV_FRAME_GLOBAL
        )
        await self._into_mode("LOITER", command)  # PX4 flies a reposition in Hold

    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        if not all(math.isfinite(v) for v in (lat, lon, alt_rel_m)):
            raise ValueError("goto: non-finite target")
        self._pilot.movable("goto")
        if not self.telemetry().armed:
            raise CommandRefused("goto", "vehicle is disarmed")
        flavour = self.flavour
        if flavour.guided_mode is None:  # PX4: DO_REPOSITION with the speed in param1
            await self._reposition_leg(lat, lon, alt_rel_m, speed_mps)
            return
        # ArduCopter: GUIDED, the target, then the speed (the target resets it to WPNAV_SPEED).
        await self._set_mode(flavour.guided_mode)
        alt_amsl = base_altitude_amsl(self.telemetry()) + alt_rel_m
        await self._link.call("goto", self._link.action.goto_location, lat, lon, alt_amsl, math.nan)
        if speed_mps is not None:
            await self.set_speed(speed_mps)

    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        await self._land_point(lat, lon)
        self._pilot.movable("land")
        await self._into_mode("LAND", self._link.call("land", self._link.action.land))

    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        self._pilot.movable("rtl")
        alt_rel_m = self._return_alt(alt_rel_m)
        if alt_rel_m is not None:
            # MAVSDK writes the flavour's parameter (PX4 RTL_RETURN_ALT in m, ArduPilot RTL_ALT in cm).
            try:
                await self._link.call(
                    "rtl altitude", self._link.action.set_return_to_launch_altitude, float(alt_rel_m)
                )
            except (CommandRefused, CommandTimeout) as exc:  # a return must not fail for its altitude
                log.warning("return altitude %.1f m not set (%s); returning at the vehicle's", alt_rel_m, exc)
        await self._into_mode("RTL", self._link.call("rtl", self._link.action.return_to_launch))
        self._set_leg_active(False)

    async def hold(self) -> None:
        """Stop where the vehicle is: ArduPilot BRAKE (LOITER if refused); PX4 its own pause
        (:meth:`Flavour.pause_params`; ``Action.hold`` would only ask for the Hold it flies in)."""
        self._pilot.movable("hold")
        pause = self._pause_now()
        if pause is not None:

            async def send() -> None:
                command = self._link.direct_command(
                    "hold", mavlink.MAV_CMD_DO_REPOSITION, pause, int_frame=mavlink.MAV_FRAME_GLOBAL
                )
                await self._into_mode("LOITER", command)  # PX4's pause holds in Hold

            await self._pause(send)
            return
        await self._hold_in_modes(self._set_mode)

    # ================================================================== fence, mission, params

    async def set_param(self, name: str, value: float) -> None:
        """Write a parameter (float, falling back to int for integer parameters).

        PX4 ignores a REAL32 PARAM_SET of an INT32 parameter (MAVSDK then times out after 10 s),
        so with a flavour whose integers travel byte-wise the type is read first.
        """
        if self.flavour.params_bytewise:
            if name not in self._param_is_int:
                try:
                    await self._link.call(f"get {name}", self._link.param.get_param_int, name)
                    self._param_is_int[name] = True
                except (CommandRefused, CommandTimeout):
                    self._param_is_int[name] = False
            if self._param_is_int[name]:
                await self._link.call(f"set {name}", self._link.param.set_param_int, name, round(value))
            else:
                await self._link.call(f"set {name}", self._link.param.set_param_float, name, float(value))
            return
        try:
            await self._link.call(f"set {name}", self._link.param.set_param_float, name, float(value))
        except CommandRefused:
            await self._link.call(f"set {name}", self._link.param.set_param_int, name, round(value))

    async def upload_fence(self, fence: FenceSpec) -> bool:
        from mavsdk.plugins.geofence import Circle, FenceType, GeofenceData, Point, Polygon

        flavour = self.flavour
        params = flavour.fence_params(fence, bool(fence.polygon or fence.circle))  # ValueError: bad action
        polygons = []
        if fence.polygon:
            if len(fence.polygon) < 3:
                raise ValueError("fence polygon needs at least 3 vertices")
            polygons.append(Polygon([Point(a, b) for a, b in fence.polygon], FenceType.INCLUSION))
        circles = []
        if fence.circle is not None:
            c = fence.circle
            circles.append(Circle(Point(c.lat, c.lon), c.radius_m, FenceType.INCLUSION))
        try:
            await self._link.call(
                "fence upload", self._link.geofence.upload_geofence, GeofenceData(polygons, circles)
            )
        except (CommandRefused, CommandTimeout) as exc:
            log.warning("fence not installed: %s", exc)
            return False
        return await self._fence_parameters(params)

    async def upload_mission(self, points: list[MissionPoint]) -> None:
        from mavsdk.plugins.mission_raw import MissionItem

        items = []
        offset = 0
        if self.flavour.mission_home_item:  # seq 0 is home on ArduPilot
            tel = self.telemetry()
            items.append(
                MissionItem(
                    0,
                    mavlink.MAV_FRAME_GLOBAL,
                    mavlink.MAV_CMD_NAV_WAYPOINT,
                    0,
                    1,
                    0,
                    0,
                    0,
                    0,
                    round((tel.home_lat or 0.0) * 1e7),
                    round((tel.home_lon or 0.0) * 1e7),
                    tel.home_alt_amsl or 0.0,
                    mavlink.MAV_MISSION_TYPE_MISSION,
                )
            )
            offset = 1
        for p in points:
            seq = len(items)
            items.append(
                MissionItem(
                    seq,
                    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                    mavlink.MAV_CMD_NAV_WAYPOINT,
                    1 if seq == offset else 0,
                    1,
                    0,
                    0,
                    0,
                    math.nan,
                    round(p.lat * 1e7),
                    round(p.lon * 1e7),
                    p.alt_rel_m,
                    mavlink.MAV_MISSION_TYPE_MISSION,
                )
            )
        await self._link.call("mission upload", self._link.mission_raw.upload_mission, items, timeout=30.0)
        self._state.mission_uploaded(offset)

    async def start_mission(self) -> None:
        self._pilot.movable("mission start")
        await self._into_mode("AUTO", self._link.call("mission start", self._link.mission_raw.start_mission))
