"""The daemon and agents end to end over loopback TCP: status, geofence, missions, sync, failures."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from gcs.missions.runner import MissionRejected
from protocol.geo import distance_m
from protocol.packets import FenceCircle, Geofence
from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.support.polling import wait_for


async def test_status_flows_from_every_agent(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(f"drone-{i}", daemon.listen_port, key, i) for i in range(4)]
        try:
            await wait_for(
                lambda: all(
                    (s := daemon.agents.session(f"drone-{i}")) and s.status_count >= 3 for i in range(4)
                ),
                10,
                "three status reports from each of four agents",
            )
            cids = sorted(daemon.agents.session(f"drone-{i}").cid for i in range(4))  # type: ignore[union-attr]
            assert cids == [1, 2, 3, 4]
            status = daemon.agents.session("drone-2").status  # type: ignore[union-attr]
            assert status is not None
            assert status.position.lat == pytest.approx(HOME[0], abs=1e-4)
            assert status.gps.fix == 3 and status.battery.pct == pytest.approx(100.0)
            assert status.mode == "STABILIZE" and not status.armed
            joined = [e for e in daemon.events.history(kind="agent_joined")]
            assert {e.agent for e in joined} == {f"drone-{i}" for i in range(4)}
        finally:
            await stop_agents(agents)


async def test_geofence_delivery_installs_fence_on_agent_and_autopilot(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(f"drone-{i}", daemon.listen_port, key, i) for i in range(2)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            fence = Geofence(
                circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=150.0),
                max_alt_m=60.0,
                breach_action="land",
            )
            delivered = await daemon.set_geofence(fence)
            assert sorted(delivered) == ["drone-0", "drone-1"]
            await wait_for(
                lambda: all(a.agent.monitor.geofence == fence and a.autopilot.fence for a in agents),
                5,
                "fence",
            )
            spec = agents[0].autopilot.fence
            assert spec is not None and spec.circle is not None
            assert spec.circle.radius_m == 150.0 and spec.max_alt_m == 60.0 and spec.breach_action == "land"
        finally:
            await stop_agents(agents)


async def test_multi_agent_mission_releases_sync_steps_in_order(tmp_path: Path) -> None:
    key = new_key()
    names = ["alpha", "bravo", "charlie"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i) for i, name in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 3, 10, "three agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completion")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            releases = daemon.events.history(kind="sync_released")
            assert [e.data["step"] for e in releases] == [0, 1, 2, 3]
            assert all(sorted(e.data["agents"]) == names for e in releases)
            assert progress.released_steps == [0, 1, 2, 3]
            assert all(a.done and a.completed_step == 4 for a in progress.agents)
            for running in agents:
                telemetry = running.autopilot.telemetry()
                assert telemetry.landed and not telemetry.armed
        finally:
            await stop_agents(agents)


async def test_no_agent_starts_next_step_before_release(tmp_path: Path) -> None:
    """A slow agent holds the others at the barrier: the fast ones wait, armed and hovering."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        fast = start_agent("fast", daemon.listen_port, key, 0, speedup=8.0)
        slow = start_agent("slow", daemon.listen_port, key, 1, speedup=1.0)
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(["fast", "slow"], sync_legs=1))
            await wait_for(lambda: fast.agent.queue.waiting_sync == 0, 20, "fast agent waiting at step 0")
            assert fast.agent.queue.completed_step == 0
            assert fast.agent.queue.depth == 2  # nothing after the barrier has started
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completion")
            assert daemon.missions.progress(mission_id).state == "completed"  # type: ignore[union-attr]
        finally:
            await stop_agents([fast, slow])


