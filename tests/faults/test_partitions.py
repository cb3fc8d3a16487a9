"""Network partitions and bad links between agents and the daemon, through the fault proxy.

Real loopback TCP, the in-process daemon and memory-autopilot agents (tests/backbone/helpers).
A partition either resets the connections (the agent notices at once) or stalls them (TCP
holds the bytes; the peers see only silence, which is what a cut radio link looks like).
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.faults.common import (
    failsafe_settings,
    first_occurrences,
    hover_mission,
    quiet_mission,
    record_releases,
    released_steps,
)
from tests.faults.proxy import FaultProxy
from tests.support.polling import wait_for

METRES_PER_DEG = 111_195.0


def _landed_at_home(lat: float, lon: float) -> bool:
    return abs(lat - HOME[0]) * METRES_PER_DEG < 2.0 and abs(lon - HOME[1]) * METRES_PER_DEG < 2.0


async def _long_partition_lands_the_vehicle_at_home(tmp_path: Path, mode: str) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        running = start_agent("orphan", proxy.port, key, settings=failsafe_settings(0.8, "rtl"), speedup=8)
        try:
            await wait_for(lambda: daemon.agents.session("orphan") is not None, 10, "agent joins")
            await daemon.missions.submit(hover_mission("orphan", north_m=12.0))
            await wait_for(lambda: running.agent.queue.current_step == 2, 20, "hovering 12 m out")
            proxy.partition(30.0, mode)  # type: ignore[arg-type]  # far longer than the 0.8 s failsafe
            await wait_for(lambda: "link_lost" in running.agent.monitor.active, 5, "link loss detected")
            await wait_for(lambda: running.autopilot.telemetry().mode == "RTL", 3, "RTL failsafe")
            assert running.agent.queue.depth == 0  # the rest of the plan was dropped
            await wait_for(lambda: running.autopilot.telemetry().landed, 20, "landed")
            t = running.autopilot.telemetry()
            assert _landed_at_home(t.lat, t.lon), (t.lat, t.lon)
            proxy.heal()
            await wait_for(lambda: daemon.agents.session("orphan") is not None, 10, "back after healing")
        finally:
            await stop_agents([running])


async def test_partition_with_resets_longer_than_the_failsafe_lands_the_vehicle_at_home(
    tmp_path: Path,
) -> None:
    """Connections reset and new ones refused: after lost_link_timeout_s the agent flies home."""
    await _long_partition_lands_the_vehicle_at_home(tmp_path, "reset")


async def test_silent_partition_longer_than_the_failsafe_lands_the_vehicle_at_home(tmp_path: Path) -> None:
    """The radio goes quiet but no socket closes: the failsafe must still fire."""
    await _long_partition_lands_the_vehicle_at_home(tmp_path, "stall")


async def test_short_partition_is_ridden_through(tmp_path: Path) -> None:
    """A 0.6 s stall (shorter than the daemon's 1 s liveness limit): TCP delivers late, nothing is lost."""
    key = new_key()
    names = ["ride-1", "ride-2"]
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        agents = [
            start_agent(n, proxy.port, key, i, settings=failsafe_settings(5.0), speedup=4)
            for i, n in enumerate(names)
        ]
        releases = [record_releases(a) for a in agents]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
            await wait_for(lambda: agents[0].agent.queue.current_step == 1, 20, "first leg")
            await proxy.partition_for(0.6, "stall")
            await wait_for(lambda: mission_id not in daemon.missions.active, 40, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
            assert released_steps(daemon, mission_id) == [0, 1, 2, 3]  # each step once, in order
            for running, seen in zip(agents, releases, strict=True):
                assert first_occurrences(seen) == [0, 1, 2, 3]
                assert not any(name == "link_lost" for _, name, _ in running.agent.reported)
                assert running.autopilot.telemetry().mode != "RTL"
            assert not daemon.events.history(kind="agent_lost")
            assert proxy.stats["partition_stall"] == 1 and proxy.stats["connections"] == 2
        finally:
            await stop_agents(agents)


async def test_stall_outlasting_daemon_liveness_loses_no_sync_step(tmp_path: Path) -> None:
    """The agent finishes a sync step inside a 2.5 s stall; the daemon drops the silent link at 1 s,
    so that 'finished' dies with the old connection. The reconnect must still complete the barrier."""
    key = new_key()
    names = ["cut", "steady"]
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        settings = failsafe_settings(30.0)
        cut = start_agent("cut", proxy.port, key, 0, settings=settings, speedup=4)
        steady = start_agent("steady", daemon.listen_port, key, 1, settings=settings, speedup=4)
        releases = {"cut": record_releases(cut), "steady": record_releases(steady)}
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission = survey_mission(names, sync_legs=3, sync_timeout_s=15)
            mission_id = await daemon.missions.submit(mission)
            queue = cut.agent.queue
            await wait_for(lambda: queue.current_step == 1 and queue.waiting_sync is None, 20, "leg 1")
            proxy.partition(2.5, "stall")
            await wait_for(lambda: queue.waiting_sync == 1, 5, "step 1 finished during the stall")
            assert proxy.partitioned
            await wait_for(lambda: daemon.events.history(kind="agent_lost"), 5, "daemon gives up on it")
            await wait_for(lambda: mission_id not in daemon.missions.active, 25, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            assert released_steps(daemon, mission_id) == [0, 1, 2, 3]
            for seen in releases.values():
                assert first_occurrences(seen) == [0, 1, 2, 3]
            finished_on_old_link = [
                r.decode().body
                for r in proxy.frames("up", 5, "forwarded")
                if r.connection == 1 and getattr(r.decode().body, "step", None) == 1
            ]
            assert finished_on_old_link == []  # it really was lost with the first connection
        finally:
            await stop_agents([cut, steady])


async def test_brief_reset_after_a_quiet_spell_does_not_trigger_the_failsafe(tmp_path: Path) -> None:
    """Keepalives keep the last contact fresh while the mission is quiet, so a short reset rides through."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        running = start_agent("quiet", proxy.port, key, settings=failsafe_settings(2.0), speedup=8)
        try:
            await wait_for(lambda: daemon.agents.session("quiet") is not None, 10, "agent joins")
            mission_id = await daemon.missions.submit(quiet_mission(["quiet"], hold_s=5.0))
            await wait_for(lambda: running.agent.queue.current_step == 2, 20, "holding")
            link = running.agent.link
            await asyncio.sleep(2.5)  # no mission traffic now: only the daemon's keepalives flow
            assert time.monotonic() - link.last_contact < 1.5
            await proxy.partition_for(0.3, "reset")  # far shorter than the 2 s failsafe
            await wait_for(lambda: link.connected, 5, "reconnected")
            assert not any(name == "link_lost" for _, name, _ in running.agent.reported)
            await wait_for(lambda: mission_id not in daemon.missions.active, 20, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
        finally:
            await stop_agents([running])


async def test_mission_completes_over_a_slow_lossy_reordering_link(tmp_path: Path) -> None:
    """40 +- 30 ms latency both ways, a third of status reports lost and a fifth reordered: status
    reports carry full state, so the barriers and completion are unaffected."""
    key = new_key()
    names = ["lossy-1", "lossy-2", "lossy-3"]
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port, seed=7) as proxy:
        for faults in (proxy.up, proxy.down):
            faults.delay_s, faults.jitter_s = 0.04, 0.03
        proxy.up.drop_rate, proxy.up.drop_types = 0.33, frozenset({2})
        proxy.up.reorder_rate = 0.2
        agents = [start_agent(n, proxy.port, key, i, speedup=8) for i, n in enumerate(names)]
        releases = [record_releases(a) for a in agents]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 3, 10, "three agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
            await wait_for(lambda: mission_id not in daemon.missions.active, 40, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
            assert released_steps(daemon, mission_id) == [0, 1, 2, 3]
            for seen in releases:
                assert first_occurrences(seen) == [0, 1, 2, 3]
            assert proxy.stats["up_dropped"] > 5 and proxy.stats["up_reordered"] > 0  # faults did happen
            assert not proxy.frames("up", 5, "dropped")  # only status reports were dropped
            assert not daemon.events.history(kind="agent_lost")
        finally:
            await stop_agents(agents)
