"""The agent bounds where its orders take the vehicle, not each order alone (agent/limits.py).

Issue 30: 20 ``go_by`` legs of 9,999 m (a 200 km target) and 3 climbs of 499 m (1.5 km above
home) each passed the per-order checks. The pure decision is tested here on its own, then
end to end: a daemon's task of such legs over real loopback TCP to an agent on the in-memory
autopilot, refused at the first leg that would cross, and the refusal recorded by the daemon.
"""

from __future__ import annotations

from pathlib import Path

from agent.config import SanityLimits
from agent.limits import Place, first_crossing, project, queue_refusal
from protocol.actions import (
    Action,
    GoBy,
    Goto,
    Hold,
    Land,
    ReturnToLaunch,
    SetSpeed,
    Takeoff,
    Waypoint,
    Waypoints,
)
from protocol.geo import distance_m, offset_latlon
from protocol.packets import Capabilities, FenceCircle, Geofence, PerformActions
from protocol.taskfile import AgentPlan, TaskFile
from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent
from tests.support.polling import wait_for

HOME_LL = (HOME[0], HOME[1])
ON_THE_GROUND = Place(HOME[0], HOME[1], 0.0)
LIMITS = SanityLimits()  # the defaults: 10 km from home, 500 m above it


def split_program(legs: int = 20, speed: float | None = None) -> list[Action]:
    """Takeoff, then ``legs`` go_by legs of 9,999 m north: each alone within 10 km."""
    actions: list[Action] = [Takeoff(step=0, alt=10.0)]
    actions += [GoBy(step=i, north=9_999.0, east=0.0, speed=speed) for i in range(1, legs + 1)]
    return actions


def test_the_split_200_km_program_is_refused_at_the_first_leg_that_crosses() -> None:
    refusal = first_crossing(split_program(), ON_THE_GROUND, LIMITS, HOME_LL)
    assert refusal is not None
    # Leg 1 ends 9,999 m out (within 10 km); leg 2 would end 20 km out.
    assert (refusal.index, refusal.step, refusal.kind) == (2, 2, "go_by")
    assert "20.0 km from home" in refusal.reason and "max_distance_from_home_m 10000" in refusal.reason
    assert first_crossing(split_program()[:2], ON_THE_GROUND, LIMITS, HOME_LL) is None


def test_three_climbs_of_499_m_are_refused_at_the_climb_that_crosses() -> None:
    climbs: list[Action] = [Takeoff(step=0, alt=1.0)]
    climbs += [GoBy(step=i, north=0.0, east=0.0, up=499.0) for i in (1, 2, 3)]  # 500 m, then 999 m
    refusal = first_crossing(climbs, ON_THE_GROUND, LIMITS, HOME_LL)
    assert refusal is not None and (refusal.index, refusal.step) == (2, 2)
    assert "999 m above home" in refusal.reason and "max_alt_m 500" in refusal.reason
    # Descents are bounded too, and an absolute target is measured from home, not from the legs.
    down = first_crossing([GoBy(step=0, north=0.0, east=0.0, up=-600.0)], ON_THE_GROUND, LIMITS, HOME_LL)
    assert down is not None and "min_alt_m" in down.reason
    high = Waypoints(step=0, points=[Waypoint(lat=HOME[0], lon=HOME[1], alt=20.0)] * 2)
    assert first_crossing([high], Place(HOME[0], HOME[1], 499.0), LIMITS, HOME_LL) is None


