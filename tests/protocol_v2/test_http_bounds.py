"""HTTP API bounds (gcs/http/guard.py), each hit while a mission is flying: the daemon keeps serving it."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import pytest
import websockets

from tests.api.fleet import Fleet, running_fleet
from tests.faults.common import hover_mission
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(120)
LIMIT = 64 << 10


async def _still_flying(fleet: Fleet, mission_id: str) -> None:
    session = fleet.daemon.agents.session("drone-1")
    assert session is not None and session.open and mission_id in fleet.daemon.missions.active
    before = session.status_count
    await wait_for(lambda: session.status_count > before + 2, 5, "status reports keep coming")


async def _raw_post(port: int, headers: str, body: bytes = b"") -> bytes:
    """POST with raw ``headers`` (and ``body``, best effort); the status line of the answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"POST /api/v1/missions HTTP/1.1\r\nHost: 127.0.0.1\r\n{headers}\r\n".encode())
    with contextlib.suppress(ConnectionError):
        writer.write(body)
        await writer.drain()
    line = await asyncio.wait_for(reader.readline(), 5.0)
    writer.close()
    return line


def _chunked(total: int, size: int = 8192) -> bytes:
    chunk = f"{size:x}\r\n".encode() + b" " * size + b"\r\n"
    return chunk * (total // size) + b"0\r\n\r\n"


async def test_api_bounds_while_a_mission_flies(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1, max_api_body_bytes=LIMIT) as fleet:
        mission_id = await fleet.daemon.missions.submit(hover_mission("drone-1", seconds=60.0))
        async with fleet.client(token=False) as anonymous, fleet.client() as operator:
            # token before body: a large POST without a token is refused from its headers
            port = fleet.daemon.http_port
            status = await _raw_post(port, f"Content-Length: {60 << 20}\r\n")
            assert status.startswith(b"HTTP/1.1 401"), status  # answered without one body byte sent
            assert (await anonymous.post("/api/v1/plan", json={})).status_code == 401
            # size: declared too large, and streamed (chunked) past the limit
            declared = await operator.post(
                "/api/v1/missions", content=b"{" * (LIMIT + 1), headers={"content-type": "application/json"}
            )
            assert declared.status_code == 413, (declared.headers, declared.text)
            auth = f"Authorization: Bearer {fleet.daemon.api_token}\r\n"
            streamed = await _raw_post(port, auth + "Transfer-Encoding: chunked\r\n", _chunked(4 * LIMIT))
            assert streamed.startswith(b"HTTP/1.1 413"), streamed  # cut off while reading
            # Host (DNS rebinding) and Origin (a page on another site) are refused, reads included
            rebound = await anonymous.get("/api/v1/agents", headers={"Host": "evil.example:8080"})
            assert rebound.status_code == 403
            foreign = await anonymous.get("/api/v1/agents", headers={"Origin": "https://evil.example"})
            assert foreign.status_code == 403
            own = await anonymous.get("/api/v1/agents", headers={"Origin": fleet.base_url})
            assert own.status_code == 200
            url = fleet.base_url.replace("http", "ws") + "/api/v1/stream"
            with pytest.raises(websockets.exceptions.WebSocketException):
                async with websockets.connect(url, origin="https://evil.example") as ws:  # type: ignore[arg-type]
                    await ws.recv()
            async with websockets.connect(url, origin=fleet.base_url) as ws:  # type: ignore[arg-type]
                assert await ws.recv()
        await _still_flying(fleet, mission_id)
