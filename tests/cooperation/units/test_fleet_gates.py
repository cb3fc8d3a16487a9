"""The cooperation service checks a status tick on columns and builds a report only for the rows a
gate flags (gcs/cooperation/fleet.py). That must change nothing: for random report sequences the
gated service decides exactly what the same service checking every report decides (same intents
at the same report, same edges), its battery columns give what the one-drone estimator gives, and
an agent's lazily built report is the newest one."""

from __future__ import annotations

import asyncio
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
from hypothesis import event, given, settings
from hypothesis import strategies as st

from gcs.cooperation.config import CollisionConfig, CooperationConfig, DivergenceConfig, EmergencyConfig
from gcs.cooperation.emergency import BatteryColumns, BatteryEstimator
from gcs.cooperation.intents import HoldIntent, Intent, ReplaceIntent
from gcs.cooperation.service import CooperationService
from gcs.link.agents_table import StatusTable, StatusTick
from protocol import status_binary
from protocol.actions import Action, GoBy, Goto, Hold, Takeoff, Waypoint, Waypoints
from protocol.geo import offset_latlon
from protocol.packets import (
    Battery,
    FenceCircle,
    FenceVertex,
    Geofence,
    GeoPoint,
    Gps,
    Position,
    StatusReport,
    VelocityNed,
)

HOME = (47.397742, 8.545594)


class Session:
    """What the service reads of an agent session (identity, cid, home, open)."""

    def __init__(self, k: int) -> None:
        self.identity, self.cid, self.open = f"drone-{k}", k + 1, True
        self.home = GeoPoint(lat=HOME[0], lon=HOME[1])


MISSION = "m-1"
PLAN: list[Action] = [
    Takeoff(step=0, alt=20.0),
    Goto(step=1, lat=offset_latlon(*HOME, 200.0, 0.0)[0], lon=HOME[1], alt=20.0, speed=5.0),
    GoBy(step=2, north=0.0, east=150.0),
    Hold(step=3, seconds=5.0),
    Waypoints(
        step=4,
        points=[
            Waypoint(lat=lat, lon=lon, alt=25.0)
            for lat, lon in (offset_latlon(*HOME, 100.0, 150.0), offset_latlon(*HOME, 100.0, 0.0))
        ],
    ),
    Goto(step=5, sync=True, lat=HOME[0], lon=HOME[1], alt=20.0),
]


def _plan_of(mission: str, ident: str) -> list[Action] | None:
    return PLAN if mission == MISSION else None


class Recording(CooperationService):
    """The service with its intents recorded instead of applied (no daemon around it)."""

    def __init__(self, config: CooperationConfig, fences: dict[str, Geofence]) -> None:
        super().__init__(config)
        self.decided: list[tuple[int, Intent]] = []
        self.step = 0
        authority = SimpleNamespace(is_held=lambda ident, owner=None: False, level=lambda ident: 0)
        self._ctx = SimpleNamespace(  # type: ignore[assignment]
            geofences=fences,
            config=SimpleNamespace(
                agent_parameters=SimpleNamespace(acceptance_radius_m=None), status_period_s=0.1
            ),
            missions=SimpleNamespace(
                plan_of=lambda mission, ident: PLAN if mission == MISSION else None, active={}
            ),
            authority=authority,
        )

    async def apply(self, intents: list[Intent]) -> None:
        self.decided += [(self.step, intent) for intent in intents]


class EveryReport(Recording):
    """The reference: every report is built and checked, as before the gates, and the collision
    avoider sees every drone (no prefilter)."""

    def __init__(self, config: CooperationConfig, fences: dict[str, Geofence]) -> None:
        super().__init__(config, fences)
        self.collision.prefilter = False

    def _gate(self, tick: StatusTick, rows: np.ndarray[Any, np.dtype[np.intp]], now: float) -> list[int]:
        super()._gate(tick, rows, now)  # the arrays and battery columns are fed the same way
        return rows.tolist()


def _report(k: int, t: float, s: dict[str, Any]) -> StatusReport:
    lat, lon = offset_latlon(HOME[0], HOME[1], s.get("origin", 30.0 * k) + s["north"], s["east"])
    return StatusReport(
        time=t,
        position=Position(lat=lat, lon=lon, alt_rel=s["alt"], alt_amsl=400.0 + s["alt"]),
        velocity=VelocityNed(vn=s["vn"], ve=0.0, vd=0.0),
        battery=Battery(pct=s["pct"]),
        gps=Gps(fix=s["fix"], satellites=10),
        mode=s["mode"],
        armed=s["armed"],
        landed=s["landed"],
        step=s["step"],
        completed_step=max(s["step"] - 1, -1),
        mission_id=s.get("mission"),
        waiting_sync=s["step"] if s.get("waiting") else None,
        paused=s.get("paused", False),
    )


