"""Pydantic models of the HTTP API, shared by the server (``gcs.http``), the client (``gcs.http.client``)
and the OpenAPI schema, so the three never disagree."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from gcs.http.planning_requests import PlanPreview
from protocol.packets import Capabilities, Geofence, GeoPoint, StatusReport

AgentName = str


class AgentView(BaseModel):
    """One agent as the daemon sees it: session, capabilities and latest status."""

    identity: str
    cid: int
    connected: bool
    lost: bool
    peer: str
    capabilities: Capabilities
    home: GeoPoint | None
    status: StatusReport | None
    status_count: int
    link_age_s: float | None = Field(default=None, description="seconds since the last packet from it")
    connected_at: float | None = None
    held: str | None = Field(
        default=None, description="why it is held: each holding source and its reason (None: not held)"
    )
    daemon: str | None = Field(
        default=None,
        description="cluster mode: the daemon holding its link now (the registry's newest epoch); "
        "None on a single daemon",
    )


class MissionCreated(BaseModel):
    mission_id: str
    plan: PlanPreview | None = None


class MissionSummary(BaseModel):
    id: str
    name: str
    state: str
    created: float
    finished: float | None
    result: str | None


class MissionGeometry(BaseModel):
    """What the map draws for a mission: each agent's planned points, and the area if planned."""

    mission_id: str
    paths: dict[str, list[tuple[float, float]]]
    area: list[tuple[float, float]] | None = None
    targets: list[tuple[float, float]] | None = None
    swath_m: float | None = None


class Coverage(BaseModel):
    """What the fleet has seen of a survey mission's area, from its flown tracks (eq. 5 footprint).

    ``grid``: text rows north first, ``#`` seen, ``.`` unseen, space outside (``?detail=grid``);
    ``unseen``: the unseen cells as a GeoJSON MultiPolygon (``?detail=geojson``).
    """

    mission_id: str
    covered_pct: float | None
    swath_m: float | None
    samples: int
    area_m2: float | None = None
    seen_m2: float | None = None
    cell_m: float | None = None
    grid: list[str] | None = None
    unseen: dict[str, Any] | None = None
    flown_m: float | None = Field(default=None, description="horizontal metres flown by the members")
    planned_m: float | None = Field(default=None, description="horizontal metres of their final plans")
    eta_s: float | None = Field(
        default=None, description="the slowest drone still flying: metres left at its current speed"
    )
    drones: list[dict[str, Any]] | None = Field(
        default=None, description="per drone: planned_m, flown_m, remaining_m, speed_mps, state"
    )


class GeofenceRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    geofence: Geofence | None = None
    agents: list[str] | None = Field(default=None, max_length=1000)


class GeofenceState(BaseModel):
    geofence: Geofence | None


class Delivered(BaseModel):
    delivered: list[str]


class Retired(BaseModel):
    """An agent taken off the fleet list (``DELETE /api/v1/agents/{identity}``)."""

    identity: str
    cid: int


class FleetCommand(BaseModel):
    """A fleet-wide order; ``agents`` narrows it (default: every connected agent)."""

    model_config = ConfigDict(extra="forbid")
    agents: list[str] | None = Field(default=None, max_length=1000)
    reason: str = Field(default="operator", max_length=200)


class FleetCommandResult(BaseModel):
    command: Literal["rtl", "land", "hold", "resume"]
    delivered: list[str]
    aborted_missions: list[str] = []


class Health(BaseModel):
    ok: bool
    agents_connected: int
    missions: int
    server_time: float


class UiConfig(BaseModel):
    """Dashboard settings served by the daemon (no secrets)."""

    tile_url: str | None = None
    status_period_s: float
    cluster: bool = False  # the dashboard asks /api/v1/cluster only then (no 404 on every load)
