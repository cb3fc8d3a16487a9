"""Shared helpers for backbone tests: a daemon and in-process agents on real loopback TCP."""

from __future__ import annotations

import asyncio
import contextlib
import secrets
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from agent.autopilot.memory import MemoryAutopilot
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from gcs.core.config import DaemonConfig
from gcs.core.daemon import Daemon
from gcs.storage.store import StoredMission
from protocol.actions import GoBy, Goto, Land, Takeoff
from protocol.geo import offset_latlon
from protocol.taskfile import AgentPlan, TaskFile
from tests.support.places import HOME
from tests.support.polling import wait_for


def daemon_config(data_dir: Path, key_hex: str, **overrides: object) -> DaemonConfig:
    values: dict[str, object] = {
        "listen_host": "127.0.0.1",
        "listen_port": 0,
        "http_host": None,
        "data_dir": data_dir,
        "fleet_key_hex": key_hex,
        "status_period_s": 0.1,
        "lost_after_periods": 10.0,
        "handshake_timeout_s": 2.0,
    }
    values.update(overrides)
    return DaemonConfig.model_validate(values)


@dataclass
class RunningAgent:
    agent: Agent
    autopilot: MemoryAutopilot
    task: asyncio.Task[None]

    async def kill(self) -> None:
        """Stop abruptly (no close packet), as a crashed companion computer would."""
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await self.task


def start_agent(
    identity: str,
    port: int,
    key_hex: str,
    index: int = 0,
    speedup: float = 8.0,
    settings: AgentSettings | None = None,
    spacing_m: float = 6.0,
    **config_overrides: object,
) -> RunningAgent:
    lat, lon = offset_latlon(HOME[0], HOME[1], 0.0, spacing_m * index)
    autopilot = MemoryAutopilot((lat, lon, HOME[2]), speedup=speedup, speed_mps=6.0, climb_mps=4.0)
    config = AgentConfig(
        identity=identity,
        gcs_port=port,
        key_hex=key_hex,
        settings=settings or AgentSettings(status_period_s=0.1, acceptance_radius_m=1.0),
        reconnect_min_s=0.05,
        reconnect_max_s=0.3,
        resend_target_s=1.0,
        monitor_period_s=0.05,
    ).model_copy(update=config_overrides)
    agent = Agent(config, autopilot)
    return RunningAgent(agent, autopilot, asyncio.create_task(agent.run(), name=f"agent-{identity}"))


async def mission_ended(daemon: Daemon, mission_id: str, timeout: float, what: str) -> StoredMission:
    """Wait until the store no longer has ``mission_id`` running; its stored record."""
    await wait_for(
        lambda: (m := daemon.store.mission(mission_id)) is not None and m.state != "running",
        timeout,
        what,
        poll=0.1,
    )
    stored = daemon.store.mission(mission_id)
    assert stored is not None
    return stored


def survey_mission(
    identities: list[str], sync_legs: int = 3, name: str = "test-mission", **task_options: object
) -> TaskFile:
    """Takeoff (sync), ``sync_legs`` legs each ending in a sync point, then land."""
    plans = []
    for index, identity in enumerate(identities):
        lat, lon = offset_latlon(HOME[0], HOME[1], 0.0, 6.0 * index)
        actions: list[object] = [Takeoff(step=0, alt=5.0, sync=True)]
        for leg in range(1, sync_legs + 1):
            if leg % 2:
                north = 10.0 * leg
                target = offset_latlon(lat, lon, north, 0.0)
                actions.append(Goto(step=leg, lat=target[0], lon=target[1], alt=5.0, sync=True))
            else:
                actions.append(GoBy(step=leg, north=-5.0, east=2.0, sync=True))
        actions.append(Land(step=sync_legs + 1))
        plans.append(AgentPlan(agent=identity, actions=actions))  # type: ignore[arg-type]
    return TaskFile.model_validate({"name": name, "plans": [p.model_dump() for p in plans], **task_options})


@contextlib.asynccontextmanager
async def running_daemon(tmp_path: Path, key_hex: str, **overrides: object) -> AsyncIterator[Daemon]:
    daemon = Daemon(daemon_config(tmp_path, key_hex, **overrides))
    await daemon.start()
    try:
        yield daemon
    finally:
        await daemon.stop()


def new_key() -> str:
    return secrets.token_hex(32)


async def stop_agents(agents: list[RunningAgent]) -> None:
    for running in agents:
        await running.kill()


def telemetry_row(agent: str, time_s: float, received: float) -> tuple[object, ...]:
    """One telemetry row in the store's column order (TELEMETRY_COLUMNS), flying in GUIDED."""
    return (
        agent,
        time_s,
        received,
        47.0,
        8.0,
        1.0,
        400.0,
        0,
        0,
        0,
        0,
        50.0,
        12.0,
        3.0,
        "GUIDED",
        1,
        0,
        3,
        10,
        2,
        "m",
        0,
    )
