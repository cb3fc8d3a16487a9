"""Reads need the token beyond loopback (gcs/http/guard.py).

The guard decides from the configured bind address. No test binds beyond loopback: the app of a
daemon whose configuration says ``http_host = "0.0.0.0"`` is served by uvicorn on 127.0.0.1 and
reached there, so every request is exactly what a LAN client would send, minus the LAN.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncGenerator, AsyncIterator
from pathlib import Path
from typing import Any, cast

import httpx
import pytest
import uvicorn
import websockets
from fastapi import FastAPI
from fastapi.routing import APIRoute
from websockets.typing import Subprotocol

from gcs.http.app import create_app, flat_routes
from gcs.http.client import FleetClient
from gcs.http.guard import is_loopback_bind
from tests.api.fleet import Fleet, running_fleet

pytestmark = pytest.mark.timeout(120)
READ_TOKEN = "read-only-token-0123456789"
OPEN = {"/", "/openapi.json", "/docs", "/api/v1/tiles/{z}/{x}/{y}"}
PATH_VALUES = {"identity": "drone-1", "mission_id": "none", "z": "0", "x": "0", "y": "0"}


@contextlib.asynccontextmanager
async def _served(app: FastAPI) -> AsyncIterator[str]:
    """``app`` on uvicorn at 127.0.0.1 (an ephemeral port); its base URL."""
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning", lifespan="off")
    )
    task = asyncio.create_task(server.serve())
    try:
        for _ in range(200):
            if server.started or task.done():
                break
            await asyncio.sleep(0.02)
        assert server.started, "uvicorn did not start"
        port = server.servers[0].sockets[0].getsockname()[1]
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        await asyncio.wait_for(task, 10)


def _app_bound_to(fleet: Fleet, host: str, **config: object) -> FastAPI:
    """The daemon's API as built for a daemon configured to listen on ``host``."""
    fleet.daemon.config = fleet.daemon.config.model_copy(update={"http_host": host, **config})
    return create_app(fleet.daemon)


def _get_routes(app: FastAPI) -> list[str]:
    paths = [r.path for r in flat_routes(app) if isinstance(r, APIRoute) and "GET" in (r.methods or ())]
    return [p.format(**PATH_VALUES) for p in paths if p not in OPEN] + ["/metrics"]


def test_loopback_binds() -> None:
    for host in ("127.0.0.1", "127.5.5.5", "localhost", "::1", "[::1]", None):
        assert is_loopback_bind(host), host
    for host in ("0.0.0.0", "::", "", "192.168.1.20", "10.0.0.1", "gcs.field.lan", "fe80::1"):
        assert not is_loopback_bind(host), host


async def test_reads_beyond_loopback_need_a_token(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1) as fleet:
        app = _app_bound_to(fleet, "0.0.0.0", api_read_token=READ_TOKEN)
        routes = _get_routes(app)
        assert "/api/v1/agents" in routes and "/api/v1/agents/drone-1/history" in routes
        async with _served(app) as base, httpx.AsyncClient(base_url=base, timeout=30) as http:
            full = {"Authorization": f"Bearer {fleet.daemon.api_token}"}
            read = {"Authorization": f"Bearer {READ_TOKEN}"}
            for path in routes:  # every GET route, without a token and with a wrong one
                for headers in ({}, {"Authorization": "Bearer wrong-token-0123456789"}):
                    answer = await http.get(path, headers=headers)
                    assert answer.status_code == 401, (path, answer.status_code)
                    assert "beyond loopback" in answer.json()["detail"]
            for headers in (full, read):
                agents = await http.get("/api/v1/agents", headers=headers)
                assert agents.status_code == 200 and agents.json()[0]["identity"] == "drone-1"
                assert (await http.get("/api/v1/agents/drone-1/history", headers=headers)).status_code == 200
            # the read-only token never writes; the dashboard's files hold no fleet data and stay open
            hold = await http.post("/api/v1/fleet/hold", json={}, headers=read)
            assert hold.status_code == 401
            for path in ("/ui/", "/ui/app.js"):
                assert (await http.get(path)).status_code == 200, path
            # the Python client sends its token on reads too
            async with FleetClient(base, READ_TOKEN) as client:
                assert [a.identity for a in await client.agents()] == ["drone-1"]
            await _stream_needs_a_token(base, fleet.daemon.api_token)


async def _stream_needs_a_token(base: str, token: str) -> None:
    url = base.replace("http", "ws", 1) + "/api/v1/stream"
    with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
        async with websockets.connect(url) as ws:
            await ws.recv()
    assert refused.value.response.status_code == 401
    # a header (scripts, FleetClient.stream) or the bearer subprotocol (a browser: the dashboard)
    async with websockets.connect(url, additional_headers={"Authorization": f"Bearer {READ_TOKEN}"}) as ws:
        assert json.loads(await asyncio.wait_for(ws.recv(), 10))[0]["type"] == "hello"
    protocols = [Subprotocol("fleetgcs"), Subprotocol(f"bearer.{token}")]
    async with websockets.connect(url, subprotocols=protocols) as ws:
        assert ws.subprotocol == "fleetgcs"
        assert json.loads(await asyncio.wait_for(ws.recv(), 10))[0]["type"] == "hello"
    async with FleetClient(base, READ_TOKEN) as client:
        stream = cast("AsyncGenerator[Any, None]", client.stream(status=False))
        hello = await asyncio.wait_for(anext(stream), 10)
        await stream.aclose()
    assert isinstance(hello, dict) and hello["type"] == "hello"


async def test_reads_on_loopback_stay_open_unless_configured(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1) as fleet:
        async with fleet.client(token=False) as anonymous:  # the daemon's own app, on 127.0.0.1
            assert (await anonymous.get("/api/v1/agents")).status_code == 200
            assert (await anonymous.post("/api/v1/fleet/hold", json={})).status_code == 401
        url = fleet.base_url.replace("http", "ws", 1) + "/api/v1/stream"
        async with websockets.connect(url) as ws:
            assert json.loads(await asyncio.wait_for(ws.recv(), 10))[0]["type"] == "hello"
        app = _app_bound_to(fleet, "127.0.0.1", http_reads_need_token="always")
        async with _served(app) as base, httpx.AsyncClient(base_url=base, timeout=30) as http:
            assert (await http.get("/api/v1/agents")).status_code == 401
            ok = await http.get(
                "/api/v1/agents", headers={"Authorization": f"Bearer {fleet.daemon.api_token}"}
            )
            assert ok.status_code == 200
