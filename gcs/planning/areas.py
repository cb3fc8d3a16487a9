"""Search-area readers: GeoJSON, QGroundControl ``.plan`` surveys and plain vertex lists (KML: interchange).

Everything returns a :class:`SearchArea` (lat/lon vertex ring, outer boundary only, not closed),
so planners never see file formats. Coordinates are validated here, at the I/O edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, Field, field_validator

from gcs.planning.geodesy import FloatArray, LocalFrame


class AreaFormatError(ValueError):
    """The file does not hold a polygon we understand."""


class SearchArea(BaseModel):
    """A search polygon as (lat, lon) vertices in degrees, ring not repeated at the end."""

    vertices: list[tuple[float, float]] = Field(min_length=3)
    name: str = "area"

    @field_validator("vertices")
    @classmethod
    def _check(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
        if len(v) > 3 and v[0] == v[-1]:
            v = v[:-1]
        for lat, lon in v:
            if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
                raise ValueError(f"vertex ({lat}, {lon}) is not a valid lat/lon in degrees")
        if len(v) < 3:
            raise ValueError("a search area needs at least three distinct vertices")
        return v

    def frame(self) -> LocalFrame:
        """Local frame centred on this area (smallest projection error)."""
        arr = np.asarray(self.vertices)
        return LocalFrame.centred_on(arr[:, 0], arr[:, 1])

    def local(self, frame: LocalFrame | None = None) -> FloatArray:
        """(N, 2) east/north vertices in ``frame`` (default: the area's own centred frame)."""
        return (frame or self.frame()).points_to_local(self.vertices)

    def crossings(self) -> tuple[str, list[tuple[float, float]]] | None:
        """Where the boundary crosses itself, in lat/lon: a message and the crossing points.

        Why: the planner finds crossings in its local frame, centred on the area, so a bow-tie's
        crossing read "(0.00, 0.00)"; an operator needs the place on the map. Edges are numbered
        from 0 (edge i joins vertex i+1 to vertex i+2, counting vertices from 1). None when the
        ring does not cross itself (or lost vertices as duplicates: numbering would not match).
        """
        from gcs.planning.polygon import as_ring, find_crossings

        frame = self.frame()
        ring = as_ring(frame.points_to_local(self.vertices))
        found = find_crossings(ring)
        if not found or len(ring) != len(self.vertices):
            return None
        n = len(self.vertices)

        def vertex(i: int) -> str:
            lat, lon = self.vertices[i % n]
            return f"vertex {i % n + 1} ({lat:.6f}, {lon:.6f})"

        def edge(i: int) -> str:
            return f"{vertex(i)} -> {vertex(i + 1)}"

        points = [(float(a), float(b)) for a, b in frame.points_to_geodetic([c.point for c in found])]
        parts = [
            f"edge {c.edge_a} crosses edge {c.edge_b} at ({lat:.6f}, {lon:.6f}) "
            f"[edge {c.edge_a}: {edge(c.edge_a)}; edge {c.edge_b}: {edge(c.edge_b)}]"
            for c, (lat, lon) in zip(found[:3], points, strict=False)
        ]
        more = f" and {len(found) - 3} more" if len(found) > 3 else ""
        return "self-intersecting area (lat, lon): " + "; ".join(parts) + more, points


def area_from_latlon(vertices: Sequence[Sequence[float]], name: str = "area") -> SearchArea:
    """Plain list of [lat, lon] pairs."""
    try:
        pts = [(float(p[0]), float(p[1])) for p in vertices]
    except (TypeError, IndexError, ValueError) as exc:
        raise AreaFormatError(f"expected a list of [lat, lon] pairs: {exc}") from exc
    return SearchArea(vertices=pts, name=name)


def area_from_geojson(obj: dict[str, Any], name: str = "area") -> SearchArea:
    """GeoJSON Polygon, MultiPolygon (first part), Feature or FeatureCollection (first polygon).

    GeoJSON orders positions [lon, lat]; only the outer ring is used (holes are not supported by
    the coverage planners and are reported rather than silently dropped).
    """
    kind = obj.get("type")
    if kind == "FeatureCollection":
        for feat in obj.get("features", []):
            geom = (feat or {}).get("geometry") or {}
            if geom.get("type") in ("Polygon", "MultiPolygon"):
                return area_from_geojson(feat, name)
        raise AreaFormatError("FeatureCollection holds no Polygon feature")
    if kind == "Feature":
        props = obj.get("properties") or {}
        return area_from_geojson(obj.get("geometry") or {}, str(props.get("name", name)))
    if kind == "MultiPolygon":
        coords = obj.get("coordinates") or []
        if not coords:
            raise AreaFormatError("empty MultiPolygon")
        return area_from_geojson({"type": "Polygon", "coordinates": coords[0]}, name)
    if kind == "Polygon":
        rings = obj.get("coordinates") or []
        if not rings:
            raise AreaFormatError("Polygon without coordinates")
        if len(rings) > 1:
            raise AreaFormatError("Polygon with holes is not supported; split the area or remove the holes")
        return area_from_latlon([(p[1], p[0]) for p in rings[0]], name)
    raise AreaFormatError(f"GeoJSON type {kind!r} is not a polygon")


def area_from_qgc_plan(obj: dict[str, Any], name: str = "area") -> SearchArea:
    """QGroundControl ``.plan``: the first survey ComplexItem's ``polygon`` ([lat, lon] rows).

    Falls back to the first inclusion geofence polygon when the plan has no survey, so a fence
    drawn in QGC can serve as a search area too.
    """
    items = (obj.get("mission") or {}).get("items") or []
    for item in items:
        if item.get("type") != "ComplexItem":
            continue
        poly = item.get("polygon") or (item.get("TransectStyleComplexItem") or {}).get("polygon")
        if poly:
            return area_from_latlon(poly, name)
    fences = (obj.get("geoFence") or {}).get("polygons") or []
    for fence in fences:
        if fence.get("inclusion", True) and fence.get("polygon"):
            return area_from_latlon(fence["polygon"], name)
    raise AreaFormatError(
        "plan file holds no survey polygon (mission.items[].polygon) nor fence polygon; a mission "
        "of waypoints is flown as it is: `gcs run DRONE.plan`, or the dashboard's 'fly mission files'"
    )


def parse_area(obj: Any, name: str = "area") -> SearchArea:
    """Dispatch on the decoded JSON's shape."""
    if isinstance(obj, list):
        return area_from_latlon(obj, name)
    if isinstance(obj, dict):
        if obj.get("fileType") == "Plan" or "mission" in obj:
            return area_from_qgc_plan(obj, name)
        if "vertices" in obj:
            return area_from_latlon(obj["vertices"], str(obj.get("name", name)))
        return area_from_geojson(obj, name)
    raise AreaFormatError(f"cannot read an area from a {type(obj).__name__}")


def load_area(path: str | Path) -> SearchArea:
    """Read an area file (.geojson/.json/.plan, .kml, or a JSON list of [lat, lon])."""
    from gcs.planning.interchange import load_area_text  # interchange builds on this module

    p = Path(path)
    try:
        return load_area_text(p.read_text(), p.stem)[0]
    except AreaFormatError as exc:
        raise AreaFormatError(f"{p}: {exc}") from None
