"""The agent's exception monitor acts on the autopilot by itself, and the daemon hears about it."""

from __future__ import annotations

from pathlib import Path

from agent.config import AgentSettings, SanityLimits
from protocol.actions import Goto, Hold, Takeoff
from protocol.geo import offset_latlon
from protocol.packets import FenceCircle, Geofence
from protocol.taskfile import AgentPlan, TaskFile
from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent, stop_agents
from tests.support.polling import wait_for


def hover_mission(identity: str, seconds: float = 60.0, north_m: float = 0.0) -> TaskFile:
    lat, lon = offset_latlon(HOME[0], HOME[1], north_m, 0.0)
    actions = [
        Takeoff(step=0, alt=5.0),
        Goto(step=1, lat=lat, lon=lon, alt=5.0),
        Hold(step=2, seconds=seconds),
    ]
    return TaskFile(name="hover", plans=[AgentPlan(agent=identity, actions=list(actions))])


async def test_low_battery_makes_the_agent_return_to_launch(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("thirsty", daemon.listen_port, key)
        try:
            await wait_for(lambda: daemon.agents.session("thirsty") is not None, 10, "agent joins")
            await daemon.missions.submit(hover_mission("thirsty", north_m=10.0))
            await wait_for(lambda: running.agent.queue.current_step == 2, 20, "hovering")
            running.autopilot.telemetry().battery_pct = 20.0  # below the 25 % low threshold
            await wait_for(lambda: running.autopilot.telemetry().mode == "RTL", 5, "RTL on low battery")
            assert running.agent.queue.depth == 0 and running.agent.queue.current_step == -1  # queue emptied
            await wait_for(
                lambda: daemon.events.history(kind="agent_exception", agent="thirsty"), 5, "exception event"
            )
            event = daemon.events.history(kind="agent_exception", agent="thirsty")[0]
            assert event.message.startswith("battery_low: 20%")
            await wait_for(lambda: running.autopilot.telemetry().landed, 30, "landed at home")
        finally:
            await stop_agents([running])


async def test_fence_breach_triggers_the_fence_action(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        # The mission leads out of the fence on purpose: the agent's own limits would refuse it.
        fly_out = SanityLimits(check_geofence=False)
        running = start_agent("wanderer", daemon.listen_port, key, limits=fly_out)
        try:
            await wait_for(lambda: daemon.agents.session("wanderer") is not None, 10, "agent joins")
            fence = Geofence(
                circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=15.0), breach_action="land"
            )
            assert await daemon.set_geofence(fence) == ["wanderer"]
            await wait_for(lambda: running.agent.monitor.geofence is not None, 5, "fence installed")
            await daemon.missions.submit(
                hover_mission("wanderer", north_m=40.0)
            )  # 40 m out: beyond the fence
            await wait_for(lambda: running.autopilot.telemetry().mode == "LAND", 30, "LAND on fence breach")

            def fence_reported() -> bool:
                session = daemon.agents.session("wanderer")
                status = session.status if session else None
                return status is not None and any("fence_breach" in e for e in status.exceptions)

            await wait_for(fence_reported, 5, "breach reported to the daemon")
            await wait_for(lambda: running.autopilot.telemetry().landed, 30, "landed")
            north = (running.autopilot.telemetry().lat - HOME[0]) * 111_195
            assert 14.0 < north < 20.0  # it stopped just past the 15 m fence, not at the 40 m goal
        finally:
            await stop_agents([running])


async def test_lost_daemon_link_applies_the_failsafe(tmp_path: Path) -> None:
    key = new_key()
    settings = AgentSettings(
        status_period_s=0.1, acceptance_radius_m=1.0, lost_link_timeout_s=0.5, lost_link_action="rtl"
    )
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    running = start_agent("orphan", daemon.listen_port, key, settings=settings)
    try:
        await wait_for(lambda: daemon.agents.session("orphan") is not None, 10, "agent joins")
        await daemon.missions.submit(hover_mission("orphan", north_m=10.0))
        await wait_for(lambda: running.agent.queue.current_step == 2, 20, "hovering")
        await daemon_cm.__aexit__(None, None, None)
        await wait_for(lambda: "link_lost" in running.agent.monitor.active, 5, "link loss detected")
        await wait_for(lambda: running.autopilot.telemetry().mode == "RTL", 5, "RTL failsafe")
        await wait_for(lambda: running.autopilot.telemetry().landed, 30, "landed at home")
    finally:
        await stop_agents([running])


async def test_short_link_loss_is_ridden_through(tmp_path: Path) -> None:
    key = new_key()
    settings = AgentSettings(
        status_period_s=0.1, acceptance_radius_m=1.0, lost_link_timeout_s=30, lost_link_action="rtl"
    )
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    running = start_agent("steadfast", port, key, settings=settings)
    try:
        await wait_for(lambda: daemon.agents.session("steadfast") is not None, 10, "agent joins")
        await daemon.missions.submit(hover_mission("steadfast", seconds=3.0, north_m=10.0))
        await wait_for(lambda: running.agent.queue.current_step == 2, 20, "hovering")
        await daemon_cm.__aexit__(None, None, None)
        await wait_for(lambda: not running.agent.link.connected, 5, "link down")
        daemon_cm = running_daemon(tmp_path, key, listen_port=port)
        daemon = await daemon_cm.__aenter__()
        await wait_for(lambda: daemon.agents.session("steadfast") is not None, 10, "reconnected")
        assert running.autopilot.telemetry().mode != "RTL" and not running.agent.monitor.active
    finally:
        await stop_agents([running])
        await daemon_cm.__aexit__(None, None, None)
