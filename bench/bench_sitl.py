"""Benchmark of the embedded simulator (``python bench/bench_sitl.py``).

1. CPU cost: N vehicles (1, 10, 50) flying, a client in a *separate process* requesting 10 Hz streams of
   7 messages per vehicle; we report the simulation thread's CPU seconds per sim-second per vehicle and
   the implied number of vehicles one core can simulate in real time.
2. Speed-up: 10 vehicles with the same client, sim run as fast as possible; sim-time / wall-time.

Prints a table and writes bench/results/sitl.json.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import platform
import selectors
import socket
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import contextlib

from sitl.dialect import mavlink as mav
from sitl.fleet import FleetConfig, SimFleet
from sitl.physics import local_to_latlon
from sitl.vehicle import GUIDED

STREAMS = [
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    mav.MAVLINK_MSG_ID_ATTITUDE,
    mav.MAVLINK_MSG_ID_VFR_HUD,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT,
    mav.MAVLINK_MSG_ID_SYS_STATUS,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
]
RATE_HZ = 10.0


def client(urls: list[str], seconds: float, out: mp.Queue) -> None:
    """Separate process: connect to every endpoint, request 10 Hz streams, read and count bytes."""
    sel = selectors.DefaultSelector()
    socks = []
    for i, url in enumerate(urls):
        _, host, port = url.split(":")
        s = socket.create_connection((host, int(port)))
        link = mav.MAVLink(None, 255, 190)
        for mid in STREAMS:
            msg = mav.MAVLink_command_long_message(
                i + 1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, mid, 1e6 / RATE_HZ, 0, 0, 0, 0, 0
            )
            s.sendall(msg.pack(link))
            link.seq = (link.seq + 1) % 256
        s.setblocking(False)
        sel.register(s, selectors.EVENT_READ)
        socks.append(s)
    total = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        for key, _ in sel.select(0.1):
            sock = key.fileobj
            assert isinstance(sock, socket.socket)
            with contextlib.suppress(BlockingIOError):
                total += len(sock.recv(1 << 16))
    for s in socks:
        s.close()
    out.put(total)


def launch(fleet: SimFleet) -> None:
    """Put every vehicle in the air on a long leg (direct calls under the fleet lock)."""
    assert fleet.wait_sim_time(fleet.cfg.prearm_delay_s + 0.1, 30.0)
    with fleet.lock:
        for v in fleet.vehicles:
            assert v.set_mode(GUIDED)
            assert v.arm(force=True)[0]
            takeoff = mav.MAVLink_command_long_message(
                v.sysid, 1, mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 20
            )
            v.handle(takeoff, 0.0)
    assert fleet.wait_sim_time(fleet.sim_time + 10.0, 60.0)
    with fleet.lock:
        for v in fleet.vehicles:
            st = v.state
            lat, lon = local_to_latlon(st.home_lat, st.home_lon, 5000.0, 0.0)
            goto = mav.MAVLink_set_position_target_global_int_message(
                0, v.sysid, 1, 6, 0x0DF8, round(lat * 1e7), round(lon * 1e7), 20, 0, 0, 0, 0, 0, 0, 0, 0
            )
            v.handle(goto, 0.0)


def measure(vehicles: int, speedup: float, seconds: float) -> dict[str, float | str]:
    """Run a fleet with a streaming client; returns CPU and time figures over the measured window."""
    cfg = FleetConfig(
        vehicles=vehicles, base_port=0, speedup=speedup if speedup > 0 else 20.0, seed=1, prearm_delay_s=1.0
    )
    fleet = SimFleet(cfg).start()
    try:
        launch(fleet)
        if speedup <= 0:  # switch to as-fast-as-possible for the measured window
            fleet.stop()
            cfg = FleetConfig(vehicles=vehicles, base_port=0, speedup=math.inf, seed=1, prearm_delay_s=1.0)
            fleet = SimFleet(cfg).start()
            launch(fleet)
        q: mp.Queue = mp.Queue()
        proc = mp.Process(target=client, args=(fleet.endpoints, seconds + 1.0, q))
        proc.start()
        time.sleep(0.5)  # connections up, streams requested
        cpu0, sim0, wall0 = fleet.cpu_time_s, fleet.sim_time, time.monotonic()
        time.sleep(seconds)
        cpu1, sim1, wall1 = fleet.cpu_time_s, fleet.sim_time, time.monotonic()
        proc.join(30)
        rx_bytes = q.get(timeout=5)
        sent = sum(ep.sent_msgs for ep in fleet._endpoints)
        dropped = sum(ep.dropped_msgs for ep in fleet._endpoints)
    finally:
        fleet.stop()
    sim = sim1 - sim0
    cpu = cpu1 - cpu0
    return {
        "vehicles": vehicles,
        "requested_speedup": speedup if speedup > 0 else "max",
        "wall_s": wall1 - wall0,
        "sim_s": sim,
        "sim_cpu_s": cpu,
        "achieved_speedup": sim / (wall1 - wall0),
        "cpu_per_sim_s_per_vehicle_ms": 1000.0 * cpu / (sim * vehicles) if sim > 0 else math.nan,
        "vehicles_per_core_realtime_10hz": (sim * vehicles) / cpu if cpu > 0 else math.nan,
        "client_rx_bytes": rx_bytes,
        "messages_sent_total": sent,
        "messages_dropped_total": dropped,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=4.0, help="wall seconds per measurement")
    ap.add_argument("--sizes", default="1,10,50", help="fleet sizes for the CPU measurement")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "sitl.json"))
    args = ap.parse_args()
    rows = []
    for n in (int(x) for x in args.sizes.split(",")):
        rows.append(measure(n, 2.0, args.seconds))
    fast = measure(10, 0.0, args.seconds)
    print(
        f"{'vehicles':>8} {'speedup':>8} {'sim s':>7} {'cpu s':>7} {'ms cpu/sim-s/veh':>17} "
        f"{'veh/core @10Hz':>15}"
    )
    for r in [*rows, fast]:
        print(
            f"{r['vehicles']:>8} {r['achieved_speedup']:>8.1f} {r['sim_s']:>7.1f} {r['sim_cpu_s']:>7.2f} "
            f"{r['cpu_per_sim_s_per_vehicle_ms']:>17.2f} {r['vehicles_per_core_realtime_10hz']:>15.0f}"
        )
    print(
        f"max speed-up with 10 vehicles (10 Hz x {len(STREAMS)} streams each): "
        f"{fast['achieved_speedup']:.1f}x"
    )
    result = {
        "benchmark": "sitl",
        "python": sys.version.split()[0],
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "physics_hz": 50,
        "streams_per_vehicle": len(STREAMS),
        "stream_rate_hz": RATE_HZ,
        "cpu_runs": rows,
        "max_speedup_10_vehicles": fast,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
