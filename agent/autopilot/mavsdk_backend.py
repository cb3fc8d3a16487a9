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
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

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
from agent.autopilot.mavlink_link import INT32_MAX, mavlink

log = logging.getLogger(__name__)

__all__ = ["MavsdkAutopilot", "to_mavsdk_url"]

_REFUSED = {
    "COMMAND_DENIED",
    "COMMAND_DENIED_LANDED_STATE_UNKNOWN",
    "COMMAND_DENIED_NOT_LANDED",
    "FAILED",
    "UNSUPPORTED",
    "BUSY",
    "DENIED",
    "ERROR",
    "INVALID_ARGUMENT",
    "PARAMETER_ERROR",
    "NO_VTOL_TRANSITION_SUPPORT",
    "TOO_MANY_GEOFENCE_ITEMS",
    "TOO_MANY_MISSION_ITEMS",
    "WRONG_TYPE",
    "PARAM_NAME_TOO_LONG",
    "PARAM_VALUE_TOO_LONG",
}
_LINK = {"NO_SYSTEM", "CONNECTION_ERROR"}


def to_mavsdk_url(connection: str) -> str:
    """Translate pymavlink-style and deprecated MAVSDK connection strings to MAVSDK 2+ URLs."""
    conn = connection.strip()
    if "://" in conn:
        scheme, rest = conn.split("://", 1)
        if scheme == "udp":  # deprecated "udp://:14540" = listen
            host, _, port = rest.rpartition(":")
            return f"udpin://{host or '0.0.0.0'}:{port}"
        if scheme == "tcp":  # deprecated "tcp://host:port" = connect
            return f"tcpout://{rest}"
        return conn
    for prefix, scheme in (
        ("tcp:", "tcpout"),
        ("tcpin:", "tcpin"),
        ("udpin:", "udpin"),
        ("udpout:", "udpout"),
        ("udp:", "udpin"),
    ):
        if conn.startswith(prefix):
            return f"{scheme}://{conn[len(prefix) :]}"
    if conn.startswith("serial:"):
        conn = conn[len("serial:") :]
    if conn.startswith("/dev/") or conn.upper().startswith("COM"):
        for sep in (",", ":"):
            if sep in conn:
                device, baud = conn.rsplit(sep, 1)
                if baud.isdigit():
                    return f"serial://{device}:{baud}"
        return f"serial://{conn}:57600"
    return conn


_mavsdk_log = logging.getLogger("mavsdk")
_logs_routed = False


def _route_mavsdk_logs() -> None:
    """Send MAVSDK's own log lines (printed to stdout by default) to the ``mavsdk`` Python logger."""
    global _logs_routed
    if _logs_routed:
        return
    from mavsdk import log_subscribe

    levels = (logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR)

    def handler(level: Any, message: str, file: str | None, line: int) -> bool:
        _mavsdk_log.log(levels[min(int(level), 3)], "%s", message)
        return True

    log_subscribe(handler)
    _logs_routed = True


_MAVSDK_MODE = {  # telemetry.FlightMode name -> our vocabulary (ArduPilot names where they match)
    "HOLD": "LOITER",
    "MISSION": "AUTO",
    "RETURN_TO_LAUNCH": "RTL",
}


