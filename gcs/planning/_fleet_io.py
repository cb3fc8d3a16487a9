"""File formats of the fleet planners (documented in docs/fleet-planners.md), validated with pydantic.

* target file (``"format": "fleetgcs-targets"``): targets as ``{lat, lon}`` or ``{x, y}`` metres
  east/north of ``origin``, plus ``config`` (drones, link_range_m, speed_mps, alt_m,
  min_separation_m, track_margin_m) and optional ``homes`` (one {lat, lon} per drone);
* missed map (``"format": "fleetgcs-missed-map"``): geo-referenced grid of 1 detected / 0 missed,
  inline ``rows`` (north first) or ``npy`` (path of a 2-D .npy next to the JSON), plus RSA options.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gcs.planning._rsa_channels import FloatArray
from gcs.planning.geodesy import LocalFrame
from gcs.planning.psa import DEFAULT_TRACK_MARGIN_M
from gcs.planning.rsa import MissedMap


class FleetFileError(ValueError):
    """A planner input file that cannot be used; the message says why."""


class LatLon(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lat: float = Field(ge=-90, le=90)
    lon: float = Field(ge=-180, le=180)


class Target(BaseModel):
    """One target: geodetic, or local metres east (x) / north (y) of the file's origin."""

    model_config = ConfigDict(extra="ignore")
    lat: float | None = Field(default=None, ge=-90, le=90)
    lon: float | None = Field(default=None, ge=-180, le=180)
    x: float | None = None
    y: float | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> Target:
        geo = self.lat is not None and self.lon is not None
        local = self.x is not None and self.y is not None
        if geo == local:
            raise ValueError("each target needs exactly one of {lat, lon} or {x, y}")
        return self


class PsaConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    drones: int = Field(default=3, ge=1, le=64)
    link_range_m: float = Field(default=20.0, gt=0, le=10_000)
    speed_mps: float = Field(default=4.0, gt=0, le=100)
    alt_m: float = Field(default=20.0, gt=0, le=10_000)
    min_separation_m: float | None = Field(
        default=None, ge=0, le=10_000, description="None = the collision margin x release factor"
    )
    # a leg starts up to the agent's acceptance radius (default 2 m) from its planned start
    track_margin_m: float = Field(default=DEFAULT_TRACK_MARGIN_M, ge=0, le=10_000)


class TargetFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: Literal["fleetgcs-targets"] = "fleetgcs-targets"
    origin: LatLon | None = None
    targets: list[Target] = Field(min_length=1, max_length=100_000)
    config: PsaConfig = PsaConfig()
    homes: list[LatLon] | None = Field(
        default=None, description="PSA: one per drone, in drone order; times the assembly flight"
    )

    @model_validator(mode="after")
    def _origin_when_local(self) -> TargetFile:
        if any(t.x is not None for t in self.targets) and self.origin is None:
            raise ValueError("targets given as x/y need an 'origin' {lat, lon}")
        return self


class MissedMapFile(BaseModel):
    model_config = ConfigDict(extra="forbid")
    format: Literal["fleetgcs-missed-map"] = "fleetgcs-missed-map"
    origin: LatLon
    cell_size_m: float = Field(gt=0, le=10_000)
    rotation_deg: float = Field(default=0.0, ge=-360, le=360)
    rows: list[list[int]] | None = None
    npy: str | None = None
    channel_spacing_m: float = Field(default=10.0, gt=0)
    flight_distance_m: float = Field(default=2000.0, gt=0)
    side: Literal["west", "east", "south", "north"] = "west"
    safety_m: float = Field(default=5.0, ge=0)
    standoff_m: float = Field(default=5.0, ge=0)

    @model_validator(mode="after")
    def _one_grid(self) -> MissedMapFile:
        if (self.rows is None) == (self.npy is None):
            raise ValueError("give exactly one of 'rows' (inline grid) or 'npy' (file path)")
        return self


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ()))
    return f"{where}: {err.get('msg', 'invalid')}" if where else str(err.get("msg", "invalid"))


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except OSError as exc:
        raise FleetFileError(f"cannot read {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise FleetFileError(f"{path} is not JSON: {exc}") from None


def load_targets(path: Path) -> tuple[TargetFile, LocalFrame, FloatArray]:
    """Parse a target file; returns the model, the planning frame and (n, 2) local targets."""
    try:
        doc = TargetFile.model_validate(_read_json(path))
    except ValidationError as exc:
        raise FleetFileError(f"{path}: {_first_error(exc)}") from None
    geo = [(t.lat, t.lon) for t in doc.targets if t.lat is not None and t.lon is not None]
    if doc.origin is not None:
        frame = LocalFrame(doc.origin.lat, doc.origin.lon)
    else:
        arr = np.asarray(geo)
        frame = LocalFrame.centred_on(arr[:, 0], arr[:, 1])
    pts = []
    for t in doc.targets:
        if t.x is not None and t.y is not None:
            pts.append((t.x, t.y))
        elif t.lat is not None and t.lon is not None:
            e, n = frame.to_local(t.lat, t.lon)
            pts.append((float(e), float(n)))
    return doc, frame, np.asarray(pts, dtype=float)


def load_missed_map(path: Path) -> tuple[MissedMapFile, MissedMap]:
    """Parse a missed-map file (inline rows or a sidecar .npy)."""
    try:
        doc = MissedMapFile.model_validate(_read_json(path))
    except ValidationError as exc:
        raise FleetFileError(f"{path}: {_first_error(exc)}") from None
    if doc.rows is not None:
        widths = {len(r) for r in doc.rows}
        if len(widths) != 1 or not doc.rows:
            raise FleetFileError(f"{path}: 'rows' must be a non-empty rectangle of 0/1")
        grid = np.asarray(doc.rows)
    else:
        npy = (path.parent / str(doc.npy)).resolve()
        try:
            grid = np.load(npy, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise FleetFileError(f"cannot load grid {npy}: {exc}") from None
    if grid.ndim != 2 or not np.isin(grid, (0, 1)).all():
        raise FleetFileError(f"{path}: the grid must be 2-D and hold only 0 (missed) and 1 (detected)")
    return doc, MissedMap(
        grid=grid.astype(np.uint8),
        cell_size=doc.cell_size_m,
        origin_lat=doc.origin.lat,
        origin_lon=doc.origin.lon,
        rotation_deg=doc.rotation_deg,
    )


def geojson_lines(
    paths_latlon: list[list[tuple[float, float]]], names: list[str], **props: object
) -> dict[str, object]:
    """FeatureCollection of one LineString per drone (GeoJSON order: lon, lat)."""
    feats = [
        {
            "type": "Feature",
            "properties": {"drone": name, **props},
            "geometry": {"type": "LineString", "coordinates": [[lon, lat] for lat, lon in p]},
        }
        for p, name in zip(paths_latlon, names, strict=True)
    ]
    return {"type": "FeatureCollection", "features": feats}
