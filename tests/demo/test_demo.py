"""The README's main job: `gcs demo` with 3 simulated vehicles, as separate processes, to completion."""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import pytest

from gcs.commands.demo_mission import (
    DemoOptions,
    DemoResult,
    DroneRow,
    plan_demo_mission,
    status_table,
    summary_table,
)
from gcs.cooperation.energy import EnergyPrediction
from gcs.observe.flight_recorder import FlightRecorder
from tests.support.processes import BIN

LOG_LINE = re.compile(r"\b(DEBUG|INFO|WARNING|ERROR|CRITICAL)\b")


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
    # The terminal shows the status table and the summary only: no log line, nothing over 100 columns.
    log_file = tmp_path / "fleetgcs-demo.log"
    assert result.stdout.startswith(f"logs (gcs demo --verbose: on the terminal instead):\n  {log_file}\n")
    assert not LOG_LINE.search(result.stdout + result.stderr), (result.stdout + result.stderr)[-3000:]
    lines = (result.stdout + result.stderr).splitlines()[2:]  # after the log file's path (pytest's)
    assert max(len(line) for line in lines) <= 100, [line for line in lines if len(line) > 100]
    assert not re.search(r"step\s+-1|-0\.0\b|nan", result.stdout), result.stdout
    logs = log_file.read_text()  # the daemon's, agents' and simulator's logs
    # The daemon kept its record: a completed mission with every sync step released.
    assert (tmp_path / "fleetgcs.sqlite").exists()
    assert "sync_released: step 0 released to 3 agents" in logs
    # Every release was announced by UDP beacon too, and the agents acted on beacons.
    announced = re.search(
        r"^barriers released: (\d+), announced by UDP release beacon: (\d+)", result.stdout, re.M
    )
    assert announced and int(announced[1]) >= 2 and announced[1] == announced[2], result.stdout[-2000:]
    assert "release beacon accepted" in logs, logs[-3000:]


def test_demo_mission_syncs_takeoff_and_survey_end_for_every_drone() -> None:
    names = ["drone-1", "drone-2", "drone-3"]
    task, paths = plan_demo_mission(DemoOptions(), names)
    assert [p.agent for p in task.plans] == names
    assert all(len(path) >= 2 for path in paths)
    sync_steps = {tuple(p.sync_steps()) for p in task.plans}
    assert len(sync_steps) == 1 and len(next(iter(sync_steps))) >= 2
    assert all(p.actions[0].kind == "takeoff" and p.actions[-1].kind in ("rtl", "land") for p in task.plans)


def test_status_table_and_summary_fit_100_columns_for_5_drones_without_sentinels() -> None:
    rows = [
        DroneRow("drone-1", None, None, None, None, None),  # not reported yet
        DroneRow("drone-2", "GUIDED", -1, None, -0.04, 100.0),  # idle, a few cm below home
        DroneRow("drone-3", "AUTO", 3, 2, 12.04, 97.5),
        DroneRow("drone-4", "RTL", 12, None, math.nan, None),
        DroneRow("a-long-drone-name-of-40-characters-xxxxxx", "LAND", 14, None, 0.3, 41.0),
    ]
    table = status_table(63.2, "1/3", rows)
    lines = table.splitlines()
    assert len(lines) == 7 and max(len(line) for line in lines) <= 100, table
    assert not re.search(r"\s-1\b|-0\.0|nan", table), table
    assert lines[3].split() == ["drone-2", "GUIDED", "-", "-", "0.0", "100.0"]
    assert lines[4].split() == ["drone-3", "AUTO", "3", "2", "12.0", "97.5"]
    names = [f"drone-{i}" for i in range(1, 6)]
    recorder = FlightRecorder(time_scale=8.0)
    predicted = {n: EnergyPrediction(time_s=140.0, distance_m=400.0, energy_wh=3.21) for n in names}
    result = DemoResult(
        False, None, recorder, dict.fromkeys(names, True), "a result message " * 8, 100.0, predicted, 8.0
    )
    summary = summary_table(result)
    assert max(len(line) for line in summary.splitlines()) <= 100, summary
