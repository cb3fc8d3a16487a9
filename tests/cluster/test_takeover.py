"""kill -9 of the daemon leading a mission: the standby takes the lease and the mission completes.

Daemons are real `gcs serve --cluster` processes (one is killed); the three agents run in this
process with the memory autopilot so the test can watch every step each of them flies.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from tests.backbone.helpers import new_key, start_agent, stop_agents, survey_mission
from tests.cluster.procs import ServeProcess, start_serve

pytestmark = pytest.mark.slow

NAMES = ["t0", "t1", "t2"]
TAKEOVER_LIMIT_S = 5.0


async def _watch_steps(agents: dict[str, object], seen: dict[str, list[int]], stop: asyncio.Event) -> None:
    """Record each step every agent starts (the queue's current step), in order."""
    deadline = time.monotonic() + 120
    while not stop.is_set() and time.monotonic() < deadline:
        for name, running in agents.items():
            step = running.agent.queue.current_step  # type: ignore[attr-defined]
            if step >= 0 and (not seen[name] or seen[name][-1] != step):
                seen[name].append(step)
        await asyncio.sleep(0.005)


async def test_standby_takes_over_after_kill_9(tmp_path: Path, nats_server: NatsServer) -> None:
    key = new_key()
    a: ServeProcess = start_serve("gcs-a", tmp_path, nats_server.url, key)
    b: ServeProcess = start_serve("gcs-b", tmp_path, nats_server.url, key)
    to_a, to_b = f"127.0.0.1:{a.agent_port}", f"127.0.0.1:{b.agent_port}"
    agents = {
        "t0": start_agent("t0", a.agent_port, key, 0, speedup=4.0, daemons=[to_b]),
        "t1": start_agent("t1", a.agent_port, key, 1, speedup=4.0, daemons=[to_b]),
        "t2": start_agent("t2", b.agent_port, key, 2, speedup=4.0, daemons=[to_a]),
    }
    seen: dict[str, list[int]] = {n: [] for n in NAMES}
    stop = asyncio.Event()
    watcher = asyncio.create_task(_watch_steps(agents, seen, stop))
    try:
        async with httpx.AsyncClient(base_url=b.api, timeout=20) as api_b:

            async def fleet_b() -> list[dict[str, object]]:
                return (await api_b.get("/api/v1/cluster/fleet")).json()

            assert (await api_b.get("/api/v1/cluster")).json()["airspace"] == "gcs-a"  # started first
            deadline = time.monotonic() + 15
            while time.monotonic() < deadline:
                rows = await fleet_b()
                if sorted(r["identity"] for r in rows if r["connected"]) == NAMES:
                    break
                await asyncio.sleep(0.1)
            else:
                raise AssertionError(f"fleet not visible through b: {rows}")

            task = survey_mission(NAMES, sync_legs=5, name="takeover")
            async with httpx.AsyncClient(base_url=a.api, timeout=20) as api_a:
                created = await api_a.post(
                    "/api/v1/missions",
                    content=task.model_dump_json(),
                    headers={"Authorization": f"Bearer {a.token}", "Content-Type": "application/json"},
                )
                assert created.status_code == 201, created.text
                mission_id = created.json()["mission_id"]

            async def progress() -> dict[str, object]:
                return (await api_b.get(f"/api/v1/missions/{mission_id}")).json()

            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and 1 not in (await progress()).get("released_steps", []):
                await asyncio.sleep(0.05)
            assert 1 in (await progress())["released_steps"], "mission did not get going"
            a.kill()
            killed = time.monotonic()
            took_over = None
            while time.monotonic() - killed < 15:
                info = (await api_b.get("/api/v1/cluster")).json()
                if mission_id in info["leading"]:
                    took_over = time.monotonic() - killed
                    break
                await asyncio.sleep(0.05)
            assert took_over is not None and took_over < TAKEOVER_LIMIT_S, f"takeover after {took_over}"
            while time.monotonic() - killed < 15 and info["airspace"] != "gcs-b":
                await asyncio.sleep(0.05)
                info = (await api_b.get("/api/v1/cluster")).json()
            assert info["airspace"] == "gcs-b", "the standby decides the airspace too"

            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and (await progress())["state"] == "running":
                await asyncio.sleep(0.1)
            final = await progress()
            assert final["state"] == "completed", json.dumps(final)[:2000]
            assert final["released_steps"] == task.plans[0].sync_steps()
            rows = {r["identity"]: r for r in await fleet_b()}
            assert all(rows[n]["daemon"] == "gcs-b" and rows[n]["connected"] for n in NAMES), rows
        stop.set()
        await watcher
        last = task.plans[0].actions[-1].step
        for name in NAMES:  # nothing lost, skipped or repeated
            assert seen[name] == list(range(last + 1)), (name, seen[name])
        for name in ("t0", "t1"):
            assert agents[name].agent.link.sessions >= 2  # type: ignore[attr-defined]
    finally:
        stop.set()
        watcher.cancel()
        await stop_agents(list(agents.values()))
        a.kill()
        b.stop()
