"""Dashboard controls in a real browser: per-drone commands, confirmations, empty map, tracks, /docs."""

from __future__ import annotations

import asyncio
import re
import sqlite3
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from tests.api.fleet import running_fleet
from tests.support.paths import MISSIONS
from tests.support.polling import wait_until
from tests.web.dashboard import drone_count, open_dashboard

PNG_1X1 = bytes.fromhex(
    "89504e470d0a1a0a0000000d49484452000000010000000108060000001f15c489"
    "0000000d4944415478da63f8cfc0f01f0005000201a0d1f1e30000000049454e44ae426082"
)


def _kinds(fleet: Any, kind: str) -> list[Any]:
    return [e for e in fleet.daemon.events.history(0, kind, None, 1000) if e.kind == kind]


async def test_per_drone_controls_and_status_columns(tmp_path: Path, browser: Any, artifacts: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=5.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _count_is(page, 2), 10, "two drones in the table")
        row = page.locator("#fleet-table tbody tr[data-agent='drone-1']")
        await page.wait_for_function(
            "document.querySelector(\"tr[data-agent='drone-1'] td.volt\").textContent.endsWith(' V')"
        )
        cells = {c: await row.locator(f"td.{c}").inner_text() for c in ("alt", "gs", "volt", "batt")}
        assert cells["alt"].endswith(" m") and cells["gs"].endswith(" m/s"), cells
        assert 13.0 < float(cells["volt"].split()[0]) < 17.0, cells
        headers = await page.locator("#fleet-table thead th").all_inner_texts()
        assert {"alt", "gs", "volt", "control"} <= set(headers), headers
        side = await page.locator("#side").bounding_box()
        last = await row.locator("button[data-cmd='resume']").bounding_box()
        assert side and last and last["x"] + last["width"] <= side["x"] + side["width"], "controls cut off"
        await page.screenshot(path=str(artifacts / "dashboard-fleet-table.png"))

        one, two = (fleet.daemon.agents.session(f"drone-{i}") for i in (1, 2))
        assert one is not None and two is not None
        await row.locator("button[data-cmd='hold']").click()
        await wait_until(lambda: _true(bool(one.status and one.status.paused)), 10, "drone-1 to hold")
        await asyncio.sleep(0.5)
        assert two.status is not None and not two.status.paused, "hold must reach only drone-1"
        # the reason for the hold, in the table and under the map marker
        await page.wait_for_function(
            "document.querySelector(\"tr[data-agent='drone-1'] td.mode\").textContent.includes('(held)')"
        )
        await page.wait_for_function(
            "document.querySelector(\"tr[data-agent='drone-1'] td.exc\").textContent"
            ".startsWith('held: operator: ')"
        )
        assert "dashboard" in await row.locator("td.exc").inner_text()
        assert await row.locator("td.step").inner_text() == "-"  # no mission: no step, not -1
        await page.wait_for_function("window.fleetgcs.agents.get('drone-1').markerNote.startsWith('held: ')")
        await page.screenshot(path=str(artifacts / "dashboard-held-reason.png"))
        await row.locator("button[data-cmd='resume']").click()
        await wait_until(lambda: _true(bool(one.status and not one.status.paused)), 10, "drone-1 to resume")

        # per-drone RTL and Land ask first (cancel sends nothing); RTL goes to that drone only
        dialog = page.locator("dialog#confirm")
        for cmd, words in (("rtl", "Return drone-2 to launch?"), ("land", "Land drone-2 where it is?")):
            await page.locator(f"#fleet-table tr[data-agent='drone-2'] button[data-cmd='{cmd}']").click()
            await dialog.wait_for(state="visible", timeout=5_000)
            assert words in await page.inner_text("#confirm-text")
            await page.click("#confirm-cancel")
            await dialog.wait_for(state="hidden", timeout=5_000)
        await asyncio.sleep(1.0)
        assert not _kinds(fleet, "fleet_rtl") and not _kinds(fleet, "fleet_land"), "a cancel sent a command"
        await page.locator("#fleet-table tr[data-agent='drone-2'] button[data-cmd='rtl']").click()
        await page.click("#confirm-ok")
        await wait_until(lambda: _true(bool(_kinds(fleet, "fleet_rtl"))), 10, "the RTL event")
        assert _kinds(fleet, "fleet_rtl")[-1].data["agents"] == ["drone-2"]
        assert page.errors == []


