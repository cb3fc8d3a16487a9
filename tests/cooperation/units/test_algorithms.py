"""Pure algorithms of the cooperation services: CPA, priorities, legs, divergence, links, energy."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from gcs.cooperation.collision import (
    CollisionAvoider,
    DroneState,
    closest_approach,
    find_conflicts,
    pair_conflicts,
)
from gcs.cooperation.config import CollisionConfig, DivergenceConfig, EnergyConfig
from gcs.cooperation.connectivity import connected_to_base, preflight_disconnections
from gcs.cooperation.divergence import DivergenceJudge, leg_error
from gcs.cooperation.divergence_monitor import DivergenceMonitor
from gcs.cooperation.emergency import BatteryEstimator, fence_violation, return_home_shortfall
from gcs.cooperation.energy import accuracy, estimate_actions, estimate_mission, leg_time
from gcs.cooperation.intents import EventIntent
from gcs.cooperation.legs import AgentPlanState, Leg
from gcs.cooperation.tracking import TrackedAgent
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action, GoBy, Goto, Land, Takeoff, Waypoint, Waypoints
from protocol.packets import Battery, FenceCircle, Geofence, Gps, Position, StatusReport
from tests.support.places import at

HOME = (47.397742, 8.545594)


def status(n: float, e: float, alt: float, step: int, **kw: object) -> StatusReport:
    lat, lon = at(n, e)
    return StatusReport(
        time=kw.pop("time", 0.0),  # type: ignore[arg-type]
        position=Position(lat=lat, lon=lon, alt_rel=alt, alt_amsl=488 + alt),
        armed=True,
        landed=False,
        step=step,
        **kw,  # type: ignore[arg-type]
    )


# --- collision ----------------------------------------------------------------------------------


def test_cpa_head_on_and_parallel() -> None:
    dp = np.array([[0.0, 50.0, 0.0], [0.0, 50.0, 0.0], [3.0, 50.0, 0.0]])
    dv = np.array([[0.0, -10.0, 0.0], [0.0, 10.0, 0.0], [0.0, -10.0, 0.0]])
    a = closest_approach(dp, dv, 4.0, 2.0, 6.0)
    assert a.conflict.tolist() == [True, False, True]  # closing, opening, 3 m lateral miss
    assert a.t_cpa[0] == pytest.approx(5.0) and a.miss_h[0] == pytest.approx(0.0)
    assert a.miss_h[2] == pytest.approx(3.0)
    # 3 m apart vertically: the cylinder (2 m vertical margin) is not entered.
    assert not closest_approach(np.array([[0.0, 50.0, 3.0]]), dv[:1], 4.0, 2.0, 6.0).conflict[0]
    # Beyond the horizon: no conflict yet.
    assert not closest_approach(dp[:1], dv[:1], 4.0, 2.0, 4.0).conflict[0]


def test_find_conflicts_matches_brute_force() -> None:
    rng = np.random.default_rng(3)
    n = 300
    pos = np.column_stack([rng.uniform(0, 400, n), rng.uniform(0, 400, n), rng.uniform(0, 6, n)])
    vel = np.column_stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), rng.uniform(-1, 1, n)])
    cfg = CollisionConfig()
    pairs, _ = find_conflicts(pos, vel, cfg)
    i, j = np.array(list(itertools.combinations(range(n), 2))).T
    brute = closest_approach(pos[j] - pos[i], vel[j] - vel[i], 4.0, 2.0, cfg.horizon_s).conflict
    assert {tuple(p) for p in pairs.tolist()} == set(zip(i[brute].tolist(), j[brute].tolist(), strict=True))
    scalar = [
        pair_conflicts((pos[b] - pos[a]).tolist(), (vel[b] - vel[a]).tolist(), 4.0, 2.0, cfg.horizon_s)
        for a, b in zip(i[:3000], j[:3000], strict=True)
    ]
    assert scalar == brute[:3000].tolist()
    assert len(pairs) > 0


def drone(ident: str, cid: int, n: float, vn: float, up: float = 10.0, **kw: object) -> DroneState:
    return DroneState(ident, cid, (n, 0.0, up), (vn, 0.0, 0.0), kw.pop("desired", (vn, 0.0, 0.0)), True)  # type: ignore[arg-type]


def test_crossing_higher_cid_holds_and_is_released_when_clear() -> None:
    avoider = CollisionAvoider(CollisionConfig(release_after_s=0.0))
    a = DroneState("a", 1, (0.0, -20.0, 10.0), (0.0, 5.0, 0.0), (0.0, 5.0, 0.0), True)
    b = DroneState("b", 2, (-20.0, 0.0, 10.0), (5.0, 0.0, 0.0), (5.0, 0.0, 0.0), True)
    decision = avoider.update([a, b], 0.0)
    assert list(decision.pause) == ["b"] and not decision.escapes  # the higher CID yields
    b_held = DroneState("b", 2, (-18.0, 0.0, 10.0), (0.0, 0.0, 0.0), (5.0, 0.0, 0.0), True)
    a_past = DroneState("a", 1, (0.0, 30.0, 10.0), (0.0, 5.0, 0.0), (0.0, 5.0, 0.0), True)
    decision = avoider.update([a_past, b_held], 1.0)
    assert decision.resume == ["b"] and not avoider.holds


def test_head_on_on_one_line_escapes_instead_of_deadlocking() -> None:
    avoider = CollisionAvoider(CollisionConfig())
    a, b = drone("a", 1, 0.0, 5.0), drone("b", 2, 30.0, -5.0)
    decision = avoider.update([a, b], 0.0)
    assert [e.ident for e in decision.escapes] == ["b"]
    assert decision.escapes[0].target_up == pytest.approx(10.0 + 2.0 + 2.0)
    assert list(decision.pause) == ["a"]  # a waits while b climbs; never both held
    # b wants to fly on down to its planned altitude: holding it (4 m above a's path) lets a pass.
    climbed = DroneState("b", 2, (30.0, 0.0, 14.0), (0.0, 0.0, 0.0), (-5.0, 0.0, -1.0), True)
    a_waiting = DroneState("a", 1, (2.0, 0.0, 10.0), (0.0, 0.0, 0.0), (5.0, 0.0, 0.0), True)
    decision = avoider.update([a_waiting, climbed], 1.0)
    assert avoider.held == {"b"} and "a" in decision.resume


def test_drone_that_cannot_yield_is_never_held() -> None:
    avoider = CollisionAvoider(CollisionConfig())
    rtl = DroneState("a", 5, (0.0, -20.0, 10.0), (0.0, 5.0, 0.0), None, False)
    b = DroneState("b", 1, (-20.0, 0.0, 10.0), (5.0, 0.0, 0.0), (5.0, 0.0, 0.0), True)
    decision = avoider.update([rtl, b], 0.0)
    assert list(decision.pause) == ["b"]  # b has the lower CID but a is returning home


def test_escape_that_cannot_be_planned_becomes_a_tracked_hold_the_partner_climbs_and_it_expires() -> None:
    """The CI trap: a drone still taking off cannot be re-planned; it was held by nobody's count.

    Its partner, hovering at a barrier 3 m away at its altitude, climbs clear instead; the held
    drone is released once the pair is clear; a hold whose escape stays impossible expires.
    """
    config = CollisionConfig(release_after_s=0.0)
    avoider = CollisionAvoider(config)
    hovering = DroneState("a", 1, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0), None, True)
    taking_off = DroneState("b", 2, (3.0, 0.0, 28.5), (0.0, 0.0, 0.0), None, True)
    decision = avoider.update([hovering, taking_off], 0.0)
    assert [e.ident for e in decision.escapes] == ["b"]
    avoider.escape_impossible(decision.escapes[0], 0.0)  # what the monitor does when no detour exists
    assert avoider.holds["b"] == {"a"}  # tracked (a waits for b to climb, as with any escape)
    decision = avoider.update([hovering, taking_off], 0.1)
    assert [e.ident for e in decision.escapes] == ["a"]  # the partner climbs, b stays held
    assert avoider.held == {"b"} and not decision.resume
    climbed = DroneState("a", 1, (0.0, 0.0, 34.0), (0.0, 0.0, 0.0), None, True)
    decision = avoider.update([climbed, taking_off], 2.0)
    assert decision.resume == ["b"] and not avoider.holds  # clear: released, nothing left behind

    # Neither can escape (the partner is returning home): the hold is bounded, then released.
    avoider = CollisionAvoider(config)
    returning = DroneState("a", 1, (0.0, 0.0, 30.0), (0.0, 0.0, 0.0), None, False)
    decision = avoider.update([returning, taking_off], 0.0)
    assert [e.ident for e in decision.escapes] == ["b"]
    avoider.escape_impossible(decision.escapes[0], 0.0)
    decision = avoider.update([returning, taking_off], 1.0)
    assert not decision.escapes and avoider.held == {"b"}
    decision = avoider.update([returning, taking_off], config.max_hold_s + 0.5)
    assert "b" in decision.resume and not decision.escapes
    assert any(kind == "collision_hold_expired" for kind, _, _ in decision.events)


# --- legs and divergence ------------------------------------------------------------------------


def test_plan_state_tracks_waypoints_and_rebuilds_the_rest() -> None:
    pts = [Waypoint(lat=p[0], lon=p[1], alt=10.0) for p in (at(20, 0), at(20, 20), at(0, 20))]
    actions = [
        Takeoff(step=0, alt=10.0, sync=True),
        Waypoints(step=1, points=pts, speed=4.0),
        GoBy(step=2, north=-5.0, east=0.0),
        Land(step=3),
    ]
    plan = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0))
    plan.update(status(0, 0, 10, 1, time=0.0))
    plan.update(status(19.5, 0.3, 10, 1, time=5.0))
    plan.update(status(20, 10, 10, 1, time=8.0))
    leg = plan.leg(None)
    assert leg is not None and leg.step == 1 and plan.waypoint == 1 and leg.speed == 4.0
    rest = plan.remaining(status(20, 10, 10, 1), completed=0)
    assert isinstance(rest[0], Waypoints) and len(rest[0].points) == 2
    assert [a.kind for a in rest] == ["waypoints", "go_by", "land"]
    detour = plan.detour(status(20, 10, 10, 1), (1.0, 2.0, 3.0), completed=0)
    assert detour is not None and detour[0].kind == "goto" and detour[0].step == 0 and not detour[0].sync
    # Sparse reports: the arrival at a corner was never sampled, the drone is 5 m down the next segment.
    sparse = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0))
    sparse.update(status(10, 0, 10, 1, time=0.0))
    sparse.update(status(20.3, 5, 10, 1, time=2.0))
    assert sparse.waypoint == 1
    # Paused: the agent reports step -1 while the action waits at the front of its queue.
    plan.update(status(20, 10, 10, -1, paused=True))
    assert plan.current_action is actions[1]
    # Waiting at the takeoff barrier: a detour re-reports step 0 with sync and keeps the rest.
    plan0 = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0))
    waiting = status(0, 0, 10, -1, waiting_sync=0, completed_step=0)
    detour0 = plan0.detour(waiting, (HOME[0], HOME[1], 12.0), completed=0)
    assert detour0 is not None and detour0[0].sync and detour0[0].step == 0 and len(detour0) == 4


def test_go_by_target_is_the_planned_one_wherever_the_step_started() -> None:
    """The agent anchors a go_by at the previous planned target (agent/executor.py): a detour or
    replan rebuilt from the daemon's estimate of the step's start (2, 3) ended metres off."""
    actions = [Takeoff(step=0, alt=10.0), GoBy(step=1, north=30.0, east=0.0), Land(step=2)]
    plan = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0))
    plan.update(status(2, 3, 10, 1))
    head = plan.remaining(status(10, 3, 10, 1), completed=0)[0]
    assert isinstance(head, Goto)
    assert (head.lat, head.lon) == pytest.approx(at(30, 0))
    leg = plan.leg(None)
    assert leg is not None and leg.target[:2] == pytest.approx(at(30, 0))


def test_leg_error_and_judge() -> None:
    start, end = at(0, 0), at(100, 0)
    leg = Leg(1, (start[0], start[1], 10.0), (end[0], end[1], 10.0), 5.0)
    err = leg_error(leg, (*at(40, 12), 10.0), 8.0)
    assert err.cross_track_m == pytest.approx(12.0, abs=0.01) and err.along_m == pytest.approx(40.0, abs=0.01)
    assert err.rejoin[:2] == pytest.approx(at(48, 0))
    judge = DivergenceJudge(DivergenceConfig(correct_m=8, replan_m=15, persist_s=0.5, cooldown_s=3))
    assert judge.judge(leg, err, 8.0, 0.0, True)[0] == "ok"  # not persisted yet
    assert judge.judge(leg, err, 8.0, 0.6, True)[0] == "correct"
    far = leg_error(leg, (*at(40, 20), 10.0), 8.0)
    assert judge.judge(leg, far, 8.0, 1.0, True)[0] == "ok"  # cool-down
    assert judge.judge(leg, far, 8.0, 3.7, True)[0] == "replan"  # persisted, cool-down over
    on_line = leg_error(leg, (*at(10, 0), 10.0), 8.0)
    assert judge.judge(leg, on_line, 20.0, 10.0, True) == (
        "lag",
        "90 m behind the planned speed 5.0 m/s on step 1",
    )


def test_no_lag_event_for_the_time_a_drone_was_paused_or_held() -> None:
    """An operator pause of 20 s on a 5 m/s leg used to read as 100 m "behind the planned speed"."""
    far = at(300, 0)
    leg = Goto(step=1, lat=far[0], lon=far[1], alt=10.0, speed=5.0)
    actions: list[Action] = [Takeoff(step=0, alt=10.0), leg]
    monitor = DivergenceMonitor(DivergenceConfig(lag_event_m=40.0), vehicle_time_scale=1.0)
    first = status(0, 0, 10, 1, time=0.0, mode="GUIDED")
    assert first.position is not None
    agent = TrackedAgent("drone-1", 1, None, first, first.position, 0.0)
    agent.plan = AgentPlanState("m", actions, (HOME[0], HOME[1], 0.0))
    agent.judge = DivergenceJudge(monitor.config)
    reports = [
        (status(0, 0, 10, 1, time=0.0, mode="GUIDED"), False),
        (status(25, 0, 10, 1, time=5.0, mode="GUIDED"), False),
        (status(26, 0, 10, -1, time=6.0, mode="BRAKE", paused=True), False),  # operator pause
        (status(26, 0, 10, 1, time=26.0, mode="GUIDED"), False),  # resumed 20 s later
        (status(36, 0, 10, 1, time=28.0, mode="BRAKE"), True),  # an operator hold of 10 s
        (status(36, 0, 10, 1, time=38.0, mode="GUIDED"), False),
        (status(56, 0, 10, 1, time=42.0, mode="GUIDED"), False),
    ]
    for report, held in reports:
        agent.seen(report, report.time)
        agent.plan.update(report)
        intents = monitor.on_status(agent, report, held, report.time)
        assert not intents, (report.time, intents)
    # Flying slowly after that is still reported: 10 s more at 1 m/s on a 5 m/s leg.
    slow = status(66, 0, 10, 1, time=52.0, mode="GUIDED")
    agent.seen(slow, slow.time)
    agent.plan.update(slow)
    (event,) = monitor.on_status(agent, slow, False, slow.time)
    assert isinstance(event, EventIntent) and event.kind == "divergence_lag"


# --- connectivity -------------------------------------------------------------------------------


def test_link_graph_multihop_and_star() -> None:
    drones = np.array([[30.0, 0.0], [60.0, 0.0], [200.0, 0.0]])
    assert connected_to_base((0.0, 0.0), drones, 40.0, True).tolist() == [True, True, False]
    assert connected_to_base((0.0, 0.0), drones, 40.0, False).tolist() == [True, False, False]


def test_preflight_finds_the_step_that_disconnects() -> None:
    far, near = at(100, 0), at(30, 0)
    plans = {
        "a": [
            Takeoff(step=0, alt=5, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=5, sync=True),
            Land(step=2),
        ],
        "b": [
            Takeoff(step=0, alt=5, sync=True),
            Goto(step=1, lat=near[0], lon=near[1], alt=5, sync=True),
            Land(step=2),
        ],
    }
    homes = {"a": (HOME[0], HOME[1], 0.0), "b": (HOME[0], HOME[1], 0.0)}
    frame = LocalFrame(*HOME)
    assert preflight_disconnections(plans, homes, frame, (0.0, 0.0), 40.0, True) == [(1, "a")]
    assert preflight_disconnections(plans, homes, frame, (0.0, 0.0), 80.0, True) == []  # b relays


# --- energy -------------------------------------------------------------------------------------


def test_plan_estimate_and_sync_waits() -> None:
    cfg = EnergyConfig()
    assert leg_time(100.0, 5.0, 2.5) == pytest.approx(22.0)
    assert leg_time(4.0, 5.0, 2.5) == pytest.approx(2 * math.sqrt(4 / 2.5))
    far, near = at(200, 0), at(20, 0)
    plans = {
        "far": [
            Takeoff(step=0, alt=10, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=10, sync=True),
            Land(step=2),
        ],
        "near": [
            Takeoff(step=0, alt=10, sync=True),
            Goto(step=1, lat=near[0], lon=near[1], alt=10, sync=True),
            Land(step=2),
        ],
    }
    homes = {k: (HOME[0], HOME[1], 0.0) for k in plans}
    est = estimate_mission(plans, homes, cfg)
    alone = sum(s.time_s for s in estimate_actions(plans["near"], homes["near"], cfg))
    assert est["near"][0] == pytest.approx(est["far"][0])  # near waits for far at the barrier
    assert est["near"][0] > alone + 30
    assert est["far"][1] == pytest.approx(10 + 200 + 10, rel=0.01)


def test_accuracy_is_one_minus_mean_relative_gap() -> None:
    assert accuracy(np.array([94.26, 105.74]), np.array([100.0, 100.0])) == pytest.approx(0.9426)


# --- emergency ----------------------------------------------------------------------------------


def test_battery_return_estimate_uses_one_clock() -> None:
    est = BatteryEstimator(window_s=20.0)
    # Flying away at 5 m/s (per wall second) and losing 0.5 %/s: 40 % left at 200 m out.
    for k in range(41):
        s = status(5.0 * k * 0.5, 0, 10, 1, time=k * 0.5, battery=Battery(pct=60.0 - 0.25 * k))
        est.add(s)
    assert est.drop_rate() == pytest.approx(0.5, rel=0.01)
    assert est.ground_speed() == pytest.approx(5.0, rel=0.05)
    verdict = return_home_shortfall(s, HOME, est, 1.5, 1.0, 10.0, 1.3)
    assert verdict is not None
    short, text = verdict
    # 100 m home at 5 m/s = 20 s, + 10 m / 1.5 m/s = 6.7 s: 26.7 s x 0.5 %/s x 1.3 + 10 % = 27 % < 50 %.
    assert not short and "needs 27%" in text
    thirsty = BatteryEstimator(window_s=20.0)  # same flight, draining 1 %/s, 40 % left at 300 m
    for k in range(41):
        s = status(200 + 2.5 * k, 0, 10, 1, time=k * 0.5, battery=Battery(pct=60.0 - 0.5 * k))
        thirsty.add(s)
    verdict = return_home_shortfall(s, HOME, thirsty, 1.5, 1.0, 10.0, 1.3)
    assert verdict is not None and verdict[0], verdict


def test_daemon_fence_check() -> None:
    fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=30.0), max_alt_m=20.0)
    gps = Gps(fix=3, satellites=10)
    assert fence_violation(status(10, 0, 10, 1, gps=gps), fence) is None
    assert "radius 30.0 m" in (fence_violation(status(40, 0, 10, 1, gps=gps), fence) or "")
    assert "ceiling" in (fence_violation(status(0, 0, 25, 1, gps=gps), fence) or "")
    assert fence_violation(status(40, 0, 10, 1), fence) is None  # no fix: the position is not trusted
