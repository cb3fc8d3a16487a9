"""QGroundControl .plan, Mission Planner .waypoints and KML: import what operators set, export round trips."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gcs.commands import plan as plan_cmd
from gcs.planning.interchange import (
    DO_CHANGE_SPEED,
    NAV_LAND,
    NAV_LOITER_TIME,
    NAV_RETURN_TO_LAUNCH,
    NAV_TAKEOFF,
    NAV_WAYPOINT,
    InterchangeError,
    export_files,
    items_to_actions,
    kml_document,
    load_area_text,
    plan_items,
    qgc_plan_document,
    read_kml,
    read_qgc_mission,
    read_qgc_survey,
    read_waypoints,
    waypoints_text,
)
from protocol.actions import GoBy, Goto, Hold, Land, ReturnToLaunch, Takeoff, Waypoint, Waypoints
from protocol.geo import distance_m
from protocol.taskfile import AgentPlan, TaskFile, load_task_text

HOME = (47.39770, 8.54560)
FIELD = [(47.3980, 8.5450), (47.3980, 8.5480), (47.4000, 8.5480), (47.4000, 8.5450)]


def qgc_survey_plan(alt: float = 35.0, spacing: float = 18.0, overlap_pct: float = 10.0, angle: float = 30.0):
    """A plan shaped like QGroundControl 4.x saves a survey (only the fields it always writes)."""
    return {
        "fileType": "Plan",
        "groundStation": "QGroundControl",
        "version": 1,
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {
            "cruiseSpeed": 15,
            "firmwareType": 3,
            "hoverSpeed": 5,
            "vehicleType": 2,
            "version": 2,
            "globalPlanAltitudeMode": 1,
            "plannedHomePosition": [HOME[0], HOME[1], 488.0],
            "items": [
                {
                    "type": "SimpleItem",
                    "command": 22,
                    "doJumpId": 1,
                    "frame": 3,
                    "params": [0, 0, 0, None, 0, 0, alt],
                    "autoContinue": True,
                    "Altitude": alt,
                    "AltitudeMode": 1,
                    "AMSLAltAboveTerrain": None,
                },
                {
                    "type": "ComplexItem",
                    "complexItemType": "survey",
                    "version": 5,
                    "angle": angle,
                    "entryLocation": 0,
                    "flyAlternateTransects": False,
                    "splitConcavePolygons": False,
                    "polygon": [list(p) for p in FIELD],
                    "TransectStyleComplexItem": {
                        "CameraCalc": {
                            "AdjustedFootprintFrontal": 25,
                            "AdjustedFootprintSide": spacing,
                            "CameraName": "Manual (no camera specs)",
                            "DistanceToSurface": alt,
                            "DistanceToSurfaceRelative": True,
                            "SideOverlap": overlap_pct,
                            "version": 1,
                        },
                        "CameraShots": 0,
                        "CameraTriggerInTurnAround": True,
                        "FollowTerrain": False,
                        "HoverAndCapture": False,
                        "Items": [],
                        "Refly90Degrees": False,
                        "TurnAroundDistance": 10,
                        "VisualTransectPoints": [],
                        "version": 1,
                    },
                },
                {
                    "type": "SimpleItem",
                    "command": 20,
                    "doJumpId": 3,
                    "frame": 2,
                    "params": [0, 0, 0, 0, 0, 0, 0],
                    "autoContinue": True,
                },
            ],
        },
    }


def _main(argv: list[str]) -> int:
    import argparse

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    plan_cmd.register(sub)
    args = parser.parse_args(argv)
    return int(args.run(args))


def _close(a, b, tol: float = 1e-8) -> bool:
    return np.asarray(a, float).shape == np.asarray(b, float).shape and np.allclose(a, b, atol=tol, rtol=0)


def _bearing(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = (b[0] - a[0]) * 111_320.0
    east = (b[1] - a[1]) * 111_320.0 * math.cos(math.radians(a[0]))
    return math.degrees(math.atan2(east, north)) % 180.0


def test_qgc_survey_settings_are_read() -> None:
    survey = read_qgc_survey(qgc_survey_plan())
    assert survey.home == HOME
    assert survey.altitude_m == 35.0 and survey.step_m == 18.0
    assert survey.side_overlap == pytest.approx(0.1) and survey.swath_m == pytest.approx(20.0)
    assert survey.qgc_angle_deg == 30.0 and survey.angle_deg == pytest.approx(-60.0)
    assert survey.area.vertices == FIELD


def test_gcs_plan_keeps_what_the_operator_set_in_qgc(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    area = tmp_path / "field.plan"
    area.write_text(json.dumps(qgc_survey_plan()))
    out = tmp_path / "out"
    assert _main(["plan", str(area), "--return", "land_home", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["altitude_m"] == 35.0 and summary["step_m"] == 18.0 and summary["swath_m"] == 20.0
    task = load_task_text((out / "mission.json").read_text())
    (plan,) = task.plans
    survey = next(a for a in plan.actions if isinstance(a, Waypoints))
    assert {p.alt for p in survey.points} == {35.0}
    pts = [(p.lat, p.lon) for p in survey.points]
    longest = max(itertools.pairwise(pts), key=lambda ab: distance_m(*ab[0], *ab[1]))
    assert _bearing(*longest) == pytest.approx(30.0, abs=0.5)  # QGC's grid angle: transects at 30 deg
    # QGC's planned home is the drone's home: it lands there
    land = plan.actions[-1]
    assert isinstance(land, Land) and _close((land.lat, land.lon), HOME, 1e-7)
    assert summary["sweep"]["angle_deg"] == pytest.approx(-60.0)


def test_gcs_plan_options_override_the_qgc_survey(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    area = tmp_path / "field.plan"
    area.write_text(json.dumps(qgc_survey_plan()))
    argv = ["plan", str(area), "--swath", "30", "--alt", "50", "--angle", "0", "--out", str(tmp_path / "o")]
    assert _main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["altitude_m"] == 50.0 and summary["step_m"] == 30.0
    assert summary["sweep"]["angle_deg"] == pytest.approx(0.0)


def test_qgc_survey_at_amsl_altitude_is_refused() -> None:
    plan = qgc_survey_plan()
    plan["mission"]["items"][1]["TransectStyleComplexItem"]["CameraCalc"]["DistanceToSurfaceRelative"] = False
    with pytest.raises(InterchangeError, match="relative altitude"):
        read_qgc_survey(plan)


def _mission_actions() -> list:
    return [
        Takeoff(step=0, alt=12.0),
        Waypoints(
            step=1,
            speed=6.0,
            points=[Waypoint(lat=47.3980, lon=8.5450, alt=12.0), Waypoint(lat=47.3990, lon=8.5460, alt=15.0)],
        ),
        GoBy(step=2, north=20.0, east=-10.0, up=3.0),
        Hold(step=3, seconds=4.0),
        Goto(step=4, lat=47.3985, lon=8.5470, alt=10.0),
        Land(step=5, lat=47.39772, lon=8.54561),
    ]


def test_plan_items_map_actions_to_mavlink_commands() -> None:
    items = plan_items(_mission_actions(), HOME)
    assert [i.command for i in items] == [
        NAV_TAKEOFF,
        DO_CHANGE_SPEED,
        NAV_WAYPOINT,
        NAV_WAYPOINT,
        NAV_WAYPOINT,
        NAV_LOITER_TIME,
        NAV_WAYPOINT,
        NAV_LAND,
    ]
    go_by = items[4]
    assert distance_m(47.3990, 8.5460, go_by.lat, go_by.lon) == pytest.approx(math.hypot(20, 10), rel=1e-3)
    assert go_by.alt == 18.0
    assert items[1].params[1] == 6.0 and items[5].params[0] == 4.0
    rtl = plan_items([Takeoff(step=0, alt=5), ReturnToLaunch(step=1)], HOME)
    assert rtl[-1].command == NAV_RETURN_TO_LAUNCH


def _same_items(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert (x.command, x.frame) == (y.command, y.frame)
        assert x.lat == pytest.approx(y.lat, abs=1e-8) and x.lon == pytest.approx(y.lon, abs=1e-8)
        assert x.alt == pytest.approx(y.alt, abs=1e-6)
        assert x.params == pytest.approx(y.params, abs=1e-8)


def test_qgc_plan_round_trip() -> None:
    items = plan_items(_mission_actions(), HOME)
    document = json.loads(json.dumps(qgc_plan_document(items, HOME)))
    home, again = read_qgc_mission(document)
    assert home == HOME
    _same_items(items, again)
    actions = items_to_actions(again)
    assert [a.kind for a in actions] == ["takeoff", "waypoints", "hold", "waypoints", "land"]
    assert actions[1].speed == 6.0 and len(actions[1].points) == 3


def test_mission_planner_waypoints_round_trip() -> None:
    items = plan_items(_mission_actions(), HOME)
    text = waypoints_text(items, HOME)
    assert text.splitlines()[0] == "QGC WPL 110"
    assert text.splitlines()[1].split("\t")[:4] == ["0", "1", "0", "16"]  # home row
    home, again = read_waypoints(text)
    assert _close(home, HOME)
    _same_items(items, again)


def test_a_stand_in_home_is_marked_in_the_waypoints_file_and_re_imports_as_no_home() -> None:
    """WPL 110 has no room for a note (QGC reads 12 tab-separated columns per line and calls a
    comment a corrupted file): row 0's ``current`` column says real home (1, as Mission Planner
    writes it) or stand-in (0). A re-import of a stand-in has no home to fly to or compare with."""
    items = plan_items(_mission_actions(), HOME)
    real, stand_in = waypoints_text(items, HOME), waypoints_text(items, HOME, home_assumed=True)
    for text in (real, stand_in):
        rows = text.splitlines()[1:]
        assert all(len(r.split("\t")) == 12 for r in rows), "QGC would call the file corrupted"
    assert real.splitlines()[1].split("\t")[1] == "1" and stand_in.splitlines()[1].split("\t")[1] == "0"
    assert stand_in.splitlines()[2:] == real.splitlines()[2:]  # the items are the same
    home, again = read_waypoints(stand_in)
    assert home is None
    _same_items(items, again)
    assert _close(read_waypoints(real)[0], HOME)
    # Mission Planner's own row for "no home" (command 0 at 0, 0), and comment lines it skips
    body = "\n".join(real.splitlines()[2:])
    assert read_waypoints(f"QGC WPL 110\n0\t1\t0\t0\t0\t0\t0\t0\t0\t0\t0\t1\n{body}")[0] is None
    home, again = read_waypoints(real.replace("\n1\t", "\n# saved by a tool\n\n1\t", 1))
    assert _close(home, HOME)
    _same_items(items, again)


def test_exports_with_a_stand_in_home_round_trip_with_it_marked() -> None:
    """Our exports re-import to the same mission, the stand-in still marked when exported again."""
    from gcs.missions.mission_files import task_from_mission_files

    actions = [
        *_mission_actions()[:4],
        Goto(step=4, lat=47.3985, lon=8.5470, alt=10.0, speed=6.0),
        Land(step=5),
    ]
    task = TaskFile(
        name="blind",
        plans=[
            AgentPlan(agent="drone-1", actions=actions),
            AgentPlan(agent="drone-2", actions=actions),
        ],
    )
    homes = {"drone-1": HOME, "drone-2": (HOME[0], HOME[1] + 1e-4)}
    files = export_files(task, homes, ["plan", "waypoints"], assumed_homes={"drone-1"})
    assert read_waypoints(files["drone-1.waypoints"])[0] is None
    assert _close(read_waypoints(files["drone-2.waypoints"])[0], homes["drone-2"])
    assert read_qgc_mission(json.loads(files["drone-1.plan"]))[0] is None
    assert _close(read_qgc_mission(json.loads(files["drone-2.plan"]))[0], homes["drone-2"])
    for suffix in ("plan", "waypoints"):
        mine = {k: v for k, v in files.items() if k.endswith(suffix)}
        again = task_from_mission_files(mine, "blind")
        assert export_files(again, homes, [suffix], assumed_homes={"drone-1"}) == mine


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("QGC WPL 110\n1\t0\t3\t16\t0\t0\t0\t0\t47\t8\t10\t1\n", "no home row"),
        ("QGC WPL 120\n", "QGC WPL 110"),
        ("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t47\t8\n", "10 columns, not 12"),
    ],
)
def test_bad_waypoint_files_say_why(text: str, message: str) -> None:
    with pytest.raises(InterchangeError, match=message):
        read_waypoints(text)


def test_kml_round_trip() -> None:
    paths = {
        "drone-1": [(47.3981, 8.5451), (47.3981, 8.5479)],
        "drone-2": [(47.3999, 8.5451), (47.3999, 8.5479)],
    }
    text = kml_document("field & friends", FIELD, paths, altitude_m=30.0)
    content = read_kml(text)
    ((name, ring),) = content.polygons
    assert name == "field & friends area"
    assert _close(ring[:-1], FIELD) and ring[-1] == ring[0]
    assert [n for n, _ in content.lines] == list(paths)
    assert all(_close(pts, paths[n]) for n, pts in content.lines)
    area, survey = load_area_text(text)
    assert _close(area.vertices, FIELD) and survey is None


GOOGLE_EARTH_KML = """<?xml version="1.0" encoding="UTF-8"?>
<kml xmlns="http://www.opengis.net/kml/2.2" xmlns:gx="http://www.google.com/kml/ext/2.2">
<Document><name>survey.kml</name>
 <Folder><name>Fields</name>
  <Placemark><name>North field</name><styleUrl>#m</styleUrl>
   <Polygon><tessellate>1</tessellate><outerBoundaryIs><LinearRing><coordinates>
     8.545,47.398,0 8.548,47.398,0 8.548,47.400,0
     8.545,47.400,0 8.545,47.398,0
   </coordinates></LinearRing></outerBoundaryIs></Polygon>
  </Placemark>
 </Folder>
