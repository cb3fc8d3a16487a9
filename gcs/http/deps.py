"""FastAPI dependencies: each route asks for the one port it needs (gcs/http/ports.py), and errors.

The ports live on ``app.state.ports`` (set once by :func:`gcs.http.app.create_app`); the
dependencies take an ``HTTPConnection`` so they serve HTTP routes and the WebSocket alike.
Errors are ``application/problem+json`` with a reason: a route raises :class:`ApiProblem`.
"""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Depends, Header
from fastapi.responses import JSONResponse
from starlette.requests import HTTPConnection

from gcs.http.ports import (
    AgentDirectory,
    ApiPorts,
    ControlView,
    EventLog,
    FleetOperator,
    MissionArchive,
    MissionControl,
    RetaskDesk,
)
from gcs.observe.live import LiveHub


class ApiProblem(Exception):
    def __init__(self, status: int, title: str, detail: str, extra: dict[str, Any] | None = None) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail
        self.extra = extra or {}  # RFC 9457 extension members (e.g. the area a plan could not use)


def problem(status: int, title: str, detail: str, extra: dict[str, Any] | None = None) -> JSONResponse:
    return JSONResponse(
        {**(extra or {}), "type": "about:blank", "title": title, "status": status, "detail": detail},
        status_code=status,
        media_type="application/problem+json",
    )


def ports(conn: HTTPConnection) -> ApiPorts:
    found: ApiPorts = conn.app.state.ports
    return found


def _agents(conn: HTTPConnection) -> AgentDirectory:
    return ports(conn).agents


def _missions(conn: HTTPConnection) -> MissionControl:
    return ports(conn).missions


def _archive(conn: HTTPConnection) -> MissionArchive:
    return ports(conn).archive


def _operator(conn: HTTPConnection) -> FleetOperator:
    return ports(conn).operator


def _authority(conn: HTTPConnection) -> ControlView:
    return ports(conn).authority


def _events(conn: HTTPConnection) -> EventLog:
    return ports(conn).events


def _hub(conn: HTTPConnection) -> LiveHub:
    return ports(conn).hub


def _retask(conn: HTTPConnection) -> RetaskDesk:
    found = ports(conn).retask
    if found is None:
        raise ApiProblem(404, "no re-tasking", "this daemon runs no retask service")
    return found


Ports = Annotated[ApiPorts, Depends(ports)]
Agents = Annotated[AgentDirectory, Depends(_agents)]
Missions = Annotated[MissionControl, Depends(_missions)]
Archive = Annotated[MissionArchive, Depends(_archive)]
Operator = Annotated[FleetOperator, Depends(_operator)]
Authority = Annotated[ControlView, Depends(_authority)]
Events = Annotated[EventLog, Depends(_events)]
Hub = Annotated[LiveHub, Depends(_hub)]
Retask = Annotated[RetaskDesk, Depends(_retask)]


def require_token(conn: HTTPConnection, authorization: str | None = Header(default=None)) -> None:
    """Every mutating call: ``Authorization: Bearer <token>`` (compared in constant time)."""
    expected = f"Bearer {ports(conn).token()}"
    if authorization is None or not hmac.compare_digest(
        authorization.encode("utf-8", "replace"), expected.encode()
    ):
        raise ApiProblem(
            401, "unauthorized", "this call needs 'Authorization: Bearer <token>' (see api.token)"
        )


TOKEN = [Depends(require_token)]
"""``dependencies=TOKEN`` on a route: it needs the API token."""
