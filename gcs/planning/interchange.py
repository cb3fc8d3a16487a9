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
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

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
from protocol.geo import distance_m, offset_latlon
from protocol.taskfile import TaskFile, first_error

MAV_FRAME_GLOBAL = 0
MAV_FRAME_MISSION = 2
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = 6
RELATIVE_FRAMES = (MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
FRAME_NAMES = {0: "above mean sea level", 5: "above mean sea level", 10: "above terrain", 11: "above terrain"}
NAV_WAYPOINT, NAV_LOITER_TIME, NAV_RETURN_TO_LAUNCH, NAV_LAND, NAV_TAKEOFF = 16, 19, 20, 21, 22
DO_CHANGE_SPEED = 178
MAX_TEXT_CHARS = 5_000_000  # an area or mission document larger than this is refused


class InterchangeError(AreaFormatError):
    """A document in a foreign format that cannot be read; the message says what is wrong."""


@dataclass(frozen=True)
class MissionItem:
    """One MAVLink mission item (``params`` are param1-4; x/y/z are lat, lon, alt).

    ``where`` says where it came from (e.g. "item 3"), for error messages only.
    """

    command: int
    frame: int
    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    where: str = field(default="", compare=False)

    def label(self) -> str:
        """``item 3 (MAV_CMD 183 DO_SET_SERVO)``: how an error names this item."""
        name = COMMAND_NAMES.get(self.command)
        command = f"MAV_CMD {self.command}" + (f" {name}" if name else "")
        return f"{self.where} ({command})" if self.where else command


COMMAND_NAMES = {
    16: "NAV_WAYPOINT",
    17: "NAV_LOITER_UNLIM",
    18: "NAV_LOITER_TURNS",
    19: "NAV_LOITER_TIME",
    20: "NAV_RETURN_TO_LAUNCH",
    21: "NAV_LAND",
    22: "NAV_TAKEOFF",
    31: "NAV_LOITER_TO_ALT",
    82: "NAV_SPLINE_WAYPOINT",
    84: "NAV_VTOL_TAKEOFF",
    85: "NAV_VTOL_LAND",
    93: "NAV_DELAY",
    112: "CONDITION_DELAY",
    114: "CONDITION_DISTANCE",
    115: "CONDITION_YAW",
    177: "DO_JUMP",
    178: "DO_CHANGE_SPEED",
    179: "DO_SET_HOME",
    183: "DO_SET_SERVO",
    189: "DO_LAND_START",
    195: "DO_SET_ROI_LOCATION",
    200: "DO_CONTROL_VIDEO",
    201: "DO_SET_ROI",
    203: "DO_DIGICAM_CONTROL",
    205: "DO_MOUNT_CONTROL",
    206: "DO_SET_CAM_TRIGG_DIST",
    211: "DO_GRIPPER",
    2000: "IMAGE_START_CAPTURE",
    2001: "IMAGE_STOP_CAPTURE",
    2500: "VIDEO_START_CAPTURE",
    2501: "VIDEO_STOP_CAPTURE",
}


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


def _relative_alt(item: MissionItem) -> float:
    """The item's altitude above home; an AMSL or terrain frame is refused, not misread."""
    if item.frame not in RELATIVE_FRAMES:
        frame = FRAME_NAMES.get(item.frame, "not relative to home")
        raise InterchangeError(
            f"{item.label()}: altitude frame {item.frame} ({frame}); fleetgcs flies altitudes relative "
            "to home: set the item's altitude to relative (QGC: 'Relative To Launch', Mission Planner: "
            "'Relative')"
        )
    return item.alt


def items_to_actions(items: Sequence[MissionItem]) -> list[Action]:
    """The fleetgcs actions a MAVLink mission describes (runs of waypoints become one action).

    Steps number the actions from 0; the result starts with a takeoff only if the mission does.
    Altitudes must be relative to home; a command without a fleetgcs action is refused, naming
    the item. A waypoint's hold time (param1) becomes a hold after it.
    """
    actions: list[Action] = []
    run: list[Waypoint] = []
    speed: float | None = None
    here: tuple[float, float] | None = None  # the last position the mission flew to

    def flush() -> None:
        if run:
            actions.append(Waypoints(step=len(actions), points=list(run), speed=speed))
            run.clear()

    for item in items:
        try:
            if item.command == NAV_WAYPOINT:
                run.append(Waypoint(lat=item.lat, lon=item.lon, alt=_relative_alt(item)))
                here = (item.lat, item.lon)
                if item.params[0] > 0:
                    flush()
                    actions.append(Hold(step=len(actions), seconds=item.params[0]))
                continue
            flush()
            if item.command == NAV_TAKEOFF:
                actions.append(Takeoff(step=len(actions), alt=_relative_alt(item)))
                if item.lat != 0.0 or item.lon != 0.0:
                    here = (item.lat, item.lon)
            elif item.command == NAV_LAND:
                in_place = item.lat == 0.0 and item.lon == 0.0
                actions.append(
                    Land(
                        step=len(actions),
                        lat=None if in_place else item.lat,
                        lon=None if in_place else item.lon,
                    )
                )
            elif item.command == NAV_RETURN_TO_LAUNCH:
                actions.append(ReturnToLaunch(step=len(actions)))
            elif item.command == NAV_LOITER_TIME:
                elsewhere = here is None or distance_m(*here, item.lat, item.lon) > 1.0
                if (item.lat != 0.0 or item.lon != 0.0) and elsewhere:  # loiter there, not here
                    run.append(Waypoint(lat=item.lat, lon=item.lon, alt=_relative_alt(item)))
                    here = (item.lat, item.lon)
                    flush()
                actions.append(Hold(step=len(actions), seconds=item.params[0]))
            elif item.command == DO_CHANGE_SPEED:
                if item.params[1] > 0:
                    speed = item.params[1]
            else:
                raise InterchangeError(f"{item.label()} has no fleetgcs action; remove it from the mission")
        except ValidationError as exc:
            raise InterchangeError(f"{item.label()}: {first_error(exc)}") from None
    flush()
    return actions


# --- QGroundControl .plan ---------------------------------------------------------------------


def qgc_plan_document(
    items: Sequence[MissionItem],
    home: tuple[float, float],
    *,
    cruise_speed: float = 5.0,
    home_alt_amsl: float = 0.0,
    note: str | None = None,
    home_assumed: bool = False,
) -> dict[str, Any]:
    """A QGroundControl ``.plan`` (file version 1, mission version 2) holding ``items``.

    ``note``: what the reader must know of the file, e.g. that its home is assumed (a top-level
    ``fleetgcsNote``; QGroundControl reads the keys it knows and ignores the others).
    ``home_assumed``: the planned home is a stand-in (``"fleetgcsHomeAssumed": true``), which
    :func:`planned_home` reads back as no home.
    """
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
    document: dict[str, Any] = {
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
    if note:
        document["fleetgcsNote"] = note
    if home_assumed:
        document[HOME_ASSUMED_KEY] = True
    return document


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


HOME_ASSUMED_KEY = "fleetgcsHomeAssumed"


def planned_home(obj: dict[str, Any]) -> tuple[float, float] | None:
    """A QGC plan's ``mission.plannedHomePosition`` as (lat, lon), or None when it has none or
    our export marked it a stand-in (``fleetgcsHomeAssumed``): nothing may plan from it."""
    home = (obj.get("mission") or {}).get("plannedHomePosition")
    if home is None or obj.get(HOME_ASSUMED_KEY) is True:
        return None
    return _latlon(home, "mission.plannedHomePosition")


def read_qgc_mission(obj: dict[str, Any]) -> tuple[tuple[float, float] | None, list[MissionItem]]:
    """The planned home and the items of a QGC ``.plan``.

    A survey complex item becomes waypoints through its transects (QGC's
    ``VisualTransectPoints``) at the survey altitude; other complex items are refused.
    """
    if obj.get("fileType") != "Plan":
        raise InterchangeError("not a QGroundControl plan (fileType is not 'Plan')")
    items = []
    raw_items = (obj.get("mission") or {}).get("items") or []
    if not isinstance(raw_items, list):
        raise InterchangeError("mission.items is not a list")
    for n, item in enumerate(raw_items, start=1):
        if not isinstance(item, dict):
            raise InterchangeError(f"item {n} is not an object")
        if item.get("type") != "SimpleItem":
            items.extend(_complex_items(item, n))
            continue
        params = item.get("params") or []
        if not isinstance(params, list) or len(params) != 7:
            raise InterchangeError(f"item {n} has {len(params)} params, not 7")
        p = [0.0 if v is None else _number(v, f"item {n} param") for v in params]
        command = _number(item.get("command", 0), f"item {n} command")
        frame = _number(item.get("frame", MAV_FRAME_GLOBAL_RELATIVE_ALT), f"item {n} frame")
        items.append(
            MissionItem(int(command), int(frame), p[4], p[5], p[6], (p[0], p[1], p[2], p[3]), f"item {n}")
        )
    return planned_home(obj), items


def _complex_items(item: dict[str, Any], n: int) -> list[MissionItem]:
    """A QGC survey's transects as waypoints at its altitude (relative to home)."""
    kind = str(item.get("complexItemType", item.get("type")))
    if kind.lower() != "survey":
        raise InterchangeError(
            f"item {n} is a {kind} complex item; of complex items only a survey can be read"
        )
    transect = item.get("TransectStyleComplexItem") or {}
    alt = _survey_altitude(item)
    if alt is None:
        raise InterchangeError(f"item {n} (survey) has no altitude (CameraCalc.DistanceToSurface)")
    points = transect.get("VisualTransectPoints") or []
    if not isinstance(points, list) or len(points) < 2:
        raise InterchangeError(
            f"item {n} (survey) has no transects (VisualTransectPoints); open and save the plan in QGC"
        )
    return [
        MissionItem(
            NAV_WAYPOINT,
            MAV_FRAME_GLOBAL_RELATIVE_ALT,
            *_latlon(row, f"item {n} (survey) transect"),
            alt,
            where=f"item {n} (survey)",
        )
        for row in points
    ]


def _survey_altitude(survey: dict[str, Any]) -> float | None:
    """A QGC survey's ``DistanceToSurface`` when relative to home; None when it has none.

    QGC says relative with ``DistanceToSurfaceRelative`` or ``DistanceMode`` 1; an AMSL or
    terrain-following altitude cannot be flown relative to home and is refused rather than misread.
    """
    transect = survey.get("TransectStyleComplexItem") or {}
    calc = transect.get("CameraCalc") or survey.get("CameraCalc") or {}
    if "DistanceToSurface" not in calc:
        return None
    relative = calc.get("DistanceToSurfaceRelative", calc.get("DistanceMode", 1) == 1)
    if not relative or transect.get("FollowTerrain"):
        raise InterchangeError(
            "the survey altitude is above mean sea level or follows terrain; fleetgcs flies "
            "altitudes relative to home: set the survey to relative altitude in QGC"
        )
    alt = _number(calc["DistanceToSurface"], "CameraCalc.DistanceToSurface")
    if alt <= 0:
        raise InterchangeError(f"survey altitude {alt} m is not above home")
    return alt


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
        alt = _survey_altitude(survey)
        if "AdjustedFootprintSide" in calc:
            step = _number(calc["AdjustedFootprintSide"], "CameraCalc.AdjustedFootprintSide")
        if "SideOverlap" in calc:
            overlap = _number(calc["SideOverlap"], "CameraCalc.SideOverlap") / 100.0
            if not 0.0 <= overlap < 1.0:
                raise InterchangeError(f"CameraCalc.SideOverlap {overlap * 100:g} % is not within 0-99 %")
        if "angle" in survey:
            angle = _number(survey["angle"], "survey angle")
    if step is not None and step <= 0:
        raise InterchangeError(f"survey line spacing {step} m is not positive")
    return QgcSurvey(area, planned_home(obj), alt, step, overlap, angle)


# --- Mission Planner .waypoints -----------------------------------------------------------------


WPL_HOME_REAL, WPL_HOME_STAND_IN = 1, 0  # row 0's ``current`` column (see waypoints_text)


def waypoints_text(
    items: Sequence[MissionItem],
    home: tuple[float, float],
    home_alt_amsl: float = 0.0,
    *,
    home_assumed: bool = False,
) -> str:
    """Mission Planner's ``QGC WPL 110`` text: row 0 is home, then one row per item.

    Row 0's ``current`` column marks the home: 1 for a real home, as Mission Planner writes it,
    0 for a stand-in (``home_assumed``: no drone or operator gave it). The format has no room for
    a note: QGroundControl reads exactly 12 tab-separated columns per line and calls a comment
    line a corrupted file; Mission Planner and QGC ignore the column on the home row, and
    :func:`read_waypoints` reads a 0 back as no home.
    """
    current = WPL_HOME_STAND_IN if home_assumed else WPL_HOME_REAL
    rows = [
        "QGC WPL 110",
        f"0\t{current}\t{MAV_FRAME_GLOBAL}\t{NAV_WAYPOINT}\t0\t0\t0\t0\t{home[0]:.8f}\t{home[1]:.8f}\t{home_alt_amsl:.6f}\t1",
    ]
    for n, it in enumerate(items, start=1):
        p = "\t".join(f"{v:.8f}" for v in it.params)
        rows.append(f"{n}\t0\t{it.frame}\t{it.command}\t{p}\t{it.lat:.8f}\t{it.lon:.8f}\t{it.alt:.6f}\t1")
    return "\n".join(rows) + "\n"


def _wpl_home(v: list[float], n: int) -> tuple[float, float] | None:
    """Row 0 as a home, or None when it is no real home: marked a stand-in (``current`` 0), or
    Mission Planner's own "no home" row (command 0 at 0, 0)."""
    if int(v[1]) == WPL_HOME_STAND_IN or int(v[3]) == 0 or (v[8] == 0.0 and v[9] == 0.0):
        return None
    return _latlon([v[8], v[9]], f"line {n} (home)")


def read_waypoints(text: str) -> tuple[tuple[float, float] | None, list[MissionItem]]:
    """Home and items of a ``QGC WPL 110`` file (as Mission Planner writes and reads it).

    The home is None when row 0 is not a real home (:func:`_wpl_home`): a stand-in is never
    flown to nor compared with. Blank lines and ``#`` comment lines are skipped, as Mission
    Planner and pymavlink do.
    """
    lines = [ln.strip() for ln in text.strip().splitlines()]
    if not lines or not lines[0].startswith("QGC WPL 110"):
        raise InterchangeError("not a Mission Planner waypoint file (first line is not 'QGC WPL 110')")
    home: tuple[float, float] | None = None
    seen_home = False
    items = []
    for n, line in enumerate(lines[1:], start=2):
        if not line or line.startswith("#"):
            continue
        cols = line.split("\t") if "\t" in line else line.split()
        if len(cols) != 12:
            raise InterchangeError(f"line {n}: {len(cols)} columns, not 12")
        try:
            v = [float(c) for c in cols]
        except ValueError:
            raise InterchangeError(f"line {n}: a column is not a number") from None
        if not all(math.isfinite(x) for x in v):
            raise InterchangeError(f"line {n}: a column is not finite")
        if int(v[0]) == 0 and not seen_home:
            seen_home, home = True, _wpl_home(v, n)
            continue
        where = f"waypoint {int(v[0])} (line {n})"
        items.append(MissionItem(int(v[3]), int(v[2]), v[8], v[9], v[10], (v[4], v[5], v[6], v[7]), where))
    if not seen_home:
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
    description: str | None = None,
) -> str:
    """KML 2.2: the area as a Polygon placemark and each drone's path as a LineString.

    With ``altitude_m`` the paths carry it, relative to the ground (``relativeToGround``).
    ``description`` goes into the document (e.g. which homes are assumed).
    """
    marks = []
    if description:
        marks.append(f"<description>{_esc(description)}</description>")
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
    home_alts: Mapping[str, float] | None = None,
    assumed_homes: Collection[str] = (),
) -> dict[str, str]:
    """File name -> text for a task file: ``<agent>.plan`` / ``<agent>.waypoints`` per plan and
    ``<task>.kml`` (the area and every plan's whole flight: home, transit, survey, return), for
    the ``formats`` asked.

    ``home_alts``: each drone's home altitude AMSL where known (else 0 m, and the files say so);
    ``assumed_homes``: drones whose home is a stand-in (no drone or operator gave it), named in
    the ``.plan`` (``fleetgcsNote``, and ``fleetgcsHomeAssumed``) and the KML description, and
    marked in the ``.waypoints`` home row (``current`` 0): a re-import reads no home from them.
    """
    bad = [f for f in formats if f not in EXPORT_FORMATS]
    if bad:
        raise ValueError(f"export formats are {', '.join(EXPORT_FORMATS)}; got {bad}")
    alts = home_alts or {}
    files: dict[str, str] = {}
    paths: dict[str, list[tuple[float, float]]] = {}
    notes: list[str] = []
    for agent_plan in task.plans:
        label = agent_plan.label
        home = homes[label]
        alt = alts.get(label)
        assumed = label in assumed_homes
        note = home_note(label, home, alt, assumed)
        if note:
            notes.append(note)
        items = plan_items(agent_plan.actions, home)
        paths[label] = flown_points(items, home)
        if "plan" in formats:
            document = qgc_plan_document(
                items,
                home,
                cruise_speed=cruise_speed,
                home_alt_amsl=alt or 0.0,
                note=note,
                home_assumed=assumed,
            )
            files[f"{label}.plan"] = json.dumps(document, indent=2)
        if "waypoints" in formats:
            files[f"{label}.waypoints"] = waypoints_text(items, home, alt or 0.0, home_assumed=assumed)
    if "kml" in formats:
        files[f"{task.name}.kml"] = kml_document(task.name, area, paths, altitude_m, " ".join(notes) or None)
    return files


def home_note(label: str, home: tuple[float, float], alt: float | None, assumed: bool) -> str | None:
    """What an export must say about a drone's home, or None when it is the drone's real one."""
    if assumed:
        return (
            f"{label}: home ({home[0]:.6f}, {home[1]:.6f}) is assumed (the area's first corner; no "
            "connected drone or --home gave it) and its altitude 0 m AMSL is not known."
        )
    if alt is None:
        return f"{label}: home altitude not known; 0 m AMSL written (mission altitudes are relative to home)."
    return None


def flown_points(items: Sequence[MissionItem], home: tuple[float, float]) -> list[tuple[float, float]]:
    """The whole flight of a mission as lat/lon: from home, through every positioned item (take-off,
    transit and survey waypoints, landing), and back home on a return-to-launch."""
    points = [home]
    for item in items:
        if item.command == NAV_RETURN_TO_LAUNCH:
            point = home
        elif item.command in (NAV_TAKEOFF, NAV_WAYPOINT, NAV_LAND, NAV_LOITER_TIME):
            point = (item.lat, item.lon)
        else:
            continue
        if point != points[-1]:
            points.append(point)
    return points


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
