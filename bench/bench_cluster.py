"""Cluster mode figures (docs/cluster.md): takeover time, barrier release latency, status throughput.

* takeover: two `gcs serve --cluster` processes share one long mission; the leader is killed with
  SIGKILL, the time until the other one reports leading it is measured; the killed one is started
  again and the next kill hits the new leader (repeated ``--kills`` times).
* takeover after a pause: the leader is paused (SIGSTOP) ``--pause`` seconds instead; the time
  until the standby leads, until the woken one steps down, and what it decided after waking.
* leaderless time after a NATS node loss: the two daemons on a three-node NATS cluster (every
  bucket replicated 3 times) share one long mission; one NATS node is killed (in turn the one the
  leader is connected to, then the standby's), the time no daemon leads the mission (lease good by
  its own clock) is summed over the ``--window`` seconds that follow; the node is started again
  and left to catch up before the next kill (``--losses`` times).
* barrier release latency: three in-process agents (memory autopilot) fly ``--barriers`` short
  sync legs; per barrier, from the last agent sending 'finished' to the last agent getting the
  release. One embedded daemon, one clustered daemon, two clustered daemons with the agents split.
* status throughput: bench/bench_load.py's synthetic agents at 10 Hz (``--agents``) against one
  embedded daemon, one clustered daemon, and two clustered daemons with half the agents each
  (each also mirrors the other's reports): loss, ingest rate, latency, daemon CPU.

Run: python bench/bench_cluster.py [--kills 10]   (about 6 minutes; writes bench/results/cluster.json)
     python bench/bench_cluster.py --only throughput   (one part, printed only)
     python bench/bench_cluster.py --only nats --lease-ttl 8   (NATS node losses, about 3 minutes)
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

from gcs.cluster.natsrun import NatsCluster, NatsServer, missing_reason  # noqa: E402
from gcs.core.daemon import Daemon  # noqa: E402
from protocol.actions import GoBy, Hold, Land, Takeoff  # noqa: E402
from protocol.packets import SyncSignal  # noqa: E402
from protocol.taskfile import AgentPlan, TaskFile  # noqa: E402
from tests.backbone.helpers import daemon_config, new_key, start_agent, stop_agents, wait_for  # noqa: E402
from tests.cluster.procs import ServeProcess, start_serve  # noqa: E402

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


async def _start_long_mission(client: httpx.AsyncClient, serve: ServeProcess, names: list[str]) -> str:
    """Once the cluster's fleet shows every agent of ``names`` connected (bounded: 100 polls), a long
    mission for them submitted to ``serve``; its id."""
    for _ in range(100):
        rows = (await client.get(f"{serve.api}/api/v1/cluster/fleet")).json()
        if sum(1 for r in rows if r["connected"]) == len(names):
            break
        await asyncio.sleep(0.1)
    created = await client.post(
        f"{serve.api}/api/v1/missions",
        content=_long_task(names).model_dump_json(),
        headers={"Authorization": f"Bearer {serve.token}", "Content-Type": "application/json"},
    )
    assert created.status_code == 201, created.text
    return str(created.json()["mission_id"])


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
            mission_id = await _start_long_mission(client, serves["gcs-a"], ["k0", "k1"])
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


async def pause_trials(
    base: Path, nats: NatsServer, pauses: int, lease_ttl_s: float, pause_s: float
) -> dict[str, Any]:
    """The leader is paused (SIGSTOP) ``pause_s`` and continued, ``pauses`` times: how long until
    the standby leads, how long the woken one takes to step down, what it decided after waking
    (fencing: nothing)."""
    key = new_key()
    serves = {n: start_serve(n, base, nats.url, key, lease_ttl_s) for n in ("gcs-a", "gcs-b")}
    ports = {n: f"127.0.0.1:{s.agent_port}" for n, s in serves.items()}
    agents = [
        start_agent("p0", serves["gcs-a"].agent_port, key, 0, daemons=[ports["gcs-b"]]),
        start_agent("p1", serves["gcs-b"].agent_port, key, 1, daemons=[ports["gcs-a"]]),
    ]
    takeover: list[float] = []
    step_down: list[float] = []
    decided = 0
    try:
        async with httpx.AsyncClient(timeout=5) as client:
            mission_id = await _start_long_mission(client, serves["gcs-a"], ["p0", "p1"])
            leader = "gcs-a"
            for trial in range(pauses):
                other = "gcs-b" if leader == "gcs-a" else "gcs-a"
                await asyncio.sleep(1.0 + 0.37 * trial % 1.0)
                serves[leader].pause()
                paused, paused_wall = time.monotonic(), time.time()
                async with httpx.AsyncClient(base_url=serves[other].api, timeout=2) as other_api:
                    while time.monotonic() - paused < 30 and not await _leader(other_api, mission_id):
                        await asyncio.sleep(0.02)
                takeover.append(time.monotonic() - paused)
                await asyncio.sleep(max(0.0, pause_s - (time.monotonic() - paused)))
                serves[leader].resume()
                woke = time.monotonic()
                async with httpx.AsyncClient(base_url=serves[leader].api, timeout=5) as old_api:
                    while time.monotonic() - woke < 30 and await _leader(old_api, mission_id):
                        await asyncio.sleep(0.01)
                    step_down.append(time.monotonic() - woke)
                    events = (
                        await old_api.get(
                            "/api/v1/events",
                            params={"mission_id": mission_id, "limit": 10_000},
                            headers={"Authorization": f"Bearer {serves[leader].token}"},
                        )
                    ).json()
                decided += sum(
                    1
                    for e in events
                    if e["time"] >= paused_wall
                    and e["kind"] != "mission_step_down"
                    and e["kind"].startswith(("mission_", "sync_", "agent_excluded"))
                )
                print(
                    f"  pause {trial + 1}: {other} leads after {takeover[-1]:.2f} s, "
                    f"{leader} stepped down {step_down[-1]:.3f} s after waking",
                    flush=True,
                )
                leader = other
    finally:
        await stop_agents(agents)
        for serve in serves.values():
            serve.stop()
    return {
        "lease_ttl_s": lease_ttl_s,
        "pause_s": pause_s,
        "pauses": len(takeover),
        "takeover_p50_s": round(percentile(takeover, 50), 3),
        "takeover_p99_s": round(percentile(takeover, 99), 3),
        "step_down_after_wake_p50_s": round(percentile(step_down, 50), 3),
        "step_down_after_wake_max_s": round(max(step_down), 3),
        "decisions_after_wake": decided,
    }


# --- leaderless time after a NATS node loss ---------------------------------------------------------


async def _sample_leading(api: str, mission_id: str, until: float, seen: list[tuple[float, bool]]) -> None:
    """One request every 0.05 s, each in flight on its own (an answer slowed by a NATS election
    must not thin the samples); each records whether the daemon led the mission when asked."""

    async def ask(client: httpx.AsyncClient, at: float) -> None:
        with contextlib.suppress(httpx.HTTPError, ValueError, KeyError):
            seen.append((at, mission_id in (await client.get("/api/v1/cluster")).json()["leading"]))

    async with httpx.AsyncClient(base_url=api, timeout=5) as client:
        asks = []
        while time.monotonic() < until:
            asks.append(asyncio.create_task(ask(client, time.monotonic())))
            await asyncio.sleep(0.05)
        await asyncio.gather(*asks)


def _leaderless(
    samples: dict[str, list[tuple[float, bool]]], start: float, end: float
) -> tuple[float, float]:
    """(total, longest) time in [start, end] during which no daemon's latest answer said it led."""
    events = sorted((at, name, led) for name, rows in samples.items() for at, led in rows)
    state = {name: True for name in samples}  # both answered "leading" or "not" before: unknown = led
    total = longest = 0.0
    since: float | None = None
    for at, name, led in events:
        if at < start or at > end:
            continue
        state[name] = led
        if not any(state.values()) and since is None:
            since = at
        elif any(state.values()) and since is not None:
            total, longest, since = total + at - since, max(longest, at - since), None
    if since is not None:
        total, longest = total + end - since, max(longest, end - since)
    return total, longest


