"""Re-tasking over the API with memory agents on loopback TCP: the operator brings a surveying drone
home (one of the exits that exclude it), the daemon proposes its unseen share (policy ask), the
operator accepts it over HTTP, the other drone flies it, and the report says so; the daemon stopped
and started again on the same store file gives the same report (API and ``gcs mission report``).
The error paths: no proposal to answer (409), no survey record (404)."""

from __future__ import annotations

from pathlib import Path

import httpx

from gcs.http.client import ApiError, FleetClient
from tests.api.fleet import client, running_fleet, survey_task
from tests.backbone.helpers import running_daemon
from tests.cli.common import gcs as gcs_tool
from tests.support.polling import wait_for


async def test_operator_rtl_of_a_surveying_drone_then_accepting_the_proposal_and_the_report_after_a_restart(
    tmp_path: Path,
) -> None:
    task = survey_task()
    assert task.survey is not None and task.survey.retask == "ask"  # the default
    async with running_fleet(tmp_path, drones=2, speedup=3.0) as fleet, client(fleet) as gcs:
        mission_id = await gcs.submit(task)
        drone_2 = fleet.daemon.agents.sessions["drone-2"]
        await wait_for(lambda: drone_2.status and drone_2.status.step >= 2, 30, "drone-2 surveying")
        assert await gcs.retask_proposals(mission_id) == []
        try:
            await gcs.retask(mission_id, "accept")
            raise AssertionError("accepting nothing must be refused")
        except ApiError as exc:
            assert exc.status == 409
        await gcs.rtl_all(["drone-2"])  # the operator takes it out of the survey
        await wait_for(lambda: fleet.daemon.events.history(kind="retask_proposed"), 20, "the proposal")
        (pending,) = await gcs.retask_proposals(mission_id)
        assert pending["dropped"] == "drone-2" and pending["state"] == "pending", pending
        assert [g["ident"] for g in pending["legs"]] == ["drone-1"] and pending["gap"]["coordinates"]
        accepted = await gcs.retask(mission_id, "accept", pending["id"])
        assert accepted["state"] == "applied" and accepted["by"] == "operator"
        progress = await gcs.wait_mission(mission_id, timeout=90)
        assert progress.state == "completed", progress
        report = await gcs.report(mission_id)
        coverage = (await gcs._http.get(f"/api/v1/missions/{mission_id}/coverage")).json()
        key = fleet.key
    # The daemon stopped (above) and started again on the same data directory: the record is the store's.
    options = {"http_host": "127.0.0.1", "http_port": 0, "api_token": "test-token"}
    async with running_daemon(tmp_path, key, **options) as daemon:
        assert mission_id not in daemon.missions.active
        url = f"http://127.0.0.1:{daemon.http_port}"
        async with FleetClient(url, "test-token") as again:
            kept = await again.report(mission_id)
        code, text, err = await gcs_tool(
            "mission", "report", mission_id, "--api", url, "--token", "test-token"
        )
    assert kept.model_dump() == report.model_dump()
    assert (
        code == 0 and f"mission {mission_id} (completed)" in text and "re-task r1 (drone-2): applied" in text
    ), text + err
    assert report.retask[0]["state"] == "applied" and not report.gaps
    assert report.covered_pct >= 95.0 and abs(report.covered_pct - coverage["covered_pct"]) <= 3.0
    drones = {d.agent: d for d in report.drones}
    assert drones["drone-1"].added_m > 0 and drones["drone-1"].flown_m > drones["drone-2"].flown_m
    assert drones["drone-2"].left and drones["drone-1"].left is None


async def test_a_mission_without_a_survey_has_no_report(tmp_path: Path) -> None:
    async with running_fleet(tmp_path, drones=1) as fleet, fleet.client() as http:
        missing = await http.get("/api/v1/missions/m-none/report")
        assert missing.status_code == 404
        answer = await http.post("/api/v1/missions/m-none/retask/latest/accept")
        assert answer.status_code == 404
        async with httpx.AsyncClient(base_url=fleet.base_url) as anonymous:
            unauthorized = await anonymous.post("/api/v1/missions/m-none/retask/latest/accept")
        assert unauthorized.status_code == 401