change = st.fixed_dictionaries(
    {
        "dt": st.sampled_from([0.1, 0.1, 0.1, 0.35, 1.3, -0.5]),  # now and then the clock goes back
        "north": st.floats(-400.0, 400.0),
        "east": st.floats(-400.0, 400.0),
        "alt": st.floats(0.0, 60.0),
        "vn": st.floats(-10.0, 10.0),
        "drain": st.floats(0.0, 3.0),
        "fix": st.sampled_from([3, 3, 3, 3, 2, 0]),
        "mode": st.sampled_from(["GUIDED"] * 8 + ["RTL", "LAND"]),
        "armed": st.sampled_from([True] * 12 + [False]),
        "landed": st.sampled_from([False] * 12 + [True]),
        "step": st.sampled_from([-1] * 6 + [0, 1]),
        "move": st.booleans(),
    }
)


flight = st.fixed_dictionaries(
    {
        "dt": st.sampled_from([0.1, 0.1, 0.1, 0.35, 1.3]),
        "dn": st.sampled_from([-2.0, 0.0, 1.0, 2.0, 3.0, 40.0, -40.0]),  # now and then a gust's jump
        "de": st.sampled_from([-2.0, 0.0, 1.0, 2.0, -30.0, 30.0]),
        "advance": st.sampled_from([False] * 10 + [True]),
        "waiting": st.sampled_from([False] * 8 + [True]),
        "paused": st.sampled_from([False] * 12 + [True]),
        "fix": st.sampled_from([3] * 12 + [2]),
    }
)


def _fly(c: dict[str, Any], s: dict[str, Any]) -> dict[str, Any]:
    """A drone in the mission: it creeps along with gusts, steps on now and then, waits, pauses."""
    step = min(s.get("step", 0) + int(c["advance"]), len(PLAN) - 1)
    return {
        "dt": c["dt"],
        "north": s["north"] + c["dn"],
        "east": s["east"] + c["de"],
        "alt": 20.0,
        "vn": c.get("vn", 1.0),
        "drain": 0.05,
        "fix": c["fix"],
        "mode": "GUIDED",
        "armed": True,
        "landed": False,
        "step": max(step, 0),
        "move": True,
        "mission": MISSION,
        "waiting": c["waiting"],
        "paused": c["paused"],
    }


FENCES = [  # none; a circle with a ceiling (checked on columns); a polygon (checked per report)
    None,
    Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=250.0), max_alt_m=45.0),
    Geofence(
        polygon=[
            FenceVertex(lat=lat, lon=lon)
            for lat, lon in (
                offset_latlon(*HOME, -300, -300),
                offset_latlon(*HOME, 300, 0),
                offset_latlon(*HOME, 0, 300),
            )
        ]
    ),
]


async def _run(
    steps: list[list[dict[str, Any]]],
    fenced: int,
    mission: bool = False,
    origins: list[float] | None = None,
    collisions: bool = False,
    collision: CollisionConfig | None = None,
) -> tuple[Recording, Recording, dict[str, StatusReport]]:
    """Both services fed the same ticks; ``origins``: each drone's start north of home (default
    30 m apart); ``collisions``: a fleet-wide collision pass after every tick, its intents recorded."""
    config = CooperationConfig(
        emergency=EmergencyConfig(gps_grace_s=0.0, battery_window_s=4.0, battery_reserve_pct=40.0),
        divergence=DivergenceConfig(persist_s=0.0, cooldown_s=0.0, lag_event_m=20.0),
        collision=collision or CollisionConfig(),
    )
    fences = {"drone-0": FENCES[fenced], "drone-2": FENCES[fenced]} if fenced else {}
    gated, every = Recording(config, fences), EveryReport(config, fences)
    agents = len(steps[0])
    sessions = [Session(k) for k in range(agents)]
    table = StatusTable(capacity=2)
    rows = [table.attach(s) for s in sessions]
    state = [
        {"north": 0.0, "east": 0.0, "alt": 20.0, "vn": 0.0, "pct": 95.0, "t": 1000.0 + k}
        for k in range(agents)
    ]
    for k, origin in enumerate(origins or []):
        state[k]["origin"] = origin
    newest: dict[str, StatusReport] = {}
    for n, step in enumerate(steps):
        for k, c in enumerate(step):
            s = state[k]
            if mission:
                c = _fly(c, s)
            s["t"] += c["dt"]
            s["pct"] = max(0.0, s["pct"] - c["drain"] * max(c["dt"], 0.0))
            if c["move"]:
                s.update(north=c["north"], east=c["east"], alt=c["alt"], vn=c["vn"])
            s.update({key: c[key] for key in ("fix", "mode", "armed", "landed", "step")})
            s.update({key: c[key] for key in ("mission", "waiting", "paused") if key in c})
            report = _report(k, s["t"], s)
            table.put(rows[k], status_binary.encode(report), time.time())
            newest[sessions[k].identity] = report
        dirty = table.take_dirty()
        owners = [sessions[rows.index(r)] for r in dirty.tolist()]
        for service in (gated, every):
            service.step = n
            cols = table.columns(dirty)  # whole rows (a copy of the columns would drop mode, mission)
            tick = StatusTick(owners, cols, table.arrivals(dirty), [None] * len(owners))
            await service._on_tick(tick)
            if collisions and service.frame is not None:
                now = state[0]["t"]
                fleet = list(service.agents.values())
                service.decided += [(n, i) for i in service._collision_pass(fleet, now)]
    return gated, every, newest


