"""Energy model accuracy, honestly: k-fold over flights, the two-step model next to a one-line baseline.

Flight logs are recorded by the daemon while flying varied simulated missions
(bench/make_energy_logs.py; generated on first use and cached), timed by the vehicle's own clock.
Every prediction is made from the plan alone (what is known before take-off): the two-step
model (step 2: planned -> flown time and distance; step 1: flown -> energy), the same with the
paper's pure KRR, the baseline (least squares of energy on planned time) and the untrained
fallback (250 W x planned time). Accuracy is the paper's: 100 % - mean |predicted - measured| /
measured, on held-out folds only.

Run: python bench/bench_energy.py [--logs DIR] [--quick] [--folds 5]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcs.cooperation.config import EnergyConfig  # noqa: E402
from gcs.cooperation.energy import (  # noqa: E402
    accuracy,
    baseline_model,
    fallback_model,
    fit_energy_model,
    kfold_accuracy,
    load_training_set,
)
from gcs.cooperation.flightlog import FlightSummary  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "energy.json"
DEFAULT_LOGS = Path("/tmp/fleetgcs-energy-logs")
PAPER_ACCURACY_PCT = 94.26


def flights_with_plans(logs_dir: Path, quick: bool) -> tuple[list[FlightSummary], list[tuple[float, float]]]:
    """Complete flights that moved, each with the (time, distance) its plan predicted."""
    logs = sorted(logs_dir.glob("*.csv"))
    if len(logs) < 20:
        from bench.make_energy_logs import make_logs

        print(f"recording flight logs into {logs_dir} (simulated flights; a few minutes)", flush=True)
        batches, drones = (2, 5) if quick else (9, 6)
        logs = asyncio.run(make_logs(logs_dir, batches, drones, 10.0, 7))
    flights, _ = load_training_set(logs, EnergyConfig())
    kept, planned = [], []
    for flight, path in zip(flights, logs, strict=True):
        sidecar = path.with_suffix(".plan.json")
        if sidecar.exists() and flight.complete and flight.distance_m > 5.0:
            t, d = json.loads(sidecar.read_text())["planned"]
            kept.append(flight)
            planned.append((float(t), float(d)))
    return kept, planned


def kfold_table(
    flights: list[FlightSummary], planned: list[tuple[float, float]], folds: int, seed: int = 7
) -> dict[str, float]:
    """Held-out accuracy (%) of every candidate, mean over ``folds`` folds of flights."""
    scores = kfold_accuracy(flights, planned, folds, seed)
    pure = kfold_accuracy(flights, planned, folds, seed, pure_krr=True)
    n = len(flights)
    order = np.random.default_rng(seed).permutation(n)
    k = min(folds, n // 2)
    fallback = fallback_model(EnergyConfig().fallback_power_w)
    fb, flown = [], []
    for f in range(k):
        test = order[f::k]
        train = np.concatenate([order[g::k] for g in range(k) if g != f])
        measured = np.array([flights[i].energy_wh for i in test])
        fb.append(accuracy(np.array([fallback.predict_wh(*planned[i]) for i in test]), measured))
        tr = [flights[i] for i in train]
        model = fit_energy_model(
            tr, [(planned[i], (flights[i].time_s, flights[i].distance_m)) for i in train]
        )
        real = (np.array([flights[i].time_s for i in test]), np.array([flights[i].distance_m for i in test]))
        flown.append(accuracy(model.energy_from_real(*real), measured))
    return {
        "two_step_from_plan": round(100 * scores["two_step"], 2),
        "baseline_least_squares_on_planned_time": round(100 * scores["baseline"], 2),
        "two_step_pure_krr_from_plan": round(100 * pure["two_step"], 2),
        "fallback_250W_x_planned_time": round(100 * float(np.mean(fb)), 2),
        "step1_only_from_flown_time_distance": round(100 * float(np.mean(flown)), 2),
    }


def bench_energy(logs_dir: Path, quick: bool, folds: int = 5) -> dict[str, object]:
    flights, planned = flights_with_plans(logs_dir, quick)
    energy = np.array([f.energy_wh for f in flights])
    ratio = np.array([f.time_s / p[0] for f, p in zip(flights, planned, strict=True)])
    selected = fit_energy_model(
        flights, [(p, (f.time_s, f.distance_m)) for f, p in zip(flights, planned, strict=True)], select=True
    )
    line = baseline_model([p[0] for p in planned], list(energy))
    result: dict[str, object] = {
        "flights": len(flights),
        "folds": folds,
        "flight_time_s_range": [
            round(min(f.time_s for f in flights), 1),
            round(max(f.time_s for f in flights), 1),
        ],
        "energy_wh_range": [round(float(energy.min()), 2), round(float(energy.max()), 2)],
        "flown_over_planned_time": {
            "mean": round(float(ratio.mean()), 3),
            "max": round(float(ratio.max()), 3),
        },
        "kfold_accuracy_pct": kfold_table(flights, planned, folds),
        "kept_by_training": selected.kind,
        "baseline_line": {"wh_per_planned_s": line.linear_coef[0], "intercept_wh": line.linear_intercept},
        "paper_accuracy_pct": PAPER_ACCURACY_PCT,
    }
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="energy model accuracy (k-fold, with the baseline)")
    parser.add_argument(
        "--logs", type=Path, default=DEFAULT_LOGS, help="flight-log directory (made if empty)"
    )
    parser.add_argument("--quick", action="store_true", help="fewer simulated flights if logs must be made")
    parser.add_argument("--folds", type=int, default=5)
    args = parser.parse_args(argv)
    result = bench_energy(args.logs, args.quick, args.folds)
    acc = result["kfold_accuracy_pct"]
    assert isinstance(acc, dict)
    print(f"\n## energy accuracy, {args.folds}-fold over {result['flights']} flights (held-out folds only)")
    print("predictor | accuracy %")
    for name, value in acc.items():
        print(f"{name} | {value}")
    print(f"paper (in-sample figure, seed 004) | {PAPER_ACCURACY_PCT}")
    print(f"kept by `gcs energy train`: {result['kept_by_training']}")
    print(json.dumps({k: v for k, v in result.items() if k != "kfold_accuracy_pct"}, indent=1))
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
