"""A daemon with its HTTP API on an ephemeral port and in-process memory agents (shared by api/web tests)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from gcs.daemon import Daemon
from tests.backbone.helpers import RunningAgent, new_key, running_daemon, start_agent, stop_agents, wait_for


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
    tmp_path: Path, drones: int = 3, speedup: float = 8.0, **overrides: object
) -> AsyncIterator[Fleet]:
    key = new_key()
    options: dict[str, object] = {"http_host": "127.0.0.1", "http_port": 0, "api_token": "test-token"}
    options.update(overrides)
    async with running_daemon(tmp_path, key, **options) as daemon:
        agents = [start_agent(f"drone-{i + 1}", daemon.listen_port, key, i, speedup) for i in range(drones)]
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
