"""Fly varied simulated missions and record one flight log (CSV + plan sidecar) per drone-flight.

The daemon's cooperation service records the logs itself (``energy.record_dir``), exactly as it
would on real flights; this script only provides the fleet: our simulator (with wind and gusts,
its own power and battery model) and in-process agents on the MAVLink backend.

Run: python bench/make_energy_logs.py OUT_DIR [--batches 8] [--drones 6] [--speedup 10] [--seed 1]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import random
import secrets
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.autopilot.mavlink_backend import MavlinkAutopilot  # noqa: E402
from agent.config import AgentConfig, AgentSettings  # noqa: E402
from agent.runtime import Agent  # noqa: E402
from gcs.cooperation.config import CooperationConfig, EnergyConfig  # noqa: E402
from gcs.core.config import DaemonConfig  # noqa: E402
from gcs.core.daemon import Daemon  # noqa: E402
from protocol.actions import Action, Goto, Land, ReturnToLaunch, Takeoff, Waypoint, Waypoints  # noqa: E402
from protocol.geo import offset_latlon  # noqa: E402
from protocol.taskfile import AgentPlan, TaskFile  # noqa: E402
from sitl.fleet import FleetConfig, SimFleet  # noqa: E402

HOME = (47.397742, 8.545594, 488.0)
CORRIDOR_M = 200.0  # homes this far apart east; each drone stays within +-60 m of its own


def random_plan(rng: random.Random, home: tuple[float, float]) -> list[Action]:
    """Take off, a few legs (goto or waypoints) at one speed and altitude, then land or RTL."""
    alt = rng.uniform(8.0, 25.0)
    speed = rng.uniform(3.0, 9.0)
    actions: list[Action] = [Takeoff(step=0, alt=alt)]
    step = 1
    for _ in range(rng.randint(1, 4)):
        kind = rng.random()
        if kind < 0.4:
            n, e = rng.uniform(-150, 150), rng.uniform(-50, 50)
            lat, lon = offset_latlon(home[0], home[1], n, e)
            actions.append(Goto(step=step, lat=lat, lon=lon, alt=alt, speed=speed))
        elif kind < 0.85:
            points = []
            for _ in range(rng.randint(2, 6)):
                lat, lon = offset_latlon(home[0], home[1], rng.uniform(-120, 120), rng.uniform(-50, 50))
                points.append(Waypoint(lat=lat, lon=lon, alt=alt))
            actions.append(Waypoints(step=step, points=points, speed=speed))
        else:  # hover at a point (no `hold` action: the agent times holds in wall seconds, so under
            # a speed-up a hold would last speedup x longer in vehicle time than the plan says)
            n, e = rng.uniform(-100, 100), rng.uniform(-50, 50)
            lat, lon = offset_latlon(home[0], home[1], n, e)
            actions.append(Goto(step=step, lat=lat, lon=lon, alt=alt + rng.uniform(-5, 5), speed=speed))
        step += 1
    if rng.random() < 0.5:
        actions.append(ReturnToLaunch(step=step))
    else:
        actions.append(Land(step=step))
    return actions


async def fly_batch(out: Path, drones: int, speedup: float, rng: random.Random, batch: int) -> int:
    key = secrets.token_hex(32)
    wind = (rng.uniform(-5, 5), rng.uniform(-5, 5))
    fleet = SimFleet(
        FleetConfig(
            vehicles=drones,
            home=HOME,
            base_port=0,
            speedup=speedup,
            seed=rng.randrange(1 << 30),
            spacing_m=CORRIDOR_M,
            prearm_delay_s=1.0,
            wind=wind,
            gust_mps=rng.uniform(0.0, 1.5),
        )
    )
    fleet.start()
    coop = CooperationConfig(
        vehicle_time_scale=speedup, energy=EnergyConfig(record_dir=out, record_time_scale=speedup)
    )
    daemon = Daemon(
        DaemonConfig(
            listen_port=0,
            http_host=None,
            data_dir=out / f".daemon-{batch}",
            fleet_key_hex=key,
            status_period_s=0.1,
            lost_after_periods=60.0,
            cooperation=coop,
        )
    )
    await daemon.start()
    names = [f"b{batch}-d{i}" for i in range(drones)]
    tasks = []
    try:
        for name, endpoint in zip(names, fleet.endpoints, strict=True):
            agent = Agent(
                AgentConfig(
                    identity=name,
                    gcs_port=daemon.listen_port,
                    key_hex=key,
                    settings=AgentSettings(status_period_s=0.1),
                    resend_target_s=0.4,
                    monitor_period_s=0.05,
                ),
                MavlinkAutopilot(endpoint, telemetry_hz=20.0),
            )
            tasks.append(asyncio.create_task(agent.run()))
        deadline = time.monotonic() + 30
        while not all((s := daemon.agents.session(n)) and s.status and s.status.gps.fix >= 3 for n in names):
            if time.monotonic() > deadline:
                raise RuntimeError("agents did not join")
            await asyncio.sleep(0.1)
        plans = []
        for i, name in enumerate(names):
            home = offset_latlon(HOME[0], HOME[1], 0.0, i * CORRIDOR_M)
            plans.append(AgentPlan(agent=name, actions=random_plan(rng, home)))
        mission_id = await daemon.missions.submit(TaskFile(name=f"energy-batch-{batch}", plans=plans))
        deadline = time.monotonic() + 900 / speedup + 60
        while mission_id in daemon.missions.active and time.monotonic() < deadline:
            await asyncio.sleep(0.2)
        settle = time.monotonic() + 15
        while time.monotonic() < settle and not all(
            (s := daemon.agents.session(n)) and s.status and s.status.landed and not s.status.armed
            for n in names
        ):
            await asyncio.sleep(0.2)
        await asyncio.sleep(0.5)  # the disarmed report closes each log
        kept = fleet.sim_time / max(fleet.wall_time_s, 1e-9)
        note = (
            f", fell behind {fleet.overruns}x ({fleet.dropped_sim_s:.1f} sim s dropped)"
            if fleet.overruns
            else ""
        )
        print(f"  simulator speed-up kept {kept:.2f}x of {speedup:g}x{note}", flush=True)
        return drones
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await daemon.stop()
        fleet.stop()


async def make_logs(out: Path, batches: int, drones: int, speedup: float, seed: int) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    rng = random.Random(seed)
    for batch in range(batches):
        started = time.monotonic()
        await fly_batch(out, drones, speedup, rng, batch)
        print(
            f"batch {batch + 1}/{batches}: {drones} flights in {time.monotonic() - started:.0f} s", flush=True
        )
    return sorted(out.glob("*.csv"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--batches", type=int, default=8)
    parser.add_argument("--drones", type=int, default=6)
    parser.add_argument("--speedup", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    logs = asyncio.run(make_logs(args.out, args.batches, args.drones, args.speedup, args.seed))
    print(f"{len(logs)} flight logs in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
