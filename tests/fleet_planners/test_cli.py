"""gcs plan --targets / --missed-map through plan_targets.add_arguments and run."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gcs.commands import plan_targets
from protocol.taskfile import load_task_text


def _args(tmp: Path, *argv: str, method: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    plan_targets.add_arguments(p)
    ns = p.parse_args(list(argv))
    ns.method, ns.out, ns.drones, ns.speed, ns.alt = method, str(tmp / "out"), None, None, None
    return ns


def test_psa_cli_writes_mission_geojson_png(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    targets = [
        {"lat": 47.0 + float(dy) * 1e-5, "lon": 8.0 + float(dx) * 1e-5}
        for dx, dy in rng.uniform(0, 100, (12, 2))
    ]
    f = tmp_path / "t.json"
    f.write_text(
        json.dumps({"targets": targets, "config": {"drones": 3, "link_range_m": 15, "speed_mps": 4}})
    )
    assert plan_targets.run(_args(tmp_path, "--targets", str(f), method="psa")) == 0
    out = tmp_path / "out"
    task = load_task_text((out / "mission.json").read_text())
    assert len(task.plans) == 3
    syncs = task.plans[0].sync_steps()
    assert len(syncs) > 4  # a barrier at every formation turn
    assert json.loads((out / "plan.geojson").read_text())["type"] == "FeatureCollection"
    assert (out / "plan.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((out / "report.json").read_text())["check_ok"] is True


def test_rsa_cli_writes_outputs(tmp_path: Path) -> None:
    g = np.ones((30, 40), dtype=int)
    g[3:8, 5:20] = 0
    g[20:27, 30:36] = 0
    np.save(tmp_path / "grid.npy", g)
    f = tmp_path / "m.json"
    f.write_text(
        json.dumps(
            {
                "origin": {"lat": 47.0, "lon": 8.0},
                "cell_size_m": 2.0,
                "npy": "grid.npy",
                "channel_spacing_m": 6,
                "flight_distance_m": 400,
            }
        )
    )
    assert plan_targets.run(_args(tmp_path, "--missed-map", str(f), method="rsa")) == 0
    task = load_task_text((tmp_path / "out" / "mission.json").read_text())
    assert len(task.plans) == json.loads((tmp_path / "out" / "report.json").read_text())["drones_needed"]


def test_bad_input_exits_2(tmp_path: Path) -> None:
    f = tmp_path / "bad.json"
    f.write_text(json.dumps({"targets": [{"x": 1, "y": 2}]}))  # x/y without origin
    assert plan_targets.run(_args(tmp_path, "--targets", str(f), method="psa")) == 2
    assert plan_targets.run(_args(tmp_path, "--targets", str(tmp_path / "none.json"), method="psa")) == 2
    f.write_text(json.dumps({"origin": {"lat": 1, "lon": 2}, "cell_size_m": 1, "rows": [[0, 2]]}))
    assert plan_targets.run(_args(tmp_path, "--missed-map", str(f), method="rsa")) == 2
    assert plan_targets.run(_args(tmp_path, method="rsa")) == 2
