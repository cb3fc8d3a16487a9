"""The pymavlink backend's telemetry: MAVLink messages from the autopilot into the vehicle state.

Runs on the link's reader thread (:mod:`agent.autopilot.mavlink_link`): each message the vehicle's
autopilot component sends is decoded under the state's lock. Which field comes from which message
(heading from GLOBAL_POSITION_INT before ATTITUDE/VFR_HUD, battery from BATTERY_STATUS before
SYS_STATUS, ...) is in ``docs/autopilot-backends.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from agent.autopilot.flavours import flavour_for
from agent.autopilot.vehicle_state import VehicleState

__all__ = ["MavlinkTelemetry"]


class MavlinkTelemetry:
    """Decodes the autopilot's messages into a :class:`VehicleState` (and its capabilities)."""

    def __init__(self, state: VehicleState) -> None:
        self.state = state
        self.capabilities: int | None = None  # AUTOPILOT_VERSION.capabilities, once answered
        self._heading_from_gpi = False
        self._battery_status_pct: float | None = None

    def on_message(self, msg: Any) -> None:  # reader thread, messages from the autopilot component
        handler = _HANDLERS.get(msg.get_type())
        if handler is not None:
            with self.state.lock:
                handler(self, msg)

    def _h_heartbeat(self, msg: Any) -> None:
        flavour = flavour_for(msg.autopilot)
        raw = flavour.decode_mode(msg.type, msg.base_mode, msg.custom_mode)
        self.state.on_heartbeat(flavour, raw, msg.base_mode, msg.system_status)

    def _h_global_position_int(self, msg: Any) -> None:
        tel = self.state.tel
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
        self.state.update_landed()

    def _h_attitude(self, msg: Any) -> None:
        if not self._heading_from_gpi:
            self.state.tel.heading_deg = math.degrees(msg.yaw) % 360.0

    def _h_vfr_hud(self, msg: Any) -> None:
        if not self._heading_from_gpi:
            self.state.tel.heading_deg = float(msg.heading) % 360.0

    def _h_gps_raw_int(self, msg: Any) -> None:
        tel = self.state.tel
        tel.gps_fix = int(msg.fix_type)
        tel.satellites = 0 if msg.satellites_visible == 255 else int(msg.satellites_visible)
        tel.latch_position()

    def _h_sys_status(self, msg: Any) -> None:
        tel = self.state.tel
        if msg.battery_remaining >= 0:
            tel.battery_pct = float(msg.battery_remaining)
        elif self._battery_status_pct is None:
            tel.battery_pct = None
        tel.voltage_v = None if msg.voltage_battery == 65535 else msg.voltage_battery / 1000.0
        tel.current_a = None if msg.current_battery < 0 else msg.current_battery / 100.0

    def _h_battery_status(self, msg: Any) -> None:
        if msg.id != 0:
            return
        tel = self.state.tel
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
        self.state.on_landed_state(int(msg.landed_state))

    def _h_home_position(self, msg: Any) -> None:
        tel = self.state.tel
        tel.home_lat = msg.latitude / 1e7
        tel.home_lon = msg.longitude / 1e7
        tel.home_alt_amsl = msg.altitude / 1000.0

    def _h_mission_current(self, msg: Any) -> None:
        self.state.on_mission_seq(int(msg.seq))

    def _h_autopilot_version(self, msg: Any) -> None:
        self.capabilities = int(msg.capabilities)


_HANDLERS: dict[str, Callable[[MavlinkTelemetry, Any], None]] = {
    "HEARTBEAT": MavlinkTelemetry._h_heartbeat,
    "GLOBAL_POSITION_INT": MavlinkTelemetry._h_global_position_int,
    "ATTITUDE": MavlinkTelemetry._h_attitude,
    "VFR_HUD": MavlinkTelemetry._h_vfr_hud,
    "GPS_RAW_INT": MavlinkTelemetry._h_gps_raw_int,
    "SYS_STATUS": MavlinkTelemetry._h_sys_status,
    "BATTERY_STATUS": MavlinkTelemetry._h_battery_status,
    "EXTENDED_SYS_STATE": MavlinkTelemetry._h_extended_sys_state,
    "HOME_POSITION": MavlinkTelemetry._h_home_position,
    "MISSION_CURRENT": MavlinkTelemetry._h_mission_current,
    "AUTOPILOT_VERSION": MavlinkTelemetry._h_autopilot_version,
}