def test_a_geofence_is_crossed_where_the_orders_lead_out_of_it() -> None:
    fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=300.0), max_alt_m=60.0)
    inside = offset_latlon(HOME[0], HOME[1], 200.0, 0.0)
    orders: list[Action] = [
        Takeoff(step=0, alt=20.0),
        Goto(step=1, lat=inside[0], lon=inside[1], alt=20.0),
        GoBy(step=2, north=-150.0, east=0.0),  # 50 m north of home: still inside
        GoBy(step=3, north=0.0, east=290.0),  # about 294 m out: inside
        GoBy(step=4, north=0.0, east=100.0),  # about 392 m out: outside
        Land(step=5),
    ]
    refusal = first_crossing(orders, ON_THE_GROUND, LIMITS, HOME_LL, fence)
    assert refusal is not None and refusal.index == 4
    assert "outside the geofence" in refusal.reason and "radius 300.0 m" in refusal.reason
    flown_out = SanityLimits(check_geofence=False)  # the fence enforced in flight only
    assert first_crossing(orders, ON_THE_GROUND, flown_out, HOME_LL, fence) is None
    climb = first_crossing([Takeoff(step=0, alt=80.0)], ON_THE_GROUND, LIMITS, HOME_LL, fence)
    assert climb is not None and "ceiling 60.0 m" in climb.reason
    # A waypoint leg is checked point by point.
    out = offset_latlon(HOME[0], HOME[1], 0.0, 400.0)
    leg = Waypoints(
        step=0,
        points=[Waypoint(lat=inside[0], lon=inside[1], alt=20.0), Waypoint(lat=out[0], lon=out[1], alt=20.0)],
    )
    refused = first_crossing([leg], Place(HOME[0], HOME[1], 20.0), LIMITS, HOME_LL, fence)
    assert refused is not None and "point 2" in refused.reason
    # Orders that end a flight are not refused for where they go, even from outside the fence.
    outside = Place(out[0], out[1], 20.0)
    assert first_crossing([Land(step=0)], outside, LIMITS, HOME_LL, fence) is None
    assert first_crossing([ReturnToLaunch(step=0)], outside, LIMITS, HOME_LL, fence) is None
    high_rtl = first_crossing([ReturnToLaunch(step=0, alt=80.0)], outside, LIMITS, HOME_LL, fence)
    assert high_rtl is not None and "return altitude" in high_rtl.reason


def test_an_ordinary_survey_is_accepted() -> None:
    rows = []
    for row in range(8):  # a 400 m x 350 m lawnmower, 50 m lanes, 40 m up
        north = 50.0 * row
        for east in (0.0, 350.0) if row % 2 == 0 else (350.0, 0.0):
            lat, lon = offset_latlon(HOME[0], HOME[1], north, east)
            rows.append(Waypoint(lat=lat, lon=lon, alt=40.0))
    survey: list[Action] = [
        Takeoff(step=0, alt=40.0, sync=True),
        SetSpeed(step=1, speed=8.0),
        Waypoints(step=2, points=rows, sync=True),
        Hold(step=3, seconds=5.0),
        GoBy(step=4, north=-100.0, east=-50.0, up=-10.0),
        ReturnToLaunch(step=5, alt=30.0),
    ]
    fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=1000.0), max_alt_m=120.0)
    assert first_crossing(survey, ON_THE_GROUND, LIMITS, HOME_LL, fence) is None
    end = project(survey[:5], ON_THE_GROUND, HOME_LL)
    assert end.alt == 30.0 and end.lat is not None and end.lon is not None
    assert 250.0 < distance_m(HOME[0], HOME[1], end.lat, end.lon) < 350.0


def test_an_appended_batch_starts_where_the_queue_ends_and_other_limits_still_hold() -> None:
    queued = split_program(legs=1)
    start = project(queued, ON_THE_GROUND, HOME_LL)  # 9,999 m out after what is queued
    refusal = first_crossing([GoBy(step=2, north=9_999.0, east=0.0)], start, LIMITS, HOME_LL)
    assert refusal is not None and refusal.index == 0
    # Without a home yet, distances are unchecked, altitudes are.
    nowhere = Place(None, None, 0.0)
    assert first_crossing(split_program(), nowhere, LIMITS, None) is None
    assert first_crossing([GoBy(step=0, north=0.0, east=0.0, up=501.0)], nowhere, LIMITS, None) is not None
    long_hold = first_crossing([Hold(step=0, seconds=5000.0)], ON_THE_GROUND, LIMITS, HOME_LL)
    assert long_hold is not None and "hold of 5000 s" in long_hold.reason
    full = queue_refusal(10, 19_995, LIMITS)
    assert full is not None and full.index is None and "max_queue_actions" in full.reason
    assert queue_refusal(5, 19_995, LIMITS) is None


