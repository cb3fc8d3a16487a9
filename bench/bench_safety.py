"""Safety figures of the vehicle authority on daemon + agents + our simulator, one row per scenario.

Per scenario: minimum 3-D separation of airborne pairs (simulator ground truth), samples inside
the 4 m x 2 m separation cylinder, longest hold (any owner), time from the order to every drone
landed (RTL-all / land-all), and events emitted (all, and command refusals).

Run: python bench/bench_safety.py   (about 2 minutes; writes bench/results/safety.json)
"""

from __future__ import annotations

import asyncio
import json
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from gcs.cooperation.config import CooperationConfig  # noqa: E402
from gcs.http.planning_requests import SearchPlanRequest, plan  # noqa: E402
from protocol.taskfile import TaskFile  # noqa: E402
from tests.cooperation.rig import SPEEDUP, Rig, rig, wait_for  # noqa: E402
from tests.scenarios.scenarios import area, crossing_task, head_on, infos, separation, stack_task  # noqa: E402

COOP = CooperationConfig(vehicle_time_scale=SPEEDUP)
Scenario = Callable[[Rig], Awaitable[float | None]]


async def _complete(r: Rig, task: TaskFile) -> None:
    mission_id = await r.daemon.missions.submit(task)
    await wait_for(lambda: mission_id not in r.daemon.missions.active, 240, "mission end")
    await wait_for(lambda: all(r.landed(n) for n in r.names), 90, "landed")


async def region_search(r: Rig) -> float | None:
    request = SearchPlanRequest(
        drones=r.names, area=area(30, -40, 90, 120), altitude_m=30, swath_m=20, division="region"
    )
    await _complete(r, plan(request, infos(r)).taskfile)
    return None


async def dashboard_search(r: Rig) -> float | None:
    await _complete(
        r, plan(SearchPlanRequest(drones=r.names, area=area(25, -30, 70, 100)), infos(r)).taskfile
    )
    return None


async def head_on_pair(r: Rig) -> float | None:
    await _complete(r, head_on(r.names))
    return None


async def _bring_down(r: Rig, kind: str) -> float:
    await r.daemon.operator.hold(None, "bench")
    await wait_for(lambda: all(r.status(n).paused for n in r.names), 10, "held")
    started = time.monotonic()
    await r.daemon.operator.bring_down(kind, None, "bench")  # type: ignore[arg-type]
    await wait_for(lambda: all(r.landed(n) for n in r.names), 180, "landed")
    return time.monotonic() - started


async def rtl_all_from_held(r: Rig) -> float | None:
    await r.daemon.missions.submit(crossing_task(r.names))
    await wait_for(lambda: all((s := r.status(n)) and s.step >= 1 for n in r.names), 60, "on their legs")
    return await _bring_down(r, "rtl")


async def land_all_from_stack(r: Rig) -> float | None:
    await r.daemon.missions.submit(stack_task(r.names))
    await wait_for(lambda: all((s := r.status(n)) and s.step >= 2 for n in r.names), 60, "stacked")
    return await _bring_down(r, "land")


SCENARIOS: list[tuple[str, int, float, Scenario]] = [
    ("region search, 3 drones, homes 5 m", 3, 5.0, region_search),
    ("dashboard search, 4 drones, homes 5 m", 4, 5.0, dashboard_search),
    ("head-on pair", 2, 6.0, head_on_pair),
    ("RTL-all from held, 4 drones", 4, 5.0, rtl_all_from_held),
    ("land-all from a stack, 3 drones", 3, 5.0, land_all_from_stack),
]


async def run_one(name: str, vehicles: int, spacing: float, scenario: Scenario) -> dict[str, object]:
    with tempfile.TemporaryDirectory() as tmp:
        async with rig(Path(tmp), vehicles, COOP, spacing_m=spacing) as r:
            start = time.monotonic()
            to_land = await scenario(r)
            closest, inside = separation(r.truth)
            events = r.daemon.events.history(limit=100_000)
            return {
                "scenario": name,
                "min_separation_m": round(closest, 2),
                "samples_inside_margin": inside,
                "longest_hold_s": round(r.daemon.authority.longest_hold(), 2),
                "time_to_land_s": None if to_land is None else round(to_land, 2),
                "events": len(events),
                "refusals": sum(1 for e in events if e.kind == "command_refused"),
                "wall_s": round(time.monotonic() - start, 1),
            }


def main() -> int:
    rows = [asyncio.run(run_one(*s)) for s in SCENARIOS]
    header = (
        f"{'scenario':40} {'min sep m':>9} {'inside':>6} {'hold s':>7} {'land s':>7} "
        f"{'events':>6} {'refused':>7}"
    )
    print(f"simulator speed-up {SPEEDUP:g}x; times are wall seconds")
    print(header)
    for row in rows:
        land = "-" if row["time_to_land_s"] is None else f"{row['time_to_land_s']:.1f}"
        print(
            f"{row['scenario']:40} {row['min_separation_m']:>9} {row['samples_inside_margin']:>6} "
            f"{row['longest_hold_s']:>7} {land:>7} {row['events']:>6} {row['refusals']:>7}"
        )
    out = ROOT / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "safety.json").write_text(json.dumps({"speedup": SPEEDUP, "scenarios": rows}, indent=2))
    return 0 if all(row["samples_inside_margin"] == 0 for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
