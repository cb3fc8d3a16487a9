"""Divergence, connectivity, geofence and energy services against the real simulator."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from agent.config import AgentSettings, SanityLimits
from gcs.cooperation.config import ConnectivityConfig, CooperationConfig, DivergenceConfig
from gcs.cooperation.divergence import leg_error
from gcs.cooperation.legs import Leg
from gcs.missions.runner import MissionRejected
from protocol.actions import Goto, Land, Takeoff, Waypoint, Waypoints
from protocol.geo import distance_m
from protocol.packets import FenceCircle, Geofence, StatusReport
from protocol.taskfile import AgentPlan, TaskFile
from tests.cooperation.rig import HOME, SPEEDUP, at, rig, wait_for


def single(actions: list[object], name: str = "solo") -> TaskFile:
    return TaskFile(name=name, plans=[AgentPlan(agent="drone-1", actions=actions)])  # type: ignore[arg-type]


async def test_drone_blown_off_its_leg_is_replanned_back_onto_it(tmp_path: Path) -> None:
    far = at(110.0, 0.0)
    task = single(
        [
            Takeoff(step=0, alt=10.0, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=10.0, speed=5.0, sync=True),
            Land(step=2),
        ],
        "crosswind",
    )
    coop = CooperationConfig(
        vehicle_time_scale=SPEEDUP, divergence=DivergenceConfig(correct_m=6.0, replan_m=9.0)
    )
    home = at(0.0, 0.0)
    leg = Leg(1, (home[0], home[1], 10.0), (far[0], far[1], 10.0), 5.0)
    track: list[tuple[float, float, float]] = []  # wall time, cross-track m, metres to go

    async def measure(session: object, status: StatusReport) -> None:
        if status.armed and not status.landed and status.position.alt_rel > 8.0:
            error = leg_error(leg, (status.position.lat, status.position.lon, 10.0), 0.0)
            track.append((time.time(), error.cross_track_m, error.length_m - error.along_m))

    async with rig(tmp_path, 1, coop, fleet_options={"wind": (0.0, 15.0)}) as r:
        r.daemon.agents.on_status.append(measure)
        mission_id = await r.daemon.missions.submit(task)
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 60, "mission end")
        assert r.daemon.missions.progress(mission_id).state == "completed"  # type: ignore[union-attr]
        replans = r.events("divergence_replan", "drone-1")
        assert replans, [e.kind for e in r.daemon.events.history()]
        first = replans[0]
        assert first.data["step"] == 1 and first.data["cross_track_m"] >= 9.0
        assert len(replans) <= coop.divergence.max_replans_per_step
        # After the replan the drone came back close to the planned line while still far from the end.
        after = [(cross, to_go) for t, cross, to_go in track if t > first.time]
        assert any(cross < 3.0 and to_go > 20.0 for cross, to_go in after), after[:: max(1, len(after) // 20)]
        final = r.status("drone-1")
        assert (
            distance_m(final.position.lat, final.position.lon, far[0], far[1]) < 6.0
        )  # landed at the target


async def test_drone_flown_out_of_link_range_triggers_the_policy(tmp_path: Path) -> None:
    far = at(90.0, 0.0)
    task = single(
        [
            Takeoff(step=0, alt=8.0, sync=True),
            Goto(step=1, lat=far[0], lon=far[1], alt=8.0, speed=6.0),
            Land(step=2),
        ],
        "too-far",
    )
    coop = CooperationConfig(
        vehicle_time_scale=SPEEDUP,
        connectivity=ConnectivityConfig(link_range_m=40.0, policy="rtl", grace_s=0.3),
    )
    async with rig(tmp_path, 1, coop) as r:
        mission_id = await r.daemon.missions.submit(task)
        warnings = r.events("connectivity_warning", "drone-1")
        assert any(e.data.get("preflight") and e.data["step"] == 1 for e in warnings)  # warned at submission
        await wait_for(lambda: r.events("connectivity_lost", "drone-1"), 40, "modelled disconnection")
        await wait_for(lambda: r.status("drone-1").mode == "RTL", 10, "RTL by policy")
        status = r.status("drone-1")
        assert (
            distance_m(HOME[0], HOME[1], status.position.lat, status.position.lon) < 75.0
        )  # turned back well short of 90 m
        await wait_for(lambda: r.landed("drone-1"), 60, "landed")
        final = r.status("drone-1")
        assert distance_m(HOME[0], HOME[1], final.position.lat, final.position.lon) < 4.0  # back home
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 10, "mission over")


async def test_fence_breach_acted_on_by_agent_and_daemon(tmp_path: Path) -> None:
    out = at(60.0, 0.0)
    task = single(
        [
            Takeoff(step=0, alt=8.0, sync=True),
            Goto(step=1, lat=out[0], lon=out[1], alt=8.0, speed=6.0),
            Land(step=2),
        ],
        "breach",
    )
    # The goto leads out of the fence on purpose: the agent's own limits would refuse it.
    fly_out = {"limits": SanityLimits(check_geofence=False)}
    async with rig(tmp_path, 1, agent_options=fly_out) as r:
        fence = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=30.0), breach_action="rtl")
        assert await r.daemon.set_geofence(fence) == ["drone-1"]
        assert r.daemon.geofences["drone-1"] == fence
        await wait_for(lambda: r.agents["drone-1"].monitor.geofence == fence, 5, "fence on the agent")
        await r.daemon.missions.submit(task)
        await wait_for(lambda: r.events("emergency_fence_breach", "drone-1"), 40, "daemon-side breach")
        daemon_event = r.events("emergency_fence_breach", "drone-1")[0]
        assert daemon_event.data["action"] == "rtl" and "radius 30.0 m" in daemon_event.message
        await wait_for(
            lambda: any(
                e.data.get("exception") == "fence_breach" for e in r.events("agent_exception", "drone-1")
            ),
            10,
            "agent-side breach",
        )
        await wait_for(lambda: r.status("drone-1").mode == "RTL", 10, "RTL")
        await wait_for(lambda: r.landed("drone-1"), 60, "landed")
        final = r.status("drone-1")
        assert distance_m(HOME[0], HOME[1], final.position.lat, final.position.lon) < 4.0


async def test_mission_too_long_for_the_battery_is_refused_before_takeoff(tmp_path: Path) -> None:
    points = [
        Waypoint(lat=p[0], lon=p[1], alt=15.0) for p in (at(400, 0), at(400, 400), at(0, 400), at(0, 0))
    ]
    long_task = single(
        [Takeoff(step=0, alt=15.0), Waypoints(step=1, points=points * 4, speed=8.0), Land(step=2)]
    )
    short_task = single([Takeoff(step=0, alt=5.0), Land(step=1)], "hop")
    async with rig(tmp_path, 1, settings=AgentSettings(status_period_s=0.05)) as r:
        r.fleet.vehicle(0).set_battery(60.0)
        await wait_for(lambda: (r.status("drone-1").battery.pct or 100) < 61, 10, "battery at 60 %")
        with pytest.raises(MissionRejected) as refused:
            await r.daemon.missions.submit(long_task)
        text = str(refused.value)
        assert re.search(r"drone-1 needs [\d.]+ Wh \(plan \d+ s, \d+ m\)", text), text
        assert re.search(r"has [\d.]+ Wh \((59|60)% of 55 Wh\)", text), text
        prediction = r.events("energy_prediction")[-1].data["agents"]["drone-1"]
        assert prediction["predicted_wh"] + prediction["reserve_wh"] > prediction["available_wh"]
        assert prediction["plan_distance_m"] > 6000
        assert r.landed("drone-1") and not r.daemon.missions.active  # never took off
        mission_id = await r.daemon.missions.submit(short_task)  # a short hop is fine
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 40, "hop done")
