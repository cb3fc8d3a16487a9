"""Benchmark of the fleet planners: PSA vs baselines, RSA scaling, partition convergence.

Run: ``.venv/bin/python bench/bench_fleet_planners.py [--quick]``. Prints tables and writes
bench/results/fleet_planners.json. ``--quick`` uses fewer instances (CI smoke).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from shapely.geometry import Point, Polygon

from gcs.planning.baselines import minmax_routes, route_lengths, tsp_split_routes
from gcs.planning.partition import Raster, Strategy, capability, simulate
from gcs.planning.psa import plan_psa
from gcs.planning.rsa import MissedMap, plan_rsa

OUT = Path(__file__).parent / "results" / "fleet_planners.json"


def bench_psa_paper(instances: int, limit_s: float) -> list[dict[str, float]]:
    """Seed 004 Fig. 11 setting: 120 m field, 3 drones, 4 m/s, 5..30 random targets."""
    rows = []
    print("\nPSA vs baselines (120 m x 120 m, 3 drones, w = 20 m, 4 m/s); ratios of the longest route")
    print(
        f"{'n':>4} {'PSA m':>8} {'minmax m':>9} {'split m':>8} {'PSA/minmax':>11} {'PSA/split':>10}"
        f" {'bound':>7} {'ok':>3}"
    )
    for n in (5, 10, 15, 20, 25, 30):
        psa, mm, sp, lb, ok = [], [], [], [], True
        for seed in range(instances):
            pts = np.random.default_rng(1000 * n + seed).uniform(0, 120, (n, 2))
            plan = plan_psa(pts, 3, 20.0, 4.0)
            ok &= plan.check(sample_dt=0.5).ok
            start = plan.rounds[0].entry
            psa.append(plan.costs.fleet_length)
            lb.append(plan.costs.lower_bound)
            mm.append(route_lengths(minmax_routes(pts, start, 3, limit_s)).max())
            sp.append(route_lengths(tsp_split_routes(pts, start, 3, limit_s)).max())
        row = {
            "n": n,
            "psa_m": float(np.mean(psa)),
            "minmax_m": float(np.mean(mm)),
            "split_m": float(np.mean(sp)),
            "psa_over_minmax": float(np.mean(np.array(psa) / np.array(mm))),
            "psa_over_split": float(np.mean(np.array(psa) / np.array(sp))),
            "theorem1_bound_m": float(np.mean(lb)),
            "all_checks_ok": bool(ok),
        }
        rows.append(row)
        print(
            f"{n:>4} {row['psa_m']:>8.0f} {row['minmax_m']:>9.0f} {row['split_m']:>8.0f} "
            f"{row['psa_over_minmax']:>11.2f} {row['psa_over_split']:>10.2f}"
            f" {row['theorem1_bound_m']:>7.0f} {'y' if ok else 'N':>3}"
        )
    return rows


def bench_psa_scaling(sizes: list[int], limit_s: float) -> list[dict[str, float]]:
    rows = []
    print("\nPSA planning time vs number of targets (field side grows as sqrt(n) * 22 m)")
    print(f"{'n':>6} {'plan s':>8} {'check s':>8} {'rounds':>6} {'PSA/split':>10} {'split s':>8}")
    for n in sizes:
        side = 22.0 * np.sqrt(n)
        pts = np.random.default_rng(n).uniform(0, side, (n, 2))
        t = time.perf_counter()
        plan = plan_psa(pts, 3, 20.0, 4.0)
        t_plan = time.perf_counter() - t
        t = time.perf_counter()
        ok = plan.check(sample_dt=1.0).ok
        t_check = time.perf_counter() - t
        t = time.perf_counter()
        split = route_lengths(tsp_split_routes(pts, plan.rounds[0].entry, 3, limit_s)).max()
        t_split = time.perf_counter() - t
        row = {
            "n": n,
            "plan_s": t_plan,
            "check_s": t_check,
            "rounds": len(plan.rounds),
            "check_ok": ok,
            "psa_over_split": plan.costs.fleet_length / split,
            "split_s": t_split,
        }
        rows.append(row)
        print(
            f"{n:>6} {t_plan:>8.3f} {t_check:>8.2f} {len(plan.rounds):>6}"
            f" {row['psa_over_split']:>10.2f} {t_split:>8.2f}"
        )
    return rows


def bench_rsa(sizes: list[int]) -> list[dict[str, float]]:
    rows = []
    print("\nRSA planning time vs map size (40 random missed blobs, 1 m cells, d_nbh 10 m)")
    print(f"{'cells':>11} {'s':>7} {'zones':>6} {'drones':>6}")
    for n in sizes:
        rng = np.random.default_rng(n)
        g = np.ones((n, n), dtype=np.uint8)
        for _ in range(40):
            r, c = rng.integers(0, max(1, n - 30), 2)
            h, w = rng.integers(2, max(3, n // 20), 2)
            g[r : r + h, c : c + w] = 0
        t = time.perf_counter()
        plan = plan_rsa(MissedMap(g, 1.0), 10.0, 6.0 * n, "west", 5.0)
        dt = time.perf_counter() - t
        rows.append({"side_cells": n, "seconds": dt, "zones": len(plan.zones), "drones": len(plan.drones)})
        print(f"{f'{n}x{n}':>11} {dt:>7.3f} {len(plan.zones):>6} {len(plan.drones):>6}")
    return rows


def _random_area(rng: np.random.Generator) -> Polygon:
    ang = np.sort(rng.uniform(0, 2 * np.pi, 12))
    rad = rng.uniform(35, 60, 12)
    poly = Polygon(np.column_stack([60 + rad * np.cos(ang), 60 + rad * np.sin(ang)]))
    for _ in range(2):
        poly = poly.difference(Point(rng.uniform(35, 85, 2)).buffer(rng.uniform(4, 9)))
    return poly


def bench_partition(
    cases: int, sizes: list[int], strips: list[int] | None = None
) -> list[dict[str, float | str]]:
    rows = []
    print(f"\nPartition: periods to converge (max relative area error <= 1%), {cases} random cases per grid")
    print(
        "paper (seed 003): (2,2)-block sharing ~30% quicker than one-to-one beyond (3,2) blocks; "
        "(1,4) strips and (4,4) grids 'about half the periods' (Sec. III-C, Figs. 7-8)"
    )
    print(
        f"{'grid':>6} {'block':>6} {'one-to-one':>11} {'block':>11} {'block/o2o':>10} "
        f"{'o2o fail':>9} {'blk fail':>9}"
    )
    shapes = [((1, n), (1, 4)) for n in strips or []] + [((n, n), (2, 2)) for n in sizes]
    for shape, block in shapes:
        n = shape[1]
        rng = np.random.default_rng(n)
        res: dict[str, list[float | None]] = {"one-to-one": [], "block": []}
        for _ in range(cases):
            raster = Raster.from_polygon(_random_area(rng), 1.0)
            a = capability(3.0, rng.uniform(0.5, 1.0, shape))
            for s in res:
                r = simulate(raster, a, s, block=block, max_periods=80)  # type: ignore[arg-type]
                res[s].append(r.periods_to(0.01))
        both = [(o, b) for o, b in zip(res["one-to-one"], res["block"], strict=True) if o and b]
        o2o = float(np.mean([o for o, _ in both])) if both else float("nan")
        blk = float(np.mean([b for _, b in both])) if both else float("nan")
        row = {
            "grid": f"{shape[0]}x{shape[1]}",
            "block": f"({block[0]},{block[1]})",
            "one_to_one_periods": o2o,
            "block_periods": blk,
            "ratio": blk / o2o,
            "one_to_one_unconverged": sum(x is None for x in res["one-to-one"]),
            "block_unconverged": sum(x is None for x in res["block"]),
        }
        rows.append(row)
        print(
            f"{row['grid']:>6} {row['block']:>6} {o2o:>11.2f} {blk:>11.2f} {row['ratio']:>10.2f} "
            f"{row['one_to_one_unconverged']:>9} {row['block_unconverged']:>9}"
        )
    return rows


TABLE_I = [
    (0.77, 4.28),
    (0.75, 3.58),
    (0.79, 3.00),
    (0.61, 5.20),
    (0.88, 4.28),
    (0.66, 3.58),
    (0.65, 3.00),
    (0.95, 5.20),
    (0.61, 4.28),
    (0.98, 3.58),
    (0.97, 3.00),
    (0.70, 5.20),
    (0.95, 4.28),
    (0.83, 3.58),
    (0.66, 3.00),
    (0.68, 5.20),
]


def bench_table_i(periods: int) -> dict[str, object]:
    """Seed 003 Sec. V-B: 16 heterogeneous UAVs (Table I) on an irregular area with holes."""
    v = np.array([x for x, _ in TABLE_I]).reshape(4, 4)
    c = np.array([y for _, y in TABLE_I]).reshape(4, 4)
    a = capability(c, v)
    area = Polygon([(0, 0), (140, 10), (160, 90), (100, 130), (20, 120), (-10, 60)])
    area = area.difference(Point(60, 60).buffer(12)).difference(Point(110, 40).buffer(8))
    raster = Raster.from_polygon(area, 1.0)
    period_s = area.area / a.sum()  # an optimal cell takes A_i / a_i = A / sum(a) to cover
    out: dict[str, object] = {"period_s": period_s}
    print(
        f"\nTable I scenario: 16 UAVs, area {area.area:.0f} m^2, one period ~ {period_s:.0f} s at the optimum"
    )
    print("paper Fig. 14: block sharing converges quicker and steeper than one-to-one (error in % vs time)")
    series: dict[str, list[float]] = {}
    divisions: dict[str, int] = {}
    strategies: tuple[Strategy, Strategy] = ("one-to-one", "block")
    for s in strategies:
        r = simulate(raster, a, s, max_periods=periods, tol=None)
        divisions[s] = r.divisions
        series[s] = [float(e) for e in r.errors[3::4]]  # end of each period
        out[s] = {
            "max_rel_error_per_period": series[s],
            "divisions": r.divisions,
            "periods_to_1pct": r.periods_to(0.01),
        }
    print(f"{'period':>6} {'t (s)':>7} {'one-to-one %':>13} {'block %':>8}")
    for k in range(periods):
        print(
            f"{k + 1:>6} {(k + 1) * period_s:>7.0f}"
            f" {100 * series['one-to-one'][k]:>13.2f} {100 * series['block'][k]:>8.2f}"
        )
    print(f"divisions: one-to-one {divisions['one-to-one']}, block {divisions['block']}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="few instances, small sizes")
    ap.add_argument("--cases", type=int, default=100, help="random cases per grid size (partition)")
    args = ap.parse_args()
    quick = args.quick
    results = {
        "psa_paper_setting": bench_psa_paper(2 if quick else 10, 0.3 if quick else 1.0),
        "psa_scaling": bench_psa_scaling([10, 100, 1000] if quick else [10, 100, 1000, 10_000], 1.0),
        "rsa_scaling": bench_rsa([100, 500] if quick else [100, 500, 1000, 2000]),
        "partition_convergence": bench_partition(
            5 if quick else args.cases, [2, 4] if quick else [2, 4, 6], [8] if quick else [8, 16]
        ),
        "table_i": bench_table_i(10 if quick else 20),
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(results, indent=1))
    print(f"\nwrote {OUT}")


if __name__ == "__main__":
    main()
