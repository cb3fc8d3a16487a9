"""What keeps PX4 drones safe when things go wrong, on both agent backends, with the daemon's collision
avoidance on: the agent's lost-link failsafe with each action, its low-battery RTL, a collision hold
that really stops a PX4 drone, and RTL-all with crossing ways home.

Times about a vehicle's motion are PX4's own (the observer's ``time_boot_ms``).
"""

from __future__ import annotations

import time

import pytest

from gcs.cooperation.config import CollisionConfig
from protocol.actions import Goto, Land, Takeoff
from protocol.geo import distance_m
from tests.px4.checks import (
    STOP_WITHIN_S,
    STOPPED_MPS,
    assert_stops_and_holds,
    cruising,
    hover_out,
    min_separation,
)
from tests.px4.rig import SPACING_M, PX4Rig
from tests.support.rig import task

pytestmark = [pytest.mark.px4, pytest.mark.slow, pytest.mark.timeout(300)]

# Read by the rig fixture. Holds, not climbs: a held drone waits until the other has passed, long
# enough to see it stop (a climb escape clears a pair in about 2 s).
COLLISION_AVOIDANCE = CollisionConfig(escape="none")
LOST_LINK_TIMEOUT_S = 2.0


def northbound(rig: PX4Rig, name: str, north: float = 80.0) -> str:
    """Every drone takes off and flies ``north`` metres north at 4 m/s, then lands there."""
    plans: dict[str, list[object]] = {}
    for i, n in enumerate(rig.names):
        far = rig.at(north, 0.0, i)
        plans[n] = [
            Takeoff(step=0, alt=8.0 + 2 * i, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=8.0 + 2 * i, speed=4.0, sync=True),
            Land(step=2, lat=far[0], lon=far[1]),
        ]
    return rig.submit(task(name, plans))


@pytest.mark.parametrize("action", ["rtl", "land", "hold"])
def test_lost_daemon_link_mid_leg(rig: PX4Rig, action: str) -> None:
    """The daemon link is cut (connections reset, new ones refused) while every drone flies a leg: after
    the lost-link timeout each agent applies its action. rtl: home; land: down short of the leg's end;
    hold: below 0.5 m/s within 3 s, within 3 m for 10 s."""
    rig.set_settings(lost_link_timeout_s=LOST_LINK_TIMEOUT_S, lost_link_action=action)
    assert rig.proxy is not None
    proxy = rig.proxy
    try:
        northbound(rig, f"lost-link-{action}")
        cruising(rig, 1, 3.0)
        rig.run(lambda: proxy.partition(120.0, "reset"))
        rig.wait(
            lambda: all(a.monitor.failsafe is not None for a in rig.agents.values()),
            LOST_LINK_TIMEOUT_S + 10.0,
            "every agent's lost-link failsafe",
        )
        fired = {n: rig.vehicle_now(n) for n in rig.names}
        if action == "hold":
            assert_stops_and_holds(rig, rig.names, fired, "after the lost-link hold")
        else:
            rig.wait(rig.all_landed, 150.0, f"every drone landed by its lost-link {action}")
            for i, name in enumerate(rig.names):
                t = rig.agents[name].autopilot.telemetry()
                from_home = distance_m(t.lat, t.lon, *rig.at(0.0, 0.0, i))
                from_end = distance_m(t.lat, t.lon, *rig.at(80.0, 0.0, i))
                if action == "rtl":
                    assert from_home < 3.0, f"{name} landed {from_home:.1f} m from home"
                else:
                    assert from_home > 10.0 and from_end > 10.0, f"{name} landed {from_home:.1f} m from home"
    finally:
        rig.run(proxy.heal)
        rig.set_settings(lost_link_timeout_s=15.0, lost_link_action="continue")
        rig.wait(lambda: all(rig.d.agents.session(n) is not None for n in rig.names), 30.0, "agents back")


def test_low_battery_sends_that_drone_home(rig: PX4Rig) -> None:
    """drone-2's battery reads below its agent's low threshold mid-leg: the agent's own RTL brings it
    home while the others finish."""
    agent = rig.agents["drone-2"]
    mission_id = northbound(rig, "low-battery")
    try:
        cruising(rig, 1, 3.0)
        rig.run(lambda: setattr(agent.settings, "battery_low_pct", 100.0))
        rig.wait(lambda: agent.monitor.failsafe is not None, 10.0, "drone-2's battery failsafe")
        assert agent.monitor.failsafe is not None and agent.monitor.failsafe.name == "battery_low"
        rig.wait(lambda: (t := agent.autopilot.telemetry()).landed and not t.armed, 150.0, "drone-2 home")
    finally:
        rig.run(lambda: setattr(agent.settings, "battery_low_pct", 25.0))
    t = agent.autopilot.telemetry()
    assert distance_m(t.lat, t.lon, *rig.at(0.0, 0.0, 1)) < 3.0, "drone-2 did not return home"
    rig.finish(mission_id, 150.0)
    for i in (0, 2):
        t = rig.agents[rig.names[i]].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *rig.at(80.0, 0.0, i)) < 3.0, f"{rig.names[i]} did not finish"


