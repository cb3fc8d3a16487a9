"""Cluster mode figures (docs/cluster.md): takeover time, barrier release latency, status throughput.

* takeover: two `gcs serve --cluster` processes share one long mission; the leader is killed with
  SIGKILL, the time until the other one reports leading it is measured; the killed one is started
  again and the next kill hits the new leader (repeated ``--kills`` times).
* barrier release latency: three in-process agents (memory autopilot) fly ``--barriers`` short
  sync legs; per barrier, from the last agent sending 'finished' to the last agent getting the
  release. One embedded daemon, one clustered daemon, two clustered daemons with the agents split.
* status throughput: bench/bench_load.py's synthetic agents at 10 Hz (``--agents``) against one
  embedded daemon, one clustered daemon, and two clustered daemons with half the agents each
  (each also mirrors the other's reports): loss, ingest rate, latency, daemon CPU.

Run: python bench/bench_cluster.py [--kills 10]   (about 3 minutes; writes bench/results/cluster.json)
     python bench/bench_cluster.py --only throughput   (one part, printed only)
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_load  # noqa: E402
import httpx  # noqa: E402

from gcs.cluster.natsrun import NatsServer, missing_reason  # noqa: E402
from gcs.daemon import Daemon  # noqa: E402
from protocol.actions import GoBy, Hold, Land, Takeoff  # noqa: E402
from protocol.packets import SyncSignal  # noqa: E402
from protocol.taskfile import AgentPlan, TaskFile  # noqa: E402
from tests.backbone.helpers import daemon_config, new_key, start_agent, stop_agents, wait_for  # noqa: E402
from tests.cluster.procs import start_serve  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def percentile(values: list[float], p: float) -> float:
    """``p`` in percent, nearest rank."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(p / 100 * len(ordered) + 0.5) - 1))]


# --- takeover ------------------------------------------------------------------------------------


def _long_task(names: list[str]) -> TaskFile:
    plans = [
        AgentPlan(
            agent=n, actions=[Takeoff(step=0, alt=5.0, sync=True), Hold(step=1, seconds=500), Land(step=2)]
        )
        for n in names
    ]
    return TaskFile.model_validate({"name": "takeover-bench", "plans": [p.model_dump() for p in plans]})


async def _leader(api: httpx.AsyncClient, mission_id: str) -> bool:
    with contextlib.suppress(httpx.HTTPError):
        return mission_id in (await api.get("/api/v1/cluster")).json()["leading"]
    return False


async def takeover_trials(base: Path, nats: NatsServer, kills: int, lease_ttl_s: float) -> dict[str, Any]:
    key = new_key()
    serves = {n: start_serve(n, base, nats.url, key, lease_ttl_s) for n in ("gcs-a", "gcs-b")}
    ports = {n: f"127.0.0.1:{s.agent_port}" for n, s in serves.items()}
    agents = [
        start_agent("k0", serves["gcs-a"].agent_port, key, 0, daemons=[ports["gcs-b"]]),
        start_agent("k1", serves["gcs-b"].agent_port, key, 1, daemons=[ports["gcs-a"]]),
    ]
    times: list[float] = []
    try:
        async with httpx.AsyncClient(timeout=5) as client:
            api = serves["gcs-a"].api
            for _ in range(100):
                rows = (await client.get(f"{api}/api/v1/cluster/fleet")).json()
                if sum(1 for r in rows if r["connected"]) == 2:
                    break
                await asyncio.sleep(0.1)
            created = await client.post(
                f"{api}/api/v1/missions",
                content=_long_task(["k0", "k1"]).model_dump_json(),
                headers={
                    "Authorization": f"Bearer {serves['gcs-a'].token}",
                    "Content-Type": "application/json",
                },
            )
            assert created.status_code == 201, created.text
            mission_id = created.json()["mission_id"]
            leader = "gcs-a"
            for trial in range(kills):
                other = "gcs-b" if leader == "gcs-a" else "gcs-a"
                await asyncio.sleep(1.0 + 0.37 * trial % 1.0)  # kill at different points of the lease period
                serves[leader].kill()
                killed = time.monotonic()
                other_api = httpx.AsyncClient(base_url=serves[other].api, timeout=2)
                async with other_api:
                    while time.monotonic() - killed < 30 and not await _leader(other_api, mission_id):
                        await asyncio.sleep(0.02)
                times.append(time.monotonic() - killed)
                print(f"  kill {trial + 1}: {other} leads after {times[-1]:.2f} s", flush=True)
                serves[leader] = start_serve(leader, base, nats.url, key, lease_ttl_s)
                leader = other
    finally:
        await stop_agents(agents)
        for serve in serves.values():
            serve.stop()
    return {
        "lease_ttl_s": lease_ttl_s,
        "kills": len(times),
        "takeover_s": [round(t, 3) for t in times],
        "p50_s": round(percentile(times, 50), 3),
        "p99_s": round(percentile(times, 99), 3),
        "max_s": round(max(times), 3),
    }


# --- barrier release latency ---------------------------------------------------------------------


def _barrier_task(names: list[str], barriers: int) -> TaskFile:
    plans = []
    for n in names:
        actions: list[Any] = [Takeoff(step=0, alt=3.0, sync=True)]
        for leg in range(1, barriers + 1):
            actions.append(GoBy(step=leg, north=1.0 if leg % 2 else -1.0, east=0.0, sync=True))
        actions.append(Land(step=barriers + 1))
        plans.append(AgentPlan(agent=n, actions=actions))
    return TaskFile.model_validate({"name": "barrier-bench", "plans": [p.model_dump() for p in plans]})


