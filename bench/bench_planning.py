"""Search-planning benchmark: planning time vs size, pattern length/turns, coverage under eq. 9 error,
and the planned coverage of every pattern (curved at shifts -0.5..0.5, with and without wind) over
random convex polygons.

Run: python bench/bench_planning.py  (writes bench/results/planning.json; < 1 min on 2 cores);
``--path-only``: only the path per covered area against Fields2Cover's stored references (issue 27),
exit status 1 if the L-shaped field is more than 5 % off F2C's length.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from shapely.geometry import Polygon

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gcs.planning.camera import Camera, spacing_from_camera
from gcs.planning.coverage import evaluate_coverage, path_error_m, simulate_track
from gcs.planning.decompose import cover_area
from gcs.planning.patterns import curved_cover, segmented, spiral, swept_footprint, zigzag
from gcs.planning.polygon import regularity

# seed 001 Tables 2-3 (Unity simulation, 5 m/s, 0 % desired overlap)
PAPER_TABLE2 = {"zigzag": (80, 181), "segmented": (91, 240), "spiral": (83, 205)}
PAPER_TABLE3 = {"zigzag": (71, 140), "spiral": (83, 205)}


def timed(fn, repeat: int = 3) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def blob(n: int, radius: float, concave: bool, seed: int = 0) -> np.ndarray:
    """n-vertex polygon of about ``radius``: a circle, or a star with radial noise when concave."""
    rng = np.random.default_rng(seed)
    ang = (np.arange(n) + (rng.uniform(0, 0.8, n) if concave else 0.0)) * 2 * math.pi / n
    r = radius * (rng.uniform(0.6, 1.0, n) if concave else np.ones(n))
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)])


def bench_vertices() -> list[dict]:
    rows = []
    for n in (10, 30, 100, 300, 1000):
        for concave in (False, True):
            poly = blob(n, 560.0, concave)  # ~1 km2
            t = timed(lambda p=poly, c=concave: cover_area(p, 30.0) if c else zigzag(p, 30.0))
            rows.append({"vertices": n, "concave": concave, "seconds": round(t, 4)})
    return rows


def bench_area() -> list[dict]:
    rows = []
    for label, side in (("1 ha", 100.0), ("10 ha", 316.2), ("1 km2", 1000.0), ("10 km2", 3162.3)):
        sq = np.array([(0, 0), (side, 0), (side, side * 0.8), (0, side)])
        for name, fn in (("zigzag", zigzag), ("spiral", spiral)):
            t = timed(lambda f=fn, s=sq: f(s, 30.0), repeat=1 if side > 2000 else 3)
            rows.append({"area": label, "pattern": name, "seconds": round(t, 4)})
    return rows


def shapes() -> dict[str, np.ndarray]:
    hexagon = np.array([(40 * math.cos(a), 40 * math.sin(a)) for a in np.arange(6) * math.pi / 3])
    irregular = np.array([(0, 0), (95, 5), (110, 60), (40, 85), (-5, 45)], float)
    return {"regular": hexagon, "irregular": irregular}


def bench_patterns(step: float) -> list[dict]:
    rows = []
    for shape, poly in shapes().items():
        zz = zigzag(poly, step)
        for name, sw in (("zigzag", zz), ("spiral", spiral(poly, step)), ("segmented", segmented(zz, 4))):
            rows.append(
                {
                    "shape": shape,
                    "regularity": round(regularity(poly), 3),
                    "pattern": name,
                    "length_m": round(sw.length, 1),
                    "turns": sw.turns,
                    "waypoints": len(sw.points),
                }
            )
    return rows


def bench_coverage(step: float, swath: float, seeds: int = 10) -> list[dict]:
    rows = []
    for shape, poly in shapes().items():
        zz = zigzag(poly, step)
        for speed in (3.0, 5.0):
            for name, sw in (
                ("zigzag", zz),
                ("segmented", segmented(zz, 4)),
                ("spiral", spiral(poly, step)),
                ("curved +0.2", curved_cover(poly, step, 0.2)),
            ):
                cov, ovl, secs = [], [], []
                for seed in range(seeds):
                    track, t = simulate_track(sw.points, speed, accel=1.0, seed=seed)
                    rep = evaluate_coverage(Polygon(poly), [track], swath)
                    cov.append(rep.covered_pct)
                    ovl.append(rep.overlap_pct)
                    secs.append(t)
                paper = PAPER_TABLE2.get(name) if speed == 5.0 else None
                rows.append(
                    {
                        "shape": shape,
                        "speed": speed,
                        "eq9_error_m": round(path_error_m(speed), 3),
                        "pattern": name,
                        "covered_pct": round(float(np.mean(cov)), 2),
                        "covered_min_pct": round(float(np.min(cov)), 2),
                        "overlap_pct": round(float(np.mean(ovl)), 2),
                        "time_s": round(float(np.mean(secs)), 1),
                        "paper_table2_covered_pct": paper[0] if paper else None,
                        "paper_table2_time_s": paper[1] if paper else None,
                    }
                )
    return rows


def random_convex(rng: np.random.Generator) -> np.ndarray:
    """The tests' generator: the hull of 3-12 random points, stretched 20-400 x 5-400 m, rotated."""
    from scipy.spatial import ConvexHull

    n = int(rng.integers(3, 13))
    pts = rng.uniform(0, 1, (n, 2)) * [rng.uniform(20, 400), rng.uniform(5, 400)]
    hull = pts[ConvexHull(pts).vertices]
    a = rng.uniform(0, math.pi)
    c, s = math.cos(a), math.sin(a)
    return hull @ np.array([[c, s], [-s, c]])


