"""The dashboard where reads need the token (as beyond loopback): the page's token reaches the
stream as the ``bearer.<token>`` subprotocol and its REST reads as a header."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.api.fleet import running_fleet
from tests.support.polling import wait_until
from tests.web.dashboard import drone_count, open_dashboard


async def _eq(value: Any, expected: Any) -> bool:
    return bool(await value == expected)


async def test_dashboard_streams_when_reads_need_the_token(tmp_path: Path, browser: Any) -> None:
    async with running_fleet(tmp_path, drones=2, http_reads_need_token="always") as fleet:
        async with fleet.client(token=False) as anonymous:
            assert (await anonymous.get("/api/v1/agents")).status_code == 401
        page = await open_dashboard(browser, fleet.base_url, "test-token")  # waits for the stream
        await wait_until(lambda: _eq(drone_count(page), 2), 10, "two drones on the map")
        assert page.errors == []
