"""The MAVSDK backend's telemetry: plugin callbacks into the vehicle state both backends keep.

MAVSDK calls these on its own threads; each runs under the state's lock. The mode comes from the
raw HEARTBEAT (through ``MavlinkDirect``, decoded by the vehicle's flavour, which also feeds the
heartbeat clock and the pilot gate); MAVSDK's own ``flight_mode`` is used only until a heartbeat
has been decoded. The heading comes from ``heading`` when the vehicle sends it, else from the
attitude's yaw.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from typing import Any

from agent.autopilot.flavours import flavour_for
from agent.autopilot.mavlink_link import mavlink
from agent.autopilot.mavsdk_link import MavsdkLink
from agent.autopilot.vehicle_state import VehicleState

__all__ = ["MavsdkTelemetry"]

_MAVSDK_MODE = {  # telemetry.FlightMode name -> our vocabulary (ArduPilot names where they match)
    "HOLD": "LOITER",
    "MISSION": "AUTO",
    "RETURN_TO_LAUNCH": "RTL",
}


class MavsdkTelemetry:
    """Subscribes to a :class:`MavsdkLink`'s plugins and folds what they report into a state."""

    def __init__(self, state: VehicleState, link: MavsdkLink) -> None:
        self.state = state
        self.link = link
        self._mode_from_heartbeat = False
        self._heading_seen = False

    def subscribe(self) -> None:
        """Subscribe every callback (once, after :meth:`MavsdkLink.open`)."""
        t = self.link.telemetry
        lock = self.state.lock

        def on(name: str, handler: Callable[[Any], None]) -> None:
            def callback(data: Any, _user: Any) -> None:
                with lock:
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
            with lock:
                self.state.on_mission_seq(int(progress.current))

        self.link.mission_raw.subscribe_mission_progress(on_progress)
        self.link.direct.subscribe_message("HEARTBEAT", self._on_heartbeat)
        self.link.direct.subscribe_message("COMMAND_ACK", self.link.on_command_ack)

    def _on_heartbeat(self, msg: Any, _user: Any) -> None:
        link = self.link
        if msg.system_id != link.sysid or msg.component_id != link.compid:
            return
        try:
            fields = json.loads(msg.fields_json)
        except (TypeError, ValueError):
            return
        if fields.get("autopilot") == mavlink.MAV_AUTOPILOT_INVALID:
            return
        with self.state.lock:
            link.last_hb = time.monotonic()
            link.autopilot_type = int(fields.get("autopilot", link.autopilot_type))
            flavour = flavour_for(link.autopilot_type)
            try:
                base_mode = int(fields["base_mode"])
                raw = flavour.decode_mode(int(fields["type"]), base_mode, int(fields["custom_mode"]))
            except (KeyError, TypeError, ValueError):
                return
            self._mode_from_heartbeat = True
            self.state.on_heartbeat(flavour, raw, base_mode, fields.get("system_status"))

    def _on_position(self, p: Any) -> None:
        tel = self.state.tel
        if not all(math.isfinite(v) for v in (p.latitude_deg, p.longitude_deg)):
            return
        tel.lat, tel.lon = float(p.latitude_deg), float(p.longitude_deg)
        tel.alt_amsl, tel.alt_rel = float(p.absolute_altitude_m), float(p.relative_altitude_m)
        tel.latch_position()
        self.state.update_landed()

    def _on_heading(self, h: Any) -> None:
        if math.isfinite(h.heading_deg):
            self.state.tel.heading_deg = float(h.heading_deg) % 360.0
            self._heading_seen = True

    def _on_attitude(self, a: Any) -> None:
        if not self._heading_seen and math.isfinite(a.yaw_deg):
            self.state.tel.heading_deg = float(a.yaw_deg) % 360.0

    def _on_home(self, h: Any) -> None:
        tel = self.state.tel
        if math.isfinite(h.latitude_deg) and math.isfinite(h.longitude_deg):
            tel.home_lat, tel.home_lon = float(h.latitude_deg), float(h.longitude_deg)
            tel.home_alt_amsl = float(h.absolute_altitude_m)

    def _on_velocity(self, v: Any) -> None:
        tel = self.state.tel
        tel.vn, tel.ve, tel.vd = float(v.north_m_s), float(v.east_m_s), float(v.down_m_s)

    def _on_battery(self, b: Any) -> None:
        if getattr(b, "id", 0) not in (0, None):
            return
        tel = self.state.tel
        tel.battery_pct = float(b.remaining_percent) if math.isfinite(b.remaining_percent) else None
        tel.voltage_v = float(b.voltage_v) if math.isfinite(b.voltage_v) else None
        tel.current_a = float(b.current_battery_a) if math.isfinite(b.current_battery_a) else None

    def _on_gps(self, g: Any) -> None:
        tel = self.state.tel
        tel.gps_fix = int(g.fix_type)
        tel.satellites = int(g.num_satellites)
        tel.latch_position()

    def _on_armed(self, armed: Any) -> None:
        self.state.tel.armed = bool(armed)
        self.state.update_landed()

    def _on_flight_mode(self, mode: Any) -> None:
        if self._mode_from_heartbeat:
            return
        name = getattr(mode, "name", str(mode))
        self.state.tel.mode = _MAVSDK_MODE.get(name, name)
        self.state.update_mission_current()

    def _on_landed_state(self, state: Any) -> None:
        self.state.on_landed_state(int(state))

    def _on_status_text(self, st: Any) -> None:
        # MAVSDK StatusTextType: DEBUG=0 ... EMERGENCY=7 (reverse of MAV_SEVERITY).
        self.link.texts.append((time.monotonic(), 7 - int(st.type), str(st.text)))