def planned_pct(poly: np.ndarray, points: np.ndarray, half: float) -> float:
    p = Polygon(poly)
    return 100.0 * p.intersection(swept_footprint(points, half)).area / p.area


def bench_planned_coverage(polygons: int = 120, seed: int = 0) -> list[dict]:
    """Planned coverage (footprint half a step on the plan itself): worst and mean over polygons."""
    rng = np.random.default_rng(seed)
    cases = [(random_convex(rng), float(rng.uniform(4.0, 40.0))) for _ in range(polygons)]
    variants: list[tuple[str, object]] = [
        ("zigzag", lambda p, st: zigzag(p, st)),
        ("segmented", lambda p, st: segmented(zigzag(p, st), 4)),
        ("spiral", lambda p, st: spiral(p, st)),
        ("spiral (corners < 150 deg only)", lambda p, st: spiral(p, st, corner_deg=150.0)),
    ]
    for shift in (-0.5, -0.25, 0.2, 0.5):
        variants.append((f"curved shift {shift:+.2f}", lambda p, st, s=shift: curved_cover(p, st, s)))
        variants.append(
            (f"curved shift {shift:+.2f} wind 45", lambda p, st, s=shift: curved_cover(p, st, s, 45.0))
        )
    rows = []
    base = [zigzag(p, st).length for p, st in cases]
    for name, build in variants:
        cov, ratio = [], []
        for (poly, st), zz in zip(cases, base, strict=True):
            sw = build(poly, st)  # type: ignore[operator]
            cov.append(planned_pct(poly, sw.points, st / 2))
            ratio.append(sw.length / zz)
        rows.append(
            {
                "pattern": name,
                "polygons": polygons,
                "worst_pct": round(float(np.min(cov)), 3),
                "mean_pct": round(float(np.mean(cov)), 4),
                "length_vs_zigzag": round(float(np.mean(ratio)), 3),
            }
        )
    return rows


# --- Fields2Cover 2.1 reference (issue 27) --------------------------------------------------------
# F2C is not installed here (it builds from its PyPI sdist against Debian's libgdal-dev and
# libgeos-dev; see docs/planning.md), so the comparison uses stored references:
# * the L-shaped field (300 x 300 m minus a 180 x 180 m corner, swath 20 m): F2C 2.1's path,
#   3,162 m, measured by issue 27 with the same footprint code;
# * the random convex and concave sets: issue 27 measured fleetgcs at commit 6d3b7e8 at 1.09x
#   (convex) and 1.18x (concave) F2C's path per covered area (medians over its own 20 + 20 random
#   fields). Those fields were not stored, so F2C's per-field reference here is estimated as what
#   6d3b7e8 plans on *these* fields (seed 27, below, stored per field) divided by that median ratio.
#   The numbers were made with `git archive 6d3b7e8 gcs protocol` unpacked into a scratch folder
#   and this file's _fly() run on that tree (the same call reproduces the 4,363 m on the
#   L-field, so the tree is the one the issue measured). It is an estimate: it assumes F2C's edge
#   over 6d3b7e8 on these fields is the median one of the fields.
F2C_REFERENCE_M = {"L-field": 3162.0}
F2C_OLD_RATIO = {"convex": 1.09, "concave": 1.18}  # 6d3b7e8 / F2C, median m per covered ha
OLD_6D3B7E8_M_PER_HA = {  # 6d3b7e8's m per covered ha on bench_path_per_area's fields, in order
    "convex": [
        1024.92, 1637.43, 1876.08, 633.77, 753.67, 1419.94, 590.94, 739.43, 1397.1, 1751.37,
        650.71, 793.57, 647.39, 682.19, 685.56, 869.47, 684.9, 616.68, 724.41, 748.38,
    ],
    "concave": [
        588.21, 663.95, 555.68, 626.25, 586.81, 708.43, 623.4, 645.04, 553.78, 735.33,
        616.12, 651.01, 543.9, 583.19, 562.21, 767.59, 628.42, 638.72, 573.6, 634.06,
    ],
}  # fmt: skip
L_FIELD_TOLERANCE = 0.05  # issue 27: the L-field within 5 % of F2C's length
L_FIELD = np.array([(0, 0), (300, 0), (300, 120), (120, 120), (120, 300), (0, 300)], dtype=float)


