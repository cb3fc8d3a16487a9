"""`gcs plan` + `gcs run`, the README's CLI flow, as separate processes against a daemon with memory
agents on loopback TCP: the task file carries its area (so the API and the dashboard show it) and
`gcs run` follows the survey by seen area and flown distance, with the daemon's ETA."""

from __future__ import annotations

import json
import re
from pathlib import Path

from protocol.geo import offset_latlon
from tests.api.fleet import running_fleet
from tests.backbone.helpers import HOME
from tests.cli.common import gcs


async def test_plan_then_run_shows_area_seen_distance_and_eta(tmp_path: Path) -> None:
    corners = [offset_latlon(HOME[0], HOME[1], n, e) for n, e in ((10, -5), (10, 35), (50, 35), (50, -5))]
    area = tmp_path / "field.json"
    area.write_text(json.dumps([list(c) for c in corners]))
    out_dir = tmp_path / "plan"
    code, out, err = await gcs(
        "plan", area, "--drones", "2", "--swath", "10", "--alt", "6", "--stagger", "2",
        "--home", f"{HOME[0]},{HOME[1]}", "--out", out_dir,
    )  # fmt: skip
    assert code == 0, out + err
    task = json.loads((out_dir / "mission.json").read_text())
    assert len(task["survey"]["area"]) == 4 and task["survey"]["swath_m"] == 10.0
    async with running_fleet(tmp_path / "d", drones=2, speedup=4.0) as fleet:
        api = ["--api", fleet.base_url, "--token", "test-token"]
        code, out, err = await gcs("run", out_dir / "mission.json", "--timeout", "120", *api)
        assert code == 0, out + err
        mission_id = out.splitlines()[0].split()[1]
        async with fleet.client() as http:
            geometry = (await http.get(f"/api/v1/missions/{mission_id}/plan")).json()
            coverage = (await http.get(f"/api/v1/missions/{mission_id}/coverage")).json()
    assert geometry["area"] and len(geometry["area"]) == 4 and geometry["swath_m"] == 10.0
    assert coverage["eta_s"] is None and coverage["flown_m"] > 0  # over: nobody left flying
    assert {d["state"] for d in coverage["drones"]} == {"done"}
    lines = [line for line in out.splitlines() if " seen " in line]
    assert lines, out
    flown = [re.search(r"flown (\d+)/(\d+) m", line) for line in lines]
    assert all(flown), lines
    done = [int(m.group(1)) for m in flown if m]
    assert done == sorted(done) and done[-1] > 0, lines
    assert any("ETA " in line for line in lines), lines  # the daemon's, while someone flies
    assert re.search(r"\(\d+\.\d % of the area seen, \d+ m flown\)$", out.splitlines()[-1]), out
