"""HTTP/WebSocket API of the daemon and the dashboard's server (FastAPI; schema from pydantic models).

Reads are open on a loopback address and need the token (or the read-only token) on any other;
every mutating call needs ``Authorization: Bearer <token>`` (gcs/http_guard.py). Errors are
``application/problem+json`` with a reason.
``/api/v1/stream`` is a WebSocket of status reports and events (each frame a JSON array of
messages), ``/metrics`` is Prometheus text, ``/`` is the dashboard (static files, no CDN).
See docs/api.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import sqlite3
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from fastapi import Body, Depends, FastAPI, Header, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from gcs.api_models import (
    AgentView,
    Coverage,
    Delivered,
    FleetCommand,
    FleetCommandResult,
    GeofenceRequest,
    GeofenceState,
    Health,
    MissionCreated,
    MissionGeometry,
    MissionSummary,
    Retired,
    UiConfig,
)
from gcs.api_planning import (
    DroneInfo,
    EnergySettings,
    PlanningError,
    PlanPreview,
    PlanRequest,
    plan,
    task_paths,
)
from gcs.authority import VehicleControl
from gcs.events import Event
from gcs.http_guard import HttpGuard
from gcs.live import LiveHub, StatusSample, StreamClient
from gcs.metrics import CONTENT_TYPE
from gcs.missions import MissionProgress, MissionRejected
from protocol.taskfile import TaskFile, TaskFileError, parse_task_document

if TYPE_CHECKING:
    from gcs.agents import AgentSession
    from gcs.daemon import Daemon

log = logging.getLogger("gcs.api")
WEB_DIR = Path(__file__).parent / "web"
PLAN_TIMEOUT_S = 60.0
MAX_ID = 2**62
STREAM_SUBPROTOCOL = "fleetgcs"
"""Chosen when offered (a browser offers it beside ``bearer.<token>``, gcs/http_guard.py)."""
MAX_HISTORY_LIMIT = 10_000
"""Samples one history page may return."""
MAX_HISTORY_SCAN = 1_000_000
"""Samples one history request may scan (``limit * every``): bounds its time and memory."""
TASK_DOCUMENT_SCHEMA: dict[str, Any] = {
    "description": "a fleetgcs task file (object) or a CoUAS task file (array of action rows)",
    "oneOf": [{"$ref": "#/components/schemas/TaskFile"}, {"type": "array", "items": {"type": "object"}}],
}


class ApiProblem(Exception):
    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail


def _problem(status: int, title: str, detail: str) -> JSONResponse:
    return JSONResponse(
        {"type": "about:blank", "title": title, "status": status, "detail": detail},
        status_code=status,
        media_type="application/problem+json",
    )


def _agent_view(daemon: Daemon, s: AgentSession) -> AgentView:
    return AgentView(
        identity=s.identity,
        cid=s.cid,
        connected=s.open,
        lost=s.identity in daemon.agents.lost,
        peer=s.peer,
        capabilities=s.capabilities,
        home=s.home,
        status=s.status,
        status_count=s.status_count,
        link_age_s=round(time.monotonic() - s.last_rx, 3),
        connected_at=s.connected_at,
    )


def _fleet_sessions(daemon: Daemon) -> list[AgentSession]:
    """This daemon's sessions, and in cluster mode the other daemons' agents (docs/cluster.md)."""
    own = daemon.agents.sessions
    return [*own.values(), *(s for i, s in daemon.agents.remote.items() if i not in own and s.open)]


def create_app(daemon: Daemon) -> FastAPI:
    """The API of ``daemon``; installs a :class:`LiveHub` (rings, stream, metrics) on first call."""
    hub = _hub_for(daemon)
    app = FastAPI(
        title="fleetgcs",
        version="0.2.0",
        description="Fleet ground control station API: fleet, missions, planning, stream. See docs/api.md.",
        docs_url=None,  # served below from local Swagger UI files: no CDN, works offline
        redoc_url=None,
    )
    app.state.hub = hub
    app.state.daemon = daemon
    # Host/Origin, token before body, body size while reading (gcs/http_guard.py).
    app.add_middleware(
        HttpGuard,
        token=lambda: daemon.api_token,
        max_body_bytes=daemon.config.max_api_body_bytes,
        listen_host=daemon.config.http_host,
        allowed_hosts=daemon.config.http_allowed_hosts,
        read_token=lambda: daemon.config.api_read_token,
        reads_need_token=True if daemon.config.http_reads_need_token == "always" else None,
    )

    @app.exception_handler(ApiProblem)
    async def _api_problem(_: Request, exc: ApiProblem) -> JSONResponse:
        return _problem(exc.status, exc.title, exc.detail)

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        return _problem(422, "invalid request", f"{where}: {first.get('msg', 'invalid')}")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        return _problem(exc.status_code, str(exc.detail), str(exc.detail))

    @app.exception_handler(Exception)
    async def _crash(_: Request, exc: Exception) -> JSONResponse:  # a bug costs one request, reported
        return _problem(500, "internal error", f"{type(exc).__name__}: {exc}"[:500])

    def require_token(authorization: str | None = Header(default=None)) -> None:
        expected = f"Bearer {daemon.api_token}"
        if authorization is None or not hmac.compare_digest(
            authorization.encode("utf-8", "replace"), expected.encode()
        ):
            raise ApiProblem(
                401, "unauthorized", "this call needs 'Authorization: Bearer <token>' (see api.token)"
            )

    token = [Depends(require_token)]

    # --- fleet --------------------------------------------------------------------------------------

    @app.get("/api/v1/health")
    async def health() -> Health:
        return Health(
            ok=True,
            agents_connected=len(daemon.agents.connected()),
            missions=len(daemon.missions.active),
            server_time=time.time(),
        )

    @app.get("/api/v1/ui-config")
    async def ui_config() -> UiConfig:
        tile_url = "/api/v1/tiles/{z}/{x}/{y}" if mbtiles is not None else daemon.config.tile_url
        return UiConfig(tile_url=tile_url, status_period_s=daemon.config.status_period_s)

    mbtiles = getattr(daemon.config, "tile_mbtiles", None)

    @app.get("/api/v1/tiles/{z}/{x}/{y}", include_in_schema=False)
    async def tile(z: int, x: int, y: int) -> Response:
        """One map tile from the configured MBTiles file (XYZ numbering; MBTiles rows are TMS)."""
        if mbtiles is None:
            raise ApiProblem(404, "no tiles", "no tile_mbtiles file is configured")
        data = await asyncio.to_thread(read_tile, mbtiles, z, x, y)
        if data is None:
            raise ApiProblem(404, "no such tile", f"{z}/{x}/{y} is not in {Path(mbtiles).name}")
        kind = "image/png" if data[:4] == b"\x89PNG" else "image/jpeg"
        if data[:4] == b"RIFF":
            kind = "image/webp"
        return Response(data, media_type=kind, headers={"Cache-Control": "max-age=86400"})

    @app.get("/api/v1/agents")
    async def agents() -> list[AgentView]:
        return [_agent_view(daemon, s) for s in sorted(_fleet_sessions(daemon), key=lambda s: s.cid)]

    @app.get("/api/v1/agents/{identity}")
    async def agent(identity: str) -> AgentView:
        session = daemon.agents.sessions.get(identity)
        if session is None:
            raise ApiProblem(404, "no such agent", f"agent {identity!r} has never connected")
        return _agent_view(daemon, session)

    @app.delete("/api/v1/agents/{identity}", dependencies=token)
    async def retire(identity: str) -> Retired:
        """Take a disconnected agent off the fleet list (a ghost, a drone gone for good).

        Its CID stays reserved in the database, so if it ever comes back it re-joins as before.
        """
        session = daemon.agents.sessions.get(identity)
        if session is None:
            raise ApiProblem(404, "no such agent", f"agent {identity!r} is not on the fleet list")
        if session.open:
            raise ApiProblem(409, "agent connected", f"{identity} is connected: stop its agent first")
        busy = [m for m in daemon.missions.active if identity in _members(m)]
        if busy:
            raise ApiProblem(409, "agent in a mission", f"{identity} flies mission {busy[0]}: abort it first")
        daemon.agents.sessions.pop(identity, None)
        daemon.agents.lost.discard(identity)
        hub.history.pop(identity, None)
        daemon.events.publish("agent_retired", f"{identity} (cid {session.cid}) retired", agent=identity)
        return Retired(identity=identity, cid=session.cid)

    @app.get("/api/v1/agents/{identity}/history", response_model=list[StatusSample])
    async def history(
        identity: str,
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
        if identity not in daemon.agents.sessions and identity not in hub.history:
            raise ApiProblem(404, "no such agent", f"agent {identity!r} has never connected")
        body = await hub.history_json(identity, since, until, limit, every)
        return Response(body, media_type="application/json")

    @app.get("/api/v1/events")
    async def events(
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
        rows = daemon.events.history(since_id, kind, agent, limit if not (mission_id or severity) else 10_000)
        return [e for e in rows if keep(e)][:limit]

    stream_open = [0]  # WebSocket stream connections now (counted before any await: no race)

    @app.websocket("/api/v1/stream")
    async def stream(
        websocket: WebSocket,
        status: bool = True,
        events: bool = True,
        agents: str | None = None,
        max_rate_hz: float = 0.0,
    ) -> None:
        """Push status reports and events; the first frame is a snapshot of the fleet.

        Output only: a client that sends anything is closed (1008). At most
        ``stream_max_clients`` at once (more are refused before the upgrade); each client's
        queue is bounded in bytes (oldest dropped) and a client that does not read for
        ``stream_send_timeout_s`` is closed.
        """
        if stream_open[0] >= daemon.config.stream_max_clients:
            await websocket.close(code=1013, reason="too many stream clients; retry later")
            return
        stream_open[0] += 1
        try:
            await _serve_stream(websocket, status, events, agents, max_rate_hz)
        finally:
            stream_open[0] -= 1

    async def _serve_stream(
        websocket: WebSocket, status: bool, events: bool, agents: str | None, max_rate_hz: float
    ) -> None:
        offered = websocket.scope.get("subprotocols") or []
        await websocket.accept(subprotocol=STREAM_SUBPROTOCOL if STREAM_SUBPROTOCOL in offered else None)
        names = frozenset(a for a in agents.split(",") if a) if agents else None
        rate = max_rate_hz if 0 < max_rate_hz < 1e6 else 0.0
        client = StreamClient(
            status=status,
            events=events,
            agents=names,
            min_interval_s=1.0 / rate if rate else 0.0,
            max_bytes=daemon.config.stream_client_buffer_bytes,
        )
        snapshot = {
            "type": "hello",
            "server_time": time.time(),
            "agents": [_agent_view(daemon, s).model_dump(mode="json") for s in _fleet_sessions(daemon)],
        }
        hub.subscribe(client)
        reader = asyncio.create_task(_refuse_input(websocket))
        timeout = daemon.config.stream_send_timeout_s
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

    @app.get("/metrics", include_in_schema=False)
    async def metrics() -> Response:
        return Response(hub.metrics.render(), media_type=CONTENT_TYPE)

    # --- missions -------------------------------------------------------------------------------------

    @app.get("/api/v1/missions")
    async def missions(
        state: Literal["running", "completed", "aborted"] | None = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    ) -> list[MissionSummary]:
        rows = daemon.store.missions(state)[-limit:][::-1]
        return [
            MissionSummary(
                id=m.id, name=m.name, state=m.state, created=m.created, finished=m.finished, result=m.result
            )
            for m in rows
        ]

    @app.post("/api/v1/missions", status_code=201, dependencies=token)
    async def submit(
        document: Any = Body(..., description=TASK_DOCUMENT_SCHEMA["description"]),  # noqa: B008
    ) -> MissionCreated:
        """Submit a fleetgcs task file or a CoUAS task file (validated against the live fleet)."""
        try:
            task = parse_task_document(document)
        except (TaskFileError, ValueError, TypeError) as exc:
            raise ApiProblem(422, "invalid task file", str(exc)[:1000]) from None
        return MissionCreated(mission_id=await _submit(task))

    async def _submit(task: TaskFile) -> str:
        try:
            return await daemon.missions.submit(task)
        except MissionRejected as exc:
            raise ApiProblem(422, "mission rejected", str(exc)) from None

    @app.post("/api/v1/plan", dependencies=token)
    async def preview(request: Annotated[PlanRequest, Body(discriminator="method")]) -> PlanPreview:
        """Plan without flying: the task file and predicted length, time and energy per drone."""
        return await _plan(request)

    @app.post("/api/v1/missions/plan", status_code=201, dependencies=token)
    async def plan_and_fly(request: Annotated[PlanRequest, Body(discriminator="method")]) -> MissionCreated:
        """Plan, then submit the plan's task file as a mission."""
        planned = await _plan(request)
        mission_id = await _submit(planned.taskfile)
        hub.plans[mission_id] = planned
        return MissionCreated(mission_id=mission_id, plan=planned)

    def _energy_settings() -> EnergySettings:
        """The pre-flight check's estimator, so a preview predicts what the daemon will check."""
        coop = next((s for s in daemon.services if getattr(s, "name", "") == "cooperation"), None)
        model = getattr(coop, "energy_model", None)
        return EnergySettings(daemon.config.cooperation.energy, model if model and model.trained_on else None)

    async def _plan(request: Any) -> PlanPreview:
        infos = _drone_infos(daemon, list(request.drones))
        try:
            energy = _energy_settings()
            return await asyncio.wait_for(asyncio.to_thread(plan, request, infos, energy), PLAN_TIMEOUT_S)
        except PlanningError as exc:
            raise ApiProblem(422, "cannot plan", str(exc)[:1000]) from None
        except TimeoutError:
            raise ApiProblem(
                422, "cannot plan", f"planning took longer than {PLAN_TIMEOUT_S:.0f} s"
            ) from None

    @app.get("/api/v1/missions/{mission_id}")
    async def mission(mission_id: str) -> MissionProgress:
        return _progress(mission_id)

    def _progress(mission_id: str) -> MissionProgress:
        progress = daemon.missions.progress(mission_id)
        if progress is None:
            raise ApiProblem(404, "no such mission", f"mission {mission_id!r} does not exist")
        return progress

    @app.get("/api/v1/missions/{mission_id}/plan")
    async def mission_geometry(mission_id: str) -> MissionGeometry:
        planned = hub.plans.get(mission_id)
        stored = daemon.store.mission(mission_id)
        if stored is None:
            raise ApiProblem(404, "no such mission", f"mission {mission_id!r} does not exist")
        if planned is not None:
            return MissionGeometry(
                mission_id=mission_id,
                paths={d.agent: d.points for d in planned.drones},
                area=planned.area,
                targets=planned.targets,
                swath_m=planned.swath_m,
            )
        return MissionGeometry(
            mission_id=mission_id, paths=task_paths(TaskFile.model_validate_json(stored.task_json))
        )

    @app.get("/api/v1/missions/{mission_id}/coverage")
    async def coverage(mission_id: str) -> Coverage:
        _progress(mission_id)
        planned = hub.plans.get(mission_id)
        tracks = {p.label: hub.track(p.label, mission_id) for p in planned.taskfile.plans} if planned else {}
        samples = sum(len(t) for t in tracks.values())
        if planned is None or planned.area is None or planned.swath_m is None:
            return Coverage(mission_id=mission_id, covered_pct=None, swath_m=None, samples=samples)
        pct = await asyncio.to_thread(_covered_pct, planned.area, list(tracks.values()), planned.swath_m)
        return Coverage(mission_id=mission_id, covered_pct=pct, swath_m=planned.swath_m, samples=samples)

    @app.post("/api/v1/missions/{mission_id}/abort", dependencies=token)
    async def abort(
        mission_id: str,
        then: Annotated[
            Literal["rtl", "hold", "land"],
            Query(description="rtl: fly home, deconflicted (default); hold: stop where they are; land"),
        ] = "rtl",
    ) -> MissionProgress:
        started = time.perf_counter()
        progress = await _mission_command(
            mission_id,
            lambda m: daemon.missions.abort(m, f"aborted by the operator ({then})", "operator", then),
        )
        hub.metrics.command_latency.labels(f"abort_{then}").observe(time.perf_counter() - started)
        return progress

    @app.post("/api/v1/missions/{mission_id}/pause", dependencies=token)
    async def pause(mission_id: str) -> MissionProgress:
        return await _timed("pause", _mission_command(mission_id, daemon.missions.pause))

    @app.post("/api/v1/missions/{mission_id}/resume", dependencies=token)
    async def resume(mission_id: str) -> MissionProgress:
        return await _timed("resume", _mission_command(mission_id, daemon.missions.resume))

    async def _timed(name: str, command: Awaitable[MissionProgress]) -> MissionProgress:
        started = time.perf_counter()
        result = await command
        hub.metrics.command_latency.labels(name).observe(time.perf_counter() - started)
        return result

    def _members(mission_id: str) -> list[str]:
        active = daemon.missions.active.get(mission_id)
        return [a for a in active.plans if a not in active.excluded] if active else []

    async def _mission_command(
        mission_id: str, command: Callable[[str], Awaitable[object]]
    ) -> MissionProgress:
        _progress(mission_id)
        try:
            await command(mission_id)
        except MissionRejected as exc:
            raise ApiProblem(409, "mission not running", str(exc)) from None
        return _progress(mission_id)

    # --- fleet commands -------------------------------------------------------------------------------

    async def _fleet_return(kind: Literal["rtl", "land"], command: FleetCommand | None) -> FleetCommandResult:
        started = time.perf_counter()
        reason = command.reason if command else "operator"
        delivered, aborted = await daemon.operator.bring_down(
            kind, command.agents if command else None, reason
        )
        hub.metrics.command_latency.labels(kind).observe(time.perf_counter() - started)
        return FleetCommandResult(command=kind, delivered=delivered, aborted_missions=aborted)

    @app.post("/api/v1/fleet/rtl", dependencies=token)
    async def fleet_rtl(command: FleetCommand | None = None) -> FleetCommandResult:
        """Take the agents out of their missions and bring every airborne one home (deconflicted)."""
        return await _fleet_return("rtl", command)

    @app.post("/api/v1/fleet/land", dependencies=token)
    async def fleet_land(command: FleetCommand | None = None) -> FleetCommandResult:
        """Take the agents out of their missions and land every airborne one where it is (in sequence)."""
        return await _fleet_return("land", command)

    async def _fleet_pause(
        kind: Literal["hold", "resume"], command: FleetCommand | None
    ) -> FleetCommandResult:
        started = time.perf_counter()
        agents, reason = (command.agents, command.reason) if command else (None, "operator")
        operate = daemon.operator.hold if kind == "hold" else daemon.operator.resume
        delivered = await operate(agents, reason)
        hub.metrics.command_latency.labels(kind).observe(time.perf_counter() - started)
        return FleetCommandResult(command=kind, delivered=delivered)

    @app.post("/api/v1/fleet/hold", dependencies=token)
    async def fleet_hold(command: FleetCommand | None = None) -> FleetCommandResult:
        """Every (or the given) agent stops where it is and keeps its queue (an operator hold)."""
        return await _fleet_pause("hold", command)

    @app.post("/api/v1/fleet/resume", dependencies=token)
    async def fleet_resume(command: FleetCommand | None = None) -> FleetCommandResult:
        """Drop the operator's hold; lower sources' holds (collision...) still apply until they clear."""
        return await _fleet_pause("resume", command)

    @app.get("/api/v1/agents/{identity}/authority")
    async def agent_authority(identity: str) -> VehicleControl:
        """Who controls this drone now, its holds by owner, and the last command decisions and why."""
        if identity not in daemon.agents.sessions and identity not in daemon.store.known_agents():
            raise ApiProblem(404, "unknown agent", f"no agent named {identity!r}")
        return daemon.authority.control(identity)

    @app.get("/api/v1/geofence")
    async def get_geofence() -> GeofenceState:
        return GeofenceState(geofence=hub.geofence)

    @app.post("/api/v1/geofence", dependencies=token)
    async def geofence(request: GeofenceRequest) -> Delivered:
        started = time.perf_counter()
        delivered = await daemon.set_geofence(request.geofence, request.agents)
        if request.agents is None:
            hub.geofence = request.geofence
        hub.metrics.command_latency.labels("geofence").observe(time.perf_counter() - started)
        return Delivered(delivered=delivered)

    # --- dashboard ------------------------------------------------------------------------------------

    @app.get("/", include_in_schema=False)
    async def root() -> RedirectResponse:
        return RedirectResponse("/ui/")

    if WEB_DIR.is_dir():
        app.mount("/ui", StaticFiles(directory=WEB_DIR, html=True), name="ui")
    else:  # an install without package data: say so instead of a silent 404
        log.warning("dashboard files missing (%s): / will answer 503", WEB_DIR)

        @app.get("/ui/", include_in_schema=False)
        async def no_dashboard() -> Response:
            raise ApiProblem(503, "dashboard not installed", f"{WEB_DIR} is missing from this install")

    _mount_docs(app)
    if daemon.cluster is not None:  # whole-fleet routes of a clustered daemon (docs/cluster.md)
        from gcs.cluster.api import cluster_router

        app.include_router(cluster_router(daemon, token))
    return app


