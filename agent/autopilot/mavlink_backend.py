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
import dataclasses
import logging
import math
import threading
import time
from typing import Any

from agent.autopilot import mavlink_mission
from agent.autopilot.base import (
    ARM_RETRY_INTERVAL_S,
    Autopilot,
    AutopilotError,
    CommandRefused,
    CommandTimeout,
    FenceSpec,
    LinkLost,
    MissionPoint,
    Telemetry,
)
from agent.autopilot.flavours import Flavour, flavour_for
from agent.autopilot.flavours.base import ShownMode, base_altitude_amsl
from agent.autopilot.mavlink_link import MavlinkLink, mavlink, mission_result_name

log = logging.getLogger(__name__)

__all__ = ["MavlinkAutopilot", "decode_mode"]

POSITION_TARGET_TYPE_MASK = 0x0DF8  # use x/y/z only: ignore velocity, acceleration, yaw, yaw rate

# Messages we ask the vehicle to stream: (name, id, rate) where rate None means telemetry_hz.
_FAST = None
_STREAMS: tuple[tuple[str, int, float | None], ...] = (
    ("GLOBAL_POSITION_INT", mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _FAST),
    ("ATTITUDE", mavlink.MAVLINK_MSG_ID_ATTITUDE, _FAST),
    ("VFR_HUD", mavlink.MAVLINK_MSG_ID_VFR_HUD, _FAST),
    ("EXTENDED_SYS_STATE", mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, _FAST),
    ("MISSION_CURRENT", mavlink.MAVLINK_MSG_ID_MISSION_CURRENT, _FAST),
    ("GPS_RAW_INT", mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 2.0),
    ("SYS_STATUS", mavlink.MAVLINK_MSG_ID_SYS_STATUS, 2.0),
    ("BATTERY_STATUS", mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 2.0),
    ("HOME_POSITION", mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0.5),
)
STREAM_FULL_REASSERT_S = 30.0
STREAM_STALE_REASSERT_MIN_S = 3.0


def decode_mode(autopilot: int, mav_type: int, base_mode: int, custom_mode: int) -> str:
    """The upper-case mode name of a HEARTBEAT (ArduPilot custom modes, PX4 main/sub modes)."""
    return flavour_for(autopilot).decode_mode(mav_type, base_mode, custom_mode)


