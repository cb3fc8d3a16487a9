"""Flight logs, the two-step energy model, and `gcs energy train|predict`."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import EnergyModel, accuracy, fit_energy_model, load_training_set
from gcs.cooperation.flightlog import COLUMNS, FlightLogError, FlightLogWriter, summarize
from protocol.actions import Goto, Land, Takeoff
from protocol.geo import offset_latlon
from protocol.packets import Battery, Position, StatusReport
from protocol.taskfile import AgentPlan, TaskFile
from tests.support.processes import BIN

HOME = (47.397742, 8.545594)


def synthetic_flight(path: Path, length_m: float, speed: float, hover_s: float) -> None:
    """Out and back north at ``speed``, with a hover; power 180 W + 0.6 v^2 (V 11.5, I = P/V)."""
    writer = FlightLogWriter(path)
    t, n = 1_700_000_000.0, 0.0
    legs = [(+1, length_m / speed), (0, hover_s), (-1, length_m / speed)]
    samples: list[tuple[float, float, float, bool]] = [(t, 0.0, 0.0, True)]
    for direction, duration in legs:
        for _ in range(int(duration / 0.5)):
            t += 0.5
            n += direction * speed * 0.5
            samples.append((t, n, abs(direction) * speed, False))
    samples.append((t + 0.5, n, 0.0, True))
    for time_s, north, v, landed in samples:
        lat, lon = offset_latlon(HOME[0], HOME[1], north, 0.0)
        power = 0.0 if landed else 180.0 + 0.6 * v * v
        writer.add(
            StatusReport(
                time=time_s,
                position=Position(lat=lat, lon=lon, alt_rel=0.0 if landed else 10.0, alt_amsl=500.0),
                battery=Battery(pct=90.0, voltage_v=11.5, current_a=power / 11.5),
                armed=True,
                landed=landed,
                mode="GUIDED",
                mission_id="m-test",
                step=1,
            )
        )
    writer.close()


def test_flight_log_format_and_summary(tmp_path: Path) -> None:
    path = tmp_path / "f.csv"
    synthetic_flight(path, 100.0, 5.0, 10.0)
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    flight = summarize(path)
    assert flight.distance_m == pytest.approx(217.8, abs=0.5)  # 2 x 100 m, the climb and the descent
    assert flight.time_s == pytest.approx(51.0, abs=0.6)
    expected_wh = (180.0 * 50.0 + 0.6 * 25.0 * 40.0) / 3600.0
    assert flight.energy_wh == pytest.approx(expected_wh, rel=0.03)
    bad = tmp_path / "bad.csv"
    bad.write_text("time,lat\n1,2\n")
    with pytest.raises(FlightLogError):
        summarize(bad)


def test_two_step_model_learns_and_extrapolates(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    paths = []
    for k in range(24):
        path = tmp_path / f"flight{k}.csv"
        synthetic_flight(path, rng.uniform(50, 400), rng.uniform(3, 9), rng.uniform(0, 60))
        paths.append(path)
    flights, pairs = load_training_set(paths, EnergyConfig())
    assert pairs == []  # no plan sidecars: step 2 stays the identity
    model = fit_energy_model(flights[:18], pairs)
    held = flights[18:]
    predicted = np.array([model.predict_wh(f.time_s, f.distance_m) for f in held])
    assert accuracy(predicted, np.array([f.energy_wh for f in held])) > 0.97
    # A flight three times longer than any trained on is still predicted sensibly (linear trend).
    long_wh = model.predict_wh(600.0, 3000.0)
    assert 600 * 180 / 3600 < long_wh < 600 * 260 / 3600
    restored = (
        EnergyModel.load(Path(tmp_path / "m.json"))
        if (tmp_path / "m.json").write_text(model.to_json())
        else None
    )
    assert restored is not None and restored.predict_wh(100, 500) == pytest.approx(model.predict_wh(100, 500))


def test_cli_train_and_predict(tmp_path: Path) -> None:
    logs = []
    for k, (length, speed, hover) in enumerate(
        [(80, 4, 0), (200, 6, 20), (300, 8, 5), (120, 5, 40), (250, 3, 0)]
    ):
        path = tmp_path / f"f{k}.csv"
        synthetic_flight(path, length, speed, hover)
        logs.append(str(path))
    model = tmp_path / "model.json"
    trained = subprocess.run(
        [BIN / "gcs", "energy", "train", *logs, "--out", model], capture_output=True, text=True, timeout=60
    )
    assert trained.returncode == 0, trained.stderr
    assert "trained on 5 flights" in trained.stdout and model.exists()
    far = offset_latlon(HOME[0], HOME[1], 150.0, 0.0)
    task = TaskFile(
        name="t",
        plans=[
            AgentPlan(
                agent="d1",
                actions=[Takeoff(step=0, alt=10), Goto(step=1, lat=far[0], lon=far[1], alt=10), Land(step=2)],
            )
        ],
    )
    mission = tmp_path / "mission.json"
    mission.write_text(task.model_dump_json())
    out = subprocess.run(
        [
            BIN / "gcs",
            "energy",
            "predict",
            mission,
            "--model",
            model,
            "--home",
            f"{HOME[0]},{HOME[1]}",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    row = json.loads(out.stdout)["d1"]
    assert row["plan_distance_m"] == pytest.approx(170.0, abs=1.0) and row["energy_wh"] > 1.0
    missing = subprocess.run(
        [BIN / "gcs", "energy", "train", str(tmp_path / "nope.csv"), "--out", model],
        capture_output=True,
        text=True,
    )
    assert missing.returncode == 2 and "nope.csv" in missing.stderr


def test_cli_train_compares_with_the_baseline_by_kfold(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    logs = []
    for k in range(12):
        path = tmp_path / f"p{k}.csv"
        length, speed, hover = rng.uniform(60, 300), rng.uniform(3, 8), rng.uniform(0, 30)
        synthetic_flight(path, length, speed, hover)
        flown = summarize(path)
        planned = [flown.time_s / rng.uniform(1.0, 1.2), flown.distance_m / rng.uniform(1.0, 1.1)]
        path.with_suffix(".plan.json").write_text(json.dumps({"planned": planned}))
        logs.append(str(path))
    model_path = tmp_path / "model.json"
    trained = subprocess.run(
        [BIN / "gcs", "energy", "train", *logs, "--out", model_path, "--folds", "4"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert trained.returncode == 0, trained.stderr
    assert "4-fold accuracy from the plan: two-step" in trained.stdout and "baseline" in trained.stdout
    model = EnergyModel.load(model_path)
    assert set(model.selection) == {"two_step", "baseline"}
    winner = "baseline" if model.selection["baseline"] > model.selection["two_step"] else "two-step"
    assert model.kind == winner and f"kept the {winner} model" in trained.stdout
