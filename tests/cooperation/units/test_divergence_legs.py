"""Divergence judges legs the way the agent flies them: go-by chains, corner cutting, barriers.

A small kinematic model of the agent (agent/executor.py: fly straight at the target, move on
when within the acceptance radius, a go_by offset taken from the previous planned target, hover
at a barrier until released) produces the status reports the daemon would see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from gcs.cooperation.config import DivergenceConfig
from gcs.cooperation.divergence import DivergenceJudge, divergence_blocked, divergence_may_act, leg_error
from gcs.cooperation.legs import AgentPlanState, agent_acceptance_radius, planned_targets, switch_point
from protocol.actions import Action, GoBy, Goto, Land, Takeoff, Waypoint, Waypoints
from protocol.geo import distance_m, ned_offset_m
from protocol.packets import Position, StatusReport
from tests.support.places import at

HOME = (47.397742, 8.545594)


@dataclass
class Flight:
    """The agent's executor over an acceleration-limited vehicle; a report every ``report_dt`` s.

    The vehicle steers its velocity toward the target (at most ``speed``, slowing to stop on it,
    acceleration at most ``accel``) like a guided-mode position controller, so corners are
    rounded and overshot; the agent polls every ``poll_dt`` and moves on within ``radius``.
    """

    speed: float = 4.3
    accel: float = 2.5
    radius: float = 2.0
    poll_dt: float = 0.05
    report_dt: float = 0.4
    report_phase: float = 0.13
    barrier_s: float = 3.0
    n: float = 0.0
    e: float = 0.0
    vn: float = 0.0
    ve: float = 0.0
    t: float = 0.0
    reports: list[StatusReport] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._next_report = self.report_phase

    def _report(self, step: int, waiting: int | None = None) -> None:
        if self.t + 1e-9 >= self._next_report:
            lat, lon = at(self.n, self.e)
            self.reports.append(
                StatusReport(
                    time=self.t,
                    position=Position(lat=lat, lon=lon, alt_rel=10.0, alt_amsl=498.0),
                    armed=True,
                    landed=False,
                    mode="GUIDED",
                    step=step,
                    waiting_sync=waiting,
                )
            )
            self._next_report += self.report_dt

    def _tick(self, tn: float, te: float) -> float:
        dn, de = tn - self.n, te - self.e
        gap = math.hypot(dn, de)
        want = min(self.speed, math.sqrt(2.0 * self.accel * gap))
        wn, we = (dn / gap * want, de / gap * want) if gap > 1e-9 else (0.0, 0.0)
        cn, ce = wn - self.vn, we - self.ve
        change = math.hypot(cn, ce)
        limit = self.accel * self.poll_dt
        if change > limit:
            cn, ce = cn / change * limit, ce / change * limit
        self.vn, self.ve = self.vn + cn, self.ve + ce
        self.n, self.e = self.n + self.vn * self.poll_dt, self.e + self.ve * self.poll_dt
        self.t += self.poll_dt
        return gap

    def _fly(self, tn: float, te: float, step: int) -> None:
        for _ in range(100_000):
            if math.hypot(tn - self.n, te - self.e) <= self.radius:
                return
            self._tick(tn, te)
            self._report(step)
        raise AssertionError("flight did not end")

    def run(self, actions: list[Action]) -> None:
        target = (self.n, self.e)  # the agent's anchor: the take-off point, then each target
        for a in actions:
            if isinstance(a, Goto):
                target = ned_offset_m(HOME[0], HOME[1], a.lat, a.lon)
                self._fly(*target, a.step)
            elif isinstance(a, GoBy):
                target = (target[0] + a.north, target[1] + a.east)
                self._fly(*target, a.step)
            elif isinstance(a, Waypoints):
                for p in a.points:
                    target = ned_offset_m(HOME[0], HOME[1], p.lat, p.lon)
                    self._fly(*target, a.step)
            else:
                continue
            if a.sync:  # the vehicle keeps going to its target and hovers there until released
                until = self.t + self.barrier_s
                while self.t < until:
                    self._tick(*target)
                    self._report(a.step, waiting=a.step)


def judge_flight(actions: list[Action], flight: Flight, radius: float) -> tuple[list[str], float]:
    """Feed the reports to the daemon's plan tracker and judge; returns verdicts and worst error."""
    plan = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0), radius)
    cfg = DivergenceConfig(persist_s=0.0, cooldown_s=0.0)
    judge = DivergenceJudge(cfg)
    verdicts: list[str] = []
    worst = 0.0
    for s in flight.reports:
        plan.update(s)
        if not divergence_may_act(s):
            continue
        leg = plan.leg(s.waiting_sync)
        assert leg is not None
        error = leg_error(leg, (s.position.lat, s.position.lon, 10.0), cfg.lookahead_m)
        worst = max(worst, error.cross_track_m)
        verdict, _ = judge.judge(leg, error, None, s.time, True)
        if verdict != "ok":
            verdicts.append(verdict)
    return verdicts, worst


