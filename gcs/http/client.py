"""Async Python client of the daemon's HTTP/WebSocket API (httpx + websockets).

    async with FleetClient("http://127.0.0.1:8080", token) as gcs:
        for agent in await gcs.agents():
            print(agent.identity, agent.status.mode if agent.status else "-")
        progress = await gcs.run_mission(task, timeout=600)     # submit and await the end
        async for name, status in gcs.statuses():               # live status reports
            ...

Responses are the API's own pydantic models (gcs.http.models), so a client and the server
cannot drift apart silently. Errors raise :class:`ApiError` with the problem+json reason.
See examples/ and docs/api.md.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import AsyncIterator, Coroutine, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, TypeVar

import httpx
from pydantic import BaseModel, TypeAdapter

from gcs.core.config import default_data_dir
from gcs.http.models import (
    AgentView,
    Delivered,
    FleetCommandResult,
    GeofenceState,
    Health,
    MissionCreated,
    MissionSummary,
    Retired,
)
from gcs.http.planning_requests import PlanPreview, PsaPlanRequest, RsaPlanRequest, SearchPlanRequest
from gcs.missions.report import CoverageReport
from gcs.missions.runner import MissionProgress
from gcs.observe.events import Event
from gcs.observe.live import StatusSample
from protocol.packets import Geofence, StatusReport
from protocol.taskfile import TaskFile

T = TypeVar("T")
TERMINAL = frozenset({"completed", "aborted"})
PlanRequestModel = SearchPlanRequest | PsaPlanRequest | RsaPlanRequest


class ApiError(Exception):
    """The daemon refused a call; ``title`` and ``detail`` come from its problem+json body."""

    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(f"HTTP {status} {title}: {detail}")
        self.status, self.title, self.detail = status, title, detail


class StatusMessage(BaseModel):
    """One status report from the stream, with the daemon's receive time."""

    agent: str
    cid: int
    received: float
    status: StatusReport


def run_script(coroutine: Coroutine[Any, Any, int | None], prog: str) -> int:
    """``asyncio.run(coroutine)`` for scripts: a refusal, an unreachable daemon, a missing token
    file or Ctrl-C end in one line on stderr and an exit code, not a traceback."""
    try:
        return int(asyncio.run(coroutine) or 0)
    except KeyboardInterrupt:
        print(f"\n{prog}: interrupted", file=sys.stderr)
        return 130
    except ApiError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    except httpx.TransportError as exc:
        print(f"{prog}: cannot reach the daemon ({exc or type(exc).__name__})", file=sys.stderr)
        return 3
    except OSError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2


def read_token(data_dir: Path | None = None) -> str:
    """The API token the daemon keeps in DATA_DIR/api.token."""
    return (Path(data_dir or default_data_dir()) / "api.token").read_text().strip()


