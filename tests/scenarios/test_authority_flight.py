"""Vehicle authority scenarios on daemon + in-process agents + our simulator (real TCP, real MAVLink).

Each test combines the services that command drones with operator commands and failsafes, and
asserts the outcome on the simulator's ground truth: every drone down, no two airborne drones
inside each other's separation cylinder, no hold longer than the bound, nothing of lower
priority undoing a higher one.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from agent.config import SanityLimits
from gcs.cooperation.config import CollisionConfig, CooperationConfig
from gcs.http.planning_requests import SearchPlanRequest, plan
from protocol.actions import Goto, Hold, Land, Takeoff
from protocol.geo import distance_m
from protocol.packets import Geofence
from protocol.taskfile import AgentPlan, TaskFile
from tests.cooperation.rig import SPEEDUP, Rig, at, rig, wait_for
from tests.scenarios.scenarios import (
    H_MARGIN,
    area,
    barrier_task,
    crossing_task,
    head_on,
    infos,
    separation,
    stack_task,
)

pytestmark = pytest.mark.slow

COOP = CooperationConfig(vehicle_time_scale=SPEEDUP)
HOLD_BOUND_S = COOP.collision.max_hold_s + 5.0


async def fly_to_end(r: Rig, task: TaskFile, timeout: float) -> None:
    mission_id = await r.daemon.missions.submit(task)
    await wait_for(lambda: mission_id not in r.daemon.missions.active, timeout, "mission end")
    progress = r.daemon.missions.progress(mission_id)
    if progress is None or progress.state != "completed":
        shown = [e for e in r.daemon.events.history() if e.kind.startswith(("collision", "sync", "agent_"))]
        trail = "; ".join(f"{e.kind} {e.agent or ''}: {e.message}" for e in shown[-15:])
        raise AssertionError(f"{progress}\nlast collision/sync/agent events: {trail}")
    await wait_for(lambda: all(r.landed(n) for n in r.names), 60, "every drone landed")


async def test_region_search_from_close_homes_completes_without_long_holds(tmp_path: Path) -> None:
    """The issue's trap: homes 5 m apart (inside the 4 m margin / 5 m release band), region division."""
    async with rig(tmp_path, 3, COOP, spacing_m=5.0) as r:
        request = SearchPlanRequest(
            drones=r.names, area=area(30, -40, 90, 120), altitude_m=30, swath_m=20, division="region"
        )
        await fly_to_end(r, plan(request, infos(r)).taskfile, 150)
        assert r.daemon.authority.longest_hold() < HOLD_BOUND_S
        closest, inside = separation(r.truth)
        assert inside == 0, f"closest {closest:.2f} m"
        layered = r.events("returns_layered")
        # Ways home that come close get distinct layers (the others may share one).
        assert layered and len(set(layered[-1].data["alt"].values())) >= 2, layered[-1].message


async def test_four_drone_dashboard_search_completes(tmp_path: Path) -> None:
    async with rig(tmp_path, 4, COOP, spacing_m=5.0) as r:
        request = SearchPlanRequest(drones=r.names, area=area(25, -30, 70, 100))  # dashboard defaults
        await fly_to_end(r, plan(request, infos(r)).taskfile, 150)
        assert r.daemon.authority.longest_hold() < HOLD_BOUND_S
        closest, inside = separation(r.truth)
        assert inside == 0, f"closest {closest:.2f} m"


async def _held_fleet(r: Rig) -> str:
    mission_id = await r.daemon.missions.submit(crossing_task(r.names))
    await wait_for(lambda: all((s := r.status(n)) and s.step >= 1 for n in r.names), 40, "all on their legs")
    held = await r.daemon.operator.hold(None, "test")
    assert sorted(held) == sorted(r.names)
    await wait_for(lambda: all(r.status(n).paused for n in r.names), 10, "all held")
    return mission_id


async def test_rtl_all_from_held_state_lands_everyone_apart(tmp_path: Path) -> None:
    async with rig(tmp_path, 4, COOP, spacing_m=5.0) as r:
        await _held_fleet(r)
        start = len(r.truth)
        delivered, aborted = await r.daemon.operator.bring_down("rtl", None, "test")
        assert sorted(delivered) == sorted(r.names) and aborted
        t0 = time.monotonic()
        await wait_for(lambda: all(r.landed(n) for n in r.names), 120, "every drone landed after RTL-all")
        landed_after = time.monotonic() - t0
        for name in r.names:
            s, home = r.status(name), r.daemon.agents.session(name).home
            assert distance_m(s.position.lat, s.position.lon, home.lat, home.lon) < 3.0, name
        closest, inside = separation(r.truth, start)
        assert inside == 0, f"closest {closest:.2f} m"
        alts = {e.agent: e.data["alt"] for e in r.events("return_planned")}
        assert len(set(alts.values())) > 1, alts  # crossing ways home get distinct layers
        assert landed_after < 120


