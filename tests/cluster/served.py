"""Real `gcs serve --cluster` processes with in-process agents (memory autopilot), and the HTTP
reads the cluster tests make of them (tests/cluster/test_fencing.py, test_nats_loss.py).

Every wait is bounded; every daemon and agent started is stopped on the way out.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx

from protocol.actions import Hold, Land, Takeoff
from protocol.taskfile import AgentPlan, TaskFile
from tests.backbone.helpers import RunningAgent, new_key, start_agent, stop_agents
from tests.cluster.procs import ServeProcess, start_serve

SPEEDUP = 4.0


def hold_task(holds: dict[str, list[float]], sync_timeout_s: float, policy: str, name: str) -> TaskFile:
    """Takeoff, then one hold per entry of ``holds[agent]`` (wall seconds), each a barrier; land."""
    plans = []
    for agent, seconds in holds.items():
        actions: list[Any] = [Takeoff(step=0, alt=5.0, sync=True)]
        actions += [Hold(step=i + 1, seconds=s, sync=True) for i, s in enumerate(seconds)]
        actions.append(Land(step=len(seconds) + 1))
        plans.append(AgentPlan(agent=agent, actions=actions))
    return TaskFile.model_validate(
        {
            "name": name,
            "plans": [p.model_dump() for p in plans],
            "sync_timeout_s": sync_timeout_s,
            "lost_agent_policy": policy,
        }
    )


async def start_fleet(
    serves: dict[str, ServeProcess], links: dict[str, str], key: str, silence: dict[str, float]
) -> dict[str, RunningAgent]:
    """Each agent linked to ``links[name]``, listing the other daemon; until gcs-b sees them all."""
    agents: dict[str, RunningAgent] = {}
    for index, (agent, daemon) in enumerate(links.items()):
        other = serves["gcs-b" if daemon == "gcs-a" else "gcs-a"]
        agents[agent] = start_agent(
            agent,
            serves[daemon].agent_port,
            key,
            index,
            speedup=SPEEDUP,
            daemons=[f"127.0.0.1:{other.agent_port}"],
            daemon_silence_s=silence.get(agent, 5.0),
        )
    rows: list[dict[str, Any]] = []
    async with httpx.AsyncClient(base_url=serves["gcs-b"].api, timeout=10) as api:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            rows = (await api.get("/api/v1/cluster/fleet")).json()
            if sorted(r["identity"] for r in rows if r["connected"]) == sorted(links):
                return agents
            await asyncio.sleep(0.1)
    await stop_agents(list(agents.values()))
    raise AssertionError(f"fleet not visible through gcs-b: {rows}")


@contextlib.asynccontextmanager
async def served_cluster(
    tmp_path: Path,
    nats_urls: str,
    links: dict[str, str],
    silence: dict[str, float],
    env: dict[str, str] | None = None,
) -> AsyncIterator[tuple[dict[str, ServeProcess], dict[str, RunningAgent]]]:
    """gcs-a (started first: the airspace decider) and gcs-b; each agent linked to ``links[name]``
    and listing the other daemon; everything stopped on the way out."""
    key = new_key()
    serves: dict[str, ServeProcess] = {}
    agents: dict[str, RunningAgent] = {}
    try:
        for name in ("gcs-a", "gcs-b"):
            serves[name] = start_serve(name, tmp_path, nats_urls, key, env=env)
        agents = await start_fleet(serves, links, key, silence)
        yield serves, agents
    finally:
        await stop_agents(list(agents.values()))
        for serve in serves.values():
            serve.stop()


async def submit(serve: ServeProcess, task: TaskFile) -> str:
    async with httpx.AsyncClient(base_url=serve.api, timeout=20) as api:
        created = await api.post(
            "/api/v1/missions",
            content=task.model_dump_json(),
            headers={"Authorization": f"Bearer {serve.token}", "Content-Type": "application/json"},
        )
    assert created.status_code == 201, created.text
    return str(created.json()["mission_id"])


async def until(predicate: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


async def watch(api: httpx.AsyncClient, mission_id: str, timeout: float) -> list[dict[str, Any]]:
    """The shared mission record as one daemon shows it, every 0.1 s until it ends (bounded)."""
    seen = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(httpx.HTTPError):
            seen.append((await api.get(f"/api/v1/missions/{mission_id}")).json())
            if seen[-1].get("state") != "running":
                break
        await asyncio.sleep(0.1)
    return seen


async def events(serve: ServeProcess, **query: str) -> list[dict[str, Any]]:
    async with httpx.AsyncClient(base_url=serve.api, timeout=10) as api:
        answer = await api.get(
            "/api/v1/events",
            params={**query, "limit": 10_000},
            headers={"Authorization": f"Bearer {serve.token}"},
        )
    answer.raise_for_status()
    return list(answer.json())


async def cluster_info(serve: ServeProcess) -> dict[str, Any]:
    async with httpx.AsyncClient(base_url=serve.api, timeout=10) as api:
        return dict((await api.get("/api/v1/cluster")).json())
