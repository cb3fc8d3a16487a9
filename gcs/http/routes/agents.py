"""``/api/v1/agents``: the fleet list, one agent, retiring a ghost, and who controls a drone."""

from __future__ import annotations

import time

from fastapi import APIRouter

from gcs.agents import AgentSession, RetireRefused
from gcs.authority import VehicleControl
from gcs.http.deps import TOKEN, Agents, ApiProblem, Archive, Authority, Events, Hub, Missions
from gcs.http.models import AgentView, Retired
from gcs.http.ports import AgentDirectory

router = APIRouter()


def agent_view(agents: AgentDirectory, s: AgentSession) -> AgentView:
    return AgentView(
        identity=s.identity,
        cid=s.cid,
        connected=s.open,
        lost=s.identity in agents.lost,
        peer=s.peer,
        capabilities=s.capabilities,
        home=s.home,
        status=s.status,
        status_count=s.status_count,
        link_age_s=round(time.monotonic() - s.last_rx, 3),
        connected_at=s.connected_at,
    )


def fleet_sessions(agents: AgentDirectory) -> list[AgentSession]:
    """This daemon's sessions, and in cluster mode the other daemons' agents (docs/cluster.md)."""
    own = agents.sessions
    return [*own.values(), *(s for i, s in agents.remote.items() if i not in own and s.open)]


@router.get("/api/v1/agents")
async def agents(directory: Agents) -> list[AgentView]:
    return [agent_view(directory, s) for s in sorted(fleet_sessions(directory), key=lambda s: s.cid)]


@router.get("/api/v1/agents/{identity}")
async def agent(identity: str, directory: Agents) -> AgentView:
    session = directory.sessions.get(identity)
    if session is None:
        raise ApiProblem(404, "no such agent", f"agent {identity!r} has never connected")
    return agent_view(directory, session)


@router.delete("/api/v1/agents/{identity}", dependencies=TOKEN)
async def retire(identity: str, directory: Agents, missions: Missions, hub: Hub, events: Events) -> Retired:
    """Take a disconnected agent off the fleet list (a ghost, a drone gone for good).

    Its CID stays reserved in the database, so if it ever comes back it re-joins as before.
    """
    flying = next((m for m, active in missions.active.items() if identity in missions.members(active)), None)
    try:
        session = directory.retire(identity, flying)
    except RetireRefused as exc:
        raise ApiProblem(exc.status, exc.title, exc.detail) from None
    hub.history.pop(identity, None)
    events.publish("agent_retired", f"{identity} (cid {session.cid}) retired", agent=identity)
    return Retired(identity=identity, cid=session.cid)


@router.get("/api/v1/agents/{identity}/authority")
async def agent_authority(
    identity: str, directory: Agents, archive: Archive, authority: Authority
) -> VehicleControl:
    """Who controls this drone now, its holds by owner, and the last command decisions and why."""
    if identity not in directory.sessions and identity not in archive.known_agents():
        raise ApiProblem(404, "unknown agent", f"no agent named {identity!r}")
    return authority.control(identity)