def _mount_docs(app: FastAPI) -> None:
    """Swagger UI at /docs from the swagger-ui-bundle package's files, so it works offline."""
    try:
        from swagger_ui_bundle import swagger_ui_path
    except ImportError:
        swagger_ui_path = None
    if swagger_ui_path is None or not Path(str(swagger_ui_path)).is_dir():

        @app.get("/docs", include_in_schema=False)
        async def docs_missing() -> Response:
            return Response(
                "Swagger UI is not installed (pip install swagger-ui-bundle-v2); "
                "the API description is at /openapi.json",
                media_type="text/plain",
            )

        return
    app.mount("/docs-assets", StaticFiles(directory=str(swagger_ui_path)), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def docs() -> Response:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title="fleetgcs API",
            swagger_js_url="/docs-assets/swagger-ui-bundle.js",
            swagger_css_url="/docs-assets/swagger-ui.css",
            swagger_favicon_url="/docs-assets/favicon-32x32.png",
        )


def read_tile(path: Path | str, z: int, x: int, y: int) -> bytes | None:
    """The tile z/x/y (XYZ, as the dashboard asks) of an MBTiles file, or None."""
    if not (0 <= z <= 24 and 0 <= x < 2**z and 0 <= y < 2**z):
        return None
    uri = f"{Path(path).resolve().as_uri()}?mode=ro"
    with contextlib.closing(sqlite3.connect(uri, uri=True)) as db:
        row = db.execute(
            "SELECT tile_data FROM tiles WHERE zoom_level=? AND tile_column=? AND tile_row=?",
            (z, x, (1 << z) - 1 - y),
        ).fetchone()
    return None if row is None else bytes(row[0])


