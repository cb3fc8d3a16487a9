"""Every view a clustered daemon gives of its fleet, checked at once (tests/cluster/test_holders.py).

``GET /api/v1/agents`` and ``/api/v1/agents/{id}``, the WebSocket stream's hello and the status
messages after it, ``GET /api/v1/cluster/fleet`` and ``gcs agents``: each agent listed once,
connected, with a fresh status, naming the daemon the registry says holds its link. Every wait is
bounded.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import time
from pathlib import Path
from typing import Any

import httpx
import websockets

from gcs.commands.agents import run_list
from gcs.core.daemon import Daemon

FRESH_S = 2.0  # a status older than this is frozen (agents report every 0.1 s)


def _rows_problems(
    view: str, rows: list[dict[str, Any]], where: dict[str, str], age: str | None
) -> list[str]:
    """What is wrong with one view's agent rows: each agent once, connected, fresh, at its holder."""
    problems = []
    names = [str(row["identity"]) for row in rows]
    for identity, daemon in where.items():
        found = [row for row in rows if row["identity"] == identity]
        if len(found) != 1:
            problems.append(f"{view}: {identity} shown {len(found)} times ({names})")
            continue
        row = found[0]
        if row.get("daemon") != daemon:
            problems.append(f"{view}: {identity} at {row.get('daemon')}, not {daemon}")
        if not row.get("connected") or row.get("lost"):
            state = f"connected {row.get('connected')}, lost {row.get('lost')}"
            problems.append(f"{view}: {identity} not connected ({state})")
        if row.get("status") is None:
            problems.append(f"{view}: {identity} has no status")
        if age is not None and (row.get(age) is None or row[age] > FRESH_S):
            problems.append(f"{view}: {identity}'s status is {row.get(age)} s old")
    if sorted(names) != sorted(where):
        problems.append(f"{view}: lists {sorted(names)}, not {sorted(where)}")
    return problems


def _cli_rows(api: str, data_dir: Path) -> list[dict[str, Any]]:
    """``gcs agents`` against ``api`` (run in a thread: it runs its own event loop), as rows."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert run_list(argparse.Namespace(api=api, token="t", data_dir=data_dir)) == 0
    lines = out.getvalue().splitlines()
    head = lines[0].split()
    assert "daemon" in head, lines[0]
    column = head.index("daemon")
    rows = []
    for line in lines[1:]:
        cells = line.split()
        rows.append(
            {
                "identity": cells[1],
                "connected": cells[2] == "up",
                "daemon": cells[column],
                "status": cells[3] if cells[3] != "-" else None,
            }
        )
    return rows


async def _stream_problems(port: int, where: dict[str, str]) -> list[str]:
    """The stream's hello lists each agent once at its holder; a fresh status of each follows."""
    url = f"ws://127.0.0.1:{port}/api/v1/stream?events=false&coverage=false"
    async with websockets.connect(url, additional_headers={"Authorization": "Bearer t"}) as ws:
        hello = json.loads(await asyncio.wait_for(ws.recv(), 10))[0]
        problems = _rows_problems("stream hello", hello["agents"], where, "link_age_s")
        opened = time.time()
        fresh: set[str] = set()
        deadline = time.monotonic() + 5
        while fresh != set(where) and time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError):
                for message in json.loads(await asyncio.wait_for(ws.recv(), 1)):
                    if message.get("type") == "status" and message["received"] >= opened:
                        fresh.add(message["agent"])
        problems += [f"stream: no status of {name} after the hello" for name in sorted(set(where) - fresh)]
    return problems


async def _view_problems(daemon: Daemon, where: dict[str, str]) -> list[str]:
    """Every view of ``daemon``: what does not show ``where`` (agent -> holding daemon)."""
    name = daemon.config.daemon_id
    api = f"http://127.0.0.1:{daemon.http_port}"
    async with httpx.AsyncClient(base_url=api, timeout=10) as client:
        listed = (await client.get("/api/v1/agents")).json()
        problems = _rows_problems(f"{name} GET agents", listed, where, "link_age_s")
        for identity in where:
            one = await client.get(f"/api/v1/agents/{identity}")
            rows = [one.json()] if one.status_code == 200 else []
            alone = {identity: where[identity]}
            problems += _rows_problems(f"{name} GET agents/{identity}", rows, alone, None)
        fleet = (await client.get("/api/v1/cluster/fleet")).json()
        problems += _rows_problems(f"{name} cluster fleet", fleet, where, None)
    assert daemon.http_port is not None
    stream = await _stream_problems(daemon.http_port, where)
    problems += [f"{name} {p}" for p in stream]
    cli = await asyncio.to_thread(_cli_rows, api, daemon.config.data_dir)
    problems += _rows_problems(f"{name} gcs agents", cli, where, None)
    return problems


async def every_view_shows(daemons: tuple[Daemon, ...], where: dict[str, str], what: str) -> None:
    """Until every view of every daemon shows ``where`` (bounded), then once more a second later:
    it stays so (an old daemon's liveness or a late message must not flip it back)."""
    problems: list[str] = []
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        problems = [p for d in daemons for p in await _view_problems(d, where)]
        if not problems:
            break
        await asyncio.sleep(0.2)
    assert not problems, f"{what}: {problems}"
    await asyncio.sleep(1.0)
    problems = [p for d in daemons for p in await _view_problems(d, where)]
    assert not problems, f"{what}, a second later: {problems}"
