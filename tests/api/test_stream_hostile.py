"""The WebSocket stream under hostile clients: output only, small messages, bounded connections.

The daemon runs as ``gcs serve`` (so the memory measured in /proc/<pid>/status is the daemon's
alone) with three ``agent run`` processes flying a hover mission; 60 unauthenticated clients each
try to push 15 MiB messages into /api/v1/stream, again and again. The daemon must stay within
50 MiB of its resident memory before the attack, and the mission must keep its telemetry.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import threading
import time
from pathlib import Path

import httpx
import pytest
import websockets

from gcs.observe.live import StreamClient
from protocol.actions import Action, Goto, Hold, Takeoff
from protocol.geo import offset_latlon
from protocol.taskfile import AgentPlan, TaskFile
from tests.api.fleet import running_fleet
from tests.backbone.helpers import HOME
from tests.faults.hostile_ws import HostileStats, push_large_messages
from tests.support.polling import wait_until
from tests.support.processes import agent_process, serve_daemon, stop_processes, wait_ready

pytestmark = pytest.mark.timeout(180)
CLIENTS = 60
MESSAGE = 15 << 20
ATTACK_S = 8.0
MIB = 1 << 20
NAMES = ["ws-1", "ws-2", "ws-3"]


def _rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError(f"no VmRSS for {pid}")


def _hover(names: list[str]) -> TaskFile:
    plans = []
    for index, name in enumerate(names):
        lat, lon = offset_latlon(HOME[0], HOME[1], 10.0, 6.0 * index)
        actions: list[Action] = [
            Takeoff(step=0, alt=5.0),
            Goto(step=1, lat=lat, lon=lon, alt=5.0),
            Hold(step=2, seconds=600.0),
        ]
        plans.append(AgentPlan(agent=name, actions=actions))
    return TaskFile(name="hover", plans=plans, allow_airborne_end=True)


def _start(tmp_path: Path) -> tuple[subprocess.Popen[bytes], list[subprocess.Popen[bytes]], int, Path]:
    data_dir, ready = tmp_path / "gcs", tmp_path / "ready"
    options = ("--status-period", "0.2", "--lost-after", "25")
    serve = serve_daemon(data_dir, ready, options=options, stderr=subprocess.PIPE)
    agents: list[subprocess.Popen[bytes]] = []
    try:
        agent_port, http_port = wait_ready(ready, serve)
        for index, name in enumerate(NAMES):
            lat, lon = offset_latlon(HOME[0], HOME[1], 0.0, 6.0 * index)
            agents.append(agent_process(name, agent_port, data_dir / "fleet.key", (lat, lon, 488), speedup=8))
    except BaseException:
        stop_processes([serve, *agents])
        raise
    return serve, agents, http_port, data_dir


async def _attack(port: int, pid: int) -> tuple[int, list[HostileStats]]:
    """60 hostile clients for ATTACK_S seconds; the daemon's peak resident memory meanwhile."""
    stop = threading.Event()
    stats = [HostileStats() for _ in range(CLIENTS)]
    threads = [
        threading.Thread(
            target=push_large_messages, args=(port, "/api/v1/stream", MESSAGE, stop, s), daemon=True
        )
        for s in stats
    ]
    for thread in threads:
        thread.start()
    peak = 0
    try:
        deadline = time.monotonic() + ATTACK_S
        while time.monotonic() < deadline:
            peak = max(peak, _rss(pid))
            await asyncio.sleep(0.1)
    finally:
        stop.set()
        for thread in threads:
            await asyncio.to_thread(thread.join, 10)
    peak = max(peak, _rss(pid))
    return peak, stats


async def test_sixty_hostile_stream_clients_leave_memory_and_telemetry_alone(tmp_path: Path) -> None:
    serve, agents, port, data_dir = _start(tmp_path)
    try:
        token = (data_dir / "api.token").read_text().strip()
        base = f"http://127.0.0.1:{port}"
        async with httpx.AsyncClient(
            base_url=base, timeout=30, headers={"Authorization": f"Bearer {token}"}
        ) as http:

            async def joined() -> bool:
                views = (await http.get("/api/v1/agents")).json()
                return sum(1 for v in views if v["connected"] and v["status"]) == len(NAMES)

            await wait_until(joined, 30, "agents to join", poll=0.2)
            created = await http.post("/api/v1/missions", json=_hover(NAMES).model_dump(mode="json"))
            assert created.status_code == 201, created.text
            url = base.replace("http", "ws", 1) + "/api/v1/stream"
            async with websockets.connect(url) as ws:  # warm the stream's code up before the baseline
                for _ in range(5):
                    await asyncio.wait_for(ws.recv(), 10)
            await asyncio.sleep(2.0)
            baseline = max(_rss(serve.pid) for _ in range(3))
            started = time.time()
            peak, stats = await _attack(port, serve.pid)
            ended = time.time()
            assert sum(s.upgraded for s in stats) >= CLIENTS, stats  # the attack reached the endpoint
            assert peak - baseline < 50 * MIB, f"RSS {baseline / MIB:.0f} -> {peak / MIB:.0f} MiB"
            # the mission kept its telemetry: nobody lost, samples all through the attack
            lost = (await http.get("/api/v1/events", params={"kind": "agent_lost"})).json()
            assert lost == [], lost
            for name in NAMES:
                samples = (await http.get(f"/api/v1/agents/{name}/history", params={"since": started})).json()
                times = [s["received"] for s in samples if s["received"] <= ended]
                assert len(times) >= ATTACK_S, (name, len(times))  # 5 Hz expected; at least 1 Hz kept
            # output only: one small message closes a client (1008)
            async with websockets.connect(url) as ws:
                await ws.send("hello")
                with pytest.raises(websockets.exceptions.ConnectionClosed) as closed:
                    for _ in range(100):
                        await asyncio.wait_for(ws.recv(), 10)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    finally:
        stop_processes([serve, *agents])
    log = serve.stderr.read().decode(errors="replace") if serve.stderr else ""
    assert "Traceback" not in log, log[-3000:]


async def test_stream_connections_are_bounded(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1, stream_max_clients=2) as fleet:
        url = fleet.base_url.replace("http", "ws", 1) + "/api/v1/stream"
        async with websockets.connect(url) as one, websockets.connect(url) as two:
            for ws in (one, two):
                assert json.loads(await asyncio.wait_for(ws.recv(), 10))[0]["type"] == "hello"
            with pytest.raises(websockets.exceptions.InvalidStatus):
                async with websockets.connect(url) as third:
                    await third.recv()
        async with websockets.connect(url) as again:  # a slot is free once a client leaves
            assert json.loads(await asyncio.wait_for(again.recv(), 10))[0]["type"] == "hello"


async def test_a_stream_clients_queue_is_bounded_in_bytes() -> None:
    client = StreamClient(max_bytes=1000)
    for index in range(100):
        client.offer(f'"{index:03d}' + "x" * 95 + '"')  # a JSON string of 100 characters
    assert client.queued_bytes <= 1000 and client.dropped == 90
    batch = json.loads(await client.next_batch())  # the newest ten, oldest first
    assert [text[:3] for text in batch] == [f"{i:03d}" for i in range(90, 100)]
    assert client.queued_bytes == 0
