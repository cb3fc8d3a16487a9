"""The operator's day (issue 28). Missions from QGroundControl and Mission Planner: hand-written files
(tests/data/missions, not made by fleetgcs) fly on our simulator through `gcs run` and the API; our
own exports re-import to the same mission; an item or a format fleetgcs cannot fly is refused, naming
it. Also: `gcs agents` says why a drone is held, a closed pipe ends a command quietly, the API's
version is the package's."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from gcs.cli import build_parser, main
from gcs.missions.mission_files import task_from_mission_files
from gcs.planning.interchange import export_files
from protocol.actions import GoBy, Goto, Hold, Land, ReturnToLaunch, Takeoff, Waypoint, Waypoints
from protocol.settings_file import package_version
from protocol.taskfile import AgentPlan, TaskFile
from tests.api.fleet import running_fleet
from tests.backbone.helpers import survey_mission
from tests.cli.common import gcs, one_line
from tests.cooperation.rig import HOME, rig
from tests.support.paths import MISSIONS, ROOT

DOWN = "http://127.0.0.1:9"  # nothing listens: an accepted mission gets as far as "cannot reach"


def _run(capsys: pytest.CaptureFixture[str], *argv: str | Path) -> tuple[int, str]:
    """`gcs run ARGV` in this process (a CLI process per call is slow on a loaded machine): code, stderr."""
    capsys.readouterr()
    code = main(["run", *map(str, argv), "--api", DOWN, "--token", "t"])
    return code, capsys.readouterr().err


def _closest(truth: list[list[tuple[float, ...]]], drone: int, north: float, east: float) -> float:
    return min(math.hypot(row[drone][0] - north, row[drone][1] - east) for row in truth)


async def test_hand_written_plan_and_waypoints_fly_on_the_simulator(tmp_path: Path) -> None:
    async with rig(tmp_path, 2, http_host="127.0.0.1", http_port=0, api_token="t") as r:
        api = ["--api", f"http://127.0.0.1:{r.daemon.http_port}", "--token", "t"]
        code, out, err = await gcs("run", MISSIONS, "--timeout", "150", *api)
        assert code == 0 and "completed" in out.splitlines()[-1], out + err
        truth = r.truth
    # drone-1 (QGC .plan): its waypoints, then the survey's last transect end at 15 m, then home (RTL)
    assert _closest(truth, 0, 30.0, 20.0) < 2.0
    assert _closest(truth, 0, 50.0, 20.0) < 2.0
    top = max(row[0][2] for row in truth) - HOME[2]
    assert 14.0 < top < 16.5, top
    assert math.hypot(truth[-1][0][0], truth[-1][0][1]) < 3.0 and truth[-1][0][3] == 0.0  # home, landed
    # drone-2 (.waypoints): lands at the file's land point, 20 m south and 36 m east of the first home
    assert math.hypot(truth[-1][1][0] + 20.0, truth[-1][1][1] - 36.0) < 3.0 and truth[-1][1][3] == 0.0


def test_our_exports_re_import_to_the_same_mission() -> None:
    home = (47.397742, 8.545594)
    task = TaskFile(
        name="exported",
        plans=[
            AgentPlan(
                agent="drone-1",
                actions=[
                    Takeoff(step=0, alt=12.0),
                    Waypoints(
                        step=1,
                        speed=6.0,
                        points=[
                            Waypoint(lat=47.3980, lon=8.5450, alt=12.0),
                            Waypoint(lat=47.3990, lon=8.5460, alt=15.0),
                        ],
                    ),
                    GoBy(step=2, north=20.0, east=-10.0, up=3.0),
                    Hold(step=3, seconds=4.0),
                    Goto(step=4, lat=47.3985, lon=8.5470, alt=10.0, speed=6.0),  # a MAVLink speed is kept
                    Land(step=5, lat=47.39772, lon=8.54561),
                ],
            ),
            AgentPlan(agent="drone-2", actions=[Takeoff(step=0, alt=8.0), ReturnToLaunch(step=1)]),
        ],
    )
    homes = {"drone-1": home, "drone-2": (47.397742, 8.5456737)}
    files = export_files(task, homes, ["plan", "waypoints"])
    for suffix in ("plan", "waypoints"):
        again = task_from_mission_files({k: v for k, v in files.items() if k.endswith(suffix)}, "exported")
        assert [p.agent for p in again.plans] == ["drone-1", "drone-2"]
        # exported again, the same files: the same MAVLink items, positions (go_by resolved) and homes
        assert export_files(again, homes, [suffix]) == {k: v for k, v in files.items() if k.endswith(suffix)}
        one = again.plans[0].actions
        assert [a.kind for a in one] == ["takeoff", "waypoints", "hold", "waypoints", "land"]
        assert isinstance(one[-1], Land) and (one[-1].lat, one[-1].lon) == (47.39772, 8.54561)
        assert [a.kind for a in again.plans[1].actions] == ["takeoff", "rtl"]


def test_an_item_fleetgcs_cannot_fly_is_refused_by_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = json.loads((MISSIONS / "drone-1.plan").read_text())
    plan["mission"]["items"].insert(
        3, {**plan["mission"]["items"][1], "command": 183, "params": [9, 1500, 0, 0, 0, 0, 0]}
    )
    (tmp_path / "drone-1.plan").write_text(json.dumps(plan))
    code, err = _run(capsys, tmp_path / "drone-1.plan")
    assert code == 2
    assert one_line(err) == (
        "gcs run: drone-1.plan: item 4 (MAV_CMD 183 DO_SET_SERVO) has no fleetgcs action; "
        "remove it from the mission"
    )
    rows = (MISSIONS / "drone-2.waypoints").read_text().splitlines()
    rows[5] = rows[5].replace("\t3\t16\t", "\t0\t16\t")  # waypoint 4 above mean sea level
    (tmp_path / "d.waypoints").write_text("\n".join(rows))
    code, err = _run(capsys, tmp_path / "d.waypoints", "--agent", "drone-2")
    assert code == 2
    line = one_line(err)
    assert line.startswith(
        "gcs run: d.waypoints: waypoint 4 (line 6) (MAV_CMD 16 NAV_WAYPOINT): "
        "altitude frame 0 (above mean sea level)"
    ), line


def test_other_documents_say_what_a_mission_is(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    area = tmp_path / "area.geojson"
    area.write_text(
        json.dumps({"type": "Polygon", "coordinates": [[[8.5, 47.3], [8.6, 47.3], [8.6, 47.4], [8.5, 47.3]]]})
    )
    line = one_line(_run(capsys, area)[1])
    assert "a GeoJSON area is not a mission: plan a search over it first" in line, line
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"name": "x"}))
    code, err = _run(capsys, other)
    assert code == 2 and "not a task file (it has no 'plans'); a mission is" in one_line(err)
    assert "Field required" not in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "holds no mission files (.plan or .waypoints)" in one_line(_run(capsys, empty)[1])
    code, err = _run(capsys, MISSIONS)  # valid: stops only at the daemon that is not there
    assert code == 3 and "cannot reach the daemon" in err


async def test_the_api_imports_mission_files_and_explains_a_plan_posted_as_a_task(tmp_path: Path) -> None:
    text = (MISSIONS / "drone-2.waypoints").read_text()
    async with running_fleet(tmp_path, drones=1) as fleet, fleet.client() as http:
        as_task = await http.post(
            "/api/v1/missions", json=json.loads((MISSIONS / "drone-1.plan").read_text())
        )
        assert as_task.status_code == 422 and "/api/v1/missions/import" in as_task.json()["detail"]
        bad = await http.post("/api/v1/missions/import", json={"files": {"drone-1.plan": "{}"}})
        assert bad.status_code == 422
        assert bad.json()["detail"].startswith("drone-1.plan: not a QGroundControl .plan")
        # drone-2's file, flown by drone-1 (renamed): accepted and started
        created = await http.post("/api/v1/missions/import", json={"files": {"drone-1.waypoints": text}})
        assert created.status_code == 201, created.text
        mission_id = created.json()["mission_id"]
        progress = (await http.get(f"/api/v1/missions/{mission_id}")).json()
        assert progress["agents"][0]["last_step"] == 3
        await http.post(f"/api/v1/missions/{mission_id}/abort", params={"then": "hold"})


async def test_imported_files_fly_to_the_end_on_the_memory_autopilot(tmp_path: Path) -> None:
    """drone-2's .waypoints ends with a land at a position: the memory autopilot hovered there until
    the 120 s step timeout (the browser test saw it); both files now complete."""
    files = {p.name: p.read_text() for p in sorted(MISSIONS.iterdir())}
    async with running_fleet(tmp_path, drones=2) as fleet, fleet.client() as http:
        created = await http.post("/api/v1/missions/import", json={"files": files})
        assert created.status_code == 201, created.text
        mission_id = created.json()["mission_id"]
        state = "running"
        for _ in range(120):  # at most 60 s; the files fly in a few seconds at 8x
            state = getattr(fleet.daemon.store.mission(mission_id), "state", "running")
            if state != "running":
                break
            await asyncio.sleep(0.5)
        assert state == "completed", (await http.get(f"/api/v1/missions/{mission_id}")).text


async def test_gcs_agents_says_why_a_drone_is_held(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    async with running_fleet(tmp_path, drones=2) as fleet, fleet.client() as http:
        held = await http.post("/api/v1/fleet/hold", json={"agents": ["drone-1"], "reason": "checking"})
        assert held.status_code == 200, held.text
        agents = (await http.get("/api/v1/agents")).json()
        assert [a["held"] for a in agents] == ["operator: fleet hold: checking", None], agents
        capsys.readouterr()
        # in a thread: the CLI's blocking client must not stop this loop serving the daemon
        code = await asyncio.to_thread(main, ["agents", "--api", fleet.base_url])
        out = capsys.readouterr().out
        # a fleet land counts grounded drones as such, not as airborne
        assert (await http.post("/api/v1/fleet/land", json={})).status_code == 200
        (event,) = fleet.daemon.events.history(0, "fleet_land", None, 10)
        assert (
            event.message == "land sent to 0 airborne agents and 2 on the ground (they stand down) (operator)"
        )
    rows = {line.split()[1]: line for line in out.splitlines()[1:]}
    assert code == 0 and rows["drone-1"].endswith("held: operator: fleet hold: checking"), out
    assert "held" not in rows["drone-2"]
    assert " -1" not in out and "-0.0" not in out, out  # no step yet is "-", a drone on the ground 0.0 m


def test_a_closed_pipe_ends_a_command_quietly() -> None:
    """`gcs mission list | head`: the reader stops early; no BrokenPipeError traceback."""
    script = (
        "import sys\n"
        "from gcs.cli import run_reporting_errors\n"
        "def body():\n"
        "    for n in range(200_000):\n"
        "        print(f'mission m-{n} completed', flush=n % 100 == 0)\n"
        "    return 0\n"
        "sys.exit(run_reporting_errors('gcs mission', body))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT
    )
    assert proc.stdout is not None and proc.stderr is not None
    first = proc.stdout.readline()
    proc.stdout.close()  # what `head -1` does after its line
    try:
        err = proc.stderr.read().decode()
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert first.startswith(b"mission m-0") and code == 0 and "Traceback" not in err, err


async def test_the_api_reports_the_package_version(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=0) as fleet, fleet.client() as http:
        info = (await http.get("/openapi.json")).json()["info"]
    assert info["version"] == package_version()


def test_every_gcs_option_has_help_text() -> None:
    missing = []

    def walk(parser: argparse.ArgumentParser, prefix: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{prefix} {name}")
            elif action.help is None and not isinstance(action, argparse._HelpAction):
                missing.append(f"{prefix} {'/'.join(action.option_strings) or action.dest}")

    walk(build_parser(), "gcs")
    assert missing == []


async def test_mission_progress_says_why_a_drone_was_excluded(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=2) as fleet, fleet.client() as http:
        task = survey_mission(["drone-1", "drone-2"], sync_legs=5).model_dump(mode="json")
        created = await http.post("/api/v1/missions", json=task)
        assert created.status_code == 201, created.text
        mission_id = created.json()["mission_id"]
        rtl = await http.post("/api/v1/fleet/rtl", json={"agents": ["drone-1"], "reason": "battery"})
        assert rtl.status_code == 200, rtl.text
        agents = {a["agent"]: a for a in (await http.get(f"/api/v1/missions/{mission_id}")).json()["agents"]}
        await http.post(f"/api/v1/missions/{mission_id}/abort", params={"then": "hold"})
    assert agents["drone-1"]["excluded"] and "battery" in agents["drone-1"]["why"], agents
    assert not agents["drone-2"]["excluded"] and agents["drone-2"]["why"] is None
