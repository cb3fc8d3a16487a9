"""Recorded data: an agent's status history (``/agents/{id}/history``) and the event log (``/events``)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query
from fastapi.responses import Response

from gcs.http.deps import Agents, ApiProblem, Events, Hub
from gcs.observe.events import Event
from gcs.observe.live import StatusSample

router = APIRouter()
MAX_ID = 2**62
MAX_HISTORY_LIMIT = 10_000
"""Samples one history page may return."""
MAX_HISTORY_SCAN = 1_000_000
"""Samples one history request may scan (``limit * every``): bounds its time and memory."""


@router.get("/api/v1/agents/{identity}/history", response_model=list[StatusSample])
async def history(
    identity: str,
    directory: Agents,
    hub: Hub,
    since: Annotated[float, Query(ge=0, le=1e12, description="UNIX time; samples after it")] = 0.0,
    until: Annotated[float | None, Query(ge=0, le=1e12, description="UNIX time; up to it")] = None,
    limit: Annotated[
        int, Query(ge=1, le=MAX_HISTORY_LIMIT, description="the newest n samples of the range")
    ] = 1000,
    every: Annotated[int, Query(ge=1, le=10_000, description="keep every n-th sample")] = 1,
) -> Response:
    """The newest ``limit`` samples in (since, until], oldest first; bounded and read off the loop."""
    if limit * every > MAX_HISTORY_SCAN:
        raise ApiProblem(
            422,
            "history request too large",
            f"limit x every = {limit * every} samples to scan; at most {MAX_HISTORY_SCAN} per request "
            "(lower limit or every, or page back with until)",
        )
    if identity not in directory.sessions and identity not in hub.history:
        raise ApiProblem(404, "no such agent", f"agent {identity!r} has never connected")
    body = await hub.history_json(identity, since, until, limit, every)
    return Response(body, media_type="application/json")


@router.get("/api/v1/events")
async def events(
    log: Events,
    hub: Hub,
    since_id: Annotated[int, Query(ge=0, le=MAX_ID)] = 0,
    kind: Annotated[str | None, Query(max_length=64)] = None,
    agent: Annotated[str | None, Query(max_length=64)] = None,
    mission_id: Annotated[str | None, Query(max_length=64)] = None,
    severity: Literal["info", "warning", "error"] | None = None,
    last: Annotated[int | None, Query(ge=1, le=2000, description="the newest n (from memory)")] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 500,
) -> list[Event]:
    def keep(e: Event) -> bool:
        return (
            e.id > since_id
            and (kind is None or e.kind == kind)
            and (agent is None or e.agent == agent)
            and (mission_id is None or e.mission_id == mission_id)
            and (severity is None or e.severity == severity)
        )

    if last is not None:
        return [e for e in hub.recent_events if keep(e)][-last:][:limit]
    rows = log.history(since_id, kind, agent, limit if not (mission_id or severity) else 10_000)
    return [e for e in rows if keep(e)][:limit]