async def barrier_trial(base: Path, nats: NatsServer | None, daemons: int, barriers: int) -> dict[str, Any]:
    key = new_key()
    started: list[Daemon] = []
    finished: dict[int, float] = {}
    released: dict[int, float] = {}
    names = ["b0", "b1", "b2"]
    agents = []
    try:
        for i in range(daemons):
            extra: dict[str, Any] = {"cluster": [nats.url], "daemon_id": f"bench-{i}"} if nats else {}
            daemon = Daemon(daemon_config(base / f"barrier-{daemons}-{i}-{bool(nats)}", key, **extra))
            await daemon.start()
            started.append(daemon)
        for index, name in enumerate(names):
            running = start_agent(name, started[index % daemons].listen_port, key, index, speedup=20.0)
            link = running.agent.link
            send, on_release = link.send_control, link._on_release

            async def timed_send(body: Any, send: Any = send) -> None:
                if isinstance(body, SyncSignal) and body.kind == "finished":
                    finished[body.step] = max(finished.get(body.step, 0.0), time.perf_counter())
                await send(body)

            async def timed_release(signal: SyncSignal, on_release: Any = on_release) -> None:
                released[signal.step] = max(released.get(signal.step, 0.0), time.perf_counter())
                await on_release(signal)

            link.send_control = timed_send  # type: ignore[method-assign]
            link._on_release = timed_release
            agents.append(running)
        leader = started[0]
        await wait_for(lambda: all(leader.agents.session(n) for n in names), 20, "agents")
        mission_id = await leader.missions.submit(_barrier_task(names, barriers))
        await wait_for(lambda: mission_id not in leader.missions.active, 120, "mission end", poll=0.05)
    finally:
        await stop_agents(agents)
        for daemon in reversed(started):
            await daemon.stop()
    steps = sorted(set(finished) & set(released))
    latencies = [(released[s] - finished[s]) * 1000 for s in steps]
    return {
        "daemons": daemons,
        "cluster": nats is not None,
        "barriers": len(latencies),
        "p50_ms": round(percentile(latencies, 50), 2),
        "p99_ms": round(percentile(latencies, 99), 2),
    }


# --- status throughput ---------------------------------------------------------------------------


def throughput(nats_url: str | None, daemons: int, agents: int, seconds: float) -> dict[str, Any]:
    """``agents`` synthetic agents at 10 Hz (bench_load's clients) split over ``daemons`` daemons."""
    harnesses = []
    try:
        for i in range(daemons):
            bench_load.DAEMON_OVERRIDES.clear()
            if nats_url:
                bench_load.DAEMON_OVERRIDES.update(cluster=[nats_url], daemon_id=f"load-{daemons}-{i}")
            harnesses.append(bench_load.Harness("daemon", agents // daemons, workers=1))
        connected = sum(h.connect() for h in harnesses)
        time.sleep(0.5)
        for h in harnesses:
            h.server_call("reset")
        for h in harnesses:
            for conn in h.worker_conns:
                conn.send(("status", bench_load.STATUS_HZ, seconds))
        for h in harnesses:
            for conn in h.worker_conns:
                conn.recv()
        sent = sum(r["sent"] for h in harnesses for r in h.workers_call("sent"))
        time.sleep(1.0)
        stats = [h.server_call("stats") for h in harnesses]
    finally:
        for h in harnesses:
            h.close()
        bench_load.DAEMON_OVERRIDES.clear()
    received = sum(s["received"] for s in stats)
    return {
        "daemons": daemons,
        "cluster": nats_url is not None,
        "agents": agents,
        "connected": connected,
        "sent": sent,
        "received": received,
        "loss": round(max(0.0, (sent - received) / sent), 4) if sent else 1.0,
        "ingest_msgs_per_s": round(received / seconds),
        "latency_p50_ms": round(max(s["p50_ms"] for s in stats), 2),
        "latency_p99_ms": round(max(s["p99_ms"] for s in stats), 2),
        "daemons_cpu_share": round(sum(s["cpu_s"] for s in stats) / (seconds + 1.0), 2),
    }


async def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--lease-ttl", type=float, default=3.0)
    parser.add_argument("--barriers", type=int, default=20)
    parser.add_argument("--agents", type=int, default=400, help="synthetic agents at 10 Hz")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument(
        "--only", choices=["takeover", "barriers", "throughput"], help="run one part (results to stdout)"
    )
    args = parser.parse_args()
    reason = missing_reason()
    if reason is not None:
        print(f"bench_cluster: {reason}", file=sys.stderr)
        return 2
    import logging

    logging.disable(logging.CRITICAL)
    results: dict[str, Any] = {"machine": bench_load.machine()}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        nats = NatsServer(base / "nats")
        nats.start()
        try:
            if args.only in (None, "takeover"):
                print("takeover (kill -9 of the leader):", flush=True)
                results["takeover"] = await takeover_trials(
                    base / "takeover", nats, args.kills, args.lease_ttl
                )
                print(json.dumps(results["takeover"]), flush=True)
            if args.only in (None, "barriers"):
                print("barrier release latency:", flush=True)
                results["barriers"] = [
                    await barrier_trial(base, None, 1, args.barriers),
                    await barrier_trial(base, nats, 1, args.barriers),
                    await barrier_trial(base, nats, 2, args.barriers),
                ]
                for row in results["barriers"]:
                    print(json.dumps(row), flush=True)
            if args.only in (None, "throughput"):
                print(f"status throughput ({args.agents} agents at 10 Hz):", flush=True)
                results["throughput"] = [
                    throughput(None, 1, args.agents, args.seconds),
                    throughput(nats.url, 1, args.agents, args.seconds),
                    throughput(nats.url, 2, args.agents, args.seconds),
                ]
                for row in results["throughput"]:
                    print(json.dumps(row), flush=True)
        finally:
            nats.stop()
    if args.only is not None:
        return 0
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cluster.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
