"""The dashboard in a real browser against a daemon with in-process simulated drones."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from tests.api.fleet import running_fleet
from tests.support.polling import wait_until
from tests.web.dashboard import drone_count, marker_positions, open_dashboard, plan_and_start, survey_corners


async def test_mission_planned_and_started_from_the_page_completes(
    tmp_path: Path, browser: Any, artifacts: Path
) -> None:
    async with running_fleet(tmp_path, drones=3, speedup=10.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _eq(drone_count(page), 3), 10, "three drones on the map")
        rows = await page.locator("#fleet-table tbody tr").count()
        assert rows == 3
        before = await marker_positions(page)

        mission_id = await plan_and_start(page, survey_corners())
        assert mission_id in fleet.daemon.missions.active

        async def moved() -> bool:
            now = await marker_positions(page)
            return all(math.dist(now[k], before[k]) > 15 for k in before)

        await wait_until(moved, 30, "every drone marker to move on the map")
        await page.wait_for_selector(".progress[data-agent='drone-1']", timeout=10_000)
        await page.screenshot(path=str(artifacts / "dashboard-mission.png"))
        await page.wait_for_function(
            "document.getElementById('mission-state').textContent === 'completed'", timeout=90_000
        )
        progress = fleet.daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed"
        bars = await page.eval_on_selector_all(".progress", "els => els.map(e => e.dataset.pct)")
        assert bars == ["100", "100", "100"]
        filled = await page.eval_on_selector_all(
            ".progress",
            "els => els.map(e => [e.querySelector('.fill').getBoundingClientRect().width,"
            " e.querySelector('.bar').getBoundingClientRect().width])",
        )
        assert all(track > 0 and abs(fill - track) <= 1 for fill, track in filled), filled
        events = await page.eval_on_selector_all("#events li", "els => els.map(e => e.dataset.kind)")
        assert "mission_completed" in events
        await page.screenshot(path=str(artifacts / "dashboard-completed.png"))
        assert page.errors == []


async def test_abort_from_the_page_holds_the_fleet(tmp_path: Path, browser: Any, artifacts: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=4.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _eq(drone_count(page), 2), 10, "two drones on the map")
        mission_id = await plan_and_start(page, survey_corners(north=20.0, size=(30.0, 30.0)))
        sessions = [fleet.daemon.agents.session(f"drone-{i}") for i in (1, 2)]

        async def cruising() -> bool:
            return all(
                s and s.status and s.status.position.alt_rel > 3.0 and s.status.step >= 1 for s in sessions
            )

        await wait_until(cruising, 40, "the drones to be airborne and flying the plan")
        await page.click("#btn-abort")
        await page.wait_for_function(
            "document.getElementById('mission-state').textContent === 'aborted'", timeout=10_000
        )
        assert mission_id not in fleet.daemon.missions.active

        async def held() -> bool:
            return all(s and s.status and s.status.paused for s in sessions)

        await wait_until(held, 10, "every drone to report a hold")
        first = [(s.status.position.lat, s.status.position.lon) for s in sessions]  # type: ignore[union-attr]
        await page.wait_for_timeout(1500)
        for s, (lat, lon) in zip(sessions, first, strict=True):
            assert s is not None and s.status is not None
            assert s.status.paused and not s.status.landed
            drift = math.dist(
                (lat * 111_000, lon * 75_000),
                (s.status.position.lat * 111_000, s.status.position.lon * 75_000),
            )
            assert drift < 2.0, f"{s.identity} moved {drift:.1f} m while held"
        table = await page.locator("#fleet-table tbody td.mode").all_inner_texts()
        assert all("(held)" in t for t in table), table
        await page.screenshot(path=str(artifacts / "dashboard-abort-hold.png"))
        # the operator then brings everyone home from the page
        await page.click("#btn-rtl-all")
        await page.click("#confirm-ok")  # fleet-wide RTL asks first
        await wait_until(
            lambda: _true(all(s.status and not s.status.paused for s in sessions)),
            10,
            "RTL to override the hold",
        )  # type: ignore[union-attr]
        assert page.errors == []


async def _eq(coro: Any, value: object) -> bool:
    return bool(await coro == value)


async def _true(value: bool) -> bool:
    return value
