"""Interchange with the tools operators already use: QGroundControl ``.plan``, Mission Planner
``.waypoints`` and KML.

* Import: a QGroundControl survey keeps what the operator set in QGC (planned home, survey
  altitude, line spacing, side overlap and grid angle: :func:`read_qgc_survey`); KML polygons
  are search areas (:func:`read_kml`); :func:`load_area_text` reads any area document.
* Export: each drone's plan becomes a MAVLink mission (:func:`plan_items`), written as a QGC
  ``.plan`` (:func:`qgc_plan_document`) or a Mission Planner ``QGC WPL 110`` file
  (:func:`waypoints_text`), and the area plus every drone's path as KML (:func:`kml_document`),
  so a plan made here can be checked, or flown one vehicle at a time, in QGC or Mission Planner.
  Sync points have no MAVLink mission equivalent and are not exported.

Pure functions on text and dicts; files are read and written by the caller.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from gcs.planning.areas import AreaFormatError, SearchArea, area_from_latlon, parse_area
from protocol.actions import (
    Action,
    GoBy,
    Goto,
    Hold,
    Land,
    ReturnToLaunch,
    SetSpeed,
    Takeoff,
    Waypoint,
    Waypoints,
)
from protocol.geo import offset_latlon
from protocol.taskfile import TaskFile

MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
NAV_WAYPOINT, NAV_LOITER_TIME, NAV_RETURN_TO_LAUNCH, NAV_LAND, NAV_TAKEOFF = 16, 19, 20, 21, 22
DO_CHANGE_SPEED = 178
MAX_TEXT_CHARS = 5_000_000  # an area or mission document larger than this is refused


class InterchangeError(AreaFormatError):
    """A document in a foreign format that cannot be read; the message says what is wrong."""


@dataclass(frozen=True)
class MissionItem:
    """One MAVLink mission item (``params`` are param1-4; x/y/z are lat, lon, alt)."""

    command: int
    frame: int
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


def _speed_item(speed: float) -> MissionItem:
    return MissionItem(DO_CHANGE_SPEED, MAV_FRAME_MISSION, params=(1.0, speed, -1.0, 0.0))


def plan_items(actions: Sequence[Action], home: tuple[float, float]) -> list[MissionItem]:
    """A plan's actions as a MAVLink mission for one vehicle (altitudes relative to home).

    ``go_by`` offsets are resolved from the planned position before them (the position a
    vehicle that flew the plan would be at); a land "here" lands at that position.
    """
    lat, lon, alt = home[0], home[1], 0.0
    items: list[MissionItem] = []
    rel = MAV_FRAME_GLOBAL_RELATIVE_ALT
    for action in actions:
        if isinstance(action, Takeoff):
            alt = action.alt
            items.append(MissionItem(NAV_TAKEOFF, rel, lat, lon, alt))
        elif isinstance(action, Goto | GoBy):
            if action.speed is not None:
                items.append(_speed_item(action.speed))
            if isinstance(action, GoBy):
                lat, lon = offset_latlon(lat, lon, action.north, action.east)
                alt += action.up
            else:
                lat, lon, alt = action.lat, action.lon, action.alt
            items.append(MissionItem(NAV_WAYPOINT, rel, lat, lon, alt))
        elif isinstance(action, Waypoints):
            if action.speed is not None:
                items.append(_speed_item(action.speed))
            for p in action.points:
                lat, lon, alt = p.lat, p.lon, p.alt
                items.append(MissionItem(NAV_WAYPOINT, rel, lat, lon, alt))
        elif isinstance(action, Land):
            if action.lat is not None and action.lon is not None:
                lat, lon = action.lat, action.lon
            items.append(MissionItem(NAV_LAND, rel, lat, lon, 0.0))
            alt = 0.0
        elif isinstance(action, ReturnToLaunch):
            items.append(MissionItem(NAV_RETURN_TO_LAUNCH, rel))
            lat, lon, alt = home[0], home[1], 0.0
        elif isinstance(action, Hold):
            items.append(MissionItem(NAV_LOITER_TIME, rel, lat, lon, alt, (action.seconds, 0.0, 0.0, 0.0)))
        elif isinstance(action, SetSpeed):
            items.append(_speed_item(action.speed))
    return items


def items_to_actions(items: Sequence[MissionItem]) -> list[Action]:
    """The fleetgcs actions a MAVLink mission describes (runs of waypoints become one action).

    Steps number the actions from 0; the result starts with a takeoff only if the mission does.
    """
    actions: list[Action] = []
    run: list[Waypoint] = []
    speed: float | None = None

    def flush() -> None:
        if run:
            actions.append(Waypoints(step=len(actions), points=list(run), speed=speed))
            run.clear()

    for item in items:
        if item.command == NAV_WAYPOINT:
            run.append(Waypoint(lat=item.lat, lon=item.lon, alt=item.alt))
            continue
        flush()
        if item.command == NAV_TAKEOFF:
            actions.append(Takeoff(step=len(actions), alt=item.alt))
        elif item.command == NAV_LAND:
            here = item.lat == 0.0 and item.lon == 0.0
            actions.append(
                Land(step=len(actions), lat=None if here else item.lat, lon=None if here else item.lon)
            )
        elif item.command == NAV_RETURN_TO_LAUNCH:
            actions.append(ReturnToLaunch(step=len(actions)))
        elif item.command == NAV_LOITER_TIME:
            actions.append(Hold(step=len(actions), seconds=item.params[0]))
        elif item.command == DO_CHANGE_SPEED and item.params[1] > 0:
            speed = item.params[1]
        else:
            raise InterchangeError(f"mission item with MAV_CMD {item.command} has no fleetgcs action")
    flush()
    return actions


# --- QGroundControl .plan ---------------------------------------------------------------------


def qgc_plan_document(
    items: Sequence[MissionItem],
    home: tuple[float, float],
    *,
    cruise_speed: float = 5.0,
    home_alt_amsl: float = 0.0,
) -> dict[str, Any]:
    """A QGroundControl ``.plan`` (file version 1, mission version 2) holding ``items``."""
    simple = []
    for n, it in enumerate(items, start=1):
        nan_free = [float(p) for p in it.params]
        simple.append(
            {
                "type": "SimpleItem",
                "autoContinue": True,
                "command": it.command,
                "doJumpId": n,
                "frame": it.frame,
                "params": [*nan_free, it.lat, it.lon, it.alt],
                "AMSLAltAboveTerrain": None,
                "Altitude": it.alt,
                "AltitudeMode": 1,
            }
        )
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "fleetgcs",
        "mission": {
            "version": 2,
            "firmwareType": 3,  # ArduPilot
            "vehicleType": 2,  # quadrotor
            "cruiseSpeed": cruise_speed,
            "hoverSpeed": cruise_speed,
            "globalPlanAltitudeMode": 1,
            "plannedHomePosition": [home[0], home[1], home_alt_amsl],
            "items": simple,
        },
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
    }


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InterchangeError(f"{what} is not a finite number: {value!r}")
    return float(value)


def _latlon(row: Any, what: str) -> tuple[float, float]:
    if not isinstance(row, list | tuple) or len(row) < 2:
        raise InterchangeError(f"{what} is not a [lat, lon, ...] array")
    lat, lon = _number(row[0], what), _number(row[1], what)
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise InterchangeError(f"{what} ({lat}, {lon}) is not a position on Earth")
    return lat, lon


def planned_home(obj: dict[str, Any]) -> tuple[float, float] | None:
    """A QGC plan's ``mission.plannedHomePosition`` as (lat, lon), or None when it has none."""
    home = (obj.get("mission") or {}).get("plannedHomePosition")
    if home is None:
        return None
    return _latlon(home, "mission.plannedHomePosition")


