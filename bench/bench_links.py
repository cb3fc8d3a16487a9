"""Missions over field-quality links: per link profile (tests/faults/links.py), the time of a
3-drone synchronized mission and the safety-order latency, on daemon + in-process agents + our
simulator at the rig's speed-up, each agent behind its own fault proxy (and MAVLink relay).

Mission time: from submission to completion (wall s, and vehicle s = wall x speed-up). Safety-order
latency: an operator RTL to all, from the daemon's call to the first command of the return reaching
each vehicle (wall s; 3 samples a run). The ``outage`` profile cuts drone-2's link for 30 s of
vehicle time on its first leg.

Run: python bench/bench_links.py [--runs 3]   (about 1 minute a run of the 4 profiles; writes
bench/results/links.json)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.cooperation.rig import SPEEDUP, rig, wait_for  # noqa: E402
from tests.faults.links import PROFILES, LinkProfile, LinkRig  # noqa: E402
from tests.scenarios.scenarios import link_task, outage_on_first_leg, rtl_delivery  # noqa: E402


async def run_once(profile: LinkProfile, seed: int) -> tuple[float, list[float]]:
    """One mission and one RTL: (mission wall s, per-drone RTL latencies)."""
    with tempfile.TemporaryDirectory() as tmp:
        async with LinkRig(profile, seed=seed) as links, rig(Path(tmp), 3, **links.rig_options(SPEEDUP)) as r:
            started = time.monotonic()
            mission_id = await r.daemon.missions.submit(link_task(r.names))
            if profile.outage_s:
                await outage_on_first_leg(r, links, "drone-2")
            await wait_for(lambda: mission_id not in r.daemon.missions.active, 120, "the mission to end")
            mission_s = time.monotonic() - started
            progress = r.daemon.missions.progress(mission_id)
            if progress is None or progress.state != "completed":
                raise RuntimeError(f"{profile.name}: mission {progress.state if progress else 'lost'}")
            reached = await rtl_delivery(r, "bench")
            await wait_for(lambda: all(r.landed(n) for n in r.names), 60, "everyone landed")
            return mission_s, list(reached.values())


def percentile(values: list[float], q: float) -> float:
    """Nearest-rank percentile (with few samples p99 is the largest)."""
    ordered = sorted(values)
    rank = max(1, round(q / 100.0 * len(ordered) + 0.5))
    return ordered[min(rank, len(ordered)) - 1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="missions per profile")
    parser.add_argument("--profile", action="append", choices=list(PROFILES), help="only these")
    args = parser.parse_args()
    rows = []
    for name in args.profile or list(PROFILES):
        profile = PROFILES[name]
        missions: list[float] = []
        latencies: list[float] = []
        for run in range(args.runs):
            mission_s, reached = asyncio.run(run_once(profile, seed=run))
            missions.append(mission_s)
            latencies += reached
        rows.append(
            {
                "profile": name,
                "runs": args.runs,
                "mission_wall_s_median": round(statistics.median(missions), 2),
                "mission_vehicle_s_median": round(statistics.median(missions) * SPEEDUP, 1),
                "rtl_p50_s": round(percentile(latencies, 50), 3),
                "rtl_p99_s": round(percentile(latencies, 99), 3),
                "rtl_samples": len(latencies),
                "rtl_bound_s": profile.rtl_bound_s,
            }
        )
    print(f"simulator speed-up {SPEEDUP:g}x; wall seconds unless marked vehicle")
    print(
        f"{'profile':14} {'mission s':>9} {'vehicle s':>9} {'RTL p50':>8} {'RTL p99':>8} "
        f"{'n':>3} {'bound':>6}"
    )
    for row in rows:
        print(
            f"{row['profile']:14} {row['mission_wall_s_median']:>9} {row['mission_vehicle_s_median']:>9} "
            f"{row['rtl_p50_s']:>8} {row['rtl_p99_s']:>8} {row['rtl_samples']:>3} {row['rtl_bound_s']:>6}"
        )
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "links.json").write_text(json.dumps({"speedup": SPEEDUP, "profiles": rows}, indent=2))
    return 0 if all(row["rtl_p99_s"] <= row["rtl_bound_s"] for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
