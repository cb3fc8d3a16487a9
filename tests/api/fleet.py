"""A daemon with its HTTP API on an ephemeral port and in-process memory agents (shared by api/web tests)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from gcs.core.daemon import Daemon
from gcs.http.client import FleetClient
from gcs.planning.areas import SearchArea
from gcs.planning.camera import spacing_from_swath
from gcs.planning.division import DroneSpec
from gcs.planning.planner import PlanConfig, plan_search
from protocol.geo import offset_latlon
from protocol.taskfile import TaskFile
from tests.backbone.helpers import HOME, RunningAgent, new_key, running_daemon, start_agent, stop_agents
from tests.support.polling import wait_for


@dataclass
class Fleet:
    daemon: Daemon
    agents: list[RunningAgent]
    key: str

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.daemon.http_port}"

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.daemon.api_token}"}

    def client(self, token: bool = True) -> httpx.AsyncClient:
        return httpx.AsyncClient(base_url=self.base_url, headers=self.headers if token else {}, timeout=30)


@contextlib.asynccontextmanager
async def running_fleet(
    tmp_path: Path, drones: int = 3, speedup: float = 8.0, spacing_m: float = 6.0, **overrides: object
) -> AsyncIterator[Fleet]:
    """``drones`` memory agents ``spacing_m`` apart east of HOME; ``overrides``: daemon options."""
    key = new_key()
    options: dict[str, object] = {"http_host": "127.0.0.1", "http_port": 0, "api_token": "test-token"}
    options.update(overrides)
    async with running_daemon(tmp_path, key, **options) as daemon:
        agents = [
            start_agent(f"drone-{i + 1}", daemon.listen_port, key, i, speedup, spacing_m=spacing_m)
            for i in range(drones)
        ]
        try:
            await wait_for(
                lambda: all(
                    (s := daemon.agents.session(a.agent.config.identity)) is not None and s.status is not None
                    for a in agents
                ),
                10,
                "agents to join",
            )
            yield Fleet(daemon, agents, key)
        finally:
            await stop_agents(agents)


def client(fleet: Fleet, token: bool = True) -> FleetClient:
    """The typed API client on the fleet's daemon, with the test token or without any."""
    return FleetClient(fleet.base_url, "test-token" if token else None)


def survey_task() -> TaskFile:
    """A 40 x 40 m field north of HOME for two drones, as `gcs plan` writes it (policy ask)."""
    corners = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((10, -5), (10, 35), (50, 35), (50, -5))]
    drones = [DroneSpec(name=f"drone-{i + 1}", endurance_s=3000) for i in range(2)]
    plan = plan_search(
        SearchArea(vertices=corners, name="field"),
        drones,
        spacing_from_swath(10.0, 6.0),
        PlanConfig(transit_alt_step=2.0),
        home_latlon=HOME[:2],
        speed=5.0,
        agent_names=["drone-1", "drone-2"],
    )
    task = TaskFile.model_validate_json(plan.taskfile.model_dump_json())
    return task.model_copy(update={"lost_agent_policy": "continue"})