def read_qgc_mission(obj: dict[str, Any]) -> tuple[tuple[float, float] | None, list[MissionItem]]:
    """The planned home and the simple items of a QGC ``.plan`` (complex items are refused)."""
    if obj.get("fileType") != "Plan":
        raise InterchangeError("not a QGroundControl plan (fileType is not 'Plan')")
    items = []
    for n, item in enumerate((obj.get("mission") or {}).get("items") or [], start=1):
        if item.get("type") != "SimpleItem":
            kind = item.get("complexItemType", item.get("type"))
            raise InterchangeError(
                f"mission item {n} is a {kind} complex item; only simple items can be read"
            )
        params = item.get("params") or []
        if len(params) != 7:
            raise InterchangeError(f"mission item {n} has {len(params)} params, not 7")
        p = [0.0 if v is None else _number(v, f"mission item {n} param") for v in params]
        items.append(
            MissionItem(
                int(item.get("command", 0)),
                int(item.get("frame", MAV_FRAME_GLOBAL_RELATIVE_ALT)),
                p[4],
                p[5],
                p[6],
                (p[0], p[1], p[2], p[3]),
            )
        )
    return planned_home(obj), items


@dataclass(frozen=True)
class QgcSurvey:
    """What the operator set in a QGroundControl survey.

    ``step_m`` is QGC's line spacing (``AdjustedFootprintSide``), ``side_overlap`` a fraction,
    ``angle_deg`` our sweep rotation (legs along ``-angle`` from east) for QGC's grid angle
    ``qgc_angle_deg`` (the transects' bearing, clockwise from north).
    """

    area: SearchArea
    home: tuple[float, float] | None
    altitude_m: float | None
    step_m: float | None
    side_overlap: float
    qgc_angle_deg: float | None

    @property
    def angle_deg(self) -> float | None:
        if self.qgc_angle_deg is None:
            return None
        return self.qgc_angle_deg % 180.0 - 90.0

    @property
    def swath_m(self) -> float | None:
        """The footprint width the spacing implies (spacing / (1 - overlap))."""
        return None if self.step_m is None else self.step_m / (1.0 - self.side_overlap)