async def test_mission_files_upload_and_start(tmp_path: Path, browser: Any) -> None:
    """A hand-written QGC .plan and a .waypoints (tests/data/missions), uploaded, asked about, started."""
    async with running_fleet(tmp_path, drones=2, speedup=8.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _count_is(page, 2), 10, "two drones in the table")
        await page.set_input_files("#mission-files", [str(p) for p in sorted(MISSIONS.iterdir())])
        await page.locator("dialog#confirm").wait_for(state="visible", timeout=5_000)
        assert "on drone-1, drone-2?" in await page.inner_text("#confirm-text")
        await page.click("#confirm-ok")
        await page.wait_for_function(
            "window.fleetgcs.mission && window.fleetgcs.mission.progress", timeout=15_000
        )
        mission_id = await page.evaluate("window.fleetgcs.mission.id")
        progress = fleet.daemon.missions.progress(mission_id)
        assert progress is not None and progress.name == "imported-mission"
        assert {a.agent: a.last_step for a in progress.agents} == {"drone-1": 4, "drone-2": 3}
        # (flying them to the end is tests/cli/test_operator_day.py's, on our MAVLink simulator)
        async with fleet.client() as http:
            await http.post(f"/api/v1/missions/{mission_id}/abort", params={"then": "hold"})
        await wait_until(
            lambda: _true(getattr(fleet.daemon.store.mission(mission_id), "state", None) == "aborted"),
            30,
            "the mission to end",
        )
        # a reload keeps the ended mission in view, each drone its colour, events on a 24-hour clock
        missing: list[str] = []
        page.on("response", lambda r: missing.append(r.url) if r.status == 404 else None)
        await page.reload()
        await page.wait_for_function("window.fleetgcs && window.fleetgcs.connected", timeout=15_000)
        await page.wait_for_function(
            f"window.fleetgcs.mission && window.fleetgcs.mission.id === '{mission_id}'", timeout=15_000
        )
        await page.wait_for_function("document.querySelector('#mission-state').textContent === 'aborted'")
        colours = await page.evaluate("[...window.fleetgcs.agents.values()].map(a => [a.identity, a.color])")
        assert dict(colours) == {"drone-1": "#1f6feb", "drone-2": "#d9480f"}, colours
        times = await page.locator("#events .t").all_inner_texts()
        assert times and all(re.fullmatch(r"\d\d:\d\d:\d\d", t) for t in times), times
        assert missing == [], "a page load asks for what is not there"
        assert page.errors == []


