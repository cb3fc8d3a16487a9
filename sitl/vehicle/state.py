"""The vehicle's faces toward the outside: the link it talks through, the snapshot it gives Python
callers, and the failures a test schedules."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from sitl.dialect import mavlink as mav


class LinkAPI(Protocol):
    """What a vehicle needs from its endpoint."""

    def send(self, msg: mav.MAVLink_message) -> None:
        """Queue one message for the connected client (dropped when none or the link is down)."""

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        """Stream ``msgid`` every ``interval_s`` sim seconds; None stops it."""


class NullLink:
    """The link of a vehicle no endpoint has attached yet: everything is dropped."""

    def send(self, msg: mav.MAVLink_message) -> None:
        """Dropped."""

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        """Ignored."""


@dataclass(slots=True, frozen=True)
class VehicleState:
    """Snapshot of a vehicle for Python callers. ``lat``/``lon``/``alt_*`` are ground truth; ``est_*`` is
    what the vehicle reports over MAVLink (GPS error, path wobble and dead reckoning included)."""

    sysid: int
    sim_time: float
    lat: float
    lon: float
    alt_rel: float
    alt_amsl: float
    est_lat: float
    est_lon: float
    est_alt_rel: float
    vn: float
    ve: float
    vd: float
    groundspeed: float
    heading_deg: float
    armed: bool
    mode: str
    custom_mode: int
    landed: bool
    battery_pct: float
    voltage_v: float
    current_a: float
    gps_fix: int
    home_lat: float
    home_lon: float
    home_alt_amsl: float
    mission_current: int
    mission_count: int
    link_down: bool
    fence_breached: bool
    energy_used_j: float
    distance_flown_m: float
    max_path_error_m: float


@dataclass(slots=True)
class Failure:
    """A scheduled failure: ``kind`` in link_drop, gps_loss, battery, wind; ``at`` sim seconds."""

    at: float
    kind: str
    duration: float = 0.0
    value: tuple[float, ...] = ()