def read_qgc_survey(obj: dict[str, Any], name: str = "area") -> QgcSurvey:
    """The area and settings of a QGC plan's first survey (or its first inclusion fence).

    Altitude is the survey's ``DistanceToSurface`` when it is relative to home (QGC's
    ``DistanceToSurfaceRelative``, or ``DistanceMode`` 1); an AMSL or terrain-following
    altitude cannot be flown relative to home and is refused rather than misread.
    """
    area = parse_area(obj, name)
    survey = next(
        (
            i
            for i in (obj.get("mission") or {}).get("items") or []
            if i.get("type") == "ComplexItem" and str(i.get("complexItemType", "")).lower() == "survey"
        ),
        None,
    )
    alt = step = angle = None
    overlap = 0.0
    if survey is not None:
        transect = survey.get("TransectStyleComplexItem") or {}
        calc = transect.get("CameraCalc") or survey.get("CameraCalc") or {}
        if "DistanceToSurface" in calc:
            relative = calc.get("DistanceToSurfaceRelative", calc.get("DistanceMode", 1) == 1)
            if not relative or transect.get("FollowTerrain"):
                raise InterchangeError(
                    "the survey altitude is above mean sea level or follows terrain; fleetgcs flies "
                    "altitudes relative to home: set the survey to relative altitude in QGC"
                )
            alt = _number(calc["DistanceToSurface"], "CameraCalc.DistanceToSurface")
        if "AdjustedFootprintSide" in calc:
            step = _number(calc["AdjustedFootprintSide"], "CameraCalc.AdjustedFootprintSide")
        if "SideOverlap" in calc:
            overlap = _number(calc["SideOverlap"], "CameraCalc.SideOverlap") / 100.0
            if not 0.0 <= overlap < 1.0:
                raise InterchangeError(f"CameraCalc.SideOverlap {overlap * 100:g} % is not within 0-99 %")
        if "angle" in survey:
            angle = _number(survey["angle"], "survey angle")
    if alt is not None and alt <= 0:
        raise InterchangeError(f"survey altitude {alt} m is not above home")
    if step is not None and step <= 0:
        raise InterchangeError(f"survey line spacing {step} m is not positive")
    return QgcSurvey(area, planned_home(obj), alt, step, overlap, angle)


# --- Mission Planner .waypoints -----------------------------------------------------------------


def waypoints_text(
    items: Sequence[MissionItem], home: tuple[float, float], home_alt_amsl: float = 0.0
) -> str:
    """Mission Planner's ``QGC WPL 110`` text: row 0 is home, then one row per item."""
    rows = [
        "QGC WPL 110",
        f"0\t1\t{MAV_FRAME_GLOBAL}\t{NAV_WAYPOINT}\t0\t0\t0\t0\t{home[0]:.8f}\t{home[1]:.8f}\t{home_alt_amsl:.6f}\t1",
    ]
    for n, it in enumerate(items, start=1):
        p = "\t".join(f"{v:.8f}" for v in it.params)
        rows.append(f"{n}\t0\t{it.frame}\t{it.command}\t{p}\t{it.lat:.8f}\t{it.lon:.8f}\t{it.alt:.6f}\t1")
    return "\n".join(rows) + "\n"