def _square_chain(legs: int, side: float = 13.7, sync_every: int = 0, stairs: bool = False) -> list[Action]:
    """go_by legs round a square, or up a staircase (north, east, north...): 90-degree corners."""
    dirs = [(side, 0.0), (0.0, side)] if stairs else [(side, 0.0), (0.0, side), (-side, 0.0), (0.0, -side)]
    actions: list[Action] = [Takeoff(step=0, alt=10.0, sync=True)]
    for k in range(legs):
        n, e = dirs[k % len(dirs)]
        sync = bool(sync_every) and (k + 1) % sync_every == 0
        actions.append(GoBy(step=k + 1, north=n, east=e, speed=5.0, sync=sync))
    actions.append(Land(step=legs + 1))
    return actions


@pytest.mark.parametrize("report_dt", [0.1, 0.4, 1.0])
def test_a_go_by_chain_flown_normally_draws_no_correction(report_dt: float) -> None:
    actions = _square_chain(24, stairs=True)
    flight = Flight(report_dt=report_dt)
    flight.run(actions)
    verdicts, worst = judge_flight(actions, flight, radius=2.0)
    assert verdicts == []
    # corner overshoot only (about 3.5 m here), whatever the chain's length: far under correct_m
    assert worst < 5.0, worst
    # each go_by is anchored at the previous planned target, so the chain ends where the plan
    # dead-reckoned from home does (within a radius, and the last report's distance before it),
    # not a radius per leg away (over 15 m)
    planned = planned_targets(actions, (HOME[0], HOME[1], 0.0))[-2]
    assert planned is not None
    last = flight.reports[-1].position
    assert last is not None
    off = distance_m(planned[0], planned[1], last.lat, last.lon)
    assert off < flight.radius + flight.speed * report_dt, off


def test_chain_with_barriers_and_waypoints_draws_no_correction() -> None:
    wps = [Waypoint(lat=p[0], lon=p[1], alt=10.0) for p in (at(60, 30), at(60, 60), at(20, 60))]
    far = at(30, 30)
    actions: list[Action] = [
        *_square_chain(10, sync_every=3)[:-1],
        Waypoints(step=11, points=wps, speed=5.0),
        GoBy(step=12, north=-8.0, east=-8.0, speed=5.0, sync=True),
        Goto(step=13, lat=far[0], lon=far[1], alt=10.0, speed=5.0),
        GoBy(step=14, north=0.0, east=-15.0, speed=5.0),
        Land(step=15),
    ]
    flight = Flight(report_dt=0.4)
    flight.run(actions)
    verdicts, worst = judge_flight(actions, flight, radius=2.0)
    assert verdicts == [] and worst < 5.0, worst


