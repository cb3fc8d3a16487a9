"""Cooperation services: collision check cost per status tick, energy model accuracy on held-out flights.

Collision: N drones at a constant density (one per 60 m x 60 m, 20 +- 3 m altitude, random
velocities up to 8 m/s); the time of one fleet-wide check (cKDTree candidates + vectorised CPA)
and of a whole avoider tick (check + priorities + holds), median of repeats. For comparison
the same CPA over all N(N-1)/2 pairs (brute force) where that fits in memory.

Energy: bench/bench_energy.py (k-fold over recorded flights, the two-step model next to the
least-squares baseline); accuracy as the paper defines it, 100 % - mean |predicted - measured| /
measured.

Run: python bench/bench_cooperation.py [--logs DIR] [--quick]
"""

from __future__ import annotations

import argparse
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

from bench.bench_energy import bench_energy  # noqa: E402
from gcs.cooperation.collision import CollisionAvoider, DroneState, closest_approach, find_conflicts  # noqa: E402
from gcs.cooperation.config import CollisionConfig  # noqa: E402

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