async def nats_loss_trials(base: Path, losses: int, lease_ttl_s: float, window_s: float) -> dict[str, Any]:
    cluster = NatsCluster(base / "nats3")
    cluster.start()
    key = new_key()
    env = {"FLEETGCS_CLUSTER_REPLICAS": "3"}
    serves: dict[str, Any] = {}
    agents = []
    rows: list[dict[str, Any]] = []
    try:
        for name in ("gcs-a", "gcs-b"):
            serves[name] = start_serve(name, base / "nats-loss", cluster.urls, key, lease_ttl_s, env=env)
        ports = {n: f"127.0.0.1:{s.agent_port}" for n, s in serves.items()}
        agents = [
            start_agent("l0", serves["gcs-a"].agent_port, key, 0, daemons=[ports["gcs-b"]]),
            start_agent("l1", serves["gcs-b"].agent_port, key, 1, daemons=[ports["gcs-a"]]),
        ]
        async with httpx.AsyncClient(timeout=5) as client:
            mission_id = await _start_long_mission(client, serves["gcs-a"], ["l0", "l1"])
            for trial in range(losses):
                await asyncio.sleep(2.0 + 0.37 * trial % 1.0)
                infos = {n: (await client.get(f"{s.api}/api/v1/cluster")).json() for n, s in serves.items()}
                leader = next((n for n, i in infos.items() if mission_id in i["leading"]), "gcs-a")
                standby = "gcs-b" if leader == "gcs-a" else "gcs-a"
                whose = leader if trial % 2 == 0 else standby
                url = infos[whose]["connected_url"]
                shared = infos[leader]["connected_url"] == infos[standby]["connected_url"]
                server = next(s for s in cluster.servers if s.url == url)
                killed = time.monotonic()
                server.kill()
                samples: dict[str, list[tuple[float, bool]]] = {n: [] for n in serves}
                await asyncio.gather(
                    *(
                        _sample_leading(s.api, mission_id, killed + window_s, samples[n])
                        for n, s in serves.items()
                    )
                )
                total, longest = _leaderless(samples, killed, killed + window_s)
                kind = "leader's" if whose == leader else "standby's"
                rows.append(
                    {"node": "shared" if shared else kind, "leaderless_s": total, "longest_s": longest}
                )
                print(f"  loss {trial + 1} ({rows[-1]['node']} node): leaderless {total:.2f} s", flush=True)
                server.start()  # the same port and store: it rejoins and catches up
                await asyncio.sleep(8.0)
    finally:
        await stop_agents(agents)
        for serve in serves.values():
            serve.stop()
        cluster.stop()
    every = [r["leaderless_s"] for r in rows]
    summary: dict[str, Any] = {"lease_ttl_s": lease_ttl_s, "window_s": window_s, "losses": len(rows)}
    summary["leaderless_p50_s"] = round(percentile(every, 50), 3)
    summary["leaderless_p99_s"] = round(percentile(every, 99), 3)
    summary["leaderless_max_s"] = round(max(every, default=float("nan")), 3)
    summary["longest_gap_p99_s"] = round(percentile([r["longest_s"] for r in rows], 99), 3)
    summary["trials"] = [{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()} for r in rows]
    return summary


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
    parser.add_argument("--pauses", type=int, default=5, help="SIGSTOP/SIGCONT of the leader")
    parser.add_argument("--pause", type=float, default=5.0, help="seconds each pause lasts")
    parser.add_argument("--lease-ttl", type=float, default=3.0)
    parser.add_argument("--losses", type=int, default=6, help="NATS node kills (3-node cluster)")
    parser.add_argument("--window", type=float, default=15.0, help="seconds watched after each loss")
    parser.add_argument("--barriers", type=int, default=20)
    parser.add_argument("--agents", type=int, default=400, help="synthetic agents at 10 Hz")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument(
        "--only",
        choices=["takeover", "pause", "nats", "barriers", "throughput"],
        help="run one part (results to stdout)",
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
            if args.only in (None, "pause"):
                print(f"takeover after a pause (SIGSTOP {args.pause:g} s of the leader):", flush=True)
                results["pause"] = await pause_trials(
                    base / "pause", nats, args.pauses, args.lease_ttl, args.pause
                )
                print(json.dumps(results["pause"]), flush=True)
            if args.only in (None, "nats"):
                print("leaderless time after a NATS node loss (one of three):", flush=True)
                results["nats_loss"] = await nats_loss_trials(
                    base / "nats-loss", args.losses, args.lease_ttl, args.window
                )
                print(json.dumps(results["nats_loss"]), flush=True)
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
