"""Plan a search over an area, show the prediction, fly it and wait for the end.

    .venv/bin/python examples/fly_search.py --api http://127.0.0.1:8080 \
        --area 47.3979,8.5454 47.3979,8.5461 47.3983,8.5461 47.3983,8.5454

The token is read from DATA_DIR/api.token (or --token). On Ctrl-C every drone returns home.
"""

from __future__ import annotations

import argparse
import asyncio

from gcs.http.client import FleetClient, read_token, run_script
from gcs.http.planning_requests import SearchPlanRequest


async def main(args: argparse.Namespace) -> int:
    area = [tuple(float(x) for x in corner.split(",")) for corner in args.area]
    request = SearchPlanRequest(area=area, swath_m=args.swath, altitude_m=args.alt, pattern=args.pattern)
    async with FleetClient(args.api, args.token or read_token()) as gcs:
        preview = await gcs.plan(request)
        for drone in preview.drones:
            print(f"{drone.agent}: {drone.length_m:.0f} m, {drone.time_s:.0f} s, {drone.energy_wh:.1f} Wh")
        created = await gcs.submit_plan(request)
        print(f"mission {created.mission_id} started")
        try:
            progress = await gcs.wait_mission(created.mission_id, timeout=args.timeout)
        except (asyncio.CancelledError, KeyboardInterrupt, TimeoutError):
            await gcs.rtl_all()
            print("stopped: every drone returns home")
            return 1
        print(f"mission {progress.state}: {progress.result}")
        return 0 if progress.state == "completed" else 1


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--api", default="http://127.0.0.1:8080")
    parser.add_argument("--token")
    parser.add_argument("--area", nargs="+", required=True, help="corners as LAT,LON")
    parser.add_argument("--swath", type=float, default=15.0)
    parser.add_argument("--alt", type=float, default=15.0)
    parser.add_argument("--pattern", default="zigzag")
    parser.add_argument("--timeout", type=float, default=1800.0)
    raise SystemExit(run_script(main(parser.parse_args()), "fly_search"))
