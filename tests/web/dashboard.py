"""Page helpers for the dashboard tests."""

from __future__ import annotations

from typing import Any

from protocol.geo import offset_latlon

HOME = (47.397742, 8.545594)


def survey_corners(
    home: tuple[float, float] = HOME, north: float = 14.0, size=(20.0, 26.0)
) -> list[tuple[float, float]]:
    """A small rectangle north of the fleet, so a mission flies in seconds."""
    n0, (dn, de) = north, size
    return [
        offset_latlon(home[0], home[1], n, e)
        for n, e in ((n0, -4), (n0, de - 4), (n0 + dn, de - 4), (n0 + dn, -4))
    ]


async def open_dashboard(browser: Any, base_url: str, token: str) -> Any:
    page = await browser.new_page(viewport={"width": 1400, "height": 860})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.errors = errors
    await page.goto(f"{base_url}/#token={token}")
    await page.wait_for_function("window.fleetgcs && window.fleetgcs.connected", timeout=15_000)
    return page


async def drone_count(page: Any) -> int:
    return int(await page.evaluate("[...window.fleetgcs.agents.values()].filter(a => a.status).length"))


async def marker_positions(page: Any) -> dict[str, list[float]]:
    """Screen positions of the drone markers, as the map draws them (drones with a position)."""
    return await page.evaluate(
        """() => Object.fromEntries([...window.fleetgcs.agents.values()]
            .filter(a => a.status && a.status.position)
            .map(a => [a.identity,
                       window.fleetgcs.toScreen(a.status.position.lat, a.status.position.lon)]))"""
    )


async def draw_area(page: Any, corners: list[tuple[float, float]]) -> None:
    """Click the corners on the map in drawing mode, as an operator would."""
    await page.click("#btn-draw")
    canvas = page.locator("#map")
    box = await canvas.bounding_box()
    for _ in range(8):  # the view fits the fleet; zoom out until the whole area is on screen
        points = [
            await page.evaluate("([a, b]) => window.fleetgcs.toScreen(a, b)", [a, b]) for a, b in corners
        ]
        if all(20 < x < box["width"] - 20 and 60 < y < box["height"] - 30 for x, y in points):
            break
        await page.click("#btn-zoom-out")
    for lat, lon in corners:
        x, y = await page.evaluate("([a, b]) => window.fleetgcs.toScreen(a, b)", [lat, lon])
        await canvas.click(position={"x": x, "y": y})
    await page.click("#btn-finish-draw")


async def plan_and_start(page: Any, corners: list[tuple[float, float]], swath: int = 14, alt: int = 5) -> str:
    await draw_area(page, corners)
    await page.fill("#swath", str(swath))
    await page.fill("#altitude", str(alt))
    await page.click("#btn-preview")
    await page.wait_for_selector("#plan-summary", timeout=20_000)
    await page.wait_for_function("!document.getElementById('btn-start').disabled")
    await page.click("#btn-start")
    await page.wait_for_function("window.fleetgcs.mission && window.fleetgcs.mission.id", timeout=20_000)
    return str(await page.evaluate("window.fleetgcs.mission.id"))