class MavlinkAutopilot(Autopilot):
    """An :class:`Autopilot` over a pymavlink connection (serial, UDP or TCP), MAVLink 2.

    Firmware differences (ArduPilot, PX4) come from :attr:`flavour`, picked from the heartbeat.

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
        command_retries: int = 3,
        telemetry_hz: float = 10.0,
        local_offset_targets: bool | None = None,
        signing_key: bytes | str | None = None,
        allow_unsigned: bool = False,
        tlog_path: str | None = None,
    ) -> None:
        if telemetry_hz <= 0:
            raise ValueError("telemetry_hz must be positive")
        self.connection = connection
        self.telemetry_hz = telemetry_hz
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.command_timeout_s = command_timeout_s
        self.command_retries = command_retries
        self._local_offset_option = local_offset_targets
        self._link = MavlinkLink(
            connection,
            target_system=target_system,
            source_system=source_system,
            source_component=source_component,
            heartbeat_timeout_s=heartbeat_timeout_s,
            command_timeout_s=command_timeout_s,
            command_retries=command_retries,
            on_message=self._on_message,
            on_tick=self._on_tick,
            on_link_restored=self._on_link_restored,
            signing_key=signing_key,
            allow_unsigned=allow_unsigned,
            tlog_path=tlog_path,
        )
        self._state_lock = threading.Lock()
        self._tel = Telemetry()
        self._landed_state: int | None = None
        self._heading_from_gpi = False
        self._battery_status_pct: float | None = None
        self._mission_seq = -1
        self._mission_offset = 0  # seq of the first uploaded point (1 on ArduPilot: seq 0 is home)
        self._capabilities: int | None = None
        self._pending_speed: float | None = None  # set_speed in a mode that refuses it
        self._leg_speed: float | None = None  # PX4: the last speed asked for, sent with each reposition
        self._shown = ShownMode()  # PX4: GUIDED while our reposition leg is flown, LOITER once held
        self._streams_ready = False
        self._stream_requested_at: dict[str, float] = {}
        self._refused_streams: set[str] = set()  # SET_MESSAGE_INTERVAL refused: never re-asserted
        self._last_full_reassert = 0.0
        self._last_home_request = 0.0
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
        await self._setup_streams()

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

    # ================================================================== streams

    def _stream_plan(self) -> list[tuple[str, int, float]]:
        return [(name, mid, self.telemetry_hz if hz is None else hz) for name, mid, hz in _STREAMS]

    async def _setup_streams(self) -> None:
        """SET_MESSAGE_INTERVAL per message; REQUEST_DATA_STREAM when the vehicle does not take it."""
        refused = 0
        fallback = False
        for name, msg_id, hz in self._stream_plan():
            try:
                await self._link.command(
                    f"stream {name}",
                    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                    (msg_id, 1e6 / hz),
                    retries=2,
                )
                self._stream_requested_at[name] = time.monotonic()
            except CommandRefused as exc:
                # PX4 refuses MISSION_CURRENT (it streams it anyway): not re-asserted, no fallback
                # while other intervals are taken.
                log.debug("SET_MESSAGE_INTERVAL %s refused (%s)", name, exc.reason)
                self._refused_streams.add(name)
                refused += 1
            except CommandTimeout:
                log.info("SET_MESSAGE_INTERVAL unanswered; falling back to REQUEST_DATA_STREAM")
                fallback = True
                break
        if fallback or (refused and refused == len(self._stream_plan())):
            self._request_data_streams()
        self._last_full_reassert = time.monotonic()
        self._streams_ready = True
        self._request_home()
        try:
            await self._link.command(
                "request AUTOPILOT_VERSION",
                mavlink.MAV_CMD_REQUEST_MESSAGE,
                (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,),
                retries=1,
            )
        except (CommandRefused, CommandTimeout):
            log.info("vehicle does not answer AUTOPILOT_VERSION requests")

    def _request_data_streams(self) -> None:
        rate = max(1, round(self.telemetry_hz))
        self._link.send(
            mavlink.MAVLink_request_data_stream_message(
                self._link.target_system, self._link.target_component, mavlink.MAV_DATA_STREAM_ALL, rate, 1
            )
        )

    def _request_home(self) -> None:
        self._last_home_request = time.monotonic()
        self._link.send_command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, (mavlink.MAVLINK_MSG_ID_HOME_POSITION,))

    def _reassert_streams(self, only_stale: bool) -> None:
        """Re-send interval requests, fire-and-forget (the vehicle may have reverted them)."""
        now = time.monotonic()
        for name, msg_id, hz in self._stream_plan():
            if name in self._refused_streams:
                continue
            if only_stale:
                last = self._link.last_seen.get(name, 0.0)
                stale_after = max(3.0 / hz, 2.0)
                if now - last < stale_after:
                    continue
                if now - self._stream_requested_at.get(name, 0.0) < STREAM_STALE_REASSERT_MIN_S:
                    continue
            self._stream_requested_at[name] = now
            self._link.send_command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, 1e6 / hz))

    def _on_tick(self) -> None:  # reader thread, every 0.5 s
        if not self._streams_ready or not self._link.link_ok():
            return
        now = time.monotonic()
        if now - self._last_full_reassert > STREAM_FULL_REASSERT_S:
            self._last_full_reassert = now
            self._reassert_streams(only_stale=False)
        else:
            self._reassert_streams(only_stale=True)
        if self._tel.home_lat is None and now - self._last_home_request > 2.0:
            self._request_home()

    def _on_link_restored(self) -> None:  # reader thread
        if self._streams_ready:
            self._last_full_reassert = time.monotonic()
            self._reassert_streams(only_stale=False)
            self._request_home()

    # ================================================================== telemetry

    def telemetry(self) -> Telemetry:
        with self._state_lock:
            snap = dataclasses.replace(self._tel, status_texts=[t.text for t in self._link.status_texts()])
        snap.last_heartbeat_monotonic = self._link.last_heartbeat_monotonic
        return snap

    def _on_message(self, msg: Any) -> None:  # reader thread, messages from the autopilot component
        handler = _HANDLERS.get(msg.get_type())
        if handler is not None:
            with self._state_lock:
                handler(self, msg)

    def _h_heartbeat(self, msg: Any) -> None:
        tel = self._tel
        flavour = flavour_for(msg.autopilot)
        tel.mode = self._shown.from_heartbeat(
            flavour, flavour.decode_mode(msg.type, msg.base_mode, msg.custom_mode)
        )
        tel.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self._update_landed()
        self._update_mission_current()

    def _h_global_position_int(self, msg: Any) -> None:
        tel = self._tel
        tel.lat = msg.lat / 1e7
        tel.lon = msg.lon / 1e7
        tel.alt_amsl = msg.alt / 1000.0
        tel.alt_rel = msg.relative_alt / 1000.0
        tel.vn, tel.ve, tel.vd = msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0
        tel.latch_position()
        tel.vehicle_time_s = msg.time_boot_ms / 1000.0
        if msg.hdg != 65535:
            tel.heading_deg = (msg.hdg / 100.0) % 360.0
            self._heading_from_gpi = True
        self._update_landed()

    def _h_attitude(self, msg: Any) -> None:
        if not self._heading_from_gpi:
            self._tel.heading_deg = math.degrees(msg.yaw) % 360.0

    def _h_vfr_hud(self, msg: Any) -> None:
        if not self._heading_from_gpi:
            self._tel.heading_deg = float(msg.heading) % 360.0

    def _h_gps_raw_int(self, msg: Any) -> None:
        self._tel.gps_fix = int(msg.fix_type)
        self._tel.satellites = 0 if msg.satellites_visible == 255 else int(msg.satellites_visible)
        self._tel.latch_position()

    def _h_sys_status(self, msg: Any) -> None:
        tel = self._tel
        if msg.battery_remaining >= 0:
            tel.battery_pct = float(msg.battery_remaining)
        elif self._battery_status_pct is None:
            tel.battery_pct = None
        tel.voltage_v = None if msg.voltage_battery == 65535 else msg.voltage_battery / 1000.0
        tel.current_a = None if msg.current_battery < 0 else msg.current_battery / 100.0

    def _h_battery_status(self, msg: Any) -> None:
        if msg.id != 0:
            return
        tel = self._tel
        if msg.battery_remaining >= 0:
            self._battery_status_pct = float(msg.battery_remaining)
            tel.battery_pct = self._battery_status_pct
        if tel.current_a is None and msg.current_battery >= 0:
            tel.current_a = msg.current_battery / 100.0
        if tel.voltage_v is None:
            cells = [v for v in msg.voltages if v != 65535]
            if cells:
                tel.voltage_v = sum(cells) / 1000.0

    def _h_extended_sys_state(self, msg: Any) -> None:
        self._landed_state = int(msg.landed_state)
        self._update_landed()

    def _h_home_position(self, msg: Any) -> None:
        tel = self._tel
        tel.home_lat = msg.latitude / 1e7
        tel.home_lon = msg.longitude / 1e7
        tel.home_alt_amsl = msg.altitude / 1000.0

    def _h_mission_current(self, msg: Any) -> None:
        self._mission_seq = int(msg.seq)
        self._update_mission_current()

    def _update_landed(self) -> None:
        tel = self._tel
        state = self._landed_state
        if state == mavlink.MAV_LANDED_STATE_ON_GROUND:
            tel.landed = True
        elif state in (
            mavlink.MAV_LANDED_STATE_IN_AIR,
            mavlink.MAV_LANDED_STATE_TAKEOFF,
            mavlink.MAV_LANDED_STATE_LANDING,
        ):
            tel.landed = False
        else:  # no EXTENDED_SYS_STATE: disarmed, or armed and still at ground level
            tel.landed = not tel.armed or tel.alt_rel < 0.3

    def _update_mission_current(self) -> None:
        tel = self._tel
        if tel.mode in ("AUTO", "MISSION") and self._mission_seq >= 0:
            tel.mission_current = max(0, self._mission_seq - self._mission_offset)
        else:
            tel.mission_current = -1

    # ================================================================== modes

    def _mode_now(self) -> str:
        with self._state_lock:
            return self._tel.mode

    async def set_mode(self, name: str) -> None:
        """Switch flight mode by name (ArduPilot custom mode / PX4 main+sub mode); waits for the ACK."""
        name = name.upper()
        what = f"mode {name}"
        vehicle = self._link.vehicle
        flavour = self.flavour
        try:
            params, custom = flavour.mode_command(name, vehicle.mav_type if vehicle is not None else 2)
        except KeyError:
            raise CommandRefused(what, f"no such {flavour.name} mode") from None
        try:
            await self._link.command(what, mavlink.MAV_CMD_DO_SET_MODE, params)
        except CommandRefused as exc:
            if "UNSUPPORTED" not in exc.reason:
                raise
            await self._set_mode_legacy(what, name, custom)
            return
        self._set_leg_active(False)
        if flavour.guided_mode is not None:
            # Accepted: the mode has changed, though the next heartbeat may be up to 1 s away.
            # Later decisions (send the speed now? switch to GUIDED first?) need it at once.
            with self._state_lock:
                self._tel.mode = name

    def _set_leg_active(self, active: bool) -> None:
        """PX4: mark whether one of our reposition legs is being flown (the mode shown follows)."""
        with self._state_lock:
            mode = self._shown.leg(self.flavour, active)
            if mode is not None:
                self._tel.mode = mode

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
        deadline = time.monotonic() + deadline_s
        last: AutopilotError | None = None
        while True:
            self._link.ensure_link("arm")
            try:
                if self.flavour.guided_mode is not None:
                    await self._ensure_mode(self.flavour.guided_mode)
                await self._link.command("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1,))
                return
            except (CommandRefused, CommandTimeout) as exc:
                last = exc
                log.info("arm attempt failed: %s", exc)
            if time.monotonic() + ARM_RETRY_INTERVAL_S >= deadline:
                break
            await asyncio.sleep(ARM_RETRY_INTERVAL_S)
        if isinstance(last, CommandRefused):
            raise CommandRefused("arm", last.reason)
        raise CommandTimeout("arm", deadline_s)

    async def disarm(self) -> None:
        await self._link.command("disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0,))

    async def takeoff(self, alt_rel_m: float) -> None:
        if not math.isfinite(alt_rel_m) or alt_rel_m <= 0:
            raise ValueError(f"takeoff altitude must be a positive number, not {alt_rel_m!r}")
        flavour = self.flavour
        if flavour.guided_mode is not None:
            await self._ensure_mode(flavour.guided_mode)
        params = flavour.takeoff_params(alt_rel_m, self.telemetry())
        await self._link.command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, params)
        self._set_leg_active(False)

    async def set_speed(self, speed_mps: float) -> None:
        """Change the cruise speed now if the mode takes it, else with the next position target.

        ArduCopter accepts DO_CHANGE_SPEED only in AUTO, GUIDED and RTL (BRAKE, LOITER, LAND
        refuse it with MAV_RESULT_FAILED), so in a hold the speed is kept and sent right after
        the next goto's target.
        """
        if not math.isfinite(speed_mps) or speed_mps <= 0:
            raise ValueError(f"speed must be a positive number, not {speed_mps!r}")
        self._leg_speed = speed_mps
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
        self._check_target("goto", lat, lon, alt_rel_m)
        flavour = self.flavour
        if flavour.guided_mode is None:  # PX4: DO_REPOSITION, the speed in param1
            if speed_mps is not None:
                self._leg_speed = speed_mps
            alt_amsl = base_altitude_amsl(self.telemetry()) + alt_rel_m
            await self._reposition("goto", lat, lon, alt_amsl, self._leg_speed)
            self._set_leg_active(True)
            return
        await self._ensure_mode(flavour.guided_mode)
        # Not acknowledged by ArduPilot: the queue watches the position. Never set the Z-ignore bit.
        self._link.send(
            mavlink.MAVLink_set_position_target_global_int_message(
                self._link.time_boot_ms(),
                self._link.target_system,
                self._link.target_component,
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                POSITION_TARGET_TYPE_MASK,
                round(lat * 1e7),
                round(lon * 1e7),
                alt_rel_m,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        )
        await self._speed_after_target(speed_mps)

    def supports_local_offset(self) -> bool:
        if self._local_offset_option is not None:
            return self._local_offset_option
        caps = self._capabilities
        return (
            self.flavour.guided_mode is not None
            and caps is not None
            and bool(caps & mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)
        )

    async def go_by(self, north_m: float, east_m: float, up_m: float, speed_mps: float | None = None) -> None:
        if not self.supports_local_offset():
            await super().go_by(north_m, east_m, up_m, speed_mps)
            return
        self._check_target("go_by", north_m, east_m, up_m)
        await self._ensure_mode(self.flavour.guided_mode or "GUIDED")
        # MAV_FRAME_LOCAL_OFFSET_NED: x/y/z relative to the vehicle's position when received, z down.
        self._link.send(
            mavlink.MAVLink_set_position_target_local_ned_message(
                self._link.time_boot_ms(),
                self._link.target_system,
                self._link.target_component,
                mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                POSITION_TARGET_TYPE_MASK,
                north_m,
                east_m,
                -up_m,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        )
        await self._speed_after_target(speed_mps)

    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        if (lat is None) != (lon is None):
            raise ValueError("land: give both lat and lon, or neither")
        if lat is not None and lon is not None:
            # ArduCopter ignores NAV_LAND's lat/lon: fly there in GUIDED, then LAND.
            await self.approach_landing_point(lat, lon)
        try:
            await self.set_mode("LAND")
        except CommandRefused as exc:
            if "no such" not in exc.reason:
                raise
            await self._link.command("land", mavlink.MAV_CMD_NAV_LAND, ())

    def ensure_link(self, what: str) -> None:
        self._link.ensure_link(what)

    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        flavour = self.flavour
        if alt_rel_m is None:
            alt_rel_m = flavour.default_return_alt(self.telemetry())
        elif not math.isfinite(alt_rel_m) or alt_rel_m <= 0:
            raise ValueError(f"return altitude must be a positive number, not {alt_rel_m!r}")
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
        2 s) it re-aims at the stopping point from where the vehicle is then: no flying back.
        """
        flavour = self.flavour
        tel = self.telemetry()
        pause = flavour.pause_params()
        if pause is not None and tel.armed and not tel.landed:
            await self._link.command(
                "hold", mavlink.MAV_CMD_DO_REPOSITION, pause, int_frame=mavlink.MAV_FRAME_GLOBAL
            )
            self._set_leg_active(False)
            return
        for i, mode in enumerate(flavour.hold_modes):
            try:
                await self.set_mode(mode)
                return
            except CommandRefused as exc:
                if i + 1 == len(flavour.hold_modes):
                    raise
                log.info("%s refused (%s); trying %s", mode, exc.reason, flavour.hold_modes[i + 1])

    async def _reposition(
        self, what: str, lat: float, lon: float, alt_amsl: float, speed: float | None
    ) -> None:
        """MAV_CMD_DO_REPOSITION as COMMAND_INT (PX4 ignores the frame: z is AMSL)."""
        params = self.flavour.reposition_params(lat, lon, alt_amsl, speed)
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

    async def upload_fence(self, fence: FenceSpec) -> bool:
        items: list[mavlink_mission.Item] = []
        if fence.polygon:
            if len(fence.polygon) < 3:
                raise ValueError("fence polygon needs at least 3 vertices")
            n = len(fence.polygon)
            for vlat, vlon in fence.polygon:
                items.append(
                    mavlink_mission.Item(
                        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                        mavlink.MAV_FRAME_GLOBAL,
                        vlat,
                        vlon,
                        0.0,
                        param1=n,
                    )
                )
        if fence.circle is not None:
            c = fence.circle
            items.append(
                mavlink_mission.Item(
                    mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
                    mavlink.MAV_FRAME_GLOBAL,
                    c.lat,
                    c.lon,
                    0.0,
                    param1=c.radius_m,
                )
            )
        flavour = self.flavour
        params = flavour.fence_params(fence, bool(items))  # ValueError on an unknown breach action
        try:
            result = await mavlink_mission.upload(
                self._link,
                items,
                mavlink.MAV_MISSION_TYPE_FENCE,
                what="fence upload",
                item_timeout_s=self.command_timeout_s,
                retries=self.command_retries,
            )
        except CommandTimeout:
            log.warning("fence upload unanswered: the vehicle does not take fences")
            return False
        if result != mavlink.MAV_MISSION_ACCEPTED:
            log.warning("fence upload rejected: %s", mission_result_name(result))
            return False
        try:
            for name, value in params:
                await self.set_param(name, value)
        except (CommandRefused, CommandTimeout) as exc:
            log.warning("fence parameters not accepted: %s", exc)
            return False
        return True

    async def upload_mission(self, points: list[MissionPoint]) -> None:
        items: list[mavlink_mission.Item] = []
        offset = 0
        if self.flavour.mission_home_item:
            # ArduPilot: seq 0 is home; it overwrites it, but it must be there.
            tel = self.telemetry()
            items.append(
                mavlink_mission.Item(
                    mavlink.MAV_CMD_NAV_WAYPOINT,
                    mavlink.MAV_FRAME_GLOBAL,
                    tel.home_lat or 0.0,
                    tel.home_lon or 0.0,
                    tel.home_alt_amsl or 0.0,
                )
            )
            offset = 1
        for p in points:
            items.append(
                mavlink_mission.Item(
                    mavlink.MAV_CMD_NAV_WAYPOINT,
                    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                    p.lat,
                    p.lon,
                    p.alt_rel_m,
                )
            )
        result = await mavlink_mission.upload(
            self._link,
            items,
            mavlink.MAV_MISSION_TYPE_MISSION,
            what="mission upload",
            item_timeout_s=self.command_timeout_s,
            retries=self.command_retries,
        )
        if result != mavlink.MAV_MISSION_ACCEPTED:
            reason = await self._link.refusal_reason(mission_result_name(result), time.monotonic() - 2.0)
            raise CommandRefused("mission upload", reason)
        with self._state_lock:
            self._mission_offset = offset
            self._update_mission_current()

    async def start_mission(self) -> None:
        tel = self.telemetry()
        await self.set_mode("AUTO")
        if self.flavour.mission_home_item and tel.armed and tel.landed:
            # ArduCopter on the ground needs MISSION_START to begin an AUTO mission.
            await self._link.command("mission start", mavlink.MAV_CMD_MISSION_START, (0, 0))

    # ================================================================== misc

    def _h_autopilot_version(self, msg: Any) -> None:
        self._capabilities = int(msg.capabilities)


_HANDLERS = {
    "HEARTBEAT": MavlinkAutopilot._h_heartbeat,
    "GLOBAL_POSITION_INT": MavlinkAutopilot._h_global_position_int,
    "ATTITUDE": MavlinkAutopilot._h_attitude,
    "VFR_HUD": MavlinkAutopilot._h_vfr_hud,
    "GPS_RAW_INT": MavlinkAutopilot._h_gps_raw_int,
    "SYS_STATUS": MavlinkAutopilot._h_sys_status,
    "BATTERY_STATUS": MavlinkAutopilot._h_battery_status,
    "EXTENDED_SYS_STATE": MavlinkAutopilot._h_extended_sys_state,
    "HOME_POSITION": MavlinkAutopilot._h_home_position,
    "MISSION_CURRENT": MavlinkAutopilot._h_mission_current,
    "AUTOPILOT_VERSION": MavlinkAutopilot._h_autopilot_version,
}
