"""``/api/v1/stream`` (WebSocket of status reports and events) and ``/metrics`` (Prometheus text)."""

from __future__ import annotations

import asyncio
import contextlib
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from fastapi.responses import Response

from gcs.http.deps import Hub, Ports
from gcs.http.ports import AgentDirectory
from gcs.http.routes.agents import agent_view, fleet_sessions
from gcs.observe.live import LiveHub, StreamClient
from gcs.observe.metrics import CONTENT_TYPE

router = APIRouter()
STREAM_SUBPROTOCOL = "fleetgcs"
"""Chosen when offered (a browser offers it beside ``bearer.<token>``, gcs/http/guard.py)."""


class StreamSlots:
    """WebSocket stream connections now, counted before any await (no race); one per app."""

    def __init__(self) -> None:
        self.open = 0


@router.websocket("/api/v1/stream")
async def stream(
    websocket: WebSocket,
    ports: Ports,
    status: bool = True,
    events: bool = True,
    agents: str | None = None,
    max_rate_hz: float = 0.0,
    coverage: bool = True,
) -> None:
    """Push status reports, events and survey coverage (at most once a second per mission); the
    first frame is a snapshot of the fleet.

    Output only: a client that sends anything is closed (1008). At most
    ``stream_max_clients`` at once (more are refused before the upgrade); each client's
    queue is bounded in bytes (oldest dropped) and a client that does not read for
    ``stream_send_timeout_s`` is closed.
    """
    slots: StreamSlots = websocket.app.state.stream_slots
    if slots.open >= ports.config().stream_max_clients:
        await websocket.close(code=1013, reason="too many stream clients; retry later")
        return
    slots.open += 1
    try:
        await _serve_stream(
            websocket, ports.agents, ports.hub, (status, events, coverage), agents, max_rate_hz
        )
    finally:
        slots.open -= 1


async def _serve_stream(
    websocket: WebSocket,
    directory: AgentDirectory,
    hub: LiveHub,
    wants: tuple[bool, bool, bool],
    agents: str | None,
    max_rate_hz: float,
) -> None:
    config = websocket.app.state.ports.config()
    offered = websocket.scope.get("subprotocols") or []
    await websocket.accept(subprotocol=STREAM_SUBPROTOCOL if STREAM_SUBPROTOCOL in offered else None)
    names = frozenset(a for a in agents.split(",") if a) if agents else None
    rate = max_rate_hz if 0 < max_rate_hz < 1e6 else 0.0
    client = StreamClient(
        status=wants[0],
        events=wants[1],
        coverage=wants[2],
        agents=names,
        min_interval_s=1.0 / rate if rate else 0.0,
        max_bytes=config.stream_client_buffer_bytes,
    )
    snapshot = {
        "type": "hello",
        "server_time": time.time(),
        "agents": [agent_view(directory, s).model_dump(mode="json") for s in fleet_sessions(directory)],
    }
    hub.subscribe(client)
    reader = asyncio.create_task(_refuse_input(websocket))
    timeout = config.stream_send_timeout_s
    try:
        async with asyncio.timeout(timeout):
            await websocket.send_json([snapshot])
        while not reader.done():
            batch = asyncio.create_task(client.next_batch())
            await asyncio.wait({batch, reader}, return_when=asyncio.FIRST_COMPLETED)
            if not batch.done():
                batch.cancel()
                break
            async with asyncio.timeout(timeout):  # a client that does not read is closed
                await websocket.send_text(batch.result())
    except (WebSocketDisconnect, RuntimeError, OSError, TimeoutError):
        pass
    finally:
        hub.unsubscribe(client)
        reader.cancel()
        with contextlib.suppress(BaseException):
            await reader
        with contextlib.suppress(Exception):  # already closed by either side: nothing to do
            async with asyncio.timeout(1.0):  # a peer that reads nothing gets no longer
                await websocket.close()


async def _refuse_input(websocket: WebSocket) -> None:
    """The stream takes no input: the first message a client sends closes it (1008), so nothing
    it sends is kept; returns when the client left or was closed."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError, OSError):
        message = await websocket.receive()
        if message.get("type") == "websocket.receive":
            await websocket.close(code=1008, reason="this stream is output only: send nothing")


@router.get("/metrics", include_in_schema=False)
async def metrics(hub: Hub) -> Response:
    return Response(hub.metrics.render(), media_type=CONTENT_TYPE)
