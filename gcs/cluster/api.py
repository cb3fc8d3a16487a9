"""HTTP routes of a clustered daemon: the whole fleet, and operator commands for any drone.

``GET /api/v1/cluster`` (this daemon, the missions and who leads them, who decides the airspace), ``GET
/api/v1/cluster/fleet`` (every agent of every daemon, with the daemon holding its link) and
``POST /api/v1/cluster/fleet/{hold,resume,rtl,land}``: each drone's command is routed to the daemon
holding its link and applied there through that daemon's vehicle authority; the answer lists the
drones it reached and, per drone, why the others were not (that daemon's refusal).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from gcs.cluster.node import AIRSPACE_LEASE
from gcs.http.models import FleetCommand, FleetCommandResult

if TYPE_CHECKING:
    from gcs.daemon import Daemon


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
    leading: list[str]
    missions: list[ClusterMission]
    takeovers: int
    airspace: str | None  # the daemon deciding collisions for the whole fleet (docs/cluster.md)
    pruned_keys: int


def cluster_router(daemon: Daemon, token: Sequence[Any]) -> APIRouter:
    node = daemon.cluster
    assert node is not None
    router = APIRouter()

    @router.get("/api/v1/cluster")
    async def cluster_info() -> ClusterInfo:
        """This daemon's place in the cluster and who leads each running mission."""
        missions = []
        for stored in node.store.missions():
            leader = None
            if stored.state == "running":
                leader, _ = await node.state.lease_holder(stored.id)
            missions.append(ClusterMission(id=stored.id, name=stored.name, state=stored.state, leader=leader))
        nc = node.state.nc
        airspace, _ = await node.state.lease_holder(AIRSPACE_LEASE)
        return ClusterInfo(
            daemon_id=node.daemon_id,
            servers=node.state.servers,
            connected=bool(nc is not None and nc.is_connected),
            leading=sorted(daemon.missions.active),
            missions=missions,
            takeovers=len(node.takeovers),
            airspace=airspace,
            pruned_keys=node.pruned_keys,
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