def _hub_for(daemon: Daemon) -> LiveHub:
    """One hub per daemon, registered as a service so ``daemon.stop()`` stops it."""
    for service in daemon.services:
        if isinstance(service, LiveHub):
            return service
    hub = LiveHub(daemon)
    daemon.services.append(hub)
    with contextlib.suppress(RuntimeError):  # no running loop yet: started on first use
        asyncio.get_running_loop().create_task(hub.start())
    return hub


def _drone_infos(daemon: Daemon, names: list[str]) -> list[DroneInfo]:
    """Planner inputs for the named agents, or for every connected agent not busy with a mission."""
    if not names:
        busy = {a for m in daemon.missions.active.values() for a in m.plans if a not in m.excluded}
        names = [
            s.identity
            for s in sorted(daemon.agents.connected(), key=lambda s: s.cid)
            if s.identity not in busy
        ]
    infos = []
    for name in names:
        session = daemon.agents.sessions.get(name)
        if session is None:
            infos.append(DroneInfo(name=name))
            continue
        home = (session.home.lat, session.home.lon) if session.home else None
        if home is None and session.status is not None and session.status.position is not None:
            home = (session.status.position.lat, session.status.position.lon)
        infos.append(
            DroneInfo(name=name, capabilities=session.capabilities, home=home, status=session.status)
        )
    return infos


def _covered_pct(
    area: list[tuple[float, float]], tracks: list[list[tuple[float, float]]], swath: float
) -> float:
    """Percent of ``area`` within swath/2 of the flown tracks (local frame of the area)."""
    import numpy as np
    import shapely
    from shapely.geometry import Polygon

    from gcs.planning.geodesy import LocalFrame

    arr = np.asarray(area)
    frame = LocalFrame.centred_on(arr[:, 0], arr[:, 1])
    poly = Polygon(frame.points_to_local(area)).buffer(0)
    lines = [shapely.linestrings(frame.points_to_local(t)) for t in tracks if len(t) > 1]
    if not lines or poly.area <= 0:
        return 0.0
    seen = shapely.union_all([shapely.buffer(line, swath / 2.0) for line in lines])
    return round(100.0 * poly.intersection(seen).area / poly.area, 2)


async def _refuse_input(websocket: WebSocket) -> None:
    """The stream takes no input: the first message a client sends closes it (1008), so nothing
    it sends is kept; returns when the client left or was closed."""
    with contextlib.suppress(WebSocketDisconnect, RuntimeError, OSError):
        message = await websocket.receive()
        if message.get("type") == "websocket.receive":
            await websocket.close(code=1008, reason="this stream is output only: send nothing")