async def test_refused_takeoff_ends_the_mission_naming_agent_step_and_reason(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i) for i, name in enumerate(["a", "b"])]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            agents[1].autopilot.refuse_arming = True  # b never reaches the takeoff barrier
            task = survey_mission(["a", "b"], sync_legs=1, sync_timeout_s=30, lost_agent_policy="abort")
            mission_id = await daemon.missions.submit(task)
            await wait_for(lambda: mission_id not in daemon.missions.active, 20, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "aborted"
            assert progress.result is not None
            assert "b step 0 (takeoff)" in progress.result and "PreArm" in progress.result, progress.result
            assert not daemon.events.history(kind="sync_timeout")  # ended by the failure, not a timeout
            assert daemon.events.history(kind="action_failed", agent="b")
            failures = daemon.events.history(kind="agent_exception", agent="b")
            assert any("PreArm" in e.message for e in failures), [e.message for e in failures]
            await wait_for(
                lambda: agents[0].autopilot.telemetry().landed, 30, "agent a back on the ground (RTL)"
            )
            t = agents[0].autopilot.telemetry()  # the deconflicted return lands it at its home
            assert t.home_lat is not None and t.home_lon is not None
            assert distance_m(t.lat, t.lon, t.home_lat, t.home_lon) < 3.0
        finally:
            await stop_agents(agents)


async def test_agent_killed_mid_mission_others_finish(tmp_path: Path) -> None:
    key = new_key()
    names = ["one", "two", "three"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i) for i, name in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 3, 10, "three agents")
            task = survey_mission(names, sync_legs=3, lost_agent_policy="continue", sync_timeout_s=30)
            mission_id = await daemon.missions.submit(task)
            await wait_for(
                lambda: 1 in daemon.missions.active[mission_id].barriers.released, 30, "step 1 released"
            )
            await agents[2].kill()
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            assert [a.agent for a in progress.agents if a.excluded] == ["three"]
            assert daemon.events.history(kind="agent_lost", agent="three")
            assert [e.data["step"] for e in daemon.events.history(kind="sync_released")] == [0, 1, 2, 3]
            for running in agents[:2]:
                assert running.autopilot.telemetry().landed
        finally:
            await stop_agents(agents)


async def test_daemon_restart_mid_mission_agents_resume_with_same_cids(tmp_path: Path) -> None:
    key = new_key()
    names = ["north", "south"]
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    agents = [start_agent(name, port, key, i, speedup=4.0) for i, name in enumerate(names)]
    try:
        await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
        cids = {n: daemon.agents.session(n).cid for n in names}  # type: ignore[union-attr]
        mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
        await wait_for(
            lambda: 0 in daemon.missions.active[mission_id].barriers.released, 30, "takeoff released"
        )
        await daemon_cm.__aexit__(None, None, None)

        await wait_for(
            lambda: all(not a.agent.link.connected for a in agents), 5, "agents notice the restart"
        )
        assert all(a.autopilot.telemetry().armed for a in agents)  # still flying their plans
        daemon_cm = running_daemon(tmp_path, key, listen_port=port)
        daemon = await daemon_cm.__aenter__()
        assert mission_id in daemon.missions.active  # restored from the database
        await wait_for(lambda: len(daemon.agents.connected()) == 2, 15, "agents reconnect")
        assert {n: daemon.agents.session(n).cid for n in names} == cids  # type: ignore[union-attr]
        await wait_for(
            lambda: mission_id not in daemon.missions.active, 60, "mission completes after restart"
        )
        progress = daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed"
        assert progress.released_steps == [0, 1, 2, 3]
        assert daemon.events.history(kind="mission_restored")
    finally:
        await stop_agents(agents)
        await daemon_cm.__aexit__(None, None, None)


async def test_mission_for_unconnected_agent_is_rejected(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("present", daemon.listen_port, key)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 1, 10, "one agent")
            with pytest.raises(MissionRejected, match="absent is not connected"):
                await daemon.missions.submit(survey_mission(["present", "absent"]))
            assert not daemon.missions.active
        finally:
            await stop_agents(agents)


async def test_agent_buffers_status_while_daemon_is_down(tmp_path: Path) -> None:
    key = new_key()
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    running = start_agent("buffered", port, key)
    try:
        await wait_for(lambda: daemon.agents.session("buffered") is not None, 10, "agent joins")
        await daemon_cm.__aexit__(None, None, None)
        await wait_for(lambda: running.agent.link.buffered[0] >= 5, 10, "status reports buffered offline")
        daemon_cm = running_daemon(tmp_path, key, listen_port=port)
        daemon = await daemon_cm.__aenter__()
        await wait_for(
            lambda: (s := daemon.agents.session("buffered")) is not None and s.status_count >= 6,
            10,
            "backlog",
        )
        assert running.agent.link.buffered == (0, 0)
    finally:
        await running.kill()
        await daemon_cm.__aexit__(None, None, None)