@settings(max_examples=250, deadline=None)
@given(
    st.integers(1, 3).flatmap(
        lambda n: st.lists(st.lists(change, min_size=n, max_size=n), min_size=2, max_size=60)
    ),
    st.integers(0, 2),
)
def test_the_gated_checks_decide_what_checking_every_report_decides(
    steps: list[list[dict[str, Any]]], fenced: int
) -> None:
    gated, every, newest = asyncio.run(_run(steps, fenced))
    event("acted" if every.decided else "no action")  # (hypothesis statistics: the runs that act)
    breach = any(getattr(i, "kind", "") == "emergency_fence_breach" for _, i in every.decided)
    event(f"fence {fenced}: {'breach' if breach else 'none'}")
    assert gated.decided == every.decided
    for ident, agent in gated.agents.items():
        other = every.agents[ident]
        assert (agent.conditions.keys(), agent.acted, agent.emergency) == (
            other.conditions.keys(),
            other.acted,
            other.emergency,
        )
        assert agent.status == newest[ident]  # built from its row when only the row was updated
        assert agent.battery is not None and other.battery is not None
        assert (agent.battery.drop_rate(), agent.battery.ground_speed()) == (
            other.battery.drop_rate(),
            other.battery.ground_speed(),
        )
    assert gated.built <= every.built


@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 2).flatmap(
        lambda n: st.lists(st.lists(flight, min_size=n, max_size=n), min_size=2, max_size=120)
    )
)
def test_in_a_mission_the_gated_checks_decide_what_checking_every_report_decides(
    steps: list[list[dict[str, Any]]],
) -> None:
    gated, every, newest = asyncio.run(_run(steps, 0, mission=True))
    event("acted" if every.decided else "no action")
    event("divergence" if any("divergence" in str(i) for _, i in every.decided) else "no divergence")
    assert gated.decided == every.decided
    for ident, agent in gated.agents.items():
        other = every.agents[ident]
        assert agent.plan is not None and other.plan is not None
        if gated.fleet.skipped[agent.slot]:  # the last reports were not tracked: as the next report does
            p = newest[ident].position
            assert p is not None
            agent.plan.passed((p.lat, p.lon, p.alt_rel))
        assert vars_of(agent.plan) == vars_of(other.plan)  # the same plan position, switch points too
        assert (agent.completed, agent.detour_step, agent.conditions.keys()) == (
            other.completed,
            other.detour_step,
            other.conditions.keys(),
        )
        assert agent.status == newest[ident]


@settings(max_examples=120, deadline=None)
@given(st.lists(st.sampled_from([0, 0, 1, 2, 3]), min_size=3, max_size=7), st.data())
def test_the_collision_prefilter_decides_what_the_whole_fleet_decides(
    clusters: list[int], data: st.DataObject
) -> None:
    """Drones in clusters 600 m apart (beyond any conflict), 3 or 7 m apart inside one, flying their
    plan with gusts, waits and pauses: the avoider seeing only the drones within reach of another
    (and those it holds or waits for) holds, releases and escapes exactly as seeing them all."""
    n = len(clusters)
    moving = st.tuples(flight, st.sampled_from([-8.0, -3.0, 0.0, 1.0, 3.0, 8.0])).map(
        lambda fv: {**fv[0], "vn": fv[1]}  # closing and opening speeds along the cluster
    )
    steps = data.draw(st.lists(st.lists(moving, min_size=n, max_size=n), min_size=2, max_size=60))
    spacing = {0: 3.0, 1: 7.0, 2: 3.0, 3: 7.0}  # inside the 4 m margin at once, or a gust away
    origins = [600.0 * c + spacing[c] * clusters[:k].count(c) for k, c in enumerate(clusters)]
    # Speeds capped at 3 m/s: the reach is 41 m, so a gust (40 m) takes a drone in or out of it.
    collision = CollisionConfig(max_speed_mps=3.0)
    run = _run(steps, 0, mission=True, origins=origins, collisions=True, collision=collision)
    gated, every, _ = asyncio.run(run)
    held = any(isinstance(i, HoldIntent) and i.owner == "collision" for _, i in every.decided)
    event("collision hold" if held else "no collision hold")
    event("an isolated drone" if any(clusters.count(c) == 1 for c in clusters) else "all clustered")
    assert gated.decided == every.decided
    assert gated.collision.avoider.holds == every.collision.avoider.holds