def test_collision_hold_stops_a_px4_drone(rig: PX4Rig) -> None:
    """drone-1 and drone-2 cross at one altitude and one time (drone-1 west to east, drone-2 south to
    north): the daemon holds one of them until the other has passed, and a held PX4 drone is below
    0.5 m/s within 3 s and stays so while held; the mission still completes."""
    cross_n, cross_e = 30.0, SPACING_M / 2  # from drone-1's origin; drone-2's is SPACING_M east

    def leg(index: int, north: float, east: float) -> tuple[float, float]:
        return rig.at(cross_n + north, cross_e + east - SPACING_M * index, index)

    plans: dict[str, list[object]] = {}
    for index, (a, b) in enumerate((((0.0, -25.0), (0.0, 25.0)), ((-25.0, 0.0), (25.0, 0.0)))):
        start, end = leg(index, *a), leg(index, *b)
        plans[rig.names[index]] = [
            Takeoff(step=0, alt=10.0, sync=True),
            Goto(step=1, lat=start[0], lon=start[1], alt=10.0, speed=5.0, sync=True),
            Goto(step=2, lat=end[0], lon=end[1], alt=10.0, speed=5.0, sync=True),
            Land(step=3),
        ]
    mission_id = rig.submit(task("crossing", plans))
    pair = ["drone-1", "drone-2"]
    holds: dict[str, list[list[float]]] = {n: [] for n in pair}  # [start, end] in vehicle seconds
    deadline = time.monotonic() + 200.0
    while time.monotonic() < deadline and rig.run(lambda: mission_id in rig.d.missions.active):
        for name in pair:
            held = rig.run(lambda n=name: rig.d.authority.is_held(n, "collision"))  # type: ignore[misc]
            now = rig.vehicle_now(name)
            open_ = holds[name] and holds[name][-1][1] < 0
            if held and not open_:
                holds[name].append([now, -1.0])
            elif not held and open_:
                holds[name][-1][1] = now
        time.sleep(0.1)
    for name in pair:
        if holds[name] and holds[name][-1][1] < 0:
            holds[name][-1][1] = rig.vehicle_now(name)
    progress = rig.finish(mission_id, 60.0)
    assert progress.state == "completed", progress
    long_holds = [(n, s, e) for n in pair for s, e in holds[n] if e - s >= STOP_WITHIN_S + 1.0]
    assert long_holds, f"no collision hold of {STOP_WITHIN_S + 1.0:.0f} s or more: {holds}"
    for name, held_from, held_until in long_holds:
        window = rig.fixes(name, held_from + STOP_WITHIN_S, held_until)
        fastest = max(f.speed for f in window)
        assert fastest < STOPPED_MPS, f"{name} held by collision avoidance at {fastest:.2f} m/s"


def test_rtl_all_with_crossing_ways_home_keeps_them_apart(rig: PX4Rig) -> None:
    """Drones hover over each other's way home; RTL-all: distinct return layers (RTL_RETURN_ALT read
    back from PX4), nobody inside the collision margins, everyone lands at its own home."""
    points = {
        n: rig.at(25.0, -SPACING_M * (i - 1) * 2, i) for i, n in enumerate(rig.names)
    }  # 1 and 3 swap sides
    hover_out(rig, "rtl-all", points)
    since = time.monotonic()
    before = len(rig.events("return_planned"))
    delivered, aborted = rig.call(rig.d.operator.bring_down("rtl", None, "test rtl-all"))
    assert sorted(delivered) == sorted(rig.names) and aborted
    rig.wait(rig.all_landed, 150.0, "every drone landed after RTL-all")
    layers = {e.agent: float(e.data["alt"]) for e in rig.events("return_planned")[before:]}
    assert len(set(layers.values())) == len(rig.names), layers
    for i, name in enumerate(rig.names):
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *rig.at(0.0, 0.0, i)) < 3.0, f"{name} not home"
        assert rig.param(name, "RTL_RETURN_ALT") == pytest.approx(layers[name], abs=0.1)
    closest, inside = min_separation(rig, since)
    assert inside == 0, f"closest {closest:.2f} m"
