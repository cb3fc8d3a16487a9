"""Assertions about what a PX4 vehicle did, read from the independent observer in PX4's own clock."""

from __future__ import annotations

import math

from gcs.cooperation.config import CollisionConfig
from protocol.actions import Goto, Hold, Land, Takeoff
from protocol.geo import distance_m
from tests.px4.rig import PX4Rig
from tests.support.rig import Sample, task

STOP_WITHIN_S = 3.0  # the acceptance: below 0.5 m/s within 3 s ...
STOPPED_MPS = 0.5
HOLD_FOR_S = 10.0  # ... and within 3 m for 10 s
HOLD_WITHIN_M = 3.0


def assert_stops_and_holds(rig: PX4Rig, names: list[str], since: dict[str, float], what: str) -> None:
    """Each vehicle's ground speed is below 0.5 m/s from ``since + 3 s`` on, and it stays within 3 m of
    where it was then for 10 s (vehicle seconds)."""
    end = {n: since[n] + STOP_WITHIN_S + HOLD_FOR_S for n in names}
    rig.wait_vehicle_time(names, {n: end[n] + 0.2 for n in names}, f"{HOLD_FOR_S:.0f} s of {what}")
    for name in names:
        window = rig.fixes(name, since[name] + STOP_WITHIN_S, end[name])
        assert len(window) >= 20, f"{name}: {len(window)} fixes in the window"
        fastest = max(f.speed for f in window)
        drift = max(distance_m(f.lat, f.lon, window[0].lat, window[0].lon) for f in window)
        assert fastest < STOPPED_MPS, (
            f"{name} {what}: still at {fastest:.2f} m/s {STOP_WITHIN_S:.0f}-"
            f"{STOP_WITHIN_S + HOLD_FOR_S:.0f} s after (PX4 mode {rig.observers[name].custom_mode:#x})"
        )
        assert drift < HOLD_WITHIN_M, f"{name} {what}: moved {drift:.1f} m while it should hold"


def min_separation(rig: PX4Rig, since_wall: float) -> tuple[float, int]:
    """(closest 3-D distance, sampler ticks with an airborne pair inside the collision margins) since
    ``since_wall``; the sampler reads every agent in the same tick."""
    margins = CollisionConfig()
    ticks: dict[float, dict[str, Sample]] = {}
    for name in rig.names:
        for s in rig.samples[name]:
            if s.t >= since_wall:
                ticks.setdefault(s.t, {})[name] = s
    closest, inside = math.inf, 0
    for row in ticks.values():
        airborne = [s for s in row.values() if s.alt > 1.0]
        for i, a in enumerate(airborne):
            for b in airborne[i + 1 :]:
                h, v = distance_m(a.lat, a.lon, b.lat, b.lon), abs(a.alt - b.alt)
                closest = min(closest, math.hypot(h, v))
                inside += h < margins.horizontal_margin_m and v < margins.vertical_margin_m
    return closest, inside


def cruising(rig: PX4Rig, step: int, speed: float, names: list[str] | None = None) -> None:
    rig.wait(
        lambda: all(
            (a := rig.agents[n]).queue.current_step == step and a.autopilot.telemetry().vn > speed
            for n in names or rig.names
        ),
        90.0,
        f"drones cruising north on step {step}",
    )


def hover_out(rig: PX4Rig, name: str, north: dict[str, tuple[float, float]], seconds: float = 120.0) -> str:
    """Every drone takes off and hovers at its point (a long synced hold): a fleet in the air."""
    plans: dict[str, list[object]] = {}
    for i, n in enumerate(rig.names):
        lat, lon = north[n]
        plans[n] = [
            Takeoff(step=0, alt=8.0 + 2 * i, sync=True),
            Goto(step=1, lat=lat, lon=lon, alt=8.0 + 2 * i, speed=5.0, sync=True),
            Hold(step=2, seconds=seconds, sync=True),
            Land(step=3),
        ]
    mission_id = rig.submit(task(name, plans))
    rig.wait(
        lambda: all(a.queue.current_step == 2 for a in rig.agents.values()), 120.0, "every drone hovering"
    )
    return mission_id
