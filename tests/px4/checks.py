"""Assertions about what a PX4 vehicle did, read from the independent observer in PX4's own clock."""

from __future__ import annotations

import math
import time

from gcs.cooperation.config import CollisionConfig
from protocol.geo import distance_m
from tests.px4.observer import Fix
from tests.px4.rig import PX4Rig
from tests.support.rig import Sample

STOP_WITHIN_S = 3.0  # the acceptance: below 0.5 m/s within 3 s ...
STOPPED_MPS = 0.5
HOLD_FOR_S = 10.0  # ... and within 3 m for 10 s
HOLD_WITHIN_M = 3.0
# Ground speed over 2 s of vehicle time: a held SIH drone's position wanders 0.2-0.45 m per second at
# rest (the same at 1x, so SIH's own noise; once 0.52 m in one second, failing a 1 s check with no fly
# back and no creep), while a drone that creeps or flies back keeps its speed over 2 s as over 1 s.
SPEED_WINDOW_S = 2.0


def ground_speeds(fixes: list[Fix], window_s: float = SPEED_WINDOW_S) -> list[float]:
    """Ground speed as horizontal displacement over each ``window_s`` of vehicle time (from every fix
    to the first one at least ``window_s`` later). GLOBAL_POSITION_INT's own velocity is the EKF's
    instant estimate: a hovering SIH quadcopter reads up to 0.7 m/s in it while it stays within
    centimetres; a drone that flies on covers its speed in metres every second, and fails this."""
    out: list[float] = []
    j = 0
    for i, a in enumerate(fixes):
        j = max(j, i + 1)
        while j < len(fixes) and fixes[j].t - a.t < window_s:
            j += 1
        if j == len(fixes):
            break
        b = fixes[j]
        out.append(distance_m(a.lat, a.lon, b.lat, b.lon) / (b.t - a.t))
    return out


def hold_verdict(fixes: list[Fix]) -> tuple[float, float]:
    """(fastest ground speed over SPEED_WINDOW_S, largest distance from the first fix) over ``fixes``."""
    span = fixes[-1].t - fixes[0].t if fixes else 0.0
    speeds = ground_speeds(fixes, min(SPEED_WINDOW_S, max(1.0, span)))  # a short hold: its whole span
    drift = max(distance_m(f.lat, f.lon, fixes[0].lat, fixes[0].lon) for f in fixes)
    return (max(speeds) if speeds else math.inf), drift


def trace(fixes: list[Fix], step_s: float = 0.5) -> str:
    """t, north/east offset (m) from the first fix, EKF speed, every ``step_s`` (failure diagnosis)."""
    out, next_t = [], -math.inf
    for f in fixes:
        if f.t >= next_t:
            north = distance_m(fixes[0].lat, f.lon, f.lat, f.lon) * (1 if f.lat >= fixes[0].lat else -1)
            east = distance_m(f.lat, fixes[0].lon, f.lat, f.lon) * (1 if f.lon >= fixes[0].lon else -1)
            out.append(f"{f.t - fixes[0].t:.1f}:{north:+.2f}/{east:+.2f}@{f.speed:.2f}")
            next_t = f.t + step_s
    return " ".join(out)


def assert_stops_and_holds(rig: PX4Rig, names: list[str], since: dict[str, float], what: str) -> None:
    """Each vehicle's ground speed (over 2 s of vehicle time) is below 0.5 m/s from ``since + 3 s`` on,
    and it stays within 3 m of where it was then for 10 s (vehicle seconds)."""
    end = {n: since[n] + STOP_WITHIN_S + HOLD_FOR_S for n in names}
    rig.wait_vehicle_time(names, {n: end[n] + 0.2 for n in names}, f"{HOLD_FOR_S:.0f} s of {what}")
    for name in names:
        window = rig.fixes(name, since[name] + STOP_WITHIN_S, end[name])
        assert len(window) >= 20, f"{name}: {len(window)} fixes in the window"
        fastest, drift = hold_verdict(window)
        print(
            f"{name} {what}: {SPEED_WINDOW_S:.0f} s speed max {fastest:.2f} m/s (EKF velocity max "
            f"{max(f.speed for f in window):.2f}), drift {drift:.2f} m, PX4 at {rig.vehicle_rate(name):.1f}x"
        )
        if fastest >= STOPPED_MPS or drift >= HOLD_WITHIN_M:
            print(f"{name} {what}, each 0.5 s: " + trace(window))
            recent = [x for x in rig.samples[name] if x.t > time.monotonic() - 30.0]
            changes = [
                x
                for k, x in enumerate(recent)
                if k == 0 or (x.step, x.mode) != (recent[k - 1].step, recent[k - 1].mode)
            ]
            t0 = time.monotonic()
            print(
                f"{name} step/mode changes (wall s ago): "
                + ", ".join(f"{t0 - x.t:.1f}:{x.step}/{x.mode}" for x in changes)
            )
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
    """Every named drone on ``step`` at a ground speed above ``speed`` (bounded). Ground speed, not
    northward: a leg at 3 m/s peaks at 2.5-2.65 m/s on PX4, and on a leg 22 degrees off north the
    northward part never passed 2.5 m/s (a 90 s time-out)."""

    def moving(name: str) -> bool:
        agent = rig.agents[name]
        t = agent.autopilot.telemetry()
        return agent.queue.current_step == step and math.hypot(t.vn, t.ve) > speed

    rig.wait(lambda: all(moving(n) for n in names or rig.names), 90.0, f"drones cruising on step {step}")
