"""A clustered daemon's dashboard: per-drone buttons act on drones linked to another daemon too.

Real Chromium (tests/web/conftest.py) on daemon b's dashboard; drone r0 is linked to daemon a.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from gcs.cluster.natsrun import NatsServer
from tests.backbone.helpers import new_key, start_agent, stop_agents
from tests.cluster.simrig import two_daemons
from tests.support.polling import wait_for
from tests.web.conftest import browser  # noqa: F401 - the Chromium fixture
from tests.web.dashboard import drone_count, open_dashboard

pytestmark = pytest.mark.slow


async def test_remote_drone_buttons_route_to_its_daemon(
    tmp_path: Path,
    nats_server: NatsServer,
    browser: Any,  # noqa: F811
) -> None:
    key = new_key()
    async with two_daemons(tmp_path, nats_server.url, key) as (a, b):
        agents = [start_agent("r0", a.listen_port, key, 0), start_agent("r1", b.listen_port, key, 1)]
        try:
            page = await open_dashboard(browser, f"http://127.0.0.1:{b.http_port}", "t")
            await page.wait_for_function("window.fleetgcs.cluster?.daemon_id === 'gcs-b'")
            for _ in range(300):  # up to 30 s on a loaded machine
                if await drone_count(page) == 2:
                    break
                await page.wait_for_timeout(100)
            assert await drone_count(page) == 2, "both drones in b's table"
            row = page.locator("#fleet-table tbody tr[data-agent='r0']")
            await row.locator("button[data-cmd='hold']").click()
            await wait_for(lambda: a.authority.is_held("r0", "operator"), 20, "a's authority to hold r0")
            remote = b.agents.session("r0")
            await wait_for(lambda: bool(remote and remote.status and remote.status.paused), 20, "r0 to hold")
            assert not b.authority.is_held("r1", "operator"), "the hold reached only r0"
            await row.locator("button[data-cmd='resume']").click()
            await wait_for(lambda: not a.authority.is_held("r0", "operator"), 20, "a to release r0")
            resumed = lambda: bool(remote and remote.status and not remote.status.paused)  # noqa: E731
            await wait_for(resumed, 20, "r0 resumes")
            assert page.errors == []
        finally:
            await stop_agents(agents)
