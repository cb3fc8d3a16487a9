"""The demo mission on both simulators, side by side (``python bench/bench_ardupilot.py``).

Flies ``gcs demo``'s planned 3-drone survey (daemon + agent processes + ``sitl run``) once on our
simulator and once on real ArduCopter SITL (``$ARDUPILOT_SITL``, else ../shared/ardupilot/arducopter;
that column is skipped when neither exists), at the same speed-up, and reports per drone: mission
time, flight time and distance, energy (integrated voltage x current), battery used, and the largest
distance between the flown track and the planned survey path. Sim-time figures are the wall
figures times the speed-up. Writes bench/results/ardupilot.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcs.commands.demo_mission import DemoOptions, run_demo  # noqa: E402

DEFAULT_BINARY = ROOT.parent / "shared" / "ardupilot" / "arducopter"


def binary() -> str | None:
    for cand in (os.environ.get("ARDUPILOT_SITL"), str(DEFAULT_BINARY)):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return str(Path(cand).resolve())
    return None


def fly(simulator: str, speedup: float, ardupilot: str | None) -> dict[str, Any]:
    options = DemoOptions(speedup=speedup, quiet=True, ardupilot=ardupilot, timeout_s=600.0)
    started = time.monotonic()
    result = asyncio.run(run_demo(options))
    wall = time.monotonic() - started
    drones = {}
    for name, record in sorted(result.recorder.records.items()):
        drones[name] = {
            "landed": result.landed.get(name, False),
            "flight_s": round(record.airborne_s * speedup, 1),
            "distance_m": round(record.distance_m, 1),
            "energy_wh": round(record.energy_wh, 2),
            "battery_used_pct": None
            if record.battery_used_pct is None
            else round(record.battery_used_pct, 1),
            "max_path_error_m": round(record.max_path_error_m, 2),
        }
    return {
        "simulator": simulator,
        "ok": result.ok,
        "result": result.message,
        "mission_s": round(result.mission_wall_s * speedup, 1),
        "wall_s": round(wall, 1),
        "drones": drones,
    }


def table(runs: list[dict[str, Any]]) -> str:
    cols = ["mission_s", "flight_s", "distance_m", "energy_wh", "battery_used_pct", "max_path_error_m"]
    lines = [f"{'simulator':11} {'drone':8} " + " ".join(f"{c:>16}" for c in cols)]
    for run in runs:
        for name, d in run["drones"].items():
            values = [run["mission_s"], *(d[c] for c in cols[1:])]
            lines.append(
                f"{run['simulator']:11} {name:8} "
                + " ".join(f"{'-' if v is None else v:>16}" for v in values)
            )
        lines.append(
            f"{run['simulator']:11} {'':8} result: {'ok' if run['ok'] else 'FAILED'} ({run['result']})"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speedup", type=float, default=5.0)
    args = ap.parse_args(argv)
    runs = [fly("ours", args.speedup, None)]
    real = binary()
    if real is None:
        print("real ArduCopter SITL not found (set ARDUPILOT_SITL): only our simulator measured")
    else:
        runs.append(fly("arducopter", args.speedup, real))
    print(table(runs))
    out = ROOT / "bench" / "results" / "ardupilot.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"speedup": args.speedup, "machine": platform.machine(), "python": platform.python_version()}
    out.write_text(json.dumps({"meta": meta, "runs": runs}, indent=2) + "\n")
    print(f"wrote {out}")
    return 0 if all(r["ok"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