async def test_land_all_from_a_stack_lands_in_sequence_apart(tmp_path: Path) -> None:
    """Three drones hover in a vertical stack; land-all must not land one on top of another."""
    async with rig(tmp_path, 3, COOP, spacing_m=5.0) as r:
        mission_id = await r.daemon.missions.submit(stack_task(r.names))
        await wait_for(lambda: all((s := r.status(n)) and s.step >= 2 for n in r.names), 60, "stacked")
        await r.daemon.operator.hold(None, "test")
        start = len(r.truth)
        delivered, _ = await r.daemon.operator.bring_down("land", None, "test")
        assert sorted(delivered) == sorted(r.names)
        await wait_for(lambda: all(r.landed(n) for n in r.names), 120, "every drone landed")
        assert mission_id not in r.daemon.missions.active
        positions = [r.status(n).position for n in r.names]
        gaps = [
            distance_m(a.lat, a.lon, b.lat, b.lon)
            for i, a in enumerate(positions)
            for b in positions[i + 1 :]
        ]
        assert min(gaps) >= H_MARGIN - 0.5, gaps  # none landed on another
        closest, inside = separation(r.truth, start)
        assert inside == 0, f"closest {closest:.2f} m"


async def test_battery_failsafe_during_a_collision_hold_still_lands(tmp_path: Path) -> None:
    coop = COOP.model_copy(update={"collision": CollisionConfig(escape="none")})  # holds, not escapes
    async with rig(tmp_path, 2, coop) as r:
        mission_id = await r.daemon.missions.submit(head_on(r.names))
        await wait_for(lambda: r.daemon.authority.is_held("drone-2", "collision"), 60, "a collision hold")
        r.fleet.vehicles[1].set_battery(20.0)  # below the agent's battery_low_pct: its own RTL
        await wait_for(lambda: (s := r.status("drone-2")) and s.failsafe, 10, "the agent's failsafe")
        await wait_for(lambda: r.landed("drone-2"), 90, "drone-2 landed by its failsafe")
        s, home = r.status("drone-2"), r.daemon.agents.session("drone-2").home
        assert distance_m(s.position.lat, s.position.lon, home.lat, home.lon) < 3.0  # RTL, not held
        decisions = r.daemon.authority.control("drone-2").decisions
        failsafe_at = next(d.time for d in decisions if d.source == "vehicle_failsafe")
        undone = [
            d
            for d in decisions
            if d.time > failsafe_at
            and d.accepted
            and d.command in ("plan", "release")
            and d.detail == "resume sent"
        ]
        assert not undone, undone  # nobody resumed or re-planned it after its failsafe
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 90, "mission end without it")
        progress = r.daemon.missions.progress(mission_id)
        assert progress is not None and {a.agent: a.excluded for a in progress.agents}["drone-2"]