def read_waypoints(text: str) -> tuple[tuple[float, float], list[MissionItem]]:
    """Home and items of a ``QGC WPL 110`` file (as Mission Planner writes and reads it)."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("QGC WPL 110"):
        raise InterchangeError("not a Mission Planner waypoint file (first line is not 'QGC WPL 110')")
    home: tuple[float, float] | None = None
    items = []
    for n, line in enumerate(lines[1:], start=2):
        cols = line.split("\t") if "\t" in line else line.split()
        if len(cols) != 12:
            raise InterchangeError(f"line {n}: {len(cols)} columns, not 12")
        try:
            v = [float(c) for c in cols]
        except ValueError:
            raise InterchangeError(f"line {n}: a column is not a number") from None
        if not all(math.isfinite(x) for x in v):
            raise InterchangeError(f"line {n}: a column is not finite")
        if int(v[0]) == 0 and home is None:
            home = _latlon([v[8], v[9]], f"line {n} (home)")
            continue
        items.append(MissionItem(int(v[3]), int(v[2]), v[8], v[9], v[10], (v[4], v[5], v[6], v[7])))
    if home is None:
        raise InterchangeError("the waypoint file has no home row (index 0)")
    return home, items


# --- KML ------------------------------------------------------------------------------------------

KML_NS = "http://www.opengis.net/kml/2.2"


def _kml_coords(points: Sequence[tuple[float, float]], alt: float | None = None) -> str:
    if alt is None:
        return " ".join(f"{lon:.8f},{lat:.8f}" for lat, lon in points)
    return " ".join(f"{lon:.8f},{lat:.8f},{alt:.2f}" for lat, lon in points)


def _esc(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def kml_document(
    name: str,
    area: Sequence[tuple[float, float]] | None,
    paths: Mapping[str, Sequence[tuple[float, float]]],
    altitude_m: float | None = None,
) -> str:
    """KML 2.2: the area as a Polygon placemark and each drone's path as a LineString.

    With ``altitude_m`` the paths carry it, relative to the ground (``relativeToGround``).
    """
    marks = []
    if area:
        ring = [*area, area[0]]
        marks.append(
            f"<Placemark><name>{_esc(name)} area</name><Polygon><outerBoundaryIs><LinearRing>"
            f"<coordinates>{_kml_coords(ring)}</coordinates></LinearRing></outerBoundaryIs></Polygon></Placemark>"
        )
    mode = "" if altitude_m is None else "<altitudeMode>relativeToGround</altitudeMode>"
    for drone, pts in paths.items():
        if len(pts) < 2:
            continue
        marks.append(
            f"<Placemark><name>{_esc(drone)}</name><LineString>{mode}"
            f"<coordinates>{_kml_coords(pts, altitude_m)}</coordinates></LineString></Placemark>"
        )
    body = "".join(marks)
    return (
        f'<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="{KML_NS}"><Document>'
        f"<name>{_esc(name)}</name>{body}</Document></kml>\n"
    )


@dataclass(frozen=True)
class KmlContent:
    """Polygons (outer rings) and named line strings of a KML document, as (lat, lon) lists."""

    polygons: list[tuple[str, list[tuple[float, float]]]]
    lines: list[tuple[str, list[tuple[float, float]]]]


def _parse_kml_coordinates(text: str, where: str) -> list[tuple[float, float]]:
    out = []
    for token in text.split():
        parts = token.split(",")
        if len(parts) < 2:
            raise InterchangeError(f"{where}: coordinate {token!r} is not lon,lat[,alt]")
        try:
            lon, lat = float(parts[0]), float(parts[1])
        except ValueError:
            raise InterchangeError(f"{where}: coordinate {token!r} is not numeric") from None
        out.append(_latlon([lat, lon], where))
    return out


def read_kml(text: str) -> KmlContent:
    """Polygons and line strings of a KML document (namespaced or not; DTDs are refused)."""
    if len(text) > MAX_TEXT_CHARS:
        raise InterchangeError(f"KML document larger than {MAX_TEXT_CHARS} characters")
    if re.search(r"<!(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        raise InterchangeError("KML with a DOCTYPE or ENTITY declaration is refused")
    try:
        root = ET.fromstring(text.lstrip("\ufeff").strip())
    except ET.ParseError as exc:
        raise InterchangeError(f"not valid KML (XML): {exc}") from None
    if root.tag.split("}")[-1] != "kml":
        raise InterchangeError(f"not KML: the root element is <{root.tag.split('}')[-1]}>")

    def local(el: ET.Element) -> str:
        return el.tag.split("}")[-1]

    polygons: list[tuple[str, list[tuple[float, float]]]] = []
    lines: list[tuple[str, list[tuple[float, float]]]] = []
    for mark in (el for el in root.iter() if local(el) == "Placemark"):
        name = next((c.text or "" for c in mark if local(c) == "name"), "").strip()
        for geom in mark.iter():
            kind = local(geom)
            if kind == "Polygon":
                outer = next((e for e in geom.iter() if local(e) == "outerBoundaryIs"), None)
                coords = next((e for e in (outer or geom).iter() if local(e) == "coordinates"), None)
                if coords is None or not (coords.text or "").strip():
                    raise InterchangeError(f"placemark {name or '?'}: a Polygon without coordinates")
                polygons.append((name, _parse_kml_coordinates(coords.text or "", f"placemark {name or '?'}")))
                if any(local(e) == "innerBoundaryIs" for e in geom.iter()):
                    raise InterchangeError(
                        f"placemark {name or '?'}: a polygon with holes is not supported; remove the holes"
                    )
            elif kind == "LineString":
                coords = next((e for e in geom if local(e) == "coordinates"), None)
                if coords is not None:
                    lines.append(
                        (name, _parse_kml_coordinates(coords.text or "", f"placemark {name or '?'}"))
                    )
    return KmlContent(polygons, lines)


def area_from_kml(text: str, name: str = "area") -> SearchArea:
    """The first polygon of a KML document as a search area."""
    content = read_kml(text)
    if not content.polygons:
        raise InterchangeError("the KML document holds no Polygon placemark")
    mark, ring = content.polygons[0]
    return area_from_latlon(ring, mark or name)


EXPORT_FORMATS = ("plan", "waypoints", "kml")


def export_files(
    task: TaskFile,
    homes: Mapping[str, tuple[float, float]],
    formats: Sequence[str],
    *,
    area: Sequence[tuple[float, float]] | None = None,
    altitude_m: float | None = None,
    cruise_speed: float = 5.0,
) -> dict[str, str]:
    """File name -> text for a task file: ``<agent>.plan`` / ``<agent>.waypoints`` per plan and
    ``<task>.kml`` (the area and every plan's flown points), for the ``formats`` asked."""
    bad = [f for f in formats if f not in EXPORT_FORMATS]
    if bad:
        raise ValueError(f"export formats are {', '.join(EXPORT_FORMATS)}; got {bad}")
    files: dict[str, str] = {}
    paths: dict[str, list[tuple[float, float]]] = {}
    for agent_plan in task.plans:
        home = homes[agent_plan.label]
        items = plan_items(agent_plan.actions, home)
        paths[agent_plan.label] = [(i.lat, i.lon) for i in items if i.command == NAV_WAYPOINT]
        if "plan" in formats:
            document = qgc_plan_document(items, home, cruise_speed=cruise_speed)
            files[f"{agent_plan.label}.plan"] = json.dumps(document, indent=2)
        if "waypoints" in formats:
            files[f"{agent_plan.label}.waypoints"] = waypoints_text(items, home)
    if "kml" in formats:
        files[f"{task.name}.kml"] = kml_document(task.name, area, paths, altitude_m)
    return files


def load_area_text(text: str, name: str = "area") -> tuple[SearchArea, QgcSurvey | None]:
    """An area document of any supported format: KML, QGC ``.plan``, GeoJSON or [[lat, lon], ...].

    The second value holds a QGC plan's survey settings (None for other formats).
    """
    if len(text) > MAX_TEXT_CHARS:
        raise InterchangeError(f"area document larger than {MAX_TEXT_CHARS} characters")
    body = text.lstrip("\ufeff").lstrip()
    if body.startswith("<"):
        return area_from_kml(body, name), None
    try:
        obj = json.loads(body)
    except json.JSONDecodeError as exc:
        raise InterchangeError(f"not JSON (GeoJSON, QGC .plan, [[lat, lon], ...]) nor KML: {exc}") from None
    if isinstance(obj, dict) and obj.get("fileType") == "Plan":
        survey = read_qgc_survey(obj, name)
        return survey.area, survey
    return parse_area(obj, name), None