class FleetClient:
    """One connection pool to one daemon; use it as an async context manager."""

    def __init__(
        self, base_url: str = "http://127.0.0.1:8080", token: str | None = None, timeout: float = 30.0
    ):
        self.base_url = base_url.rstrip("/")
        self.token = token
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.AsyncClient(base_url=self.base_url, headers=headers, timeout=timeout)

    async def __aenter__(self) -> FleetClient:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        await self._http.aclose()

    # --- plumbing ---------------------------------------------------------------------------------

    async def _call(self, method: str, path: str, model: Any, **kwargs: Any) -> Any:
        response = await self._http.request(method, path, **kwargs)
        if response.status_code >= 400:
            try:
                body = response.json()
                raise ApiError(response.status_code, str(body.get("title")), str(body.get("detail")))
            except ValueError:
                raise ApiError(response.status_code, response.reason_phrase, response.text[:500]) from None
        return TypeAdapter(model).validate_python(response.json())

    # --- fleet --------------------------------------------------------------------------------------

    async def health(self) -> Health:
        return await self._call("GET", "/api/v1/health", Health)

    async def agents(self) -> list[AgentView]:
        return await self._call("GET", "/api/v1/agents", list[AgentView])

    async def agent(self, identity: str) -> AgentView:
        return await self._call("GET", f"/api/v1/agents/{identity}", AgentView)

    async def retire(self, identity: str) -> Retired:
        """Take a disconnected agent off the fleet list."""
        return await self._call("DELETE", f"/api/v1/agents/{identity}", Retired)

    async def history(self, identity: str, since: float = 0.0, limit: int = 1000) -> list[StatusSample]:
        return await self._call(
            "GET",
            f"/api/v1/agents/{identity}/history",
            list[StatusSample],
            params={"since": since, "limit": limit},
        )

    async def events(self, **filters: Any) -> list[Event]:
        """Filters: since_id, kind, agent, mission_id, severity, last, limit."""
        params = {k: v for k, v in filters.items() if v is not None}
        return await self._call("GET", "/api/v1/events", list[Event], params=params)

    async def stream(
        self,
        status: bool = True,
        events: bool = True,
        agents: Sequence[str] | None = None,
        max_rate_hz: float = 0.0,
        coverage: bool = True,
    ) -> AsyncIterator[StatusMessage | Event | dict[str, Any]]:
        """Live messages: :class:`StatusMessage`, :class:`Event`, or a dict: the first ``hello``
        snapshot, a survey's ``coverage`` (docs/api.md)."""
        import websockets

        query = (
            f"status={str(status).lower()}&events={str(events).lower()}&max_rate_hz={max_rate_hz}"
            f"&coverage={str(coverage).lower()}"
        )
        if agents:
            query += "&agents=" + ",".join(agents)
        url = self.base_url.replace("http", "ws", 1) + "/api/v1/stream?" + query
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None  # reads beyond loopback
        async with websockets.connect(url, max_size=None, additional_headers=headers) as ws:
            async for frame in ws:
                for message in json.loads(frame):
                    kind = message.get("type")
                    if kind == "status":
                        yield StatusMessage.model_validate(message)
                    elif kind == "event":
                        yield Event.model_validate(message["event"])
                    else:
                        yield message

    async def statuses(
        self, agents: Sequence[str] | None = None, max_rate_hz: float = 0.0
    ) -> AsyncIterator[tuple[str, StatusReport]]:
        """(agent, status) for every status report, as they arrive."""
        async for message in self.stream(status=True, events=False, agents=agents, max_rate_hz=max_rate_hz):
            if isinstance(message, StatusMessage):
                yield message.agent, message.status

    # --- missions -----------------------------------------------------------------------------------

    async def submit(self, task: TaskFile | dict[str, Any] | list[Any]) -> str:
        """Submit a task file (fleetgcs model or document, or CoUAS rows); returns the mission id."""
        body = task.model_dump(mode="json") if isinstance(task, TaskFile) else task
        # The daemon may wait (fix_wait_s, default 60 s) for every agent's first 3-D fix.
        wait = task.fix_wait_s if isinstance(task, TaskFile) else 60.0
        created = await self._call("POST", "/api/v1/missions", MissionCreated, json=body, timeout=wait + 30.0)
        return str(created.mission_id)

    async def plan(self, request: PlanRequestModel | dict[str, Any]) -> PlanPreview:
        """Preview a plan (search / psa / rsa) without flying it."""
        return await self._call("POST", "/api/v1/plan", PlanPreview, json=_dump(request))

    async def submit_plan(self, request: PlanRequestModel | dict[str, Any]) -> MissionCreated:
        """Plan and fly; the answer holds the mission id and the plan."""
        return await self._call("POST", "/api/v1/missions/plan", MissionCreated, json=_dump(request))

    async def missions(self, state: str | None = None) -> list[MissionSummary]:
        params = {"state": state} if state else {}
        return await self._call("GET", "/api/v1/missions", list[MissionSummary], params=params)

    async def mission(self, mission_id: str) -> MissionProgress:
        return await self._call("GET", f"/api/v1/missions/{mission_id}", MissionProgress)

    async def wait_mission(
        self, mission_id: str, timeout: float = 3600.0, poll_s: float = 0.5
    ) -> MissionProgress:
        """Poll until the mission completes or is aborted; TimeoutError after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            progress = await self.mission(mission_id)
            if progress.state in TERMINAL:
                return progress
            if time.monotonic() > deadline:
                raise TimeoutError(f"mission {mission_id} still {progress.state} after {timeout:.0f} s")
            await asyncio.sleep(poll_s)

    async def run_mission(
        self, task: TaskFile | dict[str, Any] | list[Any], timeout: float = 3600.0
    ) -> MissionProgress:
        """Submit and await the end."""
        return await self.wait_mission(await self.submit(task), timeout)

    async def pause(self, mission_id: str) -> MissionProgress:
        return await self._call("POST", f"/api/v1/missions/{mission_id}/pause", MissionProgress)

    async def resume(self, mission_id: str) -> MissionProgress:
        return await self._call("POST", f"/api/v1/missions/{mission_id}/resume", MissionProgress)

    async def abort(self, mission_id: str, then: Literal["rtl", "hold"] = "rtl") -> MissionProgress:
        return await self._call(
            "POST", f"/api/v1/missions/{mission_id}/abort", MissionProgress, params={"then": then}
        )

    async def retask_proposals(self, mission_id: str) -> list[dict[str, Any]]:
        """The mission's re-task decisions (gcs/missions/retask.py), pending ones included."""
        return await self._call("GET", f"/api/v1/missions/{mission_id}/retask", list[dict[str, Any]])

    async def retask(
        self, mission_id: str, answer: Literal["accept", "reject"], decision: str = "latest"
    ) -> dict[str, Any]:
        """Accept or reject a pending re-task proposal (``latest``: the newest pending one)."""
        path = f"/api/v1/missions/{mission_id}/retask/{decision}/{answer}"
        return await self._call("POST", path, dict[str, Any])

    async def report(self, mission_id: str) -> CoverageReport:
        """A survey mission's coverage report: coverage %, missed area, planned vs flown, re-tasks."""
        return await self._call("GET", f"/api/v1/missions/{mission_id}/report", CoverageReport)

    # --- fleet commands -----------------------------------------------------------------------------

    async def command_fleet(
        self,
        command: Literal["rtl", "land", "hold", "resume"],
        agents: Sequence[str] | None = None,
        reason: str = "client",
    ) -> FleetCommandResult:
        body = {"agents": list(agents) if agents is not None else None, "reason": reason}
        return await self._call("POST", f"/api/v1/fleet/{command}", FleetCommandResult, json=body)

    async def rtl_all(self, agents: Sequence[str] | None = None) -> FleetCommandResult:
        return await self.command_fleet("rtl", agents)

    async def land_all(self, agents: Sequence[str] | None = None) -> FleetCommandResult:
        return await self.command_fleet("land", agents)

    async def hold_all(self, agents: Sequence[str] | None = None) -> FleetCommandResult:
        return await self.command_fleet("hold", agents)

    async def resume_all(self, agents: Sequence[str] | None = None) -> FleetCommandResult:
        return await self.command_fleet("resume", agents)

    async def set_geofence(self, geofence: Geofence | None, agents: Sequence[str] | None = None) -> list[str]:
        body = {
            "geofence": geofence.model_dump(mode="json") if geofence else None,
            "agents": list(agents) if agents is not None else None,
        }
        delivered = await self._call("POST", "/api/v1/geofence", Delivered, json=body)
        return list(delivered.delivered)

    async def geofence(self) -> Geofence | None:
        state = await self._call("GET", "/api/v1/geofence", GeofenceState)
        return state.geofence


def _dump(request: BaseModel | dict[str, Any]) -> dict[str, Any]:
    return request.model_dump(mode="json") if isinstance(request, BaseModel) else request
