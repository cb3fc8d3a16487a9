"""Geofence-proximity alarm: warn (and optionally act) before a drone reaches the fence.

The agents enforce the fence themselves (breach -> rtl/land/hold); this extension gives the
operator the earlier warning a breach reaction cannot: a ``geofence_proximity`` event when a
drone comes within ``margin_m`` of the fence boundary (or above ``max_alt_m - margin_m``), once
per approach (re-armed after it moves back beyond 1.5 x margin). With ``action`` set to
``hold`` / ``rtl`` / ``land`` it also commands the drone.

Options: ``margin_m`` (default 15), ``action`` (``report``), and the fence: ``circle``
``{lat, lon, radius_m}`` and/or ``polygon`` ``[{lat, lon}, ...]`` and ``max_alt_m``; without
them it watches the fence the operator last set through the API.
"""

from __future__ import annotations

import math
from typing import Any

from gcs.extensions import Extension
from protocol.geo import distance_m, ned_offset_m, point_in_polygon
from protocol.packets import Geofence, StatusReport


def distance_to_fence(geofence: Geofence, lat: float, lon: float, alt_rel: float) -> float:
    """Metres from the point to the nearest fence limit; negative when outside."""
    margins: list[float] = []
    if geofence.circle is not None:
        c = geofence.circle
        margins.append(c.radius_m - distance_m(c.lat, c.lon, lat, lon))
    if geofence.polygon:
        ring = [(v.lat, v.lon) for v in geofence.polygon]
        pts = [ned_offset_m(lat, lon, a, b) for a, b in ring]  # vertices relative to the drone
        edge = min(_segment_distance(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts)))
        margins.append(edge if point_in_polygon(lat, lon, ring) else -edge)
    if geofence.max_alt_m is not None:
        margins.append(geofence.max_alt_m - alt_rel)
    return min(margins) if margins else math.inf


def _segment_distance(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Distance from the origin to segment a-b (metres, local north/east)."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, -(ax * dx + ay * dy) / length2))
    return math.hypot(ax + t * dx, ay + t * dy)


class GeofenceProximityAlarm(Extension):
    name = "geofence-alarm"

    def __init__(self, options: dict[str, Any] | None = None) -> None:
        super().__init__(options)
        self.margin_m = float(self.options.get("margin_m", 15.0))
        self.action = str(self.options.get("action", "report"))
        if self.action not in ("report", "hold", "rtl", "land"):
            raise ValueError(f"geofence-alarm: action must be report, hold, rtl or land, not {self.action!r}")
        fence = {k: self.options[k] for k in ("circle", "polygon", "max_alt_m") if k in self.options}
        self.fixed_fence = Geofence.model_validate(fence) if fence else None
        self.alarmed: set[str] = set()
        self.alarms = 0

    def fence(self) -> Geofence | None:
        """The configured fence, else the one the operator last set through the API."""
        if self.fixed_fence is not None:
            return self.fixed_fence
        hub = self.context.service("live-hub") if self.context else None
        return getattr(hub, "geofence", None)

    async def on_status(self, agent: str, status: StatusReport) -> None:
        fence = self.fence()
        p = status.position
        if fence is None or status.landed or p is None:
            return
        margin = distance_to_fence(fence, p.lat, p.lon, p.alt_rel)
        if agent in self.alarmed:
            if margin > 1.5 * self.margin_m:
                self.alarmed.discard(agent)
            return
        if margin < self.margin_m:
            self.alarmed.add(agent)
            self.alarms += 1
            self.publish(
                "geofence_proximity",
                f"{margin:.1f} m from the geofence (alarm at {self.margin_m:.0f} m); action {self.action}",
                severity="warning",
                agent=agent,
                data={"margin_m": round(margin, 2), "action": self.action},
            )
            if self.action != "report":
                await self.command(agent, self.action, f"{margin:.1f} m from the fence")  # type: ignore[arg-type]


def create_extension(options: dict[str, Any]) -> GeofenceProximityAlarm:
    return GeofenceProximityAlarm(options)