def test_a_mission_flown_on_its_leg_skips_the_checks_and_a_gust_is_still_corrected() -> None:
    calm = {"dt": 0.1, "dn": 0.5, "de": 0.0, "waiting": False, "paused": False, "fix": 3}
    steps = [[{**calm, "advance": n == 0}] for n in range(150)]  # on step 1, north at the planned 5 m/s
    quiet, every, _ = asyncio.run(_run(steps, 0, mission=True))
    assert not every.decided and quiet.built <= 3  # the first report and the step change
    gust = [[{**calm, "advance": False, "de": 20.0}]]  # blown 20 m off the leg
    gated, every, _ = asyncio.run(_run(steps + gust + steps[1:20], 0, mission=True))
    acted = [n for n, i in every.decided if isinstance(i, HoldIntent | ReplaceIntent)]
    assert acted and acted[0] == 150, "the correction comes at the gust's own report"
    assert gated.decided == every.decided


def vars_of(plan: Any) -> dict[str, Any]:
    return {k: v for k, v in vars(plan).items() if k != "actions"}


def _steady(
    dt: float, drain: float, far_m: float, length: int, mps: float = 5.0
) -> list[list[dict[str, Any]]]:
    """One drone flying east at ``mps``, ``far_m`` north of home, its battery draining ``drain`` %/s."""
    base = {"north": far_m, "alt": 30.0, "vn": 0.0, "fix": 3, "mode": "GUIDED"}
    base |= {"armed": True, "landed": False, "step": -1, "move": True}
    return [[{**base, "east": mps * dt * n, "dt": dt, "drain": drain}] for n in range(length)]


def test_a_steady_flight_skips_the_checks_and_a_draining_battery_still_acts_on_time() -> None:
    quiet, _, _ = asyncio.run(_run(_steady(0.1, 0.0, 100.0, 200), 0))
    assert quiet.built <= 3  # the first report, and nothing after it changed
    steps = _steady(0.1, 0.5, 285.0, 200)  # draining 0.5 %/s: short of the return after ~10 s
    gated, every, _ = asyncio.run(_run(steps, 0))
    fired = [n for n, i in every.decided if getattr(i, "kind", None) == "emergency_battery"]
    assert fired, "the scenario must make the battery check act"
    assert gated.decided == every.decided
    before, _, _ = asyncio.run(_run(steps[: fired[0]], 0))  # the flight until it acts
    assert before.built < fired[0] / 3  # only the reports near the threshold were checked


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.lists(
            st.tuples(
                st.integers(0, 3),
                st.sampled_from([0.05, 0.1, 0.7, -0.3]),
                st.floats(0, 100),
                st.floats(-50, 50),
            ),
            min_size=1,
            max_size=6,
        ),
        min_size=1,
        max_size=80,
    )
)
def test_battery_columns_fed_a_tick_at_once_match_one_estimator_per_drone(
    ticks: list[list[tuple[int, float, float, float]]],
) -> None:
    columns = BatteryColumns(3.0, 2)  # grows to four drones on the way
    single = [BatteryEstimator(3.0) for _ in range(4)]
    clock = [100.0] * 4
    for tick in ticks:
        slots, t, pct, lat, lon = [], [], [], [], []
        for drone, dt, p, east in tick:  # a drone twice in one tick is taken in order
            clock[drone] += dt
            la, lo = offset_latlon(HOME[0], HOME[1], 0.0, east)
            report = StatusReport(
                time=clock[drone],
                position=Position(lat=la, lon=lo, alt_rel=10.0, alt_amsl=410.0),
                battery=Battery(pct=p),
                armed=True,
                landed=False,
            )
            single[drone].add(report)
            slots.append(drone)
            t.append(clock[drone])
            pct.append(p)
            lat.append(la)
            lon.append(lo)
        columns.grow(4)
        columns.add(np.array(slots, dtype=np.intp), np.array(t), np.array(pct), np.array(lat), np.array(lon))
    every = np.arange(4, dtype=np.intp)
    for drone in range(4):
        rate, speed = single[drone].drop_rate(), single[drone].ground_speed()
        assert np.isnan(columns.rate[drone]) if rate is None else columns.rate[drone] == rate
        assert np.isnan(columns.speed[drone]) if speed is None else columns.speed[drone] == speed
    np.testing.assert_array_equal(columns.drop_rate(every), columns.rate)  # the cache is current
    np.testing.assert_array_equal(columns.ground_speed(every), columns.speed)