async def test_fleet_wide_rtl_and_land_ask_first(tmp_path: Path, browser: Any, artifacts: Path) -> None:
    async with running_fleet(tmp_path, drones=2, speedup=5.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await wait_until(lambda: _count_is(page, 2), 10, "two drones on the map")
        dialog = page.locator("dialog#confirm")

        await page.click("#btn-rtl-all")
        await dialog.wait_for(state="visible", timeout=5_000)
        assert "Return all 2 drones to launch" in await page.inner_text("#confirm-text")
        await page.screenshot(path=str(artifacts / "dashboard-confirm-rtl.png"))
        await page.click("#confirm-cancel")
        await dialog.wait_for(state="hidden", timeout=5_000)
        await page.click("#btn-land-all")
        await dialog.wait_for(state="visible", timeout=5_000)
        assert "Land all 2 drones" in await page.inner_text("#confirm-text")
        await page.keyboard.press("Escape")
        await dialog.wait_for(state="hidden", timeout=5_000)
        await asyncio.sleep(1.0)
        assert not _kinds(fleet, "fleet_rtl") and not _kinds(fleet, "fleet_land"), "a cancel sent a command"

        await page.click("#btn-land-all")
        await page.click("#confirm-ok")
        await wait_until(lambda: _true(bool(_kinds(fleet, "fleet_land"))), 10, "the land event")
        assert sorted(_kinds(fleet, "fleet_land")[-1].data["agents"]) == ["drone-1", "drone-2"]
        assert not _kinds(fleet, "fleet_rtl")
        assert page.errors == []


async def test_empty_map_text_is_clear_of_the_tools_and_tracks_can_be_cleared(
    tmp_path: Path, browser: Any
) -> None:
    async with running_fleet(tmp_path, drones=0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        waiting = page.locator("#map-empty")
        await waiting.wait_for(state="visible", timeout=5_000)
        assert "waiting for drones" in await waiting.inner_text()
        text, tools = await waiting.bounding_box(), await page.locator("#map-tools").bounding_box()
        assert text is not None and tools is not None
        apart = (
            text["x"] >= tools["x"] + tools["width"]
            or text["y"] >= tools["y"] + tools["height"]
            or tools["x"] >= text["x"] + text["width"]
            or tools["y"] >= text["y"] + text["height"]
        )
        assert apart, f"waiting text {text} overlaps the map tools {tools}"
        await page.close()
    async with running_fleet(tmp_path / "flying", drones=1, speedup=5.0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await page.locator("#map-empty").wait_for(state="hidden", timeout=10_000)
        # an old track: 50 points a kilometre north, as if left over from an earlier mission
        await page.evaluate(
            "() => { const a = window.fleetgcs.agents.get('drone-1'); for (let i = 0; i < 50; i++)"
            " a.track.unshift([a.status.position.lat + 0.01 + i * 1e-5, a.status.position.lon, 'old']); }"
        )
        assert await _old_points(page) == 50
        await page.click("#btn-clear-tracks")
        assert await _old_points(page) == 0 and await _track_length(page) <= 2  # new statuses may add one
        await page.evaluate("() => window.fleetgcs.ws.close()")  # a reconnect reloads the history...
        await page.wait_for_function("window.fleetgcs.connected", timeout=10_000)
        await asyncio.sleep(1.0)
        assert await _track_length(page) <= 20, "...but not what was cleared"  # 1 s of new statuses
        assert page.errors == []


async def test_progress_bars_fill(tmp_path: Path, browser: Any) -> None:
    """Layout, not just data: a bar at 50 % is half as wide as its track, at 100 % all of it."""
    async with running_fleet(tmp_path, drones=0) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await page.evaluate(
            """() => { window.fleetgcs.mission = {id: "m", name: "m", geometry: null, progress: {
                 id: "m", name: "m", state: "running", result: null, sync_steps: [], released_steps: [],
                 agents: [
                   {agent: "a", step: 2, completed_step: 1, last_step: 3, done: false, connected: true,
                    excluded: false, waiting_sync: null},
                   {agent: "b", step: 3, completed_step: 3, last_step: 3, done: true, connected: true,
                    excluded: false, waiting_sync: null}]}};
               renderMission(); }"""
        )
        await page.wait_for_timeout(600)  # the width transition takes 0.3 s
        widths = await page.eval_on_selector_all(
            ".progress",
            """els => els.map(e => [e.querySelector('.fill').getBoundingClientRect().width,
                                    e.querySelector('.bar').getBoundingClientRect().width,
                                    e.querySelector('.fill').getBoundingClientRect().height])""",
        )
        (half, track_a, height), (full, track_b, _) = widths
        assert height > 0 and track_a > 50
        assert abs(half - track_a / 2) <= 2 and abs(full - track_b) <= 1, widths
        assert page.errors == []


async def test_api_docs_load_with_no_network_beyond_the_daemon(tmp_path: Path, browser: Any) -> None:
    async with running_fleet(tmp_path, drones=0) as fleet:
        page = await browser.new_page()
        outside: list[str] = []

        async def only_the_daemon(route: Any) -> None:
            if urlparse(route.request.url).hostname == "127.0.0.1":
                await route.continue_()
            else:
                outside.append(route.request.url)
                await route.abort()

        await page.route("**/*", only_the_daemon)
        await page.goto(f"{fleet.base_url}/docs")
        await page.wait_for_selector(".swagger-ui .info .title", timeout=20_000)
        assert "fleetgcs" in await page.inner_text(".swagger-ui .info .title")
        await page.wait_for_selector(".opblock-summary-path[data-path='/api/v1/agents']", timeout=10_000)
        assert outside == [], f"/docs fetched from outside the daemon: {outside}"
        await page.close()


async def test_tiles_from_an_mbtiles_file_under_the_map(tmp_path: Path, browser: Any) -> None:
    mbtiles = tmp_path / "field.mbtiles"
    with sqlite3.connect(mbtiles) as db:
        db.execute("CREATE TABLE tiles (zoom_level INT, tile_column INT, tile_row INT, tile_data BLOB)")
        db.execute("INSERT INTO tiles VALUES (?, ?, ?, ?)", (18, 137_652, (1 << 18) - 1 - 91_960, PNG_1X1))
    async with running_fleet(tmp_path / "d", drones=1, tile_mbtiles=mbtiles) as fleet:
        async with fleet.client(token=False) as http:
            assert (await http.get("/api/v1/ui-config")).json()["tile_url"] == "/api/v1/tiles/{z}/{x}/{y}"
            hit = await http.get("/api/v1/tiles/18/137652/91960")
            assert hit.status_code == 200 and hit.headers["content-type"] == "image/png"
            assert hit.content == PNG_1X1
            assert (await http.get("/api/v1/tiles/18/137652/91961")).status_code == 404
            assert (await http.get("/api/v1/tiles/3/99/0")).status_code == 404
        page = await browser.new_page(viewport={"width": 1400, "height": 860})
        asked: list[str] = []
        page.on("request", lambda r: asked.append(r.url) if "/api/v1/tiles/" in r.url else None)
        await page.goto(f"{fleet.base_url}/#token=test-token")
        await wait_until(lambda: _true(bool(asked)), 15, "the map to ask the daemon for tiles")
        assert all(urlparse(u).hostname == "127.0.0.1" for u in asked)
        await page.close()


async def _count_is(page: Any, n: int) -> bool:
    return await drone_count(page) == n


async def _track_length(page: Any) -> int:
    return int(await page.evaluate("window.fleetgcs.agents.get('drone-1').track.length"))


async def _old_points(page: Any) -> int:
    return int(
        await page.evaluate("window.fleetgcs.agents.get('drone-1').track.filter(p => p[2] === 'old').length")
    )


async def _true(value: bool) -> bool:
    return value


async def test_a_bow_tie_area_is_drawn_and_located_in_lat_lon(tmp_path: Path, browser: Any) -> None:
    """The preview of a self-intersecting area says where it crosses itself in lat/lon (it said
    "(0.00, 0.00)" in the planner's metres) and draws the outline with the crossing marked."""
    bowtie = [[47.3970, 8.5450], [47.3980, 8.5460], [47.3980, 8.5450], [47.3970, 8.5460]]
    async with running_fleet(tmp_path, drones=1) as fleet:
        page = await open_dashboard(browser, fleet.base_url, "test-token")
        await page.fill("#area-text", str(bowtie))
        await page.click("#btn-preview")
        await page.wait_for_function("document.querySelector('#toast').textContent.includes('cannot plan')")
        toast = await page.locator("#toast").inner_text()
        assert "at (47.397500, 8.545500)" in toast and "(0.00, 0.00)" not in toast, toast
        assert await page.evaluate("window.fleetgcs.area") == bowtie
        crossings = await page.evaluate("window.fleetgcs.crossings")
        assert len(crossings) == 1 and abs(crossings[0][0] - 47.3975) < 1e-6, crossings
        assert not page.errors, page.errors
