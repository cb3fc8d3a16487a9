"""The vehicle authority, deconflicted returns, event throttle and bounded holds, as pure units."""

from __future__ import annotations

import math

import numpy as np

from gcs.cooperation.collision import CollisionAvoider, DroneState
from gcs.cooperation.config import CollisionConfig
from gcs.cooperation.event_throttle import EventThrottle
from gcs.cooperation.returns import (
    Airborne,
    Returner,
    assign_layers,
    cleared_to_descend,
    segment_distance,
    spread_landing_spots,
)
from protocol.actions import Land, ReturnToLaunch
from tests.support.authority import authority, status


def test_a_command_refused_where_the_drone_is_linked_is_taken_back_here() -> None:
    """Cluster: the holder's authority refused what ours forwarded; ours must not keep believing
    the hold or order is in force (no resume is sent for a hold that never was)."""
    auth, link, decisions, persisted = authority()
    auth.hold("y", "operator", "ops")
    auth.hold("y", "collision", "yield")
    auth.replace("z", "daemon_emergency", "m", [ReturnToLaunch(step=0)], "battery", order="rtl")
    sent = len(link.sent)

    auth.refused_where_linked("y", "collision", "pause", "gcs-b", "outranked by vehicle failsafe rtl")
    auth.refused_where_linked("y", "operator", "pause", "gcs-b", "outranked by vehicle failsafe rtl")
    auth.refused_where_linked("z", "daemon_emergency", "replace", "gcs-b", "outranked by operator land")

    assert not auth.is_held("y") and persisted == {}
    assert auth.order_owner("z") is None and auth.may_command("z", "collision")
    assert len(link.sent) == sent  # nothing posted: taking back is bookkeeping, not a command
    last = auth.control("y").decisions[-1]
    assert (last.source, last.command, last.accepted) == ("operator", "hold", False)
    assert last.detail == "refused by gcs-b: outranked by vehicle failsafe rtl"
    assert decisions[-1][:4] == ("z", "daemon_emergency", "replace", False)


def test_holds_are_counted_per_owner_and_resume_only_after_the_last() -> None:
    auth, link, _, _ = authority()
    assert auth.hold("d1", "collision", "yield")[0]
    assert auth.hold("d1", "operator", "pause")[0]
    assert link.modes() == ["pause:collision"]  # one pause on the wire
    assert auth.release("d1", "collision", "clear")[0]
    assert link.modes() == ["pause:collision"]  # the operator still holds it
    assert not auth.release("d1", "divergence", "not mine")[0]
    assert auth.release("d1", "operator", "go")[0]
    assert link.modes() == ["pause:collision", "resume:operator"]


def test_a_lower_source_cannot_undo_a_higher_one() -> None:
    auth, link, decisions, _ = authority()
    assert auth.replace("d1", "operator", "rtl-1", [ReturnToLaunch(step=0)], "fleet rtl", order="rtl")[0]
    ok, why = auth.hold("d1", "collision", "yield")
    assert not ok and "operator rtl" in why
    assert not auth.replace("d1", "mission", "m", [Land(step=0)], "re-send")[0]
    assert not auth.replace("d1", "daemon_emergency", "m", [Land(step=0)], "battery")[0]
    assert [d[3] for d in decisions] == [True, False, False, False]  # refusals are recorded
    assert auth.control("d1").order == "rtl" and auth.control("d1").level == "operator"
    auth.observe("d1", status(armed=False, landed=True))  # down: the order ends
    assert auth.may_command("d1", "mission")
    assert len(link.sent) == 1


def test_the_vehicle_failsafe_outranks_everything_but_the_operator() -> None:
    auth, link, _, _ = authority()
    auth.hold("d1", "collision", "yield")
    auth.observe("d1", status(failsafe="battery_low: rtl"))
    assert auth.release("d1", "collision", "clear") == (True, "vehicle failsafe in force")  # no resume
    assert "resume" not in " ".join(link.modes())
    assert not auth.hold("d1", "daemon_emergency", "fence")[0]
    assert not auth.replace("d1", "collision", "m", [Land(step=0)], "escape")[0]
    assert auth.replace("d1", "operator", "land-1", [Land(step=0)], "operator land", order="land")[0]
    assert link.sent[-1][1].source == "operator" and link.sent[-1][2]  # urgent


def test_operator_holds_persist_and_a_rejoin_gets_its_plan_then_the_pause() -> None:
    auth, _, _, persisted = authority()
    auth.hold("d1", "operator", "mission paused")
    assert persisted == {"d1/operator": "mission paused"}
    fresh, link2, _, _ = authority()
    fresh.restore_hold("d1", "operator", "mission paused")  # after a daemon restart
    fresh.replace("d1", "mission", "m", [Land(step=3)], "re-sent", await_release=2, keep_holds=True)
    assert [f"{b.mode}:{b.await_release}" for _, b, _ in link2.sent] == ["replace:2", "pause:None"]
    assert all(urgent for _, _, urgent in link2.sent)  # same lane, so the order is kept
    auth.release("d1", "operator", "resume")
    assert persisted == {}


def test_longest_hold_and_automatic_holds_end_on_landing() -> None:
    auth, _, _, _ = authority()
    auth.hold("d1", "collision", "yield")
    auth.observe("d1", status(armed=False, landed=True))
    assert not auth.is_held("d1")
    assert auth.longest_hold("collision") >= 0.0 and len(auth.hold_durations) == 1


