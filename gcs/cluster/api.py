"""HTTP routes of a clustered daemon: the whole fleet, and operator commands for any drone.

``GET /api/v1/cluster`` (this daemon, the missions and who leads them, who decides the airspace), ``GET
/api/v1/cluster/fleet`` (every agent of every daemon, with the daemon holding its link) and
``POST /api/v1/cluster/fleet/{hold,resume,rtl,land}``: each drone's command is routed to the daemon
holding its link and applied there through that daemon's vehicle authority; the answer lists the
drones it reached and, per drone, why the others were not (that daemon's refusal).
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from gcs.cluster.node import AIRSPACE_LEASE
from gcs.http.models import FleetCommand, FleetCommandResult

if TYPE_CHECKING:
    from gcs.core.context import DaemonParts


LEASE_LOOKUP_S = 1.0


def public_url(url: str) -> str:
    """A NATS URL without its credentials (``nats://user:secret@host:4222`` -> ``nats://host:4222``)."""
    scheme, sep, rest = url.partition("://")
    return f"{scheme}{sep}{rest.rpartition('@')[2]}" if sep else url


def _url(parsed: Any) -> str | None:
    """nats://host:port of nats-py's parsed server address."""
    return None if parsed is None else f"nats://{parsed.hostname}:{parsed.port}"


class ClusterMission(BaseModel):
    id: str
    name: str
    state: str
    leader: str | None


class ClusterCommandResult(FleetCommandResult):
    """The local fleet routes' answer, plus why each drone not reached was not (per drone)."""

    refused: dict[str, str] = Field(default_factory=dict)


class ClusterInfo(BaseModel):
    daemon_id: str
    servers: list[str]
    connected: bool
    connected_url: str | None  # the NATS server this daemon's connection is on now
    leading: list[str]  # missions led here and deciding now (lease good by our clock)
    suspended: list[str]  # led here, lease out by our clock (NATS slow): deciding nothing now
    missions: list[ClusterMission]
    takeovers: int
    airspace: str | None  # the daemon deciding collisions for the whole fleet (docs/cluster.md)
    pruned_keys: int
    step_downs: int  # missions this daemon stopped leading because its lease ran out by its clock
    fenced_writes: int  # its writes refused: a newer leader's token was on the mission record
    fenced_orders: int  # orders forwarded to it refused: sent under an older lease token


def cluster_router(daemon: DaemonParts, token: Sequence[Any]) -> APIRouter:
    node = daemon.cluster
    assert node is not None
    router = APIRouter()

    async def holder(name: str) -> str | None:
        """The lease holder, or None when NATS does not answer within LEASE_LOOKUP_S (a node
        failing over, quorum lost): the answer stays quick and never a 500."""
        try:
            found, _ = await asyncio.wait_for(node.state.lease_holder(name), LEASE_LOOKUP_S)
        except Exception:  # NATS away or re-electing: unknown, not an error
            return None
        return found

    @router.get("/api/v1/cluster")
    async def cluster_info() -> ClusterInfo:
        """This daemon's place in the cluster and who leads each running mission."""
        leases = node.state.leases  # who decides now, read before any look-up awaits
        leading = sorted(m for m in daemon.missions.active if leases.valid(m) or m in leases.pending)
        suspended = sorted(set(daemon.missions.active) - set(leading))
        missions = []
        for stored in node.store.missions():
            leader = None
            if stored.state == "running":
                leader = await holder(stored.id)
            missions.append(ClusterMission(id=stored.id, name=stored.name, state=stored.state, leader=leader))
        nc = node.state.nc
        airspace = await holder(AIRSPACE_LEASE)
        return ClusterInfo(
            daemon_id=node.daemon_id,
            servers=[public_url(url) for url in node.state.servers],  # never a password
            connected=bool(nc is not None and nc.is_connected),
            connected_url=_url(nc.connected_url) if nc is not None and nc.is_connected else None,
            leading=leading,
            suspended=suspended,
            missions=missions,
            takeovers=len(node.leadership.takeovers),
            airspace=airspace,
            pruned_keys=node.pruned_keys,
            step_downs=node.leadership.step_downs,
            fenced_writes=node.state.leases.refused,
            fenced_orders=node.forwarder.fenced_orders,
        )

    @router.get("/api/v1/cluster/fleet")
    async def cluster_fleet() -> list[dict[str, Any]]:
        """Every agent the cluster knows, with the daemon holding its link and its last status."""
        return node.fleet()

    async def _command(
        kind: Literal["hold", "resume", "rtl", "land"], command: FleetCommand | None
    ) -> ClusterCommandResult:
        agents, reason = (command.agents, command.reason) if command else (None, "operator")
        delivered, refused = await node.command(kind, agents, reason)
        return ClusterCommandResult(command=kind, delivered=delivered, refused=refused)

    @router.post("/api/v1/cluster/fleet/hold", dependencies=list(token))
    async def cluster_hold(command: FleetCommand | None = None) -> ClusterCommandResult:
        return await _command("hold", command)

    @router.post("/api/v1/cluster/fleet/resume", dependencies=list(token))
    async def cluster_resume(command: FleetCommand | None = None) -> ClusterCommandResult:
        return await _command("resume", command)

    @router.post("/api/v1/cluster/fleet/rtl", dependencies=list(token))
    async def cluster_rtl(command: FleetCommand | None = None) -> ClusterCommandResult:
        return await _command("rtl", command)

    @router.post("/api/v1/cluster/fleet/land", dependencies=list(token))
    async def cluster_land(command: FleetCommand | None = None) -> ClusterCommandResult:
        return await _command("land", command)

    return router
