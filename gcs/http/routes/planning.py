"""``/api/v1/plan`` (preview without flying) and ``/api/v1/missions/plan`` (plan, then fly it).

The planners themselves are gcs/http/planning_requests.py; here: which drones, the daemon's energy estimator,
and a time bound, with planning run off the event loop.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Body

from gcs.http.deps import TOKEN, ApiProblem, Ports
from gcs.http.models import MissionCreated
from gcs.http.planning_requests import DroneInfo, PlanningError, PlanPreview, PlanRequest, plan
from gcs.http.ports import AgentDirectory, ApiPorts, MissionControl
from gcs.http.routes.missions import submit_task

router = APIRouter()
PLAN_TIMEOUT_S = 60.0


@router.post("/api/v1/plan", dependencies=TOKEN)
async def preview(request: Annotated[PlanRequest, Body(discriminator="method")], ports: Ports) -> PlanPreview:
    """Plan without flying: the task file and predicted length, time and energy per drone."""
    return await _plan(ports, request)


@router.post("/api/v1/missions/plan", status_code=201, dependencies=TOKEN)
async def plan_and_fly(
    request: Annotated[PlanRequest, Body(discriminator="method")], ports: Ports
) -> MissionCreated:
    """Plan, then submit the plan's task file as a mission."""
    planned = await _plan(ports, request)
    mission_id = await submit_task(ports.missions, planned.taskfile)
    ports.hub.plans[mission_id] = planned
    return MissionCreated(mission_id=mission_id, plan=planned)


async def _plan(ports: ApiPorts, request: Any) -> PlanPreview:
    infos = drone_infos(ports.agents, ports.missions, list(request.drones))
    try:
        energy = ports.energy()
        return await asyncio.wait_for(asyncio.to_thread(plan, request, infos, energy), PLAN_TIMEOUT_S)
    except PlanningError as exc:
        raise ApiProblem(422, "cannot plan", str(exc)[:1000], exc.extra) from None
    except TimeoutError:
        raise ApiProblem(422, "cannot plan", f"planning took longer than {PLAN_TIMEOUT_S:.0f} s") from None


def drone_infos(agents: AgentDirectory, missions: MissionControl, names: list[str]) -> list[DroneInfo]:
    """Planner inputs for the named agents, or for every connected agent not busy with a mission."""
    if not names:
        busy = {a for m in missions.active.values() for a in missions.members(m)}
        names = [
            s.identity for s in sorted(agents.connected(), key=lambda s: s.cid) if s.identity not in busy
        ]
    infos = []
    for name in names:
        session = agents.sessions.get(name)
        if session is None:
            infos.append(DroneInfo(name=name))
            continue
        home = (session.home.lat, session.home.lon) if session.home else None
        alt = session.home.alt_amsl if session.home else None
        if home is None and session.status is not None and session.status.position is not None:
            home = (session.status.position.lat, session.status.position.lon)
            alt = session.status.position.alt_amsl - session.status.position.alt_rel
        infos.append(
            DroneInfo(
                name=name,
                capabilities=session.capabilities,
                home=home,
                home_alt_amsl=alt,
                status=session.status,
            )
        )
    return infos
