"""The cooperation service's status-tick hook alone: event-loop us per report at N agents.

Why: the full load bench (bench_load.py) measures every service at once with the clients on the
same two cores, so its per-service figures move with the machine's load. Here only the hook
runs, on real status-table ticks (compact bodies, slices of 128 rows as gcs/link/status_tick.py hands
them over), in two modes back to back in one process:

* ``gated``: the service as it is (the tick's rows into the fleet's arrays, only the rows a
  gate flags built and checked);
* ``every``: the same service made to build and check every row (what it did before the gates,
  plus the vectorised pass), the reference the gates must agree with.

The service runs without a daemon (a small context: no fences, nobody held, the missions'
plans); its intents are counted, not applied. ``--mission``: every drone flies a Goto leg of
a mission at its planned speed (plan tracking and divergence per report before the gates).

    python bench/bench_cooperation_tick.py --agents 2000 [--mission] [--ticks 40]
"""

from __future__ import annotations

import argparse
import asyncio
import time
from types import SimpleNamespace
from typing import Any

import numpy as np

from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.intents import Intent
from gcs.cooperation.service import CooperationService
from gcs.link.agents_table import StatusTable, StatusTick
from protocol import status_binary
from protocol.actions import Action, Goto, Takeoff
from protocol.geo import offset_latlon
from protocol.packets import Battery, GeoPoint, Gps, Position, StatusReport

SLICE = 128  # gcs/link/status_tick.py TICK_SLICE
GRID_M = 40.0
HOME = (47.397742, 8.545594)


class Session:
    def __init__(self, k: int) -> None:
        self.identity, self.cid, self.open = f"d{k}", k + 1, True
        self.home = GeoPoint(lat=HOME[0], lon=HOME[1])
        self.row = -1


class Service(CooperationService):
    """The service with a small context; intents counted instead of applied."""

    def __init__(self, plans: dict[str, list[Action]], every: bool) -> None:
        super().__init__(CooperationConfig())
        self.every = every
        self.intents = 0
        parameters = SimpleNamespace(acceptance_radius_m=None, link_range_m=None)
        self._ctx = SimpleNamespace(  # type: ignore[assignment]
            geofences={},
            config=SimpleNamespace(agent_parameters=parameters, status_period_s=0.1),
            missions=SimpleNamespace(plan_of=lambda mission, ident: plans.get(ident), active={}),
            authority=SimpleNamespace(is_held=lambda ident, owner=None: False, level=lambda ident: 0),
        )

    def _gate(self, tick: StatusTick, rows: np.ndarray[Any, np.dtype[np.intp]], now: float) -> list[int]:
        picked = super()._gate(tick, rows, now)
        return rows.tolist() if self.every else picked

    async def apply(self, intents: list[Intent]) -> None:
        self.intents += len(intents)


def run(agents: int, mission: bool, every: bool, ticks: int, spacing: float = GRID_M) -> dict[str, float]:
    sessions = [Session(k) for k in range(agents)]
    table = StatusTable(agents)
    for s in sessions:
        s.row = table.attach(s)
    start = [offset_latlon(*HOME, spacing * (k // 50), spacing * (k % 50)) for k in range(agents)]
    plans: dict[str, list[Action]] = {}
    for k, (lat, lon) in enumerate(start):
        far = offset_latlon(lat, lon, 5000.0, 0.0)
        plans[f"d{k}"] = [
            Takeoff(step=0, alt=12.3),
            Goto(step=1, lat=far[0], lon=far[1], alt=12.3, speed=5.0),
        ]
    service = Service(plans if mission else {}, every)

    def body(k: int, t: float) -> bytes:
        lat, lon = offset_latlon(*start[k], 5.0 * (t - 1000.0) if mission else 0.0, 0.0)
        return status_binary.encode(
            StatusReport(
                time=t,
                position=Position(lat=lat, lon=lon, alt_rel=12.3, alt_amsl=500.3),
                battery=Battery(pct=87.5 - 0.01 * (t - 1000.0), voltage_v=12.1, current_a=14.2),
                gps=Gps(fix=3, satellites=14),
                mode="GUIDED",
                armed=True,
                landed=False,
                step=1 if mission else -1,
                completed_step=0 if mission else -1,
                mission_id="m" if mission else None,
            )
        )

    def tick(t: float) -> list[StatusTick]:
        for k, s in enumerate(sessions):
            table.put(s.row, body(k, t), time.time())
        rows = table.take_dirty()
        whole = StatusTick(
            [sessions[r] for r in rows.tolist()],
            table.columns(rows),
            table.arrivals(rows),
            [None] * len(rows),
        )
        return [whole.slice(a, a + SLICE) for a in range(0, len(rows), SLICE)]

    async def main() -> dict[str, float]:
        t = 1000.0
        for _ in range(3):  # joins and the first reports
            for part in tick(t):
                await service._on_tick(part)
            t += 0.1
        busy, built = 0.0, service.built
        for _ in range(ticks):
            parts = tick(t)
            t += 0.1
            started = time.perf_counter()
            for part in parts:
                await service._on_tick(part)
            busy += time.perf_counter() - started
        checks: dict[bool, list[float]] = {True: [], False: []}
        for _ in range(10):
            for prefilter in (True, False):
                service.collision.prefilter = prefilter
                started = time.perf_counter()
                service._fleet_checks(time.monotonic())
                checks[prefilter].append(time.perf_counter() - started)
        reports = agents * ticks
        return {
            "us_per_report": busy * 1e6 / reports,
            "built_per_report": (service.built - built) / reports,
            "intents": float(service.intents),
            "fleet_check_ms": float(np.median(checks[True])) * 1e3,
            "fleet_check_no_prefilter_ms": float(np.median(checks[False])) * 1e3,
        }

    return asyncio.run(main())


def cli() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", type=int, default=2000)
    parser.add_argument(
        "--ticks", type=int, default=40, help="status ticks measured (each: every agent once)"
    )
    parser.add_argument("--mission", action="store_true", help="every drone flies a mission leg")
    parser.add_argument("--spacing", type=float, default=GRID_M, help="metres between grid neighbours")
    args = parser.parse_args()
    for every in (False, True):
        row = run(args.agents, args.mission, every, args.ticks, args.spacing)
        mode = "every" if every else "gated"
        print(
            f"{args.agents} agents {'mission' if args.mission else 'hover'} {mode:5s}: "
            f"{row['us_per_report']:.2f} us per report, {row['built_per_report']:.3f} reports built "
            f"per report, {row['intents']:.0f} intents, fleet check {row['fleet_check_ms']:.1f} ms "
            f"({row['fleet_check_no_prefilter_ms']:.1f} ms without the collision prefilter)"
        )


if __name__ == "__main__":
    cli()
