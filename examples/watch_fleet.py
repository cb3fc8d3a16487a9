"""Print the fleet, then every status report as it arrives (Ctrl-C to stop).

.venv/bin/python examples/watch_fleet.py --api http://127.0.0.1:8080
"""

from __future__ import annotations

import argparse

from gcs.http.client import FleetClient, run_script


async def main(api: str) -> None:
    async with FleetClient(api) as gcs:  # reading needs no token
        for agent in await gcs.agents():
            mode = agent.status.mode if agent.status else "-"
            print(f"{agent.identity:12} cid {agent.cid:3} {'up' if agent.connected else 'down':4} {mode}")
        async for name, status in gcs.statuses(max_rate_hz=1):
            p = status.position
            if p is None:  # no 3-D fix yet
                print(
                    f"{name:12} {status.mode:8} no position yet (GPS fix {status.gps.fix}) step {status.step}"
                )
                continue
            print(
                f"{name:12} {status.mode:8} {p.lat:.6f} {p.lon:.6f} alt {p.alt_rel:5.1f} m step {status.step}"
            )


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--api", default="http://127.0.0.1:8080")
    raise SystemExit(run_script(main(parser.parse_args().api), "watch_fleet"))
