"""Whole-fleet operator commands (``/api/v1/fleet/{rtl,land,hold,resume}``) and the geofence.

Each command goes to the operator's use cases (gcs/control/operator.py), which ask the vehicle authority;
the route only times it for ``/metrics``.
"""

from __future__ import annotations

import time
from typing import Literal

from fastapi import APIRouter

from gcs.http.deps import TOKEN, Hub, Operator, Ports
from gcs.http.models import Delivered, FleetCommand, FleetCommandResult, GeofenceRequest, GeofenceState
from gcs.http.ports import FleetOperator
from gcs.observe.live import LiveHub

router = APIRouter()


async def _fleet_return(
    operator: FleetOperator, hub: LiveHub, kind: Literal["rtl", "land"], command: FleetCommand | None
) -> FleetCommandResult:
    started = time.perf_counter()
    reason = command.reason if command else "operator"
    delivered, aborted = await operator.bring_down(kind, command.agents if command else None, reason)
    hub.metrics.command_latency.labels(kind).observe(time.perf_counter() - started)
    return FleetCommandResult(command=kind, delivered=delivered, aborted_missions=aborted)


@router.post("/api/v1/fleet/rtl", dependencies=TOKEN)
async def fleet_rtl(operator: Operator, hub: Hub, command: FleetCommand | None = None) -> FleetCommandResult:
    """Take the agents out of their missions and bring every airborne one home (deconflicted)."""
    return await _fleet_return(operator, hub, "rtl", command)


@router.post("/api/v1/fleet/land", dependencies=TOKEN)
async def fleet_land(operator: Operator, hub: Hub, command: FleetCommand | None = None) -> FleetCommandResult:
    """Take the agents out of their missions and land every airborne one where it is (in sequence)."""
    return await _fleet_return(operator, hub, "land", command)


async def _fleet_pause(
    operator: FleetOperator, hub: LiveHub, kind: Literal["hold", "resume"], command: FleetCommand | None
) -> FleetCommandResult:
    started = time.perf_counter()
    agents, reason = (command.agents, command.reason) if command else (None, "operator")
    operate = operator.hold if kind == "hold" else operator.resume
    delivered = await operate(agents, reason)
    hub.metrics.command_latency.labels(kind).observe(time.perf_counter() - started)
    return FleetCommandResult(command=kind, delivered=delivered)


@router.post("/api/v1/fleet/hold", dependencies=TOKEN)
async def fleet_hold(operator: Operator, hub: Hub, command: FleetCommand | None = None) -> FleetCommandResult:
    """Every (or the given) agent stops where it is and keeps its queue (an operator hold)."""
    return await _fleet_pause(operator, hub, "hold", command)


@router.post("/api/v1/fleet/resume", dependencies=TOKEN)
async def fleet_resume(
    operator: Operator, hub: Hub, command: FleetCommand | None = None
) -> FleetCommandResult:
    """Drop the operator's hold; lower sources' holds (collision...) still apply until they clear."""
    return await _fleet_pause(operator, hub, "resume", command)


@router.get("/api/v1/geofence")
async def get_geofence(hub: Hub) -> GeofenceState:
    return GeofenceState(geofence=hub.geofence)


@router.post("/api/v1/geofence", dependencies=TOKEN)
async def geofence(request: GeofenceRequest, ports: Ports) -> Delivered:
    started = time.perf_counter()
    delivered = await ports.set_geofence(request.geofence, request.agents)
    if request.agents is None:
        ports.hub.geofence = request.geofence
    ports.hub.metrics.command_latency.labels("geofence").observe(time.perf_counter() - started)
    return Delivered(delivered=delivered)
