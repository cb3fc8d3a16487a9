"""One call from a search area to per-drone paths and a task file (the CLI's engine).

area (lat/lon) -> local frame -> validate (self-intersection is an error) -> cover pattern ->
divide among drones (path or region) -> lat/lon paths -> TaskFile. Pure apart from the frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from gcs.planning.areas import SearchArea
from gcs.planning.camera import Spacing
from gcs.planning.coverage import CoverageReport, evaluate_coverage
from gcs.planning.decompose import cover_area, sweep_angle
from gcs.planning.division import (
    DroneSpec,
    InsufficientCapabilityError,
    path_division,
    region_division,
)
from gcs.planning.geodesy import FloatArray, LocalFrame
from gcs.planning.mission import mission_from_paths
from gcs.planning.partition import partition_for_search
from gcs.planning.patterns import Sweep, curved_cover, path_length, segmented, spiral, zigzag
from gcs.planning.polygon import PolygonType, classify, convex_hull, min_height_rotation, require_simple
from protocol.taskfile import SurveyArea, TaskFile

Pattern = Literal["zigzag", "spiral", "segmented", "curved"]


class PlanConfig(BaseModel):
    """How to cover and divide; defaults follow the papers where they are sound."""

    pattern: Pattern = "zigzag"
    division: Literal["path", "region", "partition"] = "path"
    concave: Literal["decompose", "hull"] = Field(
        default="decompose", description="cover a concave area's cells, or its convex hull as the papers do"
    )
    segments: int = Field(default=4, ge=1, description="segmented pattern: parts per leg (seed 001 S)")
    shift: float = Field(default=0.2, ge=-0.5, le=0.5, description="curved pattern: midpoint shift x step")
    wind_from_deg: float | None = None
    angle_deg: float | None = Field(default=None, description="force the leg direction (rotation, degrees)")
    allow_partial: bool = False
    return_mode: Literal["rtl", "land_home"] = "rtl"
    transit_alt_step: float = 0.0
    name: str = "search"


@dataclass
class SearchPlan:
    """Everything the CLI writes: per-drone local sweeps, lat/lon paths, the task file, a summary."""

    frame: LocalFrame
    area_local: FloatArray
    spacing: Spacing
    drones: list[DroneSpec]
    paths_local: list[FloatArray]
    paths_latlon: list[list[tuple[float, float]]]
    home_local: FloatArray
    taskfile: TaskFile
    coverage: CoverageReport
    regions_local: list[Any] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)


def build_sweep(
    vertices: FloatArray, step: float, config: PlanConfig, angle: float | None, start: FloatArray | None
) -> Sweep:
    """The configured pattern over one (possibly concave) polygon in local metres."""
    convex = classify(vertices) == PolygonType.CONVEX or config.concave == "hull"
    if config.pattern == "spiral":
        return spiral(vertices, step, start=start)  # spirals fill the hull (seed 001 §5)
    if config.pattern == "curved":
        cells = None if convex else cover_area  # concave: bend the legs of every cell
        return curved_cover(
            vertices, step, config.shift, config.wind_from_deg, angle=angle, start=start, base=cells
        )
    base = zigzag(vertices, step, angle, start=start) if convex else cover_area(vertices, step, angle, start)
    if config.pattern == "segmented":
        return segmented(base, config.segments)
    return base


def plan_search(
    area: SearchArea,
    drones: Sequence[DroneSpec],
    spacing: Spacing,
    config: PlanConfig | None = None,
    home_latlon: tuple[float, float] | None = None,
    speed: float | None = None,
    agent_names: Sequence[str] | None = None,
    homes_latlon: Sequence[tuple[float, float]] | None = None,
) -> SearchPlan:
    """Plan the search; raises SelfIntersectionError, CameraError or InsufficientCapabilityError.

    ``home_latlon`` is the fleet's common home (default: the area's first vertex);
    ``homes_latlon`` gives each drone its own (its launch point), which division costs and a
    ``land_home`` return use, so drones do not all converge on one landing spot.
    """
    cfg = config or PlanConfig()
    if not drones:
        raise ValueError("need at least one drone")
    frame = area.frame()
    poly = require_simple(area.local(frame))
    ptype = classify(poly)
    work = convex_hull(poly) if (ptype == PolygonType.CONCAVE and cfg.concave == "hull") else poly
    if home_latlon is None:
        home_latlon = area.vertices[0]
    he, hn = frame.to_local(*home_latlon)
    home = np.array([float(he), float(hn)])
    if homes_latlon is not None:
        if len(homes_latlon) != len(drones):
            raise ValueError(f"{len(homes_latlon)} homes for {len(drones)} drones")
        own = frame.points_to_local(list(homes_latlon))
        drones = [
            d.model_copy(update={"home": (float(e), float(n))}) for d, (e, n) in zip(drones, own, strict=True)
        ]
    drones = [d if d.home is not None else d.model_copy(update={"home": (home[0], home[1])}) for d in drones]
    if cfg.angle_deg is not None:
        angle = math.radians(cfg.angle_deg)
    elif cfg.pattern == "spiral":
        angle = min_height_rotation(work)[0]  # spirals need no rotation; region cuts use the narrowest
    else:
        angle = sweep_angle(work, spacing.step)  # the shortest flown, not the hull's narrowest
    paths: list[FloatArray] = []
    regions: list[Any] = []
    meta: dict[str, Any] = {}
    if cfg.division == "path" or len(drones) == 1:
        sweep = build_sweep(work, spacing.step, cfg, angle, home)
        meta = sweep.summary()
        shares = path_division(sweep.points, drones, home, allow_partial=cfg.allow_partial)
        paths = [s.points for s in shares]
        budget = [
            {
                "drone": s.drone,
                "survey_m": round(s.survey_m, 1),
                "transit_m": round(s.transit_m, 1),
                "range_m": round(s.range_m, 1),
            }
            for s in shares
        ]
    else:
        paths, regions, budget = _region_paths(work, drones, spacing, cfg, angle, home)
    latlon = [[(float(a), float(b)) for a, b in frame.points_to_geodetic(p)] if len(p) else [] for p in paths]
    task = mission_from_paths(
        latlon,
        spacing.altitude,
        speed,
        agent_names,
        homes_latlon=[
            (float(a), float(b))
            for a, b in frame.points_to_geodetic([d.home or (home[0], home[1]) for d in drones])
        ],
        return_mode=cfg.return_mode,
        transit_alt_step=cfg.transit_alt_step,
        name=cfg.name,
        survey=SurveyArea(
            area=list(area.vertices),
            swath_m=spacing.swath,
            altitude_m=spacing.altitude if spacing.altitude > 0 else None,
        ),
    )
    cov = evaluate_coverage(Polygon(poly), [p for p in paths if len(p)], spacing.swath)
    summary = {
        "area": area.name,
        "polygon_type": ptype.value,
        "area_m2": round(Polygon(poly).area, 1),
        "altitude_m": round(spacing.altitude, 2),
        "swath_m": round(spacing.swath, 2),
        "step_m": round(spacing.step, 2),
        "pattern": cfg.pattern,
        "division": cfg.division,
        "sweep": meta,
        "drones": budget,
        "coverage": cov.summary(),
        "total_length_m": round(sum(path_length(p) for p in paths if len(p) > 1), 1),
    }
    return SearchPlan(frame, poly, spacing, list(drones), paths, latlon, home, task, cov, regions, summary)


def _region_paths(
    work: FloatArray,
    drones: Sequence[DroneSpec],
    spacing: Spacing,
    cfg: PlanConfig,
    angle: float,
    home: FloatArray,
) -> tuple[list[FloatArray], list[Any], list[dict[str, Any]]]:
    """Region or partition division: each drone sweeps its own part of the area (paths, the
    regions, the range budget); raises InsufficientCapabilityError when a part is out of range."""
    if cfg.division == "partition":
        # seed 003's capability-proportional partition (the divide protocol's fixed point),
        # with a drone's capability its flyable range, as region division uses
        parts = partition_for_search(Polygon(work), [d.range_m for d in drones])
        total = sum(p.area for p in parts) or 1.0
        areas: list[tuple[BaseGeometry, float]] = [(part, part.area / total) for part in parts]
    else:
        areas = [(rs.region, rs.fraction) for rs in region_division(work, drones, angle, home)]
    paths: list[FloatArray] = []
    regions: list[Any] = []
    budget: list[dict[str, Any]] = []
    short = 0.0
    for d, (region, fraction) in zip(drones, areas, strict=True):
        regions.append(region)
        pts: list[FloatArray] = []
        cur = home
        for part in getattr(region, "geoms", [region]):
            if part.geom_type != "Polygon" or part.area <= 1e-6:
                continue
            sw = build_sweep(np.asarray(part.exterior.coords)[:-1], spacing.step, cfg, angle, cur)
            pts.append(sw.points)
            cur = sw.points[-1]
        p = np.vstack(pts) if pts else np.empty((0, 2))
        survey = path_length(p)
        trip = 0.0 if len(p) == 0 else float(np.hypot(*(p[0] - home)) + np.hypot(*(p[-1] - home)))
        if survey + trip > d.range_m:
            short += survey + trip - d.range_m
        budget.append(
            {
                "drone": d.name,
                "survey_m": round(survey, 1),
                "transit_m": round(trip, 1),
                "range_m": round(d.range_m, 1),
                "area_fraction": round(fraction, 5),
            }
        )
        paths.append(p)
    if short > 0 and not cfg.allow_partial:
        raise InsufficientCapabilityError(
            f"{cfg.division} division: drones would need {short:.0f} m more range than they have; "
            "add drones, charge batteries or shrink the area",
            shortfall_m=short,
        )
    return paths, regions, budget
