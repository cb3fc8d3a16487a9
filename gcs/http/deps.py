"""FastAPI dependencies: each route asks for the one port it needs (gcs/http/ports.py), and errors.

The ports live on ``app.state.ports`` (set once by :func:`gcs.http.app.create_app`); the
dependencies take an ``HTTPConnection`` so they serve HTTP routes and the WebSocket alike.
Errors are ``application/problem+json`` with a reason: a route raises :class:`ApiProblem`.
"""

from __future__ import annotations

import hmac
from typing import Annotated

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
)
from gcs.live import LiveHub


class ApiProblem(Exception):
    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail


def problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse(
        {"type": "about:blank", "title": title, "status": status, "detail": detail},
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


Ports = Annotated[ApiPorts, Depends(ports)]
Agents = Annotated[AgentDirectory, Depends(_agents)]
Missions = Annotated[MissionControl, Depends(_missions)]
Archive = Annotated[MissionArchive, Depends(_archive)]
Operator = Annotated[FleetOperator, Depends(_operator)]
Authority = Annotated[ControlView, Depends(_authority)]
Events = Annotated[EventLog, Depends(_events)]
Hub = Annotated[LiveHub, Depends(_hub)]


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
