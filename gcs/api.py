"""HTTP API of the daemon (FastAPI: the OpenAPI schema comes from the same pydantic models).

Reads are open on the configured (default loopback) address; every mutating call needs
``Authorization: Bearer <token>``. Errors are ``application/problem+json`` with a reason.
"""

from __future__ import annotations

import hmac
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from fastapi import Body, Depends, FastAPI, Header, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from gcs.events import Event
from gcs.missions import MissionProgress, MissionRejected
from protocol.packets import Capabilities, Geofence, GeoPoint, StatusReport
from protocol.taskfile import TaskFileError, parse_task_document

if TYPE_CHECKING:
    from gcs.daemon import Daemon


class ApiProblem(Exception):
    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail


class AgentView(BaseModel):
    identity: str
    cid: int
    connected: bool
    lost: bool
    peer: str
    capabilities: Capabilities
    home: GeoPoint | None
    status: StatusReport | None
    status_count: int


class MissionCreated(BaseModel):
    mission_id: str


class GeofenceRequest(BaseModel):
    geofence: Geofence | None = None
    agents: list[str] | None = None


class Delivered(BaseModel):
    delivered: list[str]


def _problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse(
        {"type": "about:blank", "title": title, "status": status, "detail": detail},
        status_code=status,
        media_type="application/problem+json",
    )


def create_app(daemon: Daemon) -> FastAPI:
    app = FastAPI(title="fleetgcs", version="0.1.0", description="Fleet ground control station API")

    @app.exception_handler(ApiProblem)
    async def _api_problem(_: Request, exc: ApiProblem) -> JSONResponse:
        return _problem(exc.status, exc.title, exc.detail)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        return _problem(422, "invalid request", f"{where}: {first.get('msg', 'invalid')}")

    def require_token(authorization: str | None = Header(default=None)) -> None:
        expected = f"Bearer {daemon.api_token}"
        if authorization is None or not hmac.compare_digest(authorization.encode(), expected.encode()):
            raise ApiProblem(
                401, "unauthorized", "this call needs 'Authorization: Bearer <token>' (see api.token)"
            )

    @app.get("/api/v1/health")
    async def health() -> dict[str, Any]:
        return {
            "ok": True,
            "agents_connected": len(daemon.agents.connected()),
            "missions": len(daemon.missions.active),
        }

    @app.get("/api/v1/agents")
    async def agents() -> list[AgentView]:
        return [
            AgentView(
                identity=s.identity,
                cid=s.cid,
                connected=s.open,
                lost=s.identity in daemon.agents.lost,
                peer=s.peer,
                capabilities=s.capabilities,
                home=s.home,
                status=s.status,
                status_count=s.status_count,
            )
            for s in sorted(daemon.agents.sessions.values(), key=lambda s: s.cid)
        ]

    @app.get("/api/v1/events")
    async def events(
        since_id: int = 0, kind: str | None = None, agent: str | None = None, limit: int = 500
    ) -> list[Event]:
        return daemon.events.history(since_id, kind, agent, limit)

    @app.post("/api/v1/missions", status_code=201, dependencies=[Depends(require_token)])
    async def submit(document: Any = Body(...)) -> MissionCreated:  # noqa: B008 - FastAPI idiom
        try:
            task = parse_task_document(document)
            mission_id = await daemon.missions.submit(task)
        except (TaskFileError, MissionRejected) as exc:
            raise ApiProblem(422, "mission rejected", str(exc)) from None
        return MissionCreated(mission_id=mission_id)

    @app.get("/api/v1/missions/{mission_id}")
    async def mission(mission_id: str) -> MissionProgress:
        progress = daemon.missions.progress(mission_id)
        if progress is None:
            raise ApiProblem(404, "no such mission", f"mission {mission_id!r} does not exist")
        return progress

    @app.post("/api/v1/missions/{mission_id}/abort", dependencies=[Depends(require_token)])
    async def abort(mission_id: str) -> MissionProgress:
        return await _mission_command(
            mission_id, lambda m: daemon.missions.abort(m, "aborted by the operator")
        )

    @app.post("/api/v1/missions/{mission_id}/pause", dependencies=[Depends(require_token)])
    async def pause(mission_id: str) -> MissionProgress:
        return await _mission_command(mission_id, daemon.missions.pause)

    @app.post("/api/v1/missions/{mission_id}/resume", dependencies=[Depends(require_token)])
    async def resume(mission_id: str) -> MissionProgress:
        return await _mission_command(mission_id, daemon.missions.resume)

    async def _mission_command(mission_id: str, command: Callable[[str], Awaitable[None]]) -> MissionProgress:
        try:
            await command(mission_id)
        except MissionRejected as exc:
            raise ApiProblem(409, "mission not running", str(exc)) from None
        progress = daemon.missions.progress(mission_id)
        assert progress is not None
        return progress

    @app.post("/api/v1/geofence", dependencies=[Depends(require_token)])
    async def geofence(request: GeofenceRequest) -> Delivered:
        return Delivered(delivered=await daemon.set_geofence(request.geofence, request.agents))

    return app
