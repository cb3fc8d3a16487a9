"""The MAVSDK backend's link: one MAVSDK instance, its plugins, and the calls through them.

Built on the ``mavsdk`` package **4.x**, the native ctypes binding of the MAVSDK C++ library (no
``mavsdk_server`` process, no gRPC). Blocking plugin calls run in the default executor, bounded by
the command timeout and cut short when the heartbeat stops (:meth:`MavsdkLink.call`); raw commands
(modes, take-off, repositions) go through the ``MavlinkDirect`` plugin with our own ACK wait
(:meth:`MavsdkLink.direct_command`). A refusal carries the vehicle's last STATUSTEXT, as the
pymavlink link's do. The heartbeat clock and the status texts are written by the telemetry feed
(:mod:`agent.autopilot.mavsdk_telemetry`) under the shared state lock.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from agent.autopilot.base import CommandRefused, CommandTimeout, LinkLost
from agent.autopilot.mavlink_link import INT32_MAX, mavlink

log = logging.getLogger(__name__)

__all__ = ["MavsdkLink", "to_mavsdk_url"]

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


class MavsdkLink:
    """One MAVSDK connection to one autopilot (the first that shows up on :attr:`url`)."""

    def __init__(
        self, url: str, lock: threading.Lock, *, heartbeat_timeout_s: float, command_timeout_s: float
    ) -> None:
        self.url = url
        self.lock = lock  # the vehicle state's: status texts and the heartbeat clock are written under it
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.command_timeout_s = command_timeout_s
        self.texts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=20)
        self.last_hb = 0.0
        self.sysid = 0
        self.compid = 1
        self.autopilot_type = mavlink.MAV_AUTOPILOT_GENERIC
        self.mavsdk: Any = None
        self.system: Any = None
        self.telemetry: Any = None
        self.action: Any = None
        self.geofence: Any = None
        self.mission_raw: Any = None
        self.param: Any = None
        self.direct: Any = None
        self._ack_waiters: list[tuple[int, asyncio.AbstractEventLoop, asyncio.Queue[int]]] = []
        self.closed = False

    async def open(self, timeout: float, companion: bool) -> None:
        """Open the connection, wait for the first autopilot and start its plugins."""
        from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.geofence import Geofence
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.mission_raw import MissionRaw
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry as MavsdkTelemetry

        _route_mavsdk_logs()
        loop = asyncio.get_running_loop()
        kind = ComponentType.COMPANION_COMPUTER if companion else ComponentType.GROUND_STATION
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(kind))
        result = await loop.run_in_executor(None, self.mavsdk.add_any_connection, self.url)
        if result != ConnectionResult.SUCCESS:
            raise LinkLost(f"MAVSDK cannot open {self.url}: {getattr(result, 'name', result)}")
        system = await loop.run_in_executor(None, self.mavsdk.first_autopilot, timeout)
        if system is None:
            raise LinkLost(f"no autopilot on {self.url} within {timeout:.0f} s")
        self.system = system
        self.sysid = system.get_system_id()
        kind_name = getattr(system.autopilot_type(), "name", "")
        self.autopilot_type = {
            "ARDUPILOT": mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            "PX4": mavlink.MAV_AUTOPILOT_PX4,
        }.get(kind_name, mavlink.MAV_AUTOPILOT_GENERIC)
        self.telemetry = MavsdkTelemetry(system)
        self.action = Action(system)
        self.geofence = Geofence(system)
        self.mission_raw = MissionRaw(system)
        self.param = Param(system)
        self.direct = MavlinkDirect(system)
        self.last_hb = time.monotonic()

    async def set_rates(self, telemetry_hz: float) -> None:
        """Ask for the telemetry rates (fast ones at ``telemetry_hz``, the rest at 1 Hz); best effort."""
        loop = asyncio.get_running_loop()
        for setter in ("position", "velocity_ned", "attitude_euler", "landed_state", "in_air"):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(
                    loop.run_in_executor(None, getattr(self.telemetry, f"set_rate_{setter}"), telemetry_hz),
                    self.command_timeout_s,
                )
        for setter in ("home", "battery", "gps_info"):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(
                    loop.run_in_executor(None, getattr(self.telemetry, f"set_rate_{setter}"), 1.0),
                    self.command_timeout_s,
                )

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        mavsdk, self.mavsdk = self.mavsdk, None
        if mavsdk is not None:
            await asyncio.get_running_loop().run_in_executor(None, mavsdk.destroy)

    def status_texts(self) -> list[str]:
        with self.lock:
            return [t for _, _, t in self.texts]

    def ensure_link(self, what: str) -> None:
        if self.system is None or self.closed:
            raise LinkLost(f"{what}: not connected")
        age = time.monotonic() - self.last_hb
        if age > self.heartbeat_timeout_s:
            raise LinkLost(f"{what}: no heartbeat from the vehicle for {age:.1f} s")

    def refusal_text(self, since: float) -> str | None:
        with self.lock:
            recent = [(sev, text) for t, sev, text in self.texts if t >= since]
        serious = [text for sev, text in recent if sev <= mavlink.MAV_SEVERITY_WARNING]
        pick = serious or [text for _, text in recent]
        return pick[-1] if pick else None

    async def call(self, what: str, fn: Callable[..., Any], *args: Any, timeout: float | None = None) -> Any:
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
            text = self.refusal_text(started - 0.5)
            if text is None:
                await asyncio.sleep(0.25)
                text = self.refusal_text(started - 0.5)
            raise CommandRefused(what, f"{text} [{name}]" if text else name) from exc

    def on_command_ack(self, msg: Any, _user: Any) -> None:
        if msg.system_id != self.sysid:
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

    async def direct_command(
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
            "target_system": self.sysid,
            "target_component": self.compid,
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
            target_system_id=self.sysid,
            target_component_id=self.compid,
            fields_json=json.dumps(fields),
        )
        loop = asyncio.get_running_loop()
        queue: asyncio.Queue[int] = asyncio.Queue()
        waiter = (command, loop, queue)
        self._ack_waiters.append(waiter)
        started = time.monotonic()
        try:
            for _ in range(3):
                await loop.run_in_executor(None, self.direct.send_message, message)
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
                    text = self.refusal_text(started - 0.5)
                    raise CommandRefused(what, f"{text} [{name}]" if text else name)
            raise CommandTimeout(what, 4.5)
        finally:
            self._ack_waiters.remove(waiter)