def random_concave(rng: np.random.Generator) -> np.ndarray:
    """A star-shaped field: 5-12 vertices at radii 40-100 % of 100-400 m, angles jittered."""
    n = int(rng.integers(5, 13))
    radius = rng.uniform(100.0, 400.0)
    ang = (np.arange(n) + rng.uniform(0.0, 0.7, n)) * 2 * math.pi / n
    r = radius * rng.uniform(0.4, 1.0, n)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)])


def _fly(poly: np.ndarray, swath: float) -> dict:
    """Plan one drone over ``poly`` (local metres, given to the planner in lat/lon as the CLI does)."""
    from gcs.planning.areas import SearchArea
    from gcs.planning.camera import spacing_from_swath
    from gcs.planning.division import DroneSpec
    from gcs.planning.geodesy import LocalFrame
    from gcs.planning.planner import plan_search

    frame = LocalFrame(47.0, 8.0)
    area = SearchArea(vertices=[(float(a), float(b)) for a, b in frame.points_to_geodetic(poly)])
    t0 = time.perf_counter()
    plan = plan_search(area, [DroneSpec(name="a", endurance_s=1e6)], spacing_from_swath(swath, 30.0))
    secs = time.perf_counter() - t0
    covered = plan.coverage.covered_pct / 100.0 * float(plan.summary["area_m2"])
    length = float(plan.summary["total_length_m"])
    return {
        "length_m": length,
        "covered_pct": plan.coverage.covered_pct,
        "m_per_ha": length / covered * 1e4,
        "floor_m_per_ha": floor_m_per_ha(covered, swath),
        "seconds": secs,
    }


def floor_m_per_ha(covered_m2: float, swath: float) -> float:
    """The least path per covered hectare of *any* path seeing ``covered_m2`` with a footprint ``swath``
    wide: a path of length L sees at most swath x L plus the disc at its ends (pi swath^2 / 4), so
    L >= (covered - pi swath^2 / 4) / swath. A reference below it cannot be a flown path's."""
    return max(covered_m2 - math.pi * swath * swath / 4.0, 0.0) / swath / covered_m2 * 1e4


def bench_path_per_area(fields: int = 20, seed: int = 27, swath: float = 20.0) -> dict:
    """Path length per covered area on random convex and concave fields, against the stored F2C
    references (issue 27's comparison; see F2C_REFERENCE_M above for where they come from)."""
    out: dict = {"ideal_m_per_ha": round(1e4 / swath, 1)}  # parallel legs one swath apart, no turns
    for kind, gen in (("convex", random_convex), ("concave", random_concave)):
        rng = np.random.default_rng(seed)
        rows = [_fly(gen(rng), swath) for _ in range(fields)]
        ours = np.array([r["m_per_ha"] for r in rows])
        old = (
            np.array(OLD_6D3B7E8_M_PER_HA[kind][:fields]) if (fields, seed, swath) == (20, 27, 20.0) else None
        )
        floor = np.array([r["floor_m_per_ha"] for r in rows])
        out[kind] = {
            "fields": fields,
            "median_m_per_ha": round(float(np.median(ours)), 2),
            "min_covered_pct": round(min(r["covered_pct"] for r in rows), 3),
            "median_plan_s": round(float(np.median([r["seconds"] for r in rows])), 4),
            "vs_floor_median": round(float(np.median(ours / np.maximum(floor, 1e-9))), 4),
        }
        if old is not None:
            f2c = old / F2C_OLD_RATIO[kind]  # the estimated F2C reference per field
            r = ours / f2c
            out[kind] |= {
                "vs_6d3b7e8_median": round(float(np.median(ours / old)), 4),
                "f2c_est_median_m_per_ha": round(float(np.median(f2c)), 2),
                "vs_f2c_est_median": round(float(np.median(r)), 4),
                "vs_f2c_est_p90": round(float(np.percentile(r, 90)), 4),
                "vs_f2c_est_worst": round(float(np.max(r)), 4),
                # fields whose estimated F2C reference no path with this footprint can reach
                "f2c_est_below_floor": int(np.sum(f2c < floor)),
                "floor_vs_f2c_est_median": round(float(np.median(floor / f2c)), 4),
            }
    lf = _fly(L_FIELD, swath)
    ratio = lf["length_m"] / F2C_REFERENCE_M["L-field"]
    out["L-field"] = {
        "length_m": round(lf["length_m"], 1),
        "covered_pct": round(lf["covered_pct"], 3),
        "f2c_m": F2C_REFERENCE_M["L-field"],
        "vs_f2c": round(ratio, 4),
        "within_5_pct": abs(ratio - 1.0) <= L_FIELD_TOLERANCE,
    }
    return out