async def test_a_daemon_task_of_split_legs_is_refused_at_the_first_crossing_leg(tmp_path: Path) -> None:
    """End to end: the daemon's task flies takeoff and leg 1, leg 2 is refused, the daemon records why."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        # A vehicle with the battery for it: the daemon's own energy check lets the task through,
        # as a faulty or hostile daemon would; only the agent's limits stand in the way.
        big = Capabilities(max_speed_mps=100.0, endurance_s=172_800.0, battery_wh=100_000.0)
        running = start_agent("roamer", daemon.listen_port, key, speedup=40.0, capabilities=big)
        try:
            await wait_for(lambda: (s := daemon.agents.session("roamer")) and s.status, 10, "joined")
            actions = [*split_program(speed=100.0), ReturnToLaunch(step=21)]
            plan = AgentPlan(agent="roamer", actions=actions)
            task = TaskFile(name="split", plans=[plan], on_action_failed="end")
            mission_id = await daemon.missions.submit(task)
            farthest = 0.0

            def refused() -> bool:
                nonlocal farthest
                t = running.autopilot.telemetry()
                farthest = max(farthest, distance_m(HOME[0], HOME[1], t.lat, t.lon))
                return bool(daemon.events.history(kind="action_failed", agent="roamer"))

            await wait_for(refused, 30, "the refusal reported as the failure of a step")
            failed = daemon.events.history(kind="action_failed", agent="roamer")[0]
            assert failed.data is not None and failed.data["step"] == 2, failed
            assert "refused by the agent" in failed.data["reason"]
            assert "max_distance_from_home_m" in failed.data["reason"]
            exceptions = [e.message for e in daemon.events.history(kind="agent_exception", agent="roamer")]
            assert any(
                "command_refused" in m and "20.0 km from home" in m and "from step 2 on" in m
                for m in exceptions
            ), exceptions
            # Leg 1 was flown (9,999 m north), nothing beyond it; the task's policy (end) then
            # brings the vehicle home.
            assert 9_000.0 < farthest <= 10_000.0, farthest
            await wait_for(
                lambda: mission_id not in daemon.missions.active, 10, "mission ended by its policy"
            )
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "aborted", progress
            assert progress.result is not None and "refused by the agent" in progress.result
        finally:
            await running.kill()


async def test_an_action_is_checked_again_from_the_actual_position_before_it_starts(tmp_path: Path) -> None:
    """Accepted from home, a go_by is refused when it starts from where the vehicle really is.

    The go_by starts a new batch, so it has no planned point before it (agent/executor.py
    ``anchor``): it is taken from the vehicle's position. (In a plan, a go_by is taken from the
    previous action's target and its end does not move with the vehicle.)
    """
    key = new_key()
    limits = SanityLimits(max_distance_from_home_m=1000.0)
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("drifter", daemon.listen_port, key, speedup=1.0, limits=limits)
        try:
            await wait_for(lambda: (s := daemon.agents.session("drifter")) and s.status, 10, "joined")
            take_off: list[Action] = [Takeoff(step=0, alt=5.0)]
            daemon.agents.post(
                "drifter", PerformActions(mission_id="drift", mode="replace", actions=take_off)
            )
            queue = running.agent.queue
            await wait_for(lambda: queue.completed_step == 0, 20, "airborne")
            plan: list[Action] = [
                Hold(step=1, seconds=3.0),
                GoBy(step=2, north=600.0, east=0.0),  # 600 m from home, as planned: accepted
                Land(step=3),
            ]
            daemon.agents.post("drifter", PerformActions(mission_id="drift", mode="replace", actions=plan))
            await wait_for(lambda: queue.current_step == 1, 20, "holding")
            assert queue.depth == 2  # the go_by and the land: nothing was refused
            t = running.autopilot.telemetry()  # carried 500 m north (a gust, a bad fix) during the hold
            t.lat, t.lon = offset_latlon(HOME[0], HOME[1], 500.0, 0.0)

            def refused() -> bool:
                s = daemon.agents.session("drifter")
                return bool(s and s.status and s.status.failure and s.status.failure.step == 2)

            await wait_for(refused, 20, "the go_by refused as it starts")
            session = daemon.agents.session("drifter")
            assert session is not None and session.status is not None and session.status.failure is not None
            reason = session.status.failure.reason
            assert "refused by the agent" in reason and "max_distance_from_home_m 1000" in reason, reason
            assert queue.depth == 0 and running.autopilot.telemetry().armed  # holding in the air
            now = running.autopilot.telemetry()
            assert distance_m(HOME[0], HOME[1], now.lat, now.lon) < 1000.0
        finally:
            await running.kill()