class MavsdkAutopilot(Autopilot):
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
        self._lock = threading.Lock()
        self._tel = Telemetry()
        self._texts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=20)
        self._last_hb = 0.0
        self._sysid = 0
        self._compid = 1
        self._autopilot_type = mavlink.MAV_AUTOPILOT_GENERIC
        self._mode_from_heartbeat = False
        self._shown = ShownMode()  # PX4: GUIDED while our reposition leg is flown, LOITER once held
        self._leg_speed: float | None = None  # PX4: the last speed asked for, sent with each reposition
        self._param_is_int: dict[str, bool] = {}
        self._mission_seq = -1
        self._mission_offset = 0
        self._landed_state = 0
        self._heading_seen = False
        self._mavsdk: Any = None
        self._system: Any = None
        self._telemetry: Any = None
        self._action: Any = None
        self._geofence: Any = None
        self._mission_raw: Any = None
        self._param: Any = None
        self._direct: Any = None
        self._ack_waiters: list[tuple[int, asyncio.AbstractEventLoop, asyncio.Queue[int]]] = []
        self._closed = False

    # ================================================================== lifecycle

    async def connect(self, timeout: float = 30.0) -> None:
        from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.geofence import Geofence
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.mission_raw import MissionRaw
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry as MavsdkTelemetry

        _route_mavsdk_logs()
        loop = asyncio.get_running_loop()
        kind = ComponentType.COMPANION_COMPUTER if self.companion else ComponentType.GROUND_STATION
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(kind))
        result = await loop.run_in_executor(None, self._mavsdk.add_any_connection, self.url)
        if result != ConnectionResult.SUCCESS:
            raise LinkLost(f"MAVSDK cannot open {self.url}: {getattr(result, 'name', result)}")
        system = await loop.run_in_executor(None, self._mavsdk.first_autopilot, timeout)
        if system is None:
            raise LinkLost(f"no autopilot on {self.url} within {timeout:.0f} s")
        self._system = system
        self._sysid = system.get_system_id()
        kind_name = getattr(system.autopilot_type(), "name", "")
        self._autopilot_type = {
            "ARDUPILOT": mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            "PX4": mavlink.MAV_AUTOPILOT_PX4,
        }.get(kind_name, mavlink.MAV_AUTOPILOT_GENERIC)
        self._telemetry = MavsdkTelemetry(system)
        self._action = Action(system)
        self._geofence = Geofence(system)
        self._mission_raw = MissionRaw(system)
        self._param = Param(system)
        self._direct = MavlinkDirect(system)
        self._last_hb = time.monotonic()
        self._subscribe()
        for setter in ("position", "velocity_ned", "attitude_euler", "landed_state", "in_air"):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(
                    loop.run_in_executor(
                        None, getattr(self._telemetry, f"set_rate_{setter}"), self.telemetry_hz
                    ),
                    self.command_timeout_s,
                )
        for setter in ("home", "battery", "gps_info"):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(
                    loop.run_in_executor(None, getattr(self._telemetry, f"set_rate_{setter}"), 1.0),
                    self.command_timeout_s,
                )

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        mavsdk, self._mavsdk = self._mavsdk, None
        if mavsdk is not None:
            await asyncio.get_running_loop().run_in_executor(None, mavsdk.destroy)

    # ================================================================== telemetry

    def _subscribe(self) -> None:
        t = self._telemetry

        def on(name: str, handler: Callable[[Any], None]) -> None:
            def callback(data: Any, _user: Any) -> None:
                with self._lock:
                    handler(data)

            getattr(t, f"subscribe_{name}")(callback)

        on("position", self._on_position)
        on("home", self._on_home)
        on("velocity_ned", self._on_velocity)
        on("heading", self._on_heading)
        on("attitude_euler", self._on_attitude)
        on("battery", self._on_battery)
        on("gps_info", self._on_gps)
        on("armed", self._on_armed)
        on("flight_mode", self._on_flight_mode)
        on("landed_state", self._on_landed_state)
        on("status_text", self._on_status_text)

        def on_progress(progress: Any, _user: Any) -> None:
            with self._lock:
                self._mission_seq = int(progress.current)
                self._update_mission_current()

        self._mission_raw.subscribe_mission_progress(on_progress)
        self._direct.subscribe_message("HEARTBEAT", self._on_heartbeat)
        self._direct.subscribe_message("COMMAND_ACK", self._on_command_ack)

    def _on_heartbeat(self, msg: Any, _user: Any) -> None:
        if msg.system_id != self._sysid or msg.component_id != self._compid:
            return
        try:
            fields = json.loads(msg.fields_json)
        except (TypeError, ValueError):
            return
        if fields.get("autopilot") == mavlink.MAV_AUTOPILOT_INVALID:
            return
        with self._lock:
            self._last_hb = time.monotonic()
            self._autopilot_type = int(fields.get("autopilot", self._autopilot_type))
            flavour = flavour_for(self._autopilot_type)
            try:
                raw = flavour.decode_mode(
                    int(fields["type"]), int(fields["base_mode"]), int(fields["custom_mode"])
                )
            except (KeyError, TypeError, ValueError):
                return
            self._mode_from_heartbeat = True
            self._tel.mode = self._shown.from_heartbeat(flavour, raw)
            self._tel.armed = bool(int(fields["base_mode"]) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self._update_landed()
            self._update_mission_current()

    def _on_position(self, p: Any) -> None:
        tel = self._tel
        if not all(math.isfinite(v) for v in (p.latitude_deg, p.longitude_deg)):
            return
        tel.lat, tel.lon = float(p.latitude_deg), float(p.longitude_deg)
        tel.alt_amsl, tel.alt_rel = float(p.absolute_altitude_m), float(p.relative_altitude_m)
        tel.latch_position()
        self._update_landed()

    def _on_heading(self, h: Any) -> None:
        if math.isfinite(h.heading_deg):
            self._tel.heading_deg = float(h.heading_deg) % 360.0
            self._heading_seen = True

    def _on_attitude(self, a: Any) -> None:
        if not self._heading_seen and math.isfinite(a.yaw_deg):
            self._tel.heading_deg = float(a.yaw_deg) % 360.0

    def _on_home(self, h: Any) -> None:
        if math.isfinite(h.latitude_deg) and math.isfinite(h.longitude_deg):
            self._tel.home_lat, self._tel.home_lon = float(h.latitude_deg), float(h.longitude_deg)
            self._tel.home_alt_amsl = float(h.absolute_altitude_m)

    def _on_velocity(self, v: Any) -> None:
        self._tel.vn, self._tel.ve, self._tel.vd = float(v.north_m_s), float(v.east_m_s), float(v.down_m_s)

    def _on_battery(self, b: Any) -> None:
        if getattr(b, "id", 0) not in (0, None):
            return
        tel = self._tel
        tel.battery_pct = float(b.remaining_percent) if math.isfinite(b.remaining_percent) else None
        tel.voltage_v = float(b.voltage_v) if math.isfinite(b.voltage_v) else None
        tel.current_a = float(b.current_battery_a) if math.isfinite(b.current_battery_a) else None

    def _on_gps(self, g: Any) -> None:
        self._tel.gps_fix = int(g.fix_type)
        self._tel.satellites = int(g.num_satellites)
        self._tel.latch_position()

    def _on_armed(self, armed: Any) -> None:
        self._tel.armed = bool(armed)
        self._update_landed()

    def _on_flight_mode(self, mode: Any) -> None:
        if self._mode_from_heartbeat:
            return
        name = getattr(mode, "name", str(mode))
        self._tel.mode = _MAVSDK_MODE.get(name, name)
        self._update_mission_current()

    def _on_landed_state(self, state: Any) -> None:
        self._landed_state = int(state)
        self._update_landed()

    def _on_status_text(self, st: Any) -> None:
        # MAVSDK StatusTextType: DEBUG=0 ... EMERGENCY=7 (reverse of MAV_SEVERITY).
        self._texts.append((time.monotonic(), 7 - int(st.type), str(st.text)))

    def _update_landed(self) -> None:
        tel = self._tel
        if self._landed_state == 1:
            tel.landed = True
        elif self._landed_state in (2, 3, 4):
            tel.landed = False
        else:
            tel.landed = not tel.armed or tel.alt_rel < 0.3

    def _update_mission_current(self) -> None:
        tel = self._tel
        if tel.mode in ("AUTO", "MISSION") and self._mission_seq >= 0:
            tel.mission_current = max(0, self._mission_seq - self._mission_offset)
        else:
            tel.mission_current = -1

    def telemetry(self) -> Telemetry:
        with self._lock:
            snap = dataclasses.replace(self._tel, status_texts=[t for _, _, t in self._texts])
            snap.last_heartbeat_monotonic = self._last_hb
        return snap

    # ================================================================== plumbing

    @property
    def flavour(self) -> Flavour:
        """The vehicle's firmware conventions, from MAVSDK's autopilot type and each heartbeat."""
        return flavour_for(self._autopilot_type)

    def _set_leg_active(self, active: bool) -> None:
        with self._lock:
            mode = self._shown.leg(self.flavour, active)
            if mode is not None:
                self._tel.mode = mode

    def ensure_link(self, what: str) -> None:
        if self._system is None or self._closed:
            raise LinkLost(f"{what}: not connected")
        age = time.monotonic() - self._last_hb
        if age > self.heartbeat_timeout_s:
            raise LinkLost(f"{what}: no heartbeat from the vehicle for {age:.1f} s")

    def _refusal_text(self, since: float) -> str | None:
        with self._lock:
            recent = [(sev, text) for t, sev, text in self._texts if t >= since]
        serious = [text for sev, text in recent if sev <= mavlink.MAV_SEVERITY_WARNING]
        pick = serious or [text for _, text in recent]
        return pick[-1] if pick else None

    async def _call(self, what: str, fn: Callable[..., Any], *args: Any, timeout: float | None = None) -> Any:
        """Run a blocking MAVSDK call in the executor, mapping its errors onto ours."""
        from mavsdk import MavsdkError

        self.ensure_link(what)
        limit = timeout or self.command_timeout_s
        started = time.monotonic()
        loop = asyncio.get_running_loop()
        task = loop.run_in_executor(None, fn, *args)
        try:
            deadline = started + limit
            while True:
                done, _ = await asyncio.wait({task}, timeout=min(0.1, max(0.0, deadline - time.monotonic())))
                if done:
                    return task.result()
                self.ensure_link(what)
                if time.monotonic() >= deadline:
                    raise CommandTimeout(what, limit)
        except MavsdkError as exc:
            result = getattr(exc, "result", None)
            name = getattr(result, "name", str(result))
            if name == "TIMEOUT":
                raise CommandTimeout(what, limit) from exc
            if name in _LINK:
                raise LinkLost(f"{what}: {name}") from exc
            text = self._refusal_text(started - 0.5)
            if text is None:
                await asyncio.sleep(0.25)
                text = self._refusal_text(started - 0.5)
            raise CommandRefused(what, f"{text} [{name}]" if text else name) from exc

    def _on_command_ack(self, msg: Any, _user: Any) -> None:
        if msg.system_id != self._sysid:
            return
        try:
            fields = json.loads(msg.fields_json)
            command, result = int(fields["command"]), int(fields["result"])
        except (TypeError, ValueError, KeyError):
            return
        for cmd, loop, queue in list(self._ack_waiters):
            if cmd == command:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(queue.put_nowait, result)

    async def _direct_command(
        self, what: str, command: int, params: tuple[float, ...], int_frame: int | None = None
    ) -> None:
        """A raw COMMAND_LONG (COMMAND_INT with ``int_frame``: params 5/6 lat/lon in degrees)
        through MavlinkDirect, waiting for its COMMAND_ACK."""
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        self.ensure_link(what)
        # JSON has no NaN and MavlinkDirect turns a "NaN" string into 0 (measured); a JSON null is
        # NaN in a float field (MAVSDK 4.x libcmavsdk). COMMAND_INT lat/lon NaN: INT32_MAX.
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        if any(math.isinf(x) for x in p):
            raise ValueError(f"{what}: infinite command parameter {params!r}")
        if int_frame is None and not all(math.isfinite(x) for x in p[4:6]):
            raise ValueError(f"{what}: NaN lat/lon needs COMMAND_INT {params!r}")
        f: list[float | None] = [x if math.isfinite(x) else None for x in p]
        fields: dict[str, Any] = {
            "target_system": self._sysid,
            "target_component": self._compid,
            "command": command,
        }
        if int_frame is None:
            fields |= {"confirmation": 0, **{f"param{i + 1}": f[i] for i in range(7)}}
        else:
            fields |= {
                "frame": int_frame,
                "current": 0,
                "autocontinue": 0,
                **{f"param{i + 1}": f[i] for i in range(4)},
                "x": round(p[4] * 1e7) if math.isfinite(p[4]) else INT32_MAX,
                "y": round(p[5] * 1e7) if math.isfinite(p[5]) else INT32_MAX,
                "z": f[6],
            }
        message = MavlinkMessage(
            message_name="COMMAND_LONG" if int_frame is None else "COMMAND_INT",
            system_id=0,
            component_id=0,
            target_system_id=self._sysid,
            target_component_id=self._compid,
            fields_json=json.dumps(fields),
        )
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[int] = asyncio.Queue()
        waiter = (command, loop, queue)
        self._ack_waiters.append(waiter)
        started = time.monotonic()
        try:
            for _ in range(3):
                await loop.run_in_executor(None, self._direct.send_message, message)
                deadline = time.monotonic() + 1.5
                while (remaining := deadline - time.monotonic()) > 0:
                    try:
                        result = await asyncio.wait_for(queue.get(), min(remaining, 0.1))
                    except TimeoutError:
                        self.ensure_link(what)
                        continue
                    if result == mavlink.MAV_RESULT_ACCEPTED:
                        return
                    if result == mavlink.MAV_RESULT_IN_PROGRESS:
                        continue
                    entry = mavlink.enums["MAV_RESULT"].get(result)
                    name = entry.name if entry else str(result)
                    text = self._refusal_text(started - 0.5)
                    raise CommandRefused(what, f"{text} [{name}]" if text else name)
            raise CommandTimeout(what, 4.5)
        finally:
            self._ack_waiters.remove(waiter)

    async def _set_mode(self, name: str) -> None:
        """MAV_CMD_DO_SET_MODE by name, encoded by the flavour (a no-op when already in it)."""
        if self.telemetry().mode == name:
            return
        try:
            params, _ = self.flavour.mode_command(name, mavlink.MAV_TYPE_QUADROTOR)
        except KeyError:
            raise CommandRefused(f"mode {name}", f"no such {self.flavour.name} mode") from None
        await self._direct_command(f"mode {name}", mavlink.MAV_CMD_DO_SET_MODE, params)
        self._set_leg_active(False)

    # ================================================================== commands

    async def arm(self, deadline_s: float = 60.0) -> None:
        deadline = time.monotonic() + deadline_s
        last: AutopilotError | None = None
        while True:
            self.ensure_link("arm")
            try:
                if self.flavour.guided_mode is not None:
                    await self._set_mode(self.flavour.guided_mode)
                await self._call("arm", self._action.arm)
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
        await self._call("disarm", self._action.disarm)

    async def takeoff(self, alt_rel_m: float) -> None:
        if not math.isfinite(alt_rel_m) or alt_rel_m <= 0:
            raise ValueError(f"takeoff altitude must be a positive number, not {alt_rel_m!r}")
        flavour = self.flavour
        if flavour.guided_mode is not None:
            # MAVSDK's ArduPilot takeoff sends NAV_TAKEOFF without switching mode; ArduCopter needs GUIDED.
            await self._set_mode(flavour.guided_mode)
        params = flavour.takeoff_params(alt_rel_m, self.telemetry())
        await self._direct_command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, params)
        self._set_leg_active(False)

    async def set_speed(self, speed_mps: float) -> None:
        if not math.isfinite(speed_mps) or speed_mps <= 0:
            raise ValueError(f"speed must be a positive number, not {speed_mps!r}")
        self._leg_speed = speed_mps
        await self._call("set speed", self._action.set_current_speed, speed_mps)

    def _amsl(self, alt_rel_m: float) -> float:
        return base_altitude_amsl(self.telemetry()) + alt_rel_m

    async def _reposition(
        self, what: str, lat: float, lon: float, alt_amsl: float, speed: float | None
    ) -> None:
        params = self.flavour.reposition_params(lat, lon, alt_amsl, speed)
        await self._direct_command(
            what, mavlink.MAV_CMD_DO_REPOSITION, params, int_frame=mavlink.MAV_FRAME_GLOBAL
        )

    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        if not all(math.isfinite(v) for v in (lat, lon, alt_rel_m)):
            raise ValueError("goto: non-finite target")
        if not self.telemetry().armed:
            raise CommandRefused("goto", "vehicle is disarmed")
        flavour = self.flavour
        if flavour.guided_mode is None:  # PX4: DO_REPOSITION with the speed in param1
            if speed_mps is not None:
                self._leg_speed = speed_mps
            await self._reposition("goto", lat, lon, self._amsl(alt_rel_m), self._leg_speed)
            self._set_leg_active(True)
            return
        # ArduCopter: GUIDED, the target, then the speed (the target resets it to WPNAV_SPEED).
        await self._set_mode(flavour.guided_mode)
        await self._call("goto", self._action.goto_location, lat, lon, self._amsl(alt_rel_m), math.nan)
        if speed_mps is not None:
            await self.set_speed(speed_mps)

    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        if (lat is None) != (lon is None):
            raise ValueError("land: give both lat and lon, or neither")
        if lat is not None and lon is not None:
            await self.approach_landing_point(lat, lon)
        await self._call("land", self._action.land)

    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        if alt_rel_m is None:
            alt_rel_m = self.flavour.default_return_alt(self.telemetry())
        elif not math.isfinite(alt_rel_m) or alt_rel_m <= 0:
            raise ValueError(f"return altitude must be a positive number, not {alt_rel_m!r}")
        if alt_rel_m is not None:
            # MAVSDK writes the flavour's parameter (PX4 RTL_RETURN_ALT in m, ArduPilot RTL_ALT in cm).
            try:
                await self._call("rtl altitude", self._action.set_return_to_launch_altitude, float(alt_rel_m))
            except (CommandRefused, CommandTimeout) as exc:  # a return must not fail for its altitude
                log.warning("return altitude %.1f m not set (%s); returning at the vehicle's", alt_rel_m, exc)
        await self._call("rtl", self._action.return_to_launch)
        self._set_leg_active(False)

    async def hold(self) -> None:
        """Stop where the vehicle is: ArduPilot BRAKE (LOITER if refused); PX4 its own pause
        (:meth:`Flavour.pause_params`; ``Action.hold`` would only ask for the Hold it flies in)."""
        flavour = self.flavour
        tel = self.telemetry()
        pause = flavour.pause_params()
        if pause is not None and tel.armed and not tel.landed:
            await self._direct_command(
                "hold", mavlink.MAV_CMD_DO_REPOSITION, pause, int_frame=mavlink.MAV_FRAME_GLOBAL
            )
            self._set_leg_active(False)
            return
        for i, mode in enumerate(flavour.hold_modes):
            try:
                await self._set_mode(mode)
                return
            except CommandRefused as exc:
                if i + 1 == len(flavour.hold_modes):
                    raise
                log.info("%s refused (%s); trying %s", mode, exc.reason, flavour.hold_modes[i + 1])

    # ================================================================== fence, mission, params

    async def set_param(self, name: str, value: float) -> None:
        """Write a parameter (float, falling back to int for integer parameters).

        PX4 ignores a REAL32 PARAM_SET of an INT32 parameter (MAVSDK then times out after 10 s),
        so with a flavour whose integers travel byte-wise the type is read first.
        """
        if self.flavour.params_bytewise:
            if name not in self._param_is_int:
                try:
                    await self._call(f"get {name}", self._param.get_param_int, name)
                    self._param_is_int[name] = True
                except (CommandRefused, CommandTimeout):
                    self._param_is_int[name] = False
            if self._param_is_int[name]:
                await self._call(f"set {name}", self._param.set_param_int, name, round(value))
            else:
                await self._call(f"set {name}", self._param.set_param_float, name, float(value))
            return
        try:
            await self._call(f"set {name}", self._param.set_param_float, name, float(value))
        except CommandRefused:
            await self._call(f"set {name}", self._param.set_param_int, name, round(value))

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
            await self._call("fence upload", self._geofence.upload_geofence, GeofenceData(polygons, circles))
            for name, value in params:
                await self.set_param(name, value)
        except (CommandRefused, CommandTimeout) as exc:
            log.warning("fence not installed: %s", exc)
            return False
        return True

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
        await self._call("mission upload", self._mission_raw.upload_mission, items, timeout=30.0)
        with self._lock:
            self._mission_offset = offset
            self._update_mission_current()

    async def start_mission(self) -> None:
        await self._call("mission start", self._mission_raw.start_mission)
