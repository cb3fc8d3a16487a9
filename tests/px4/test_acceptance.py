"""Issue 23's acceptance on real PX4, on both agent backends, in one flight (60-71 s wall with PX4 at
1.7-1.9x), ready for CI: a mission pause stops PX4 drones (below 0.5 m/s within 3 s, within 3 m for
10 s), a collision hold stops one, and RTL-all brings the crossing pair home in distinct layers,
never inside the margins.

One flight, not three: every take-off and landing costs PX4 time the CI budget does not have. It flies
first in the package (module order), while every drone stands at the home its agent joined with: the
daemon's RTL-all program flies each drone to that home, and later flights land drones elsewhere.
drone-3 stays on the ground, out of the pair's way (in the air it drew collision holds of its own).
Times about a vehicle's motion are PX4's own (the observer's ``time_boot_ms``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

from protocol.actions import Goto, Hold, Land, Takeoff
from protocol.geo import distance_m
from tests.px4.checks import (
    STOP_WITHIN_S,
    STOPPED_MPS,
    assert_stops_and_holds,
    cruising,
    hold_verdict,
    min_separation,
    trace,
)
from tests.px4.rig import SPACING_M, PX4Rig
from tests.support.rig import task

pytestmark = [pytest.mark.px4, pytest.mark.slow, pytest.mark.timeout(300)]

PAIR = ["drone-1", "drone-2"]
APPROACH_SPEED = 3.0  # the paused leg: as the synchronized flight's, whose pause passed every time
CROSSING_SPEED = 3.5  # slow enough that the passing drone keeps the other held for several seconds
CROSS_N, CROSS_E = 50.0, SPACING_M / 2  # the crossing point from drone-1's origin: both approach legs
# run north, long enough (54 m and 25 m) for the pair to cruise before the pause and after it
# The daemon predicts a conflict when the closest approach is under horizontal_margin_m (4 m). Under
# load the pair leaves the barrier up to about 2 s apart (PX4's clock, each drone's arrival within the
# acceptance radius), which at 3.5 m/s on crossing legs is a 5-6 m miss: measured once, no hold. 7 m
# makes the conflict certain for the hold this test is about (the detector's thresholds are pinned by
# tests/cooperation without an autopilot); the RTL-all check below still uses the default margins.
CROSSING_MARGIN_M = 7.0


class Stages:
    """Wall and PX4 seconds per stage of the flight, printed as it goes (where the CI minutes go)."""

    def __init__(self, rig: PX4Rig) -> None:
        self.rig = rig
        self.wall, self.vehicle = time.monotonic(), rig.vehicle_now(PAIR[0])

    def mark(self, what: str) -> None:
        wall, vehicle = time.monotonic(), self.rig.vehicle_now(PAIR[0])
        print(f"stage {what}: {wall - self.wall:.1f} s wall, {vehicle - self.vehicle:.1f} s of PX4 time")
        self.wall, self.vehicle = wall, vehicle


def crossing_plans(rig: PX4Rig) -> dict[str, list[object]]:
    """drone-1 flies north-west to its start, then west to east; drone-2 north to its start, then
    south to north: they cross at one point, altitude and time, then hover where their ways home cross
    (drone-1 58 m north-east of its home, drone-2 75 m north of drone-1's, 5 m east)."""
    # Every point from drone-1's origin: drone-2's need not be SPACING_M east of it (an earlier run of
    # the package may have landed it elsewhere, where PX4 then took its home).

    def leg(north: float, east: float) -> tuple[float, float]:
        return rig.at(CROSS_N + north, CROSS_E + east, 0)

    plans: dict[str, list[object]] = {}
    for name, (a, b) in zip(PAIR, (((0.0, -25.0), (0.0, 25.0)), ((-25.0, 0.0), (25.0, 0.0))), strict=True):
        start, end = leg(*a), leg(*b)
        plans[name] = [
            Takeoff(step=0, alt=10.0, sync=True),
            Goto(step=1, lat=start[0], lon=start[1], alt=10.0, speed=APPROACH_SPEED, sync=True),
            Goto(step=2, lat=end[0], lon=end[1], alt=10.0, speed=CROSSING_SPEED, sync=True),
            Hold(step=3, seconds=120.0, sync=True),
            Land(step=4),
        ]
    return plans


def watch_collision_holds(
    rig: PX4Rig, pair: list[str], until: Callable[[], bool]
) -> dict[str, list[list[float]]]:
    """[start, end] (PX4 seconds) of every collision hold of ``pair`` until ``until()`` (bounded).

    Polled every 0.1 s, and under load each poll takes longer: PX4's clock is read after a poll that
    first sees a hold (it began no later) and before each poll that still sees it (it lasted at least
    until then). So the interval lies inside the real hold, and a drone that the release already set
    moving is not counted as held (read after each poll, a 9.1 s hold once measured 0.75 m/s: its end
    could take in the departure)."""
    holds: dict[str, list[list[float]]] = {n: [] for n in pair}
    open_: dict[str, bool] = dict.fromkeys(pair, False)
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline and not rig.run(until):
        for name in pair:
            before = rig.vehicle_now(name)
            held = rig.run(lambda n=name: rig.d.authority.is_held(n, "collision"))  # type: ignore[misc]
            if held and not open_[name]:
                after = rig.vehicle_now(name)
                holds[name].append([after, after])
            elif held:
                holds[name][-1][1] = before
            open_[name] = held
        time.sleep(0.1)
    return holds


def watch_return(
    rig: PX4Rig, pair: list[str], until: Callable[[], bool], timeout: float
) -> dict[str, dict[int, float]]:
    """Wait for ``until()`` (bounded) and return, per drone, the PX4 seconds from now to the first
    poll that saw it on each step of its return program (where the RTL-all minutes go)."""
    start = {n: rig.vehicle_now(n) for n in pair}
    reached: dict[str, dict[int, float]] = {n: {} for n in pair}
    deadline = time.monotonic() + timeout
    while not rig.run(until):
        assert time.monotonic() < deadline, f"timed out after {timeout:.0f} s waiting for every drone landed"
        for name in pair:
            step = rig.run(lambda n=name: rig.agents[n].queue.current_step)  # type: ignore[misc]
            if step >= 0 and step not in reached[name]:
                reached[name][step] = round(rig.vehicle_now(name) - start[name], 1)
        time.sleep(0.1)
    return reached


# In CI (issue 23's acceptance): since the second pause and the rig's settings of session 6 it passed
# 9 of 9 runs on both backends (docs/testing.md, 'PX4 SITL'); like every flight, it has one rerun.
def test_pause_and_collision_hold_stop_px4_drones_then_rtl_all_keeps_them_apart(rig: PX4Rig) -> None:
    """drone-1 and drone-2 take off, fly north to the starts of two crossing legs at 3 m/s and are
    paused on the way: each is below 0.5 m/s (over 2 s of PX4 time) from 3 s after the pause and stays
    within 3 m for 10 s. Resumed, they cross at one altitude and one time with the daemon's collision
    avoidance on (holds only): the held PX4 drone is below 0.5 m/s from 3 s into every hold longer than
    4 s until its release. Then, from where the crossing left them (ways home crossing), RTL-all:
    distinct return layers, each flown, nobody inside the collision margins, both land at home."""
    stages = Stages(rig)
    # Collision avoidance is off for the take-off and the pause: the pause is the mission's alone, and
    # with the crossing's wider margin two drones climbing 10 m apart drew a hold at take-off once.
    mission_id = rig.submit(task("pause-crossing", crossing_plans(rig)))
    cruising(rig, 1, APPROACH_SPEED - 1.0, PAIR)  # PX4 flies a 3 m/s leg at 2.5-2.65 m/s
    stages.mark("take-off, cruising")
    paused_at = {n: rig.vehicle_now(n) for n in PAIR}
    rig.call(rig.d.missions.pause(mission_id, "test pause"))
    assert_stops_and_holds(rig, PAIR, paused_at, "after the mission pause")
    stages.mark("pause")
    with rig.collision_avoidance(horizontal_margin_m=CROSSING_MARGIN_M):
        rig.call(rig.d.missions.resume(mission_id, "test resume"))  # diverging legs, 12 m apart
        crossed_since = time.monotonic()
        holds = watch_collision_holds(
            rig, PAIR, lambda: all(rig.agents[n].queue.current_step == 3 for n in PAIR)
        )
        stages.mark("to the starts, crossing")
        long_holds = [(n, s, e) for n in PAIR for s, e in holds[n] if e - s >= STOP_WITHIN_S + 1.0]
        events = [e.message for e in rig.run(lambda: rig.d.events.history()) if "collision" in e.kind]
        print(f"crossing: closest pair {min_separation(rig, crossed_since)}, holds {holds}, events {events}")
        assert long_holds, f"no collision hold of {STOP_WITHIN_S + 1.0:.0f} s or more: {holds}, {events}"
        for name, held_from, held_until in long_holds:
            window = rig.fixes(name, held_from + STOP_WITHIN_S, held_until)
            fastest, _ = hold_verdict(window)
            print(f"{name} collision hold {held_until - held_from:.1f} s: speed max {fastest:.2f} m/s")
            if fastest >= STOPPED_MPS:
                print(f"{name} collision hold from 3 s on, each 0.5 s: {trace(window)}")
            assert fastest < STOPPED_MPS, f"{name} held by collision avoidance at {fastest:.2f} m/s"
    with rig.collision_avoidance():  # RTL-all with the daemon's default margins
        since = time.monotonic()
        before = len(rig.events("return_planned"))
        delivered, aborted = rig.call(rig.d.operator.bring_down("rtl", None, "test rtl-all"))
        assert set(PAIR) <= set(delivered) and mission_id in aborted, (delivered, aborted)
        reached = watch_return(rig, PAIR, rig.all_landed, 150.0)
        stages.mark("RTL-all, landed")
        print(f"RTL-all, PX4 s from its order to each program step (0 layer, 1 home, 2 land): {reached}")
    layers = {e.agent: float(e.data["alt"]) for e in rig.events("return_planned")[before:]}
    assert set(PAIR) <= set(layers) and len({layers[n] for n in PAIR}) == len(PAIR), layers
    for i, name in enumerate(PAIR):
        t = rig.agents[name].autopilot.telemetry()
        assert distance_m(t.lat, t.lon, *rig.at(0.0, 0.0, i)) < 3.0, f"{name} not home"
        # Several drones return by the daemon's program (climb to the layer, home in it, wait, land),
        # flown as repositions: the layer shows in the altitudes flown on the way, not RTL_RETURN_ALT.
        way = [
            x for x in rig.samples[name] if x.t > since and distance_m(x.lat, x.lon, *rig.at(0, 0, i)) > 8.0
        ]
        assert way, f"{name}: no samples on the way home"
        top = max(x.alt for x in way)
        assert abs(top - layers[name]) < 2.0, f"{name} returned at {top:.1f} m, its layer {layers[name]} m"
    closest, inside = min_separation(rig, since)
    assert inside == 0, f"closest {closest:.2f} m"
