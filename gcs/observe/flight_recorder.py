"""Per-drone flight records built from status reports: track, distance, time, energy, path error.

Time is the vehicle's own clock when the agent reports it (a simulator's sim time, right under
any speed-up, kept or not), else wall time stretched by the nominal speed-up
(:class:`gcs.cooperation.flightlog.VehicleClock`); ``speedup_kept`` compares the two.

Distance is summed over horizontal track segments longer than a noise floor, so GPS jitter
while hovering does not add up. Energy integrates voltage x current over time; when an autopilot
reports no current, the battery percentage drop is reported instead. Path error is the largest
horizontal distance between the flown track and the planned survey path, sampled while the
drone executes a survey step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from shapely.geometry import LineString, Point

from gcs.cooperation.flightlog import JITTER_FLOOR_M, VehicleClock
from protocol.geo import LocalFrame, distance_m
from protocol.packets import StatusReport


@dataclass
class FlightRecord:
    agent: str
    samples: int = 0
    first_time: float | None = None
    last_time: float | None = None
    airborne_s: float = 0.0
    distance_m: float = 0.0
    energy_wh: float = 0.0
    battery_start_pct: float | None = None
    battery_end_pct: float | None = None
    max_path_error_m: float = 0.0
    max_alt_m: float = 0.0
    landed: bool = True
    armed: bool = False
    track: list[tuple[float, float, float, float]] = field(default_factory=list)  # time, lat, lon, alt_rel
    first_wall: float | None = None
    last_wall: float | None = None
    vehicle_clock: bool = False  # True once the agent reported the vehicle's own clock
    clock: VehicleClock = field(default_factory=VehicleClock)
    _last: StatusReport | None = None
    _last_t: float = 0.0

    def add(self, status: StatusReport, planned: LineString | None, frame: LocalFrame | None) -> None:
        position = status.position
        if position is None:
            return  # no 3-D fix yet
        self.samples += 1
        now = self.clock(status)
        self.vehicle_clock = self.vehicle_clock or status.vehicle_time is not None
        if self.first_time is None:
            self.first_time = now
            self.first_wall = status.time
        self.last_wall = status.time
        previous = self._last
        if previous is not None and previous.position is not None and now > self._last_t:
            dt = now - self._last_t
            step = distance_m(previous.position.lat, previous.position.lon, position.lat, position.lon)
            if step > JITTER_FLOOR_M:
                self.distance_m += step
            if not previous.landed:
                self.airborne_s += dt
            v, a = status.battery.voltage_v, status.battery.current_a
            if v is not None and a is not None and math.isfinite(v * a):
                self.energy_wh += v * max(a, 0.0) * dt / 3600.0
        if status.battery.pct is not None:
            if self.battery_start_pct is None:
                self.battery_start_pct = status.battery.pct
            self.battery_end_pct = status.battery.pct
        if planned is not None and frame is not None and not status.landed:
            here = Point(*frame.local_point(position.lat, position.lon))
            self.max_path_error_m = max(self.max_path_error_m, planned.distance(here))
        self.max_alt_m = max(self.max_alt_m, position.alt_rel)
        self.landed, self.armed = status.landed, status.armed
        self.last_time = now
        self.track.append((now, position.lat, position.lon, position.alt_rel))
        self._last = status
        self._last_t = now

    @property
    def duration_s(self) -> float:
        if self.first_time is None or self.last_time is None:
            return 0.0
        return self.last_time - self.first_time

    @property
    def speedup_kept(self) -> float | None:
        """Vehicle seconds per wall second over the record (None without a vehicle clock)."""
        if not self.vehicle_clock or self.first_wall is None or self.last_wall is None:
            return None
        wall = self.last_wall - self.first_wall
        return self.duration_s / wall if wall > 0 else None

    @property
    def battery_used_pct(self) -> float | None:
        if self.battery_start_pct is None or self.battery_end_pct is None:
            return None
        return self.battery_start_pct - self.battery_end_pct


class FlightRecorder:
    """Collects :class:`FlightRecord` per agent; planned paths are given in lat/lon."""

    def __init__(self, time_scale: float = 1.0) -> None:
        self.time_scale = time_scale  # nominal speed-up, for agents that report no vehicle clock
        self.records: dict[str, FlightRecord] = {}
        self._planned: dict[str, LineString] = {}
        self._survey_steps: dict[str, set[int]] = {}
        self._frame: LocalFrame | None = None

    def set_plan(self, agent: str, path_latlon: list[tuple[float, float]], survey_steps: set[int]) -> None:
        """The survey path to measure ``agent``'s path error against (local metres around the first point)."""
        if len(path_latlon) < 2:
            return
        if self._frame is None:
            self._frame = LocalFrame(*path_latlon[0])
        self._planned[agent] = LineString([self._frame.local_point(lat, lon) for lat, lon in path_latlon])
        self._survey_steps[agent] = survey_steps

    def add(self, agent: str, status: StatusReport) -> None:
        if status.position is None:
            return  # no 3-D fix yet: nothing to record
        record = self.records.setdefault(agent, FlightRecord(agent))
        surveying = status.step in self._survey_steps.get(agent, set())
        record.add(status, self._planned.get(agent) if surveying else None, self._frame)