async def test_fence_emergency_hold_survives_a_collision_escape(tmp_path: Path) -> None:
    """drone-2 is held by a fence breach; drone-1 flies at it: drone-1 must be the one to give way."""
    # drone-2's takeoff climbs through the fence ceiling on purpose: the agents' own limits would refuse it.
    fly_out = {"limits": SanityLimits(check_geofence=False)}
    async with rig(tmp_path, 2, COOP, agent_options=fly_out) as r:
        fence = Geofence(max_alt_m=8.0, breach_action="hold")
        assert await r.daemon.set_geofence(fence, ["drone-2"]) == ["drone-2"]
        here2 = r.status("drone-2").position
        west, east = at(0.0, -25.0), at(0.0, 40.0)
        plans = [
            AgentPlan(
                agent="drone-1",
                actions=[
                    Takeoff(step=0, alt=10.0),
                    Goto(step=1, lat=west[0], lon=west[1], alt=10.0, speed=3.0),
                    Goto(step=2, lat=east[0], lon=east[1], alt=10.0, speed=2.0),  # straight through drone-2
                    Land(step=3),
                ],
            ),
            AgentPlan(
                agent="drone-2",
                actions=[
                    Takeoff(step=0, alt=10.0),
                    Hold(step=1, seconds=5),
                    Hold(step=2, seconds=5),
                    Land(step=3),
                ],
            ),
        ]
        mission_id = await r.daemon.missions.submit(TaskFile(name="fence", plans=plans))
        # The vehicle's own fence failsafe (BRAKE: "fence: hold") or the agent's reaction ("fence_breach").
        await wait_for(lambda: "fence" in (r.status("drone-2").failsafe or ""), 30, "fence hold")
        held_at = r.status("drone-2").position
        await wait_for(lambda: r.daemon.missions.progress(mission_id).agents[0].done, 90, "drone-1 passed")
        s2 = r.status("drone-2")
        assert s2.armed and not s2.landed and "fence" in (s2.failsafe or "")
        assert distance_m(s2.position.lat, s2.position.lon, held_at.lat, held_at.lon) < 2.0  # not moved
        assert distance_m(held_at.lat, held_at.lon, here2.lat, here2.lon) < 3.0
        collision_orders = [
            d
            for d in r.daemon.authority.control("drone-2").decisions
            if d.source == "collision" and d.accepted
        ]
        assert not collision_orders, collision_orders
        closest, inside = separation(r.truth)
        assert inside == 0, f"closest {closest:.2f} m"
        delivered, _ = await r.daemon.operator.bring_down("land", ["drone-2"], "test")  # operator overrides
        assert delivered == ["drone-2"]
        await wait_for(lambda: r.landed("drone-2"), 60, "operator land overrides the failsafe hold")


async def test_agent_restarted_at_an_unreleased_barrier_waits_for_the_release(tmp_path: Path) -> None:
    async with rig(tmp_path, 2, COOP) as r:
        mission_id = await r.daemon.missions.submit(barrier_task(r.names))
        await wait_for(lambda: r.status("drone-1").waiting_sync == 1, 60, "drone-1 at barrier 1")
        assert 1 not in r.daemon.missions.active[mission_id].barriers.released
        await r.restart_agent("drone-1")  # a new process: its queue is gone
        ran_ahead: list[float] = []
        released_at: list[float] = []

        def watch() -> bool:
            s = r.status("drone-1")
            if 1 in r.daemon.missions.active[mission_id].barriers.released and not released_at:
                released_at.append(time.monotonic())
            if s is not None and s.step >= 2 and not ran_ahead:
                ran_ahead.append(time.monotonic())
            return bool(released_at)

        await wait_for(watch, 90, "barrier 1 released")
        assert not ran_ahead or ran_ahead[0] >= released_at[0], "drone-1 flew step 2 before the release"
        resent = r.events("mission_resent", "drone-1")
        assert resent and "waiting at barrier 1" in resent[-1].message
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 90, "mission end")
        assert r.daemon.missions.progress(mission_id).state == "completed"


async def test_pause_survives_agent_and_daemon_restarts(tmp_path: Path) -> None:
    async with rig(tmp_path, 2, COOP) as r:
        mission_id = await r.daemon.missions.submit(barrier_task(r.names))
        await wait_for(lambda: all(r.status(n).step >= 1 for n in r.names), 40, "on their way")
        await r.daemon.missions.pause(mission_id, "operator pause")
        await wait_for(lambda: all(r.status(n).paused for n in r.names), 10, "paused")

        await r.restart_agent("drone-2")  # mid-leg: its queue is re-sent, paused
        await wait_for(lambda: (s := r.status("drone-2")) and s.paused and s.queue_depth > 0, 20, "re-paused")
        before = r.status("drone-2").position
        for _ in range(20):  # 2 s wall = 16 s of flight at this speed-up
            s = r.status("drone-2")
            assert s.paused and distance_m(s.position.lat, s.position.lon, before.lat, before.lon) < 3.0
            await asyncio.sleep(0.1)

        await r.restart_daemon()
        assert mission_id in r.daemon.missions.paused
        await wait_for(lambda: all(r.daemon.agents.session(n) for n in r.names), 20, "agents back")
        await wait_for(lambda: all((s := r.status(n)) and s.paused for n in r.names), 10, "still paused")
        assert all(r.daemon.authority.is_held(n, "operator") for n in r.names)

        await r.daemon.missions.resume(mission_id, "operator resume")
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 120, "mission end")
        assert r.daemon.missions.progress(mission_id).state == "completed"
