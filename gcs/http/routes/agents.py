"""``/api/v1/agents``: the fleet list, one agent, retiring a ghost, and who controls a drone."""

from __future__ import annotations

import time

from fastapi import APIRouter

from gcs.control.authority import VehicleControl
from gcs.http.deps import TOKEN, Agents, ApiProblem, Archive, Authority, Events, Hub, Missions
from gcs.http.models import AgentView, Retired
from gcs.http.ports import AgentDirectory, ControlView
from gcs.link.session import AgentSession
from gcs.link.sessions import RetireRefused

router = APIRouter()


def held(authority: ControlView | None, identity: str) -> str | None:
    """``operator: fleet hold: dashboard``: who holds the drone and why, or None."""
    holds = authority.control(identity).holds if authority is not None else {}
    return "; ".join(f"{owner}: {why}" for owner, why in sorted(holds.items())) or None


def agent_view(agents: AgentDirectory, s: AgentSession, authority: ControlView | None = None) -> AgentView:
    return AgentView(
        identity=s.identity,
        cid=s.cid,
        connected=s.open,
        lost=s.identity in agents.lost and agents.sessions.get(s.identity) is s,
        peer=s.peer,
        capabilities=s.capabilities,
        home=s.home,
        status=s.status,
        status_count=s.status_count,
        link_age_s=round(time.monotonic() - s.last_rx, 3),
        connected_at=s.connected_at,
        held=held(authority, s.identity),
        daemon=agents.holder(s.identity),
    )


def link_session(agents: AgentDirectory, identity: str) -> AgentSession | None:
    """Where ``identity``'s link is, the one answer every view gives (:meth:`SessionRegistry.link`)."""
    return agents.link(identity)


def fleet_sessions(agents: AgentDirectory) -> list[AgentSession]:
    """This daemon's sessions, and in cluster mode the other daemons' agents (docs/cluster.md),
    each agent once, where its link is (:meth:`SessionRegistry.fleet`)."""
    return agents.fleet()


@router.get("/api/v1/agents")
async def agents(directory: Agents, authority: Authority) -> list[AgentView]:
    return [
        agent_view(directory, s, authority) for s in sorted(fleet_sessions(directory), key=lambda s: s.cid)
    ]


@router.get("/api/v1/agents/{identity}")
async def agent(identity: str, directory: Agents, authority: Authority) -> AgentView:
    session = link_session(directory, identity)
    if session is None:
        raise ApiProblem(404, "no such agent", f"agent {identity!r} has never connected")
    return agent_view(directory, session, authority)


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
