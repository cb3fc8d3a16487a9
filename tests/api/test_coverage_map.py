"""Live coverage map: a survey planned like `gcs plan` and submitted as a file (`gcs run`), flown by
memory agents over real loopback TCP; the daemon's coverage endpoint rasterises the flown tracks."""

from __future__ import annotations

import asyncio
from pathlib import Path

import httpx
import pytest

from gcs.commands.run import SeenProgress, follow
from gcs.planning.areas import SearchArea
from gcs.planning.camera import spacing_from_swath
from gcs.planning.division import DroneSpec
from gcs.planning.planner import PlanConfig, plan_search
from gcs.planning.seen import seen_grid
from protocol.geo import offset_latlon
from protocol.taskfile import TaskFile
from tests.api.fleet import client, running_fleet
from tests.backbone.helpers import HOME
from tests.support.polling import wait_for


def _survey_task() -> TaskFile:
    corners = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((10, -5), (10, 25), (40, 25), (40, -5))]
    area = SearchArea(vertices=corners, name="field")
    drones = [DroneSpec(name=f"drone-{i + 1}", endurance_s=3000) for i in range(2)]
    plan = plan_search(
        area,
        drones,
        spacing_from_swath(10.0, 6.0),
        PlanConfig(transit_alt_step=2.0),
        home_latlon=HOME[:2],
        speed=5.0,
        agent_names=["drone-1", "drone-2"],
    )
    # what `gcs plan` writes to mission.json and `gcs run` submits
    return TaskFile.model_validate_json(plan.taskfile.model_dump_json())


async def test_file_survey_shows_its_area_and_a_coverage_map_from_flown_tracks(tmp_path: Path) -> None:
    task = _survey_task()
    assert task.survey is not None and task.survey.swath_m == 10.0 and task.survey.altitude_m == 6.0
    async with running_fleet(tmp_path, drones=2, speedup=12.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(task)
        geometry = (await gcs._http.get(f"/api/v1/missions/{mission_id}/plan")).json()
        assert geometry["area"] and len(geometry["area"]) == 4 and geometry["swath_m"] == 10.0
        progress = await gcs.wait_mission(mission_id, timeout=60)
        assert progress.state == "completed"
        body = (await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage?detail=grid")).json()
        assert body["samples"] > 10
        assert body["covered_pct"] >= 95.0, body["grid"]
        assert body["area_m2"] == pytest.approx(900.0, rel=0.1)
        assert body["grid"] and all(len(r) == len(body["grid"][0]) for r in body["grid"])
        geo = (await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage?detail=geojson")).json()
        assert geo["unseen"]["type"] == "MultiPolygon"
        bad = await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage?detail=png")
        assert bad.status_code == 422
        # the test's own computation from the daemon's telemetry agrees with the endpoint
        hub = fleet.daemon.live_hub()
        tracks = [hub.track3d(p.label, mission_id) for p in task.plans]
        assert all(min(alt for _, _, alt in t) < 1.0 < max(alt for _, _, alt in t) for t in tracks)
        assert seen_grid(task.survey.area, tracks, 10.0, 6.0).covered_pct == body["covered_pct"]


async def test_survey_in_flight_is_partly_seen(tmp_path: Path) -> None:
    task = _survey_task()
    async with running_fleet(tmp_path, drones=2, speedup=3.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(task)
        sessions = [fleet.daemon.agents.sessions[n] for n in ("drone-1", "drone-2")]
        await wait_for(lambda: all(s.status and s.status.step >= 2 for s in sessions), 30, "surveying")
        body = (await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage")).json()
        assert body["covered_pct"] is not None and body["covered_pct"] < 100.0
        await gcs.abort(mission_id, then="hold")


def test_seen_progress_eta_ignores_takeoff_and_extrapolates() -> None:
    seen = SeenProgress()
    assert seen.text() == "" and seen.eta_s() is None
    for t, pct in ((0.0, 0.0), (10.0, 0.0), (20.0, 10.0), (30.0, 30.0)):
        seen.add(t, pct)
    assert seen.eta_s() == pytest.approx(35.0)  # 70 % left at 2 %/s since seeing began
    assert seen.text() == "  seen  30.0 %  ETA 0m35s"
    seen.add(40.0, 100.0)
    assert seen.eta_s() is None and "ETA" not in seen.text()


async def test_gcs_run_follows_a_survey_by_seen_area(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=12.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(_survey_task())
        with httpx.Client(base_url=fleet.base_url, headers=fleet.headers, timeout=10) as http:
            progress = await asyncio.to_thread(follow, http, mission_id, 60.0)
    out = capsys.readouterr().out
    assert progress["state"] == "completed"
    assert progress["seen_pct"] >= 95.0
    assert " seen " in out and "%" in out
