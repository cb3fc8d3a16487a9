"""Cooperation services: collision check cost per status tick, energy model accuracy on held-out flights.

Collision: N drones at a constant density (one per 60 m x 60 m, 20 +- 3 m altitude, random
velocities up to 8 m/s); the time of one fleet-wide check (cKDTree candidates + vectorised CPA)
and of a whole avoider tick (check + priorities + holds), median of repeats. For comparison
the same CPA over all N(N-1)/2 pairs (brute force) where that fits in memory.

Energy: flight logs recorded by the daemon while flying varied simulated missions
(bench/make_energy_logs.py; generated on first use and cached), split 70/30 into training and
held-out flights (and 5-fold cross-validation); accuracy as the paper defines it,
100 % - mean |predicted - measured| / measured.

Run: python bench/bench_cooperation.py [--logs DIR] [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcs.cooperation.collision import CollisionAvoider, DroneState, closest_approach, find_conflicts  # noqa: E402
from gcs.cooperation.config import CollisionConfig, EnergyConfig  # noqa: E402
from gcs.cooperation.energy import (  # noqa: E402
    EnergyModel,
    accuracy,
    fallback_model,
    fit_energy_model,
    load_training_set,
)
from gcs.cooperation.flightlog import FlightSummary  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "cooperation.json"
DEFAULT_LOGS = Path("/tmp/fleetgcs-energy-logs")


def fleet(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    side = 60.0 * np.sqrt(n)
    pos = np.column_stack([rng.uniform(0, side, n), rng.uniform(0, side, n), rng.uniform(17, 23, n)])
    heading = rng.uniform(0, 2 * np.pi, n)
    speed = rng.uniform(0, 8, n)
    vel = np.column_stack([speed * np.cos(heading), speed * np.sin(heading), rng.uniform(-0.5, 0.5, n)])
    return pos, vel


def timed(fn: object, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()  # type: ignore[operator]
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1000.0


def bench_collision(sizes: list[int]) -> list[dict[str, float]]:
    rng = np.random.default_rng(1)
    cfg = CollisionConfig()
    rows = []
    for n in sizes:
        pos, vel = fleet(n, rng)
        drones = [
            DroneState(f"d{k}", k + 1, tuple(pos[k]), tuple(vel[k]), tuple(vel[k]), True)  # type: ignore[arg-type]
            for k in range(n)
        ]
        repeats = 50 if n <= 1000 else 10
        check_ms = timed(lambda pos=pos, vel=vel: find_conflicts(pos, vel, cfg), repeats)
        pairs, _ = find_conflicts(pos, vel, cfg)

        def tick(drones: list[DroneState] = drones) -> None:
            CollisionAvoider(cfg).update(drones, 0.0)

        tick_ms = timed(tick, repeats)
        brute_ms = float("nan")
        if n <= 2000:
            i, j = (
                np.array(list(itertools.combinations(range(n), 2))).T
                if n > 1
                else (np.array([]), np.array([]))
            )

            def brute(
                i: np.ndarray = i, j: np.ndarray = j, pos: np.ndarray = pos, vel: np.ndarray = vel
            ) -> None:
                closest_approach(pos[j] - pos[i], vel[j] - vel[i], 4.0, 2.0, cfg.horizon_s)

            brute_ms = timed(brute, 5 if n > 500 else repeats)
        rows.append(
            {
                "drones": n,
                "conflicting_pairs": len(pairs),
                "check_ms": round(check_ms, 3),
                "avoider_tick_ms": round(tick_ms, 3),
                "brute_force_all_pairs_ms": round(brute_ms, 3),
            }
        )
        print(
            f"{n:6d} drones: check {check_ms:8.3f} ms, avoider tick {tick_ms:8.3f} ms, "
            f"brute force {brute_ms:9.3f} ms, {len(pairs)} conflicts",
            flush=True,
        )
    return rows


def predict_all(model: EnergyModel, sims: list[tuple[float, float]]) -> np.ndarray:
    return np.array([model.predict_wh(t, d) for t, d in sims])


def evaluate(
    flights: list[FlightSummary], sims: list[tuple[float, float]], train: list[int], test: list[int]
) -> dict[str, float]:
    tr_f = [flights[k] for k in train]
    pairs = [(sims[k], (flights[k].time_s, flights[k].distance_m)) for k in train]
    measured = np.array([flights[k].energy_wh for k in test])
    test_sims = [sims[k] for k in test]
    two_step = fit_energy_model(tr_f, pairs)
    pure = fit_energy_model(tr_f, pairs, pure_krr=True)
    real_td = (np.array([flights[k].time_s for k in test]), np.array([flights[k].distance_m for k in test]))
    return {
        "two_step_from_plan": accuracy(predict_all(two_step, test_sims), measured),
        "two_step_pure_krr_from_plan": accuracy(predict_all(pure, test_sims), measured),
        "step1_from_flown_time_distance": accuracy(two_step.energy_from_real(*real_td), measured),
        "step1_pure_krr_from_flown": accuracy(pure.energy_from_real(*real_td), measured),
        "fallback_250W_from_plan": accuracy(predict_all(fallback_model(250.0), test_sims), measured),
    }


def bench_energy(logs_dir: Path, quick: bool) -> dict[str, object]:
    logs = sorted(logs_dir.glob("*.csv"))
    if len(logs) < 20:
        from bench.make_energy_logs import make_logs

        print(f"recording flight logs into {logs_dir} (simulated flights; a few minutes)", flush=True)
        batches, drones = (2, 5) if quick else (9, 6)
        logs = asyncio.run(make_logs(logs_dir, batches, drones, 10.0, 7))
    cfg = EnergyConfig()
    flights, _ = load_training_set(logs, cfg)
    sims: list[tuple[float, float]] = []
    keep: list[int] = []
    for k, path in enumerate(logs):
        sidecar = path.with_suffix(".plan.json")
        if sidecar.exists() and flights[k].complete and flights[k].distance_m > 5.0:
            planned = json.loads(sidecar.read_text())["planned"]
            sims.append((float(planned[0]), float(planned[1])))
            keep.append(k)
    flights = [flights[k] for k in keep]
    n = len(flights)
    order = np.random.default_rng(7).permutation(n).tolist()
    cut = round(0.7 * n)
    held_out = evaluate(flights, sims, order[:cut], order[cut:])
    folds = [order[f::5] for f in range(5)]
    cv: dict[str, list[float]] = {}
    for f in range(5):
        train = [k for g in range(5) if g != f for k in folds[g]]
        for name, value in evaluate(flights, sims, train, folds[f]).items():
            cv.setdefault(name, []).append(value)
    energy = np.array([f.energy_wh for f in flights])
    result = {
        "flights": n,
        "train": cut,
        "held_out": n - cut,
        "flight_time_s_range": [
            round(min(f.time_s for f in flights), 1),
            round(max(f.time_s for f in flights), 1),
        ],
        "distance_m_range": [
            round(min(f.distance_m for f in flights), 1),
            round(max(f.distance_m for f in flights), 1),
        ],
        "energy_wh_range": [round(float(energy.min()), 2), round(float(energy.max()), 2)],
        "held_out_accuracy_pct": {k: round(100 * v, 2) for k, v in held_out.items()},
        "cv5_accuracy_pct": {k: round(100 * float(np.mean(v)), 2) for k, v in cv.items()},
        "paper_accuracy_pct": 94.26,
    }
    print(json.dumps(result, indent=1), flush=True)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="cooperation services benchmark")
    parser.add_argument(
        "--logs", type=Path, default=DEFAULT_LOGS, help="flight-log directory (made if empty)"
    )
    parser.add_argument("--quick", action="store_true", help="fewer simulated flights if logs must be made")
    args = parser.parse_args(argv)
    collision = bench_collision([10, 100, 1000, 5000])
    energy = bench_energy(args.logs, args.quick)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(
        json.dumps(
            {
                "machine": {
                    "python": platform.python_version(),
                    "cpu": platform.processor() or platform.machine(),
                },
                "collision_check_per_tick": collision,
                "energy_model": energy,
            },
            indent=1,
        )
        + "\n"
    )
    print(f"written {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
