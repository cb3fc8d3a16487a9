"""Live coverage on daemon + agents + our MAVLink simulator: a small survey planned with `gcs plan`.

The task file carries its area and swath (so the dashboard draws them); the daemon's telemetry
(LiveHub.track3d) and the simulator's ground truth, rasterised with the same eq. 5 footprint,
both see the whole area once the mission completes, and agree.
"""

from __future__ import annotations

import json
from pathlib import Path

from gcs.cli import main as gcs_main
from gcs.planning.seen import seen_grid
from protocol.geo import offset_latlon
from protocol.taskfile import load_task_text
from tests.cooperation.rig import HOME, rig, wait_for


async def test_planned_survey_is_seen_whole_by_telemetry_and_ground_truth(tmp_path: Path) -> None:
    corners = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((15, -10), (15, 30), (45, 30), (45, -10))]
    (tmp_path / "area.json").write_text(json.dumps([list(c) for c in corners]))
    out = tmp_path / "plan"
    args = ["plan", str(tmp_path / "area.json"), "--drones", "2", "--swath", "10", "--alt", "8"]
    args += ["--home", f"{HOME[0]},{HOME[1]}", "--stagger", "3", "--out", str(out)]
    assert gcs_main(args) == 0
    task = load_task_text((out / "mission.json").read_text())
    assert task.survey is not None and task.survey.swath_m == 10.0 and task.survey.altitude_m == 8.0
    async with rig(tmp_path, 2) as r:
        hub = r.daemon.live_hub()
        mission_id = await r.daemon.missions.submit(task)
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 150, "survey end")
        assert r.daemon.missions.progress(mission_id).state == "completed"  # type: ignore[union-attr]
        telemetry = [hub.track3d(name, mission_id) for name in r.names]
        truth = [
            [(*offset_latlon(HOME[0], HOME[1], row[k][0], row[k][1]), row[k][2] - HOME[2]) for row in r.truth]
            for k in range(2)
        ]
    assert all(len(t) > 20 for t in telemetry)
    seen_telemetry = seen_grid(task.survey.area, telemetry, 10.0, 8.0)
    seen_truth = seen_grid(task.survey.area, truth, 10.0, 8.0)
    assert seen_truth.covered_pct >= 99.0, seen_truth.rows()
    assert seen_telemetry.covered_pct >= 97.0, seen_telemetry.rows()
    assert abs(seen_telemetry.covered_pct - seen_truth.covered_pct) <= 3.0
