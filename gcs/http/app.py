"""The daemon's HTTP/WebSocket API and the dashboard's server: one FastAPI app composed of routers.

Reads are open on a loopback address and need the token (or the read-only token) on any other;
every mutating call needs ``Authorization: Bearer <token>`` (gcs/http/guard.py). Errors are
``application/problem+json`` with a reason. Each resource is one ``APIRouter`` in gcs/http/routes/;
routes reach the daemon only through the ports of gcs/http/ports.py (FastAPI dependencies).
See docs/api.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import fastapi.routing
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute

from gcs.http.deps import TOKEN, ApiProblem, problem
from gcs.http.guard import HttpGuard
from gcs.http.ports import ApiPorts
from gcs.http.routes import agents, dashboard, fleet, history, missions, planning, stream
from protocol.settings_file import package_version

if TYPE_CHECKING:
    from gcs.core.context import DaemonParts
    from gcs.observe.live import LiveHub

ROUTERS = (
    dashboard.router,
    agents.router,
    history.router,
    stream.router,
    missions.router,
    planning.router,
    fleet.router,
)
"""Included in this order (the order of the OpenAPI document's paths)."""


def create_app(daemon: DaemonParts, hub: LiveHub | None = None) -> FastAPI:
    """The API of ``daemon``, over ``hub`` (default: the daemon's own, :meth:`Daemon.live_hub`)."""
    app = FastAPI(
        title="fleetgcs",
        version=package_version(),  # the package's, as `gcs --version` says
        description="Fleet ground control station API: fleet, missions, planning, stream. See docs/api.md.",
        docs_url=None,  # served by dashboard.mount_dashboard from local Swagger UI files: no CDN
        redoc_url=None,
    )
    ports = ApiPorts.of(daemon, hub if hub is not None else daemon.live_hub())
    app.state.ports = ports
    app.state.hub = ports.hub
    if ports.hub.coverage_source is None:  # the stream's coverage messages (gcs/missions/live_coverage.py)
        from gcs.missions.live_coverage import CoverageFeed

        ports.hub.coverage_source = CoverageFeed(daemon)
    app.state.stream_slots = stream.StreamSlots()
    config = daemon.config
    # Host/Origin, token before body, body size while reading (gcs/http/guard.py).
    app.add_middleware(
        HttpGuard,
        token=ports.token,
        max_body_bytes=config.max_api_body_bytes,
        listen_host=config.http_host,
        allowed_hosts=config.http_allowed_hosts,
        read_token=lambda: ports.config().api_read_token,
        reads_need_token=True if config.http_reads_need_token == "always" else None,
    )
    _install_problem_handlers(app)
    for router in ROUTERS:
        app.include_router(router)
    dashboard.mount_dashboard(app)
    if daemon.cluster is not None:  # whole-fleet routes of a clustered daemon (docs/cluster.md)
        from gcs.cluster.api import cluster_router

        app.include_router(cluster_router(daemon, TOKEN))
    return app


def _install_problem_handlers(app: FastAPI) -> None:
    """Every error as ``application/problem+json``; a bug costs one request, reported (500)."""

    @app.exception_handler(ApiProblem)
    async def _api_problem(_: Request, exc: ApiProblem) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, exc.extra)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        return problem(422, "invalid request", f"{where}: {first.get('msg', 'invalid')}")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        return problem(exc.status_code, str(exc.detail), str(exc.detail))

    @app.exception_handler(Exception)
    async def _crash(_: Request, exc: Exception) -> JSONResponse:
        return problem(500, "internal error", f"{type(exc).__name__}: {exc}"[:500])


def flat_routes(app: FastAPI) -> list[BaseRoute]:
    """Every route of ``app``, those of included routers too (FastAPI >= 0.13x keeps an included
    router as one entry of ``app.routes``; older versions copy its routes there)."""
    contexts = getattr(fastapi.routing, "iter_route_contexts", None)
    if contexts is None:
        return list(app.routes)
    return [context.original_route for context in contexts(app.routes)]