def test_layers_separate_crossing_ways_home_and_share_parallel_ones() -> None:
    crossing = [
        Returner("a", (0.0, -20.0), 10.0, (0.0, 20.0)),
        Returner("b", (-20.0, 0.0), 10.0, (20.0, 0.0)),
        Returner("c", (100.0, 100.0), 10.0, (120.0, 100.0)),
    ]
    plans = {p.ident: p for p in assign_layers(crossing, 6.0, 15.0, 3.0)}
    assert plans["a"].alt != plans["b"].alt
    assert plans["c"].layer == 0 and plans["c"].alt == 15.0
    assert segment_distance((0, 0), (10, 0), (0, 5), (10, 5)) == 5.0
    assert segment_distance((0, -5), (0, 5), (-5, 0), (5, 0)) == 0.0


def test_landing_spots_of_a_stack_are_spread_and_the_lowest_lands_first() -> None:
    stack = [
        Returner(n, (0.0, 0.0), alt, (0.0, 0.0)) for n, alt in (("low", 8.0), ("mid", 13.0), ("top", 18.0))
    ]
    plans = assign_layers(stack, 6.0, 0.0, 3.0)
    from gcs.cooperation.returns import ReturnPlan

    plans = [ReturnPlan(p.ident, p.layer, r.alt) for p, r in zip(plans, stack, strict=True)]
    spots = spread_landing_spots(stack, plans, 8.0)
    points = list(spots.values())
    gaps = [math.dist(a, b) for i, a in enumerate(points) for b in points[i + 1 :]]
    assert spots["low"] == (0.0, 0.0) and min(gaps) >= 8.0 - 1e-9
    others = [Airborne("low", (0.0, 0.0), 8.0, (0.0, 0.0)), Airborne("mid", (0.0, 10.0), 13.0, (0.0, 10.0))]
    assert cleared_to_descend("low", (0.0, 0.0), 8.0, others, 6.0)  # nobody below it
    assert not cleared_to_descend("top", (0.0, 3.0), 18.0, others, 6.0)  # "low" is below, 3 m away
    assert cleared_to_descend("mid", (0.0, 10.0), 13.0, others, 6.0)  # 10 m from "low"


def test_event_throttle_aggregates_repeats() -> None:
    now = [0.0]
    out: list[str] = []
    throttle = EventThrottle(
        lambda kind, message, *_: out.append(message), window_s=10.0, clock=lambda: now[0]
    )
    for _ in range(50):
        throttle.publish("collision_hold", "yield to d2", "warning", "d1")
    now[0] = 11.0
    throttle.publish("collision_hold", "yield to d2", "warning", "d1")
    assert out == ["yield to d2", "yield to d2 (49 similar in the last 11 s)"]


def test_a_hold_for_a_hovering_partner_becomes_an_escape_within_the_bound() -> None:
    config = CollisionConfig(max_hold_s=5.0, escape="climb")
    avoider = CollisionAvoider(config)

    def drones(t: float) -> list[DroneState]:
        return [
            DroneState("a", 1, (0.0, 0.0, 10.0), (0.0, 0.0, 0.0), None, yieldable=False),  # hovers
            DroneState("b", 2, (0.0, -6.0, 10.0), (0.0, 0.0, 0.0), (0.0, 2.0, 0.0), yieldable=True),
        ]

    first = avoider.update(drones(0.0), 0.0)
    assert first.escapes or first.pause  # it must either wait or climb out now
    decision = first
    for t in np.arange(0.5, 8.0, 0.5):
        decision = avoider.update(drones(float(t)), float(t))
        if decision.escapes:
            break
    assert "b" in avoider.escaping and not avoider.holds.get("b")  # never held past the bound


def test_parked_drones_are_obstacles_not_partners() -> None:
    avoider = CollisionAvoider(CollisionConfig())
    parked = DroneState("p", 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), None, yieldable=False, grounded=True)
    rising = DroneState("r", 2, (0.0, 3.0, 1.0), (0.0, 0.0, 2.0), (0.0, 0.0, 2.0), yieldable=True)
    decision = avoider.update([parked, rising], 0.0)
    assert not decision.pause and not decision.escapes  # a take-off beside a parked drone is fine


def test_take_off_drift_toward_a_parked_drone_is_no_conflict() -> None:
    """A take-off drifting 0.3 m/s toward a landed, disarmed drone 3 m away made an escape that
    could not be planned (an error event); flying at it is still a conflict."""
    avoider = CollisionAvoider(CollisionConfig())
    parked = DroneState("p", 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), None, yieldable=False, grounded=True)
    drift = DroneState("r", 2, (0.0, 3.0, 1.0), (0.0, -0.3, 2.0), (0.0, 0.0, 2.0), yieldable=True)
    decision = avoider.update([parked, drift], 0.0)
    assert not decision.pause and not decision.escapes and not decision.events
    toward = DroneState("r", 2, (0.0, 6.0, 1.0), (0.0, -3.0, 0.0), (0.0, -3.0, 0.0), yieldable=True)
    decision = avoider.update([parked, toward], 1.0)
    assert decision.pause or decision.escapes
