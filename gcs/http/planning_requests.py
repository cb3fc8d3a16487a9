"""Planning requests of the API and dashboard: area/targets/missed map -> task file + preview.

Three methods, one request body discriminated by ``method``:

* ``search``: an area (lat/lon ring, or a GeoJSON / QGroundControl document), a pattern and a
  division -> :func:`gcs.planning.planner.plan_search`;
* ``psa``: targets -> the Polygon-guided Scanning Algorithm (connected line formation);
* ``rsa``: a missed-area grid -> the Rectangle-based Scheduling Algorithm.

Every request is bounded (vertices, targets, grid cells, total survey length) so that a bad or
hostile request costs a bounded amount of CPU; every planner failure becomes a
:class:`PlanningError` with a message for the operator, never a crash. The preview predicts
length, time and energy per drone so the operator can judge a plan before flying it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from shapely.geometry import Polygon

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import EnergyModel
from protocol.actions import Goto, Land, Takeoff, Waypoints
from protocol.packets import Capabilities, StatusReport
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.planning.areas import SearchArea
    from gcs.planning.camera import Spacing
    from gcs.planning.division import DroneSpec
    from gcs.planning.planner import SearchPlan

MAX_SURVEY_M = 400_000.0  # total survey lines a request may ask for (bounded planning time)
MAX_EXTENT_M = 30_000.0

Lat = Annotated[float, Field(ge=-90.0, le=90.0, allow_inf_nan=False)]
Lon = Annotated[float, Field(ge=-180.0, le=180.0, allow_inf_nan=False)]
AgentName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")]


class PlanningError(ValueError):
    """A planning request that cannot be planned; the message says why.

    ``extra``: what the dashboard can show of it, e.g. a self-intersecting area's ``area`` and
    ``crossings`` ([lat, lon] lists) so it draws the outline and marks where it crosses itself.
    """

    def __init__(self, message: str, extra: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.extra = extra or {}


class LatLonPoint(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lat: Lat
    lon: Lon


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(default="plan", min_length=1, max_length=128)
    drones: list[AgentName] = Field(
        default_factory=list,
        max_length=64,
        description="agent identities; empty = every connected idle agent",
    )
    altitude_m: float = Field(default=20.0, gt=1.0, le=500.0, description="survey altitude above home")
    speed_mps: float = Field(default=5.0, gt=0.1, le=50.0)


class SearchPlanRequest(_Request):
    """Cover an area: pattern + division (seed 001's ASAF planner)."""

    method: Literal["search"] = "search"
    area: list[tuple[Lat, Lon]] | None = Field(
        default=None, min_length=3, max_length=500, description="[lat, lon] ring (not closed)"
    )
    area_document: dict[str, Any] | None = Field(
        default=None, description="instead of 'area': a GeoJSON or QGroundControl .plan document"
    )
    area_text: str | None = Field(
        default=None,
        max_length=2_000_000,
        description="instead of 'area': a KML, GeoJSON or QGroundControl .plan document as text",
    )
    pattern: Literal["zigzag", "spiral", "segmented", "curved"] = "zigzag"
    division: Literal["path", "region", "partition"] = "region"
    swath_m: float = Field(default=20.0, ge=1.0, le=5000.0, description="sensor footprint width")
    side_overlap: float = Field(default=0.0, ge=0.0, le=0.9)
    home: LatLonPoint | None = Field(
        default=None,
        description="home of drones that report none (default: the first known drone's home)",
    )
    transit_alt_step: float = Field(default=3.0, ge=0.0, le=50.0)
    return_mode: Literal["rtl", "land_home"] = "rtl"
    allow_partial: bool = False


class PsaPlanRequest(_Request):
    """Visit targets with a connected line formation (CoUAS seed 004's PSA)."""

    method: Literal["psa"] = "psa"
    targets: list[LatLonPoint] = Field(min_length=1, max_length=2000)
    link_range_m: float = Field(default=20.0, ge=1.0, le=5000.0)


class RsaPlanRequest(_Request):
    """Re-search the missed cells of a grid map (seed 002's RSA); the map decides how many drones fly."""

    method: Literal["rsa"] = "rsa"
    origin: LatLonPoint = Field(description="the map's south-west corner")
    cell_size_m: float = Field(ge=0.5, le=1000.0)
    rows: list[list[Literal[0, 1]]] = Field(
        min_length=1, max_length=300, description="1 detected / 0 missed, northernmost row first"
    )
    rotation_deg: float = Field(default=0.0, ge=-360.0, le=360.0)
    channel_spacing_m: float = Field(default=10.0, ge=0.5, le=5000.0)
    flight_distance_m: float = Field(default=2000.0, ge=10.0, le=200_000.0)
    side: Literal["west", "east", "south", "north"] = "west"
    safety_m: float = Field(default=5.0, ge=0.0, le=1000.0)
    standoff_m: float = Field(default=5.0, ge=0.0, le=1000.0)


PlanRequest = Annotated[SearchPlanRequest | PsaPlanRequest | RsaPlanRequest, Field(discriminator="method")]


class DroneEstimate(BaseModel):
    """Predicted cost of one drone's part: path, length, time, energy."""

    agent: str
    points: list[tuple[float, float]]
    length_m: float
    time_s: float
    energy_wh: float
    home: tuple[float, float] | None = Field(default=None, description="where the estimate starts")
    home_alt_amsl: float | None = Field(
        default=None, description="the drone's home altitude, when it reported one"
    )
    home_assumed: bool = Field(
        default=False, description="no drone or request gave this home: the area's first corner stands in"
    )


class PlanPreview(BaseModel):
    """A plan before (or as) it flies: the task file and what the map and the operator need."""

    method: str
    name: str
    taskfile: TaskFile
    drones: list[DroneEstimate]
    area: list[tuple[float, float]] | None = None
    targets: list[tuple[float, float]] | None = None
    swath_m: float | None = None
    coverage_pct: float | None = None
    total_length_m: float
    max_time_s: float
    total_energy_wh: float
    summary: dict[str, Any] = {}


class DroneInfo(BaseModel):
    """What the planner needs to know of a drone (from its live session, or defaults)."""

    name: str
    capabilities: Capabilities = Capabilities()
    home: tuple[float, float] | None = None
    home_alt_amsl: float | None = None  # from the autopilot's home position (exports use it)
    status: StatusReport | None = None


@dataclass(frozen=True)
class EnergySettings:
    """The daemon's energy estimator: its config and (trained) model, so previews match the pre-flight."""

    config: EnergyConfig = field(default_factory=EnergyConfig)
    model: EnergyModel | None = None


def plan(
    request: SearchPlanRequest | PsaPlanRequest | RsaPlanRequest,
    drones: Sequence[DroneInfo],
    energy: EnergySettings | None = None,
) -> PlanPreview:
    """Plan synchronously (call it in a worker thread); raises PlanningError with a readable reason.

    ``energy``: the daemon's energy config and model (default: untrained, power x time), so the
    preview predicts what the pre-flight check will (:func:`predict_plan_energy`).
    """
    if not drones:
        raise PlanningError("no drones to plan for: name them in 'drones' or connect agents")
    settings = energy or EnergySettings()
    try:
        if isinstance(request, SearchPlanRequest):
            return _plan_search(request, drones, settings)
        if isinstance(request, PsaPlanRequest):
            return _plan_psa(request, drones, settings)
        return _plan_rsa(request, drones, settings)
    except PlanningError:
        raise
    except (ValueError, ArithmeticError, IndexError) as exc:  # planner and geometry errors
        raise PlanningError(f"{request.method} planning failed: {exc}") from None


def _plan_search(
    request: SearchPlanRequest, drones: Sequence[DroneInfo], energy: EnergySettings
) -> PlanPreview:
    from gcs.planning.areas import AreaFormatError, parse_area
    from gcs.planning.camera import Spacing, spacing_from_swath
    from gcs.planning.division import DroneSpec
    from gcs.planning.interchange import QgcSurvey, load_area_text, read_qgc_survey
    from gcs.planning.polygon import SelfIntersectionError

    given = [x for x in (request.area, request.area_document, request.area_text) if x is not None]
    if len(given) != 1:
        raise PlanningError(
            "give exactly one of 'area' ([lat, lon] ring), 'area_document' (GeoJSON/.plan) "
            "or 'area_text' (KML, GeoJSON or .plan as text)"
        )
    survey: QgcSurvey | None = None
    try:
        if request.area_text is not None:
            area, survey = load_area_text(request.area_text, request.name)
        elif isinstance(request.area_document, dict) and request.area_document.get("fileType") == "Plan":
            survey = read_qgc_survey(request.area_document, request.name)
            area = survey.area
        else:
            area = parse_area(
                request.area if request.area is not None else request.area_document, request.name
            )
    except (AreaFormatError, ValueError, TypeError, KeyError, IndexError, AttributeError) as exc:
        raise PlanningError(f"area: {exc}") from None
    # a QGC survey's own settings stand unless the request sets them
    chosen = request.model_fields_set
    altitude = request.altitude_m
    if survey is not None and survey.altitude_m is not None and "altitude_m" not in chosen:
        altitude = survey.altitude_m
    if survey is not None and survey.step_m is not None and not chosen & {"swath_m", "side_overlap"}:
        spacing = Spacing(
            altitude=altitude,
            swath=survey.swath_m or survey.step_m,
            step=survey.step_m,
            side_overlap=survey.side_overlap,
        )
    else:
        spacing = spacing_from_swath(request.swath_m, altitude, request.side_overlap)
    angle = survey.angle_deg if survey is not None else None
    if survey is not None and survey.home is not None and request.home is None:
        request = request.model_copy(update={"home": LatLonPoint(lat=survey.home[0], lon=survey.home[1])})
    local = area.local()
    extent = float(np.ptp(local, axis=0).max())
    if not np.isfinite(local).all() or extent > MAX_EXTENT_M:
        raise PlanningError(
            f"area is {extent / 1000:.0f} km across; the limit is {MAX_EXTENT_M / 1000:.0f} km"
        )
    lines_m = Polygon(local).area / spacing.step
    if lines_m > MAX_SURVEY_M:
        raise PlanningError(
            f"area needs about {lines_m / 1000:.0f} km of survey lines at {spacing.step:.1f} m spacing "
            f"(limit {MAX_SURVEY_M / 1000:.0f} km); widen the swath or split the area"
        )
    # Each drone starts from its own home when its agent reported one (transits, returns and the
    # exports then start where it really stands), else the request's, else the first known one;
    # with none known, the area's first corner stands in and the exports say so.
    shared = (
        (request.home.lat, request.home.lon)
        if request.home
        else next((d.home for d in drones if d.home is not None), None)
    )
    home = shared or area.vertices[0]
    homes = [d.home or home for d in drones]
    specs = [
        DroneSpec(
            name=d.name,
            speed_mps=request.speed_mps,
            endurance_s=d.capabilities.endurance_s,
            battery=_battery_fraction(d),
        )
        for d in drones
    ]
    try:
        result = _search(area, specs, spacing, request, angle, home, homes)
    except SelfIntersectionError as exc:
        found = area.crossings()
        raise PlanningError(
            f"search planning failed: {found[0] if found else exc}",
            {
                "area": [list(v) for v in area.vertices],
                "crossings": [list(p) for p in found[1]] if found else [],
            },
        ) from None
    estimates = _estimates(result.taskfile, drones, result.paths_latlon, homes, request.speed_mps, energy)
    for estimate, drone in zip(estimates, drones, strict=True):
        estimate.home_alt_amsl = drone.home_alt_amsl if drone.home is not None else None
        estimate.home_assumed = drone.home is None and shared is None
    return _preview(
        "search",
        request.name,
        result.taskfile,
        estimates,
        area=list(area.vertices),
        swath_m=spacing.swath,
        coverage_pct=float(result.summary["coverage"].get("covered_pct", 0.0))
        if isinstance(result.summary.get("coverage"), dict)
        else None,
        summary={k: v for k, v in result.summary.items() if k in ("area_m2", "step_m", "polygon_type")},
    )


def _search(
    area: SearchArea,
    specs: list[DroneSpec],
    spacing: Spacing,
    request: SearchPlanRequest,
    angle: float | None,
    home: tuple[float, float],
    homes: list[tuple[float, float]],
) -> SearchPlan:
    """The search planner with the request's settings (raises SelfIntersectionError and others)."""
    from gcs.planning.planner import PlanConfig, plan_search

    return plan_search(
        area,
        specs,
        spacing,
        PlanConfig(
            pattern=request.pattern,
            division=request.division,
            name=request.name,
            transit_alt_step=request.transit_alt_step,
            return_mode=request.return_mode,
            allow_partial=request.allow_partial,
            angle_deg=angle,
        ),
        home_latlon=home,
        speed=request.speed_mps,
        agent_names=[s.name for s in specs],
        homes_latlon=homes,
    )


def _plan_psa(request: PsaPlanRequest, drones: Sequence[DroneInfo], energy: EnergySettings) -> PlanPreview:
    from gcs.planning._psa_mission import psa_mission
    from gcs.planning.geodesy import LocalFrame
    from gcs.planning.psa import plan_psa

    lats = np.array([t.lat for t in request.targets])
    lons = np.array([t.lon for t in request.targets])
    frame = LocalFrame.centred_on(lats, lons)
    pts = frame.points_to_local(list(zip(lats.tolist(), lons.tolist(), strict=True)))
    if float(np.ptp(pts, axis=0).max()) > MAX_EXTENT_M:
        raise PlanningError(f"targets spread over more than {MAX_EXTENT_M / 1000:.0f} km")
    result = plan_psa(pts, len(drones), request.link_range_m, request.speed_mps)
    traj = result.trajectory
    names = [d.name for d in drones]
    task = psa_mission(traj, frame, request.altitude_m, request.speed_mps, names, name=request.name)
    paths = []
    for j in range(len(drones)):
        lat, lon = frame.to_geodetic(traj.positions[j, :, 0], traj.positions[j, :, 1])
        paths.append(list(zip(lat.tolist(), lon.tolist(), strict=True)))
    homes = [d.home if d.home is not None else p[0] for d, p in zip(drones, paths, strict=True)]
    estimates = _estimates(task, drones, paths, homes, request.speed_mps, energy)
    return _preview(
        "psa",
        request.name,
        task,
        estimates,
        targets=[(t.lat, t.lon) for t in request.targets],
        summary={"rounds": len(result.rounds), "fleet_length_m": round(result.costs.fleet_length, 1)},
    )


def _plan_rsa(request: RsaPlanRequest, drones: Sequence[DroneInfo], energy: EnergySettings) -> PlanPreview:
    from gcs.planning.geodesy import LocalFrame
    from gcs.planning.mission import mission_from_paths
    from gcs.planning.rsa import MissedMap, plan_rsa

    widths = {len(r) for r in request.rows}
    if len(widths) != 1 or 0 in widths or max(widths) > 300:
        raise PlanningError("'rows' must be a rectangle of 1..300 columns of 0/1")
    missed = MissedMap(
        grid=np.asarray(request.rows, dtype=np.uint8),
        cell_size=request.cell_size_m,
        origin_lat=request.origin.lat,
        origin_lon=request.origin.lon,
        rotation_deg=request.rotation_deg,
    )
    if max(missed.extent) > MAX_EXTENT_M:
        raise PlanningError(f"the map is more than {MAX_EXTENT_M / 1000:.0f} km across")
    result = plan_rsa(
        missed,
        d_nbh=request.channel_spacing_m,
        d_flt=request.flight_distance_m,
        side=request.side,
        d_sfty=request.safety_m,
        standoff=request.standoff_m,
    )
    if not result.drones:
        raise PlanningError("the map has no missed cells: nothing to fly")
    if len(result.drones) > len(drones):
        raise PlanningError(
            f"RSA needs {len(result.drones)} drones for this map and flight distance; "
            f"only {len(drones)} available (give more drones or a longer flight distance)"
        )
    frame = LocalFrame(request.origin.lat, request.origin.lon)
    used = list(drones[: len(result.drones)])
    paths = []
    for d in result.drones:
        en = missed.to_east_north(d.path)
        lat, lon = frame.to_geodetic(en[:, 0], en[:, 1])
        paths.append(list(zip(lat.tolist(), lon.tolist(), strict=True)))
    task = mission_from_paths(
        paths,
        request.altitude_m,
        request.speed_mps,
        [d.name for d in used],
        homes_latlon=[p[-1] for p in paths],
        return_mode="land_home",
        name=request.name,
    )
    estimates = _estimates(task, used, paths, [p[-1] for p in paths], request.speed_mps, energy)
    corners = missed.to_east_north(
        np.array([[0, 0], [missed.extent[0], 0], [*missed.extent], [0, missed.extent[1]]])
    )
    clat, clon = frame.to_geodetic(corners[:, 0], corners[:, 1])
    return _preview(
        "rsa",
        request.name,
        task,
        estimates,
        area=list(zip(clat.tolist(), clon.tolist(), strict=True)),
        summary={"zones": len(result.zones), "drones_needed": len(result.drones)},
    )


def _battery_fraction(drone: DroneInfo) -> float:
    pct = drone.status.battery.pct if drone.status is not None else None
    return 1.0 if pct is None else min(1.0, max(0.05, pct / 100.0))


def _estimates(
    task: TaskFile,
    drones: Sequence[DroneInfo],
    paths: Sequence[Sequence[tuple[float, float]]],
    homes: Sequence[tuple[float, float]],
    speed: float,
    energy: EnergySettings,
) -> list[DroneEstimate]:
    """Each drone's planned time, distance and energy: the task file through the one estimator.

    :func:`gcs.cooperation.energy.predict_plan_energy`, as the daemon's pre-flight check uses it:
    climbs, legs with acceleration, landings, the hover at each barrier, then the trained model
    (or the drone's mean power from its capabilities x time).
    """
    from gcs.cooperation.energy import capability_power_w, predict_plan_energy

    cfg = energy.config.model_copy(update={"speed_mps": speed})
    plans = {p.label: list(p.actions) for p in task.plans}
    by_label = {p.label: (d, h) for p, d, h in zip(task.plans, drones, homes, strict=False)}
    power = {
        label: capability_power_w(d.capabilities.battery_wh, d.capabilities.endurance_s, cfg)
        for label, (d, _) in by_label.items()
    }
    predicted = predict_plan_energy(
        plans, {label: (h[0], h[1], 0.0) for label, (_, h) in by_label.items()}, cfg, energy.model, power
    )
    out = []
    for plan_, d, path, h in zip(task.plans, drones, paths, homes, strict=False):
        e = predicted[plan_.label]
        out.append(
            DroneEstimate(
                agent=d.name,
                points=[(float(a), float(b)) for a, b in path],
                length_m=round(e.distance_m, 1),
                time_s=round(e.time_s, 1),
                energy_wh=round(e.energy_wh, 2),
                home=(float(h[0]), float(h[1])),
            )
        )
    return out


def export_preview(preview: PlanPreview, formats: Sequence[str], speed_mps: float = 5.0) -> dict[str, str]:
    """A previewed plan as files for QGroundControl (.plan), Mission Planner (.waypoints) and KML.

    File name -> text (``gcs.planning.interchange.export_files``); each drone's home is the one
    its estimate started from. Raises ValueError for an unknown format.
    """
    from gcs.planning.interchange import export_files

    homes, alts, assumed = {}, {}, []
    for agent_plan, estimate in zip(preview.taskfile.plans, preview.drones, strict=False):
        label = agent_plan.label
        homes[label] = estimate.home or (estimate.points[0] if estimate.points else (0.0, 0.0))
        if estimate.home_alt_amsl is not None:
            alts[label] = estimate.home_alt_amsl
        if estimate.home_assumed or estimate.home is None:
            assumed.append(label)
    altitude = max(
        (a.alt for p in preview.taskfile.plans for a in p.actions if isinstance(a, Takeoff)), default=None
    )
    return export_files(
        preview.taskfile,
        homes,
        formats,
        area=preview.area,
        altitude_m=altitude,
        cruise_speed=speed_mps,
        home_alts=alts,
        assumed_homes=assumed,
    )


def _preview(
    method: str, name: str, task: TaskFile, estimates: list[DroneEstimate], **extra: Any
) -> PlanPreview:
    return PlanPreview(
        method=method,
        name=name,
        taskfile=task,
        drones=estimates,
        total_length_m=round(sum(e.length_m for e in estimates), 1),
        max_time_s=max((e.time_s for e in estimates), default=0.0),
        total_energy_wh=round(sum(e.energy_wh for e in estimates), 2),
        **extra,
    )


def task_paths(task: TaskFile) -> dict[str, list[tuple[float, float]]]:
    """The lat/lon points each plan of a task file visits (for maps of task-file missions)."""
    out: dict[str, list[tuple[float, float]]] = {}
    for p in task.plans:
        pts: list[tuple[float, float]] = []
        for a in p.actions:
            if isinstance(a, Goto):
                pts.append((a.lat, a.lon))
            elif isinstance(a, Waypoints):
                pts.extend((w.lat, w.lon) for w in a.points)
            elif isinstance(a, Land) and a.lat is not None and a.lon is not None:
                pts.append((a.lat, a.lon))
            elif isinstance(a, Takeoff):
                continue
        out[p.label] = pts
    return out