def test_a_real_divergence_is_still_seen() -> None:
    """A drone blown 12 m off a go-by leg mid-way is corrected: the model does not hide drift."""
    actions = _square_chain(4)
    flight = Flight(report_dt=0.4)
    flight.run(actions)
    plan = AgentPlanState("m", list(actions), (HOME[0], HOME[1], 0.0), 2.0)
    judge = DivergenceJudge(DivergenceConfig(persist_s=0.0, cooldown_s=0.0))
    seen = []
    for s in flight.reports:
        plan.update(s)
        pos = s.position
        if s.step == 2 and s.waiting_sync is None:
            n, e = ned_offset_m(HOME[0], HOME[1], pos.lat, pos.lon)
            if 4.0 < e < 8.0:  # mid-leg of the eastward go-by: pretend the wind pushed it north
                pos = Position(lat=at(n + 12.0, e)[0], lon=at(n + 12.0, e)[1], alt_rel=10.0, alt_amsl=498.0)
        leg = plan.leg(s.waiting_sync)
        if leg is None:
            continue
        verdict, _ = judge.judge(leg, leg_error(leg, (pos.lat, pos.lon, 10.0), 8.0), None, s.time, True)
        seen.append(verdict)
    assert "correct" in seen


def test_switch_point_lies_on_the_observed_chord() -> None:
    before = (*at(0.0, 0.0), 10.0)
    after = (*at(9.0, 1.0), 10.0)
    target = (*at(10.0, 0.0), 10.0)
    p = switch_point(target, before, after, 2.0)
    n, e = ned_offset_m(HOME[0], HOME[1], p[0], p[1])
    # the model point (8, 0) projected on the chord (0,0)->(9,1)
    f = (8 * 9) / (81 + 1)
    assert (n, e) == pytest.approx((9 * f, 1 * f), abs=1e-3)
    # a target 30 m off (a wrong estimate) still gives a point of the chord, never off the track
    wrong = (*at(10.0, 30.0), 10.0)
    q = switch_point(wrong, before, after, 2.0)
    qn, qe = ned_offset_m(HOME[0], HOME[1], q[0], q[1])
    assert abs(qn * 1 - qe * 9) < 1e-3 and 0 <= qn <= 9.0 + 1e-6
    assert switch_point(None, before, after, 2.0) == before  # hovered (barrier): starts from before
    assert switch_point(target, None, after, 2.0) == after
    assert agent_acceptance_radius(None, 2.5) == 2.5 and agent_acceptance_radius(1.5, 2.5) == 1.5


def _status(**kw: object) -> StatusReport:
    lat, lon = at(0, 0)
    base: dict[str, object] = {
        "time": 0.0,
        "position": Position(lat=lat, lon=lon, alt_rel=10.0, alt_amsl=498.0),
        "armed": True,
        "landed": False,
        "mode": "GUIDED",
        "step": 3,
    }
    base.update(kw)
    return StatusReport(**base)  # type: ignore[arg-type]


def test_divergence_may_act_only_on_a_drone_flying_its_plan() -> None:
    assert divergence_may_act(_status())
    assert divergence_blocked(_status(waiting_sync=3)) == "waiting at the barrier of step 3"
    assert not divergence_may_act(_status(paused=True))
    assert not divergence_may_act(_status(), held=True)
    assert not divergence_may_act(_status(), emergency=True)
    assert not divergence_may_act(_status(), escaping=True)
    assert not divergence_may_act(_status(), detour=True)
    for mode in ("RTL", "LAND", "BRAKE", "SMART_RTL"):
        assert divergence_blocked(_status(mode=mode)) == f"in {mode}"
    assert not divergence_may_act(_status(exceptions=["battery_low: 24%"]))
    assert not divergence_may_act(_status(exceptions=["fence_breach: outside the fence polygon"]))
    assert divergence_may_act(_status(exceptions=["gps_glitch_cleared"]))
    assert not divergence_may_act(_status(landed=True, armed=False))


def test_waypoints_after_a_go_by_chain_are_tracked_from_where_the_step_started() -> None:
    """The first waypoint segment starts where the drone is (a radius short of the chain's end)."""
    wps = [Waypoint(lat=p[0], lon=p[1], alt=10.0) for p in (at(130, 175), at(150, 110))]
    actions: list[Action] = [
        *_square_chain(24, side=12.0, sync_every=6, stairs=True)[:-1],
        Waypoints(step=25, points=wps, speed=5.0),
        Land(step=26),
    ]
    for report_dt in (0.1, 0.4, 1.0):
        flight = Flight(report_dt=report_dt)
        flight.run(actions)
        verdicts, worst = judge_flight(actions, flight, radius=2.0)
        assert verdicts == [] and worst < 5.0, (report_dt, verdicts, worst)
