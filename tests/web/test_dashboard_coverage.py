"""The dashboard's live coverage in a real browser: a survey submitted as a task file (as `gcs run`
does) shows its area, the stream's coverage layer and the coverage % in the mission panel; a
drone the operator brings home leaves a re-task proposal that the page shows with its legs and
accepts with a click (POST .../retask/{id}/accept)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.api.fleet import client, running_fleet, survey_task
from tests.support.polling import wait_for, wait_until
from tests.web.dashboard import open_dashboard


async def test_coverage_layer_and_a_retask_accepted_from_the_page(
    tmp_path: Path, browser: Any, artifacts: Path
) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=3.0) as fleet, client(fleet) as gcs:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        mission_id = await gcs.submit(survey_task())
        await page.wait_for_function(
            f"window.fleetgcs.mission && window.fleetgcs.mission.id === {mission_id!r}"
            " && window.fleetgcs.mission.geometry && window.fleetgcs.mission.geometry.area",
            timeout=20_000,
        )

        async def some_seen() -> bool:
            return bool(
                await page.evaluate(
                    "(() => { const l = window.fleetgcs.mission.live;"
                    " return !!l && l.seen.reduce((a, b) => a + b, 0) > 4 && l.msg.covered_pct > 5"
                    " && l.runs.length > 0 && l.edges.length > 0; })()"
                )
            )

        await wait_until(some_seen, 60, "the coverage layer to show seen cells")
        text = await page.text_content("#coverage")
        assert text and text.startswith("covered ") and " % · flown " in text, text
        drone_2 = fleet.daemon.agents.sessions["drone-2"]
        await wait_for(lambda: drone_2.status and drone_2.status.step >= 2, 30, "drone-2 surveying")
        await page.screenshot(path=str(artifacts / "dashboard-coverage.png"))
        await gcs.rtl_all(["drone-2"])  # the operator takes it out of the survey
        accept = page.locator(".retask[data-state='pending'] button.accept")
        await accept.wait_for(timeout=30_000)
        legs = await page.text_content(".retask[data-state='pending'] .legs")
        assert legs and "drone-1: +" in legs and " Wh" in legs, legs
        await page.screenshot(path=str(artifacts / "dashboard-retask.png"))
        await accept.click()
        await page.wait_for_selector(".retask[data-state='applied']", timeout=15_000)
        (decision,) = await gcs.retask_proposals(mission_id)
        assert decision["state"] == "applied" and decision["by"] == "operator"
        await page.wait_for_function(
            "document.getElementById('mission-state').textContent === 'completed'", timeout=90_000
        )
        assert "ETA" not in (await page.text_content("#coverage") or "")
        assert page.errors == []