async def test_pause_holds_the_fleet_and_resume_finishes_the_leg(tmp_path: Path) -> None:
    key = new_key()
    names = ["p1", "p2"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i, speedup=3.0) for i, name in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=1))
            await wait_for(lambda: all(a.agent.queue.current_step == 1 for a in agents), 20, "first leg")
            await wait_for(lambda: agents[0].autopilot.telemetry().alt_rel > 4.0, 10, "at altitude")
            await daemon.missions.pause(mission_id)
            await wait_for(lambda: all(a.autopilot.telemetry().mode == "BRAKE" for a in agents), 5, "braking")
            held = [(a.autopilot.telemetry().lat, a.autopilot.telemetry().lon) for a in agents]
            await wait_for(
                lambda: all((s := daemon.agents.session(n)) and s.status and s.status.paused for n in names),
                5,
                "paused",
            )
            await asyncio.sleep(0.5)
            assert [(a.autopilot.telemetry().lat, a.autopilot.telemetry().lon) for a in agents] == held
            assert all(a.agent.queue.depth == 2 for a in agents)  # the interrupted leg is queued again
            await daemon.missions.resume(mission_id)
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completion")
            assert daemon.missions.progress(mission_id).state == "completed"  # type: ignore[union-attr]
            assert [e.kind for e in daemon.events.history() if e.kind.startswith("mission_")][-3:] == [
                "mission_paused",
                "mission_resumed",
                "mission_completed",
            ]
        finally:
            await stop_agents(agents)


async def test_sync_arrival_survives_a_daemon_restart(tmp_path: Path) -> None:
    """An agent already waiting at a barrier when the daemon dies is counted after the restart."""
    key = new_key()
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    fast = start_agent("early", port, key, 0, speedup=8.0)
    slow = start_agent("late", port, key, 1, speedup=1.0)
    try:
        await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
        task = survey_mission(["early", "late"], sync_legs=1, sync_timeout_s=60)
        mission_id = await daemon.missions.submit(task)
        await wait_for(lambda: fast.agent.queue.waiting_sync == 0, 20, "early agent waiting at step 0")
        await wait_for(
            lambda: "early" in daemon.missions.active[mission_id].barriers.arrivals.get(0, set()),
            5,
            "arrival",
        )
        assert fast.agent.link.buffered == (0, 0)  # its 'finished' was delivered to the old daemon
        await daemon_cm.__aexit__(None, None, None)
        daemon_cm = running_daemon(tmp_path, key, listen_port=port)
        daemon = await daemon_cm.__aenter__()
        await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completes")
        assert daemon.missions.progress(mission_id).state == "completed"  # type: ignore[union-attr]
        assert not daemon.events.history(kind="sync_timeout")
    finally:
        await stop_agents([fast, slow])
        await daemon_cm.__aexit__(None, None, None)


async def test_withdrawn_agent_no_longer_counts_towards_completion(tmp_path: Path) -> None:
    key = new_key()
    names = ["stays", "leaves"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i) for i, name in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
            await wait_for(lambda: 0 in daemon.missions.active[mission_id].barriers.released, 20, "airborne")
            assert await daemon.missions.withdraw("leaves", "battery critical")
            daemon.returns.start(["leaves"], "rtl", "daemon_emergency", "battery critical")
            await wait_for(lambda: agents[1].autopilot.telemetry().landed, 30, "withdrawn agent back home")
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completes")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
            assert {a.agent: a.excluded for a in progress.agents} == {"stays": False, "leaves": True}
            assert agents[0].autopilot.telemetry().landed and agents[0].agent.queue.completed_step == 4
        finally:
            await stop_agents(agents)