</Document></kml>
"""


def test_gcs_plan_reads_a_kml_area(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    area = tmp_path / "survey.kml"
    area.write_text(GOOGLE_EARTH_KML)
    out = tmp_path / "out"
    argv = ["plan", str(area), "--swath", "25", "--alt", "30", "--drones", "2", "--out", str(out)]
    assert _main([*argv, "--export", "plan,waypoints,kml"]) == 0
    printed = capsys.readouterr()
    summary = json.loads(printed.out)
    assert summary["area"] == "North field"
    # no --home: the area's first corner stands in, and both the command and the files say so
    assert "note: the exports' homes are the area's first corner" in printed.err, printed.err
    assert "assumed" in json.loads((out / "drone-1.plan").read_text())["fleetgcsNote"]
    assert summary["coverage"]["covered_pct"] > 99.9
    task = load_task_text((out / "mission.json").read_text())
    for plan in task.plans:
        survey = next(a for a in plan.actions if isinstance(a, Waypoints))
        home, items = read_qgc_mission(json.loads((out / f"{plan.label}.plan").read_text()))
        wp_home, wp_items = read_waypoints((out / f"{plan.label}.waypoints").read_text())
        assert home is None and wp_home is None  # stand-ins, marked as such: no home to plan from
        _same_items(items, wp_items)
        flown = [(i.lat, i.lon) for i in items if i.command == NAV_WAYPOINT]
        wanted = [(p.lat, p.lon) for p in survey.points]
        assert any(_close(flown[k : k + len(wanted)], wanted, 1e-7) for k in range(len(flown)))
        assert items[0].command == NAV_TAKEOFF and items[-1].command == NAV_RETURN_TO_LAUNCH
    exported = read_kml((out / "plan.kml").read_text())
    assert [n for n, _ in exported.lines] == [p.label for p in task.plans]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('<?xml version="1.0"?><!DOCTYPE kml [<!ENTITY a "aaaa">]><kml/>', "DOCTYPE or ENTITY"),
        ("<kml><Document>", "not valid KML"),
        ("<gpx/>", "root element is <gpx>"),
        (
            '<kml xmlns="http://www.opengis.net/kml/2.2"><Placemark><LineString><coordinates>8,47 9,47'
            "</coordinates></LineString></Placemark></kml>",
            "no Polygon placemark",
        ),
        (
            "<kml><Placemark><Polygon><outerBoundaryIs><LinearRing><coordinates>8,47 x,y 9,48"
            "</coordinates></LinearRing></outerBoundaryIs></Polygon></Placemark></kml>",
            "not numeric",
        ),
        ("nonsense", "not JSON .* nor KML"),
    ],
)
def test_bad_area_documents_say_why(text: str, message: str) -> None:
    with pytest.raises(InterchangeError, match=message):
        load_area_text(text)


def test_cli_reports_a_bad_kml_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    area = tmp_path / "broken.kml"
    area.write_text("<kml><Document>")
    assert _main(["plan", str(area), "--swath", "20", "--alt", "30", "--out", str(tmp_path / "o")]) == 2
    assert "broken.kml: not valid KML" in capsys.readouterr().err


def test_dashboard_preview_reads_kml_text_and_qgc_settings() -> None:
    from gcs.http.planning_requests import DroneInfo, PlanningError, SearchPlanRequest, plan

    drones = [DroneInfo(name="drone-1", home=HOME)]
    kml = plan(SearchPlanRequest(area_text=GOOGLE_EARTH_KML, swath_m=25, altitude_m=30), drones)
    assert kml.coverage_pct is not None and kml.coverage_pct > 99.9
    qgc = plan(SearchPlanRequest(area_document=qgc_survey_plan()), drones)
    assert qgc.summary["step_m"] == 18.0 and qgc.swath_m == pytest.approx(20.0)
    survey = next(a for a in qgc.taskfile.plans[0].actions if isinstance(a, Waypoints))
    assert {p.alt for p in survey.points} == {35.0}
    told = plan(SearchPlanRequest(area_document=qgc_survey_plan(), swath_m=40, altitude_m=25), drones)
    assert told.summary["step_m"] == 40.0
    with pytest.raises(PlanningError, match="area: not valid KML"):
        plan(SearchPlanRequest(area_text="<kml><Document>"), drones)


def test_a_previewed_plan_exports_for_qgc_mission_planner_and_kml() -> None:
    from gcs.http.planning_requests import DroneInfo, SearchPlanRequest, export_preview, plan

    drones = [DroneInfo(name="drone-1", home=HOME), DroneInfo(name="drone-2", home=HOME)]
    preview = plan(SearchPlanRequest(area=FIELD, swath_m=30, altitude_m=25), drones)
    files = export_preview(preview, ["plan", "waypoints", "kml"])
    expected = [
        f"{preview.name}.kml",
        "drone-1.plan",
        "drone-1.waypoints",
        "drone-2.plan",
        "drone-2.waypoints",
    ]
    assert sorted(files) == sorted(expected)
    for name in ("drone-1", "drone-2"):
        home, items = read_qgc_mission(json.loads(files[f"{name}.plan"]))
        assert _close(home, HOME)
        _same_items(items, read_waypoints(files[f"{name}.waypoints"])[1])
    kml = read_kml(files[f"{preview.name}.kml"])
    assert _close(kml.polygons[0][1][:-1], FIELD)
    with pytest.raises(ValueError, match="export formats"):
        export_preview(preview, ["gpx"])


def test_exports_carry_each_drones_real_home_and_the_whole_flight() -> None:
    """Exported homes were the area's first corner at 0 m AMSL for every drone, and the KML had no
    transit or return legs: now each drone's own home (with its altitude), from home and back."""
    from gcs.http.planning_requests import DroneInfo, SearchPlanRequest, export_preview, plan

    homes = {"drone-1": (47.39770, 8.54560), "drone-2": (47.39770, 8.54630)}
    drones = [DroneInfo(name=n, home=h, home_alt_amsl=488.5) for n, h in homes.items()]
    preview = plan(SearchPlanRequest(area=FIELD, swath_m=30, altitude_m=25), drones)
    files = export_preview(preview, ["plan", "waypoints", "kml"])
    kml = read_kml(files[f"{preview.name}.kml"])
    for name, home in homes.items():
        document = json.loads(files[f"{name}.plan"])
        assert document["mission"]["plannedHomePosition"] == pytest.approx([*home, 488.5])
        assert "fleetgcsNote" not in document
        assert _close(read_waypoints(files[f"{name}.waypoints"])[0], home)
        line = dict(kml.lines)[name]
        assert _close(line[0], home) and _close(line[-1], home), line  # out from home and back
        assert distance_m(*line[0], *line[1]) > 20  # the transit leg to the survey
    assert "<description>" not in files[f"{preview.name}.kml"]
    # No home known anywhere: the area's first corner stands in, and the files say so.
    blind = plan(SearchPlanRequest(area=FIELD, swath_m=30, altitude_m=25), [DroneInfo(name="drone-1")])
    files = export_preview(blind, ["plan", "kml"])
    note = json.loads(files["drone-1.plan"])["fleetgcsNote"]
    assert "assumed" in note and "0 m AMSL is not known" in note, note
    assert "assumed" in files[f"{blind.name}.kml"]
