"""Mission runner policies on in-memory agents: failed actions (end / skip / retry), barriers no
agent ever reaches, and the pre-flight wait for every agent's first 3-D fix."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from agent.autopilot.base import CommandRefused
from gcs.missions.runner import MissionRejected
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.support.polling import wait_for


async def test_skip_policy_flies_on_after_a_refused_takeoff(tmp_path: Path) -> None:
    """on_action_failed=skip: the failed step counts as done (its barrier too); the others go on."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(n, daemon.listen_port, key, i) for i, n in enumerate(["a", "b"])]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            agents[1].autopilot.refuse_arming = True
            task = survey_mission(["a", "b"], sync_legs=1, on_action_failed="skip", sync_timeout_s=30)
            mission_id = await daemon.missions.submit(task)
            await wait_for(lambda: 0 in daemon.missions.active[mission_id].barriers.released, 20, "step 0")
            assert daemon.events.history(kind="action_skipped", agent="b")
            # b, on the ground and disarmed, now fails its goto at once: skipped too, so all finish.
            await wait_for(lambda: mission_id not in daemon.missions.active, 30, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            assert agents[0].autopilot.telemetry().landed
        finally:
            await stop_agents(agents)


async def test_retry_policy_retries_then_ends(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("a", daemon.listen_port, key, 0)]
        try:
            await wait_for(lambda: daemon.agents.session("a") is not None, 10, "agent")
            agents[0].autopilot.refuse_arming = True
            task = survey_mission(["a"], sync_legs=1, on_action_failed="retry", action_retries=2)
            mission_id = await daemon.missions.submit(task)
            await wait_for(lambda: mission_id not in daemon.missions.active, 20, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "aborted"
            assert len(daemon.events.history(kind="action_retry", agent="a")) == 2
            assert len(daemon.events.history(kind="action_failed", agent="a")) == 3
            assert progress.result and "a step 0 (takeoff)" in progress.result
        finally:
            await stop_agents(agents)


async def test_retry_policy_recovers_when_the_autopilot_accepts_again(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("a", daemon.listen_port, key, 0)]
        try:
            await wait_for(lambda: daemon.agents.session("a") is not None, 10, "agent")
            autopilot = agents[0].autopilot
            arm = autopilot.arm

            async def refuse_once(deadline_s: float = 60.0) -> None:
                autopilot.arm = arm  # type: ignore[method-assign]  # the retry is accepted
                raise CommandRefused("arm", "PreArm: once")

            autopilot.arm = refuse_once  # type: ignore[method-assign]
            task = survey_mission(["a"], sync_legs=1, on_action_failed="retry", action_retries=1)
            mission_id = await daemon.missions.submit(task)
            await wait_for(lambda: mission_id not in daemon.missions.active, 30, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            assert len(daemon.events.history(kind="action_retry", agent="a")) == 1
        finally:
            await stop_agents(agents)


async def test_barrier_no_agent_reaches_times_out_from_the_mission_start(tmp_path: Path) -> None:
    """Every agent gone before the first barrier: the watchdog (started at submit) ends the mission."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(n, daemon.listen_port, key, i) for i, n in enumerate(["a", "b"])]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            task = survey_mission(["a", "b"], sync_legs=1, sync_timeout_s=1.5, lost_agent_policy="abort")
            mission_id = await daemon.missions.submit(task)
            for agent in agents:
                await agent.kill()
            await wait_for(lambda: mission_id not in daemon.missions.active, 20, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "aborted"
            assert progress.result and "never arrived" in progress.result
            events = daemon.events.history(kind="sync_timeout")
            assert events and events[0].data["missing"] == ["a", "b"]
        finally:
            await stop_agents(agents)


async def test_watchdog_lets_long_legs_run(tmp_path: Path) -> None:
    """An agent still flying towards the barrier is not timed out by the watchdog."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("a", daemon.listen_port, key, 0, speedup=1.0)]
        try:
            await wait_for(lambda: daemon.agents.session("a") is not None, 10, "agent")
            task = survey_mission(["a"], sync_legs=1, sync_timeout_s=0.5, lost_agent_policy="abort")
            mission_id = await daemon.missions.submit(task)
            await asyncio.sleep(2.0)  # four watchdog periods into a takeoff that takes longer
            assert mission_id in daemon.missions.active
            assert not daemon.events.history(kind="sync_timeout")
        finally:
            await stop_agents(agents)


async def test_preflight_waits_for_a_fix_and_says_so(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("a", daemon.listen_port, key, 0)]
        try:
            await wait_for(lambda: daemon.agents.session("a") is not None, 10, "agent")
            tel = agents[0].autopilot.telemetry()
            tel.gps_fix, tel.position_known = 0, False
            await wait_for(  # (the session is there before its first report: status None until then)
                lambda: (s := daemon.agents.session("a")) and s.status and s.status.position is None,
                5,
                "no position",
            )

            async def fix_later() -> None:
                await asyncio.sleep(0.8)
                tel.gps_fix, tel.position_known = 3, True

            fixer = asyncio.create_task(fix_later())
            mission_id = await daemon.missions.submit(survey_mission(["a"], sync_legs=1, fix_wait_s=10))
            await fixer
            assert daemon.events.history(kind="preflight_waiting")
            assert daemon.events.history(kind="preflight_fix")
            await wait_for(lambda: mission_id not in daemon.missions.active, 30, "mission end")
            # and a fix that never comes: refused with the reason, after the bounded wait
            tel.gps_fix, tel.position_known = 0, False
            await wait_for(  # (the session is there before its first report: status None until then)
                lambda: (s := daemon.agents.session("a")) and s.status and s.status.position is None,
                5,
                "no position",
            )
            with pytest.raises(MissionRejected, match=r"no 3-D fix after 1 s from a \(GPS fix 0"):
                await daemon.missions.submit(survey_mission(["a"], sync_legs=1, fix_wait_s=1))
        finally:
            await stop_agents(agents)


async def test_a_mission_without_agents_says_why_they_left(tmp_path: Path) -> None:
    """Withdrawn by a battery emergency is not "lost": the result names each agent's reason."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(n, daemon.listen_port, key, i) for i, n in enumerate(["a", "b"])]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(["a", "b"], sync_legs=1))
            await daemon.missions.withdraw("a", "energy: battery emergency")
            await daemon.missions.withdraw("b", "operator: fleet rtl")
            await wait_for(lambda: mission_id not in daemon.missions.active, 10, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "aborted", progress
            assert progress.result is not None and "lost" not in progress.result, progress.result
            assert "a: withdrawn: energy: battery emergency" in progress.result
            assert "b: withdrawn: operator: fleet rtl" in progress.result
        finally:
            await stop_agents(agents)
