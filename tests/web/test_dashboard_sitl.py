"""The dashboard against the real pieces: our MAVLink simulator, agent processes, the daemon."""

from __future__ import annotations

import math
import os
import secrets
from pathlib import Path
from typing import Any

import pytest

from gcs.commands.demo_mission import DemoOptions, _start_agents, _start_simulator, _stop
from gcs.core.config import DaemonConfig
from gcs.core.daemon import Daemon
from tests.support.polling import wait_until
from tests.web.dashboard import marker_positions, open_dashboard, plan_and_start, survey_corners

HOME = (47.397742, 8.545594, 488.0)


@pytest.mark.slow
@pytest.mark.timeout(180)
async def test_simulated_drones_fly_a_mission_started_from_the_page(
    tmp_path: Path, browser: Any, artifacts: Path
) -> None:
    key = secrets.token_hex(32)
    key_file = tmp_path / "fleet.key"
    key_file.write_text(key + "\n")
    os.chmod(key_file, 0o600)
    daemon = Daemon(
        DaemonConfig(
            listen_port=0,
            http_host="127.0.0.1",
            http_port=0,
            data_dir=tmp_path,
            fleet_key_hex=key,
            status_period_s=0.2,
            api_token="sitl-token",
        )
    )
    await daemon.start()
    processes = []
    try:
        sim, endpoints = await _start_simulator(DemoOptions(drones=2, speedup=8.0, home=HOME, quiet=True))
        processes.append(sim)
        names = ["drone-1", "drone-2"]
        agents = await _start_agents(endpoints, names, daemon.listen_port, key_file, quiet=True)
        processes = agents + processes  # agents stop first

        def ready() -> bool:
            return all(
                (s := daemon.agents.session(n)) is not None and s.status is not None and s.status.gps.fix >= 3
                for n in names
            )

        async def fleet_ready() -> bool:
            return ready()

        await wait_until(fleet_ready, 60, "simulated drones to join with a GPS fix")
        page = await open_dashboard(browser, f"http://127.0.0.1:{daemon.http_port}", "sitl-token")
        before: dict[str, list[float]] = {}

        async def every_marker() -> bool:  # the page's first sample of a drone may predate its fix
            before.update(await marker_positions(page))
            return sorted(before) == names

        await wait_until(every_marker, 30, "a marker for every drone")
        home = daemon.agents.sessions["drone-1"].home
        assert home is not None
        mission_id = await plan_and_start(
            page, survey_corners((home.lat, home.lon), north=15.0, size=(16.0, 24.0))
        )

        async def moved() -> bool:
            now = await marker_positions(page)
            return all(math.dist(now[k], before[k]) > 10 for k in before)

        await wait_until(moved, 60, "the simulated drones to move on the map")
        await page.screenshot(path=str(artifacts / "dashboard-sitl-flying.png"))
        await page.wait_for_function(
            "document.getElementById('mission-state').textContent === 'completed'", timeout=120_000
        )
        progress = daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed"
        await page.screenshot(path=str(artifacts / "dashboard-sitl-completed.png"))
        assert page.errors == []
    finally:
        await _stop(processes)
        await daemon.stop()
