"""The README's main job: `gcs demo` with 3 simulated vehicles, as separate processes, to completion."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from gcs.demo import DemoOptions, plan_demo_mission

BIN = Path(sys.executable).parent


@pytest.mark.slow
def test_gcs_demo_flies_three_drones_to_a_landed_finish(tmp_path: Path) -> None:
    result = subprocess.run(
        [BIN / "gcs", "demo", "--drones", "3", "--speedup", "8", "--timeout", "150", "--data-dir", tmp_path],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "result: SUCCESS" in result.stdout
    rows = re.findall(
        r"^(drone-\d)\s+(yes|NO)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)$", result.stdout, re.M
    )
    assert [r[0] for r in rows] == ["drone-1", "drone-2", "drone-3"], result.stdout
    for _, landed, dist, air, energy, used, path_error in rows:
        assert landed == "yes"
        assert float(dist) > 150.0  # takeoff, survey share, return
        assert float(air) > 5.0 and float(energy) > 0.1 and float(used) > 0.0
        assert float(path_error) < 5.0  # the survey is flown within a few metres of the plan
    # The daemon kept its record: a completed mission with every sync step released.
    assert (tmp_path / "fleetgcs.sqlite").exists()
    assert "sync_released: step 0 released to 3 agents" in result.stderr
    # Every release was announced by UDP beacon too, and the agents acted on beacons.
    announced = re.search(
        r"^barriers released: (\d+), announced by UDP release beacon: (\d+)", result.stdout, re.M
    )
    assert announced and int(announced[1]) >= 2 and announced[1] == announced[2], result.stdout[-2000:]
    assert "release beacon accepted" in result.stderr, result.stderr[-3000:]


def test_demo_mission_syncs_takeoff_and_survey_end_for_every_drone() -> None:
    names = ["drone-1", "drone-2", "drone-3"]
    task, paths = plan_demo_mission(DemoOptions(), names)
    assert [p.agent for p in task.plans] == names
    assert all(len(path) >= 2 for path in paths)
    sync_steps = {tuple(p.sync_steps()) for p in task.plans}
    assert len(sync_steps) == 1 and len(next(iter(sync_steps))) >= 2
    assert all(p.actions[0].kind == "takeoff" and p.actions[-1].kind in ("rtl", "land") for p in task.plans)