def print_path_per_area(res: dict) -> None:
    """Ours against the references, one line per set."""
    print("\n## path per covered area, swath 20 m: ours vs Fields2Cover 2.1 (stored references, issue 27)")
    print(f"ideal (legs one swath apart, no turns): {res['ideal_m_per_ha']} m/ha")
    print(
        "set | fields | ours median m/ha | F2C est. median m/ha | ours/F2C est. median | p90 | worst "
        "| ours/6d3b7e8 | min covered % | plan s | ours/floor | F2C est. below floor | floor/F2C est."
    )
    for kind in ("convex", "concave"):
        r = res[kind]
        print(
            f"{kind} | {r['fields']} | {r['median_m_per_ha']} | {r.get('f2c_est_median_m_per_ha', '-')} | "
            f"{r.get('vs_f2c_est_median', '-')} | {r.get('vs_f2c_est_p90', '-')} | "
            f"{r.get('vs_f2c_est_worst', '-')} | {r.get('vs_6d3b7e8_median', '-')} | "
            f"{r['min_covered_pct']} | {r['median_plan_s']} | {r['vs_floor_median']} | "
            f"{r.get('f2c_est_below_floor', '-')} of {r['fields']} | {r.get('floor_vs_f2c_est_median', '-')}"
        )
    print(
        "(floor: the least path per covered ha of any path with this footprint, swath x length plus the "
        "end discs; a reference below it is not a flown path's)"
    )
    lf = res["L-field"]
    print(
        f"L-field | ours {lf['length_m']:.0f} m ({lf['covered_pct']} % covered) | F2C {lf['f2c_m']:.0f} m | "
        f"{lf['vs_f2c']:.4f}x | within 5 %: {'yes' if lf['within_5_pct'] else 'NO'}"
    )


def table(rows: list[dict], title: str) -> None:
    print(f"\n## {title}")
    keys = list(rows[0])
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(str(r[k]) for k in keys))


def main() -> int:
    if "--path-only" in sys.argv[1:]:  # the F2C comparison alone (a few seconds); 1 if the L-field is off
        res = bench_path_per_area()
        print_path_per_area(res)
        return 0 if res["L-field"]["within_5_pct"] else 1
    t0 = time.perf_counter()
    cam = Camera(resolution_px=640, fov_deg=60.0, min_pixels=20)  # seed 001 §6.1 camera, 0.5 m tag
    sp = spacing_from_camera(cam, 0.5, side_overlap=0.0)
    results = {
        "spacing": sp.model_dump(),
        "vertices": bench_vertices(),
        "area": bench_area(),
        "patterns": bench_patterns(sp.step),
        "coverage": bench_coverage(sp.step, sp.swath),
        "paper_table3": PAPER_TABLE3,
        "planned_coverage": bench_planned_coverage(),
        "path_per_area": bench_path_per_area(),
    }
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    print(f"camera: h_max {sp.h_max:.2f} m, swath {sp.swath:.2f} m, step {sp.step:.2f} m (0 % overlap)")
    table(results["vertices"], "planning time vs vertex count (~1 km2, step 30 m)")
    table(results["area"], "planning time vs area (step 30 m)")
    table(results["patterns"], "pattern length and turns")
    table(
        results["coverage"], "covered % under eq. 9 path error (mean of 10 seeds), seed 001 Table 2 alongside"
    )
    print(f"\nseed 001 Table 3 (zigzag vs spiral, 5 m/s): {PAPER_TABLE3}")
    table(
        results["planned_coverage"],
        "planned coverage over random convex polygons (footprint = line step, on the plan itself)",
    )
    print_path_per_area(results["path_per_area"])
    out = Path(__file__).resolve().parent / "results" / "planning.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"\nwrote {out} in {results['wall_s']} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
