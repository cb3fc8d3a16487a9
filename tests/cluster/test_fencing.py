"""A daemon paused (SIGSTOP) or stalled mid-mission does not act on stale state when it wakes.

Real `gcs serve --cluster` processes on one real nats-server; the agents run in this process
(memory autopilot, 4x) so the test sees what each of them waits for. docs/cluster.md, "Fencing".
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from protocol.taskfile import TaskFile
from tests.cluster.served import events as _events
from tests.cluster.served import hold_task
from tests.cluster.served import served_cluster as _served
from tests.cluster.served import submit as _submit
from tests.cluster.served import until as _until
from tests.cluster.served import watch as _watch

pytestmark = pytest.mark.slow

# What a leader decides; none of it may come from a daemon whose lease ran out while it slept.
DECISIONS = {
    "sync_timeout",
    "sync_released",
    "mission_aborted",
    "mission_completed",
    "agent_excluded",
    "mission_resent",
    "mission_paused",
    "mission_resumed",
    "action_retry",
    "action_skipped",
    "mission_takeover",
}


def _task(holds: dict[str, float], sync_timeout_s: float, policy: str) -> TaskFile:
    """Takeoff, a hold of ``holds[agent]`` wall seconds, a 1 s hold (each a barrier), land."""
    return hold_task({a: [s, 1.0] for a, s in holds.items()}, sync_timeout_s, policy, "fencing")


async def test_paused_leader_decides_nothing_when_it_wakes(tmp_path: Path, nats_server: NatsServer) -> None:
    """The leader is paused 5 s while two of its agents wait at a barrier; its sync timeout
    falls due while it sleeps. The standby takes over, the agents move to it, the barrier is
    released there. The old leader wakes: no abort, release, exclusion or record change from it."""
    links = {"t0": "gcs-a", "t1": "gcs-a", "t2": "gcs-b"}
    # a's agents give up on it after 2 s of silence; t2 reaches the barrier 4.5 s after the
    # others: after a's sync timeout (4 s, due while it sleeps), before the standby's.
    async with _served(tmp_path, nats_server.url, links, {"t0": 2.0, "t1": 2.0}) as (serves, agents):
        a, b = serves["gcs-a"], serves["gcs-b"]
        task = _task({"t0": 1.0, "t1": 1.0, "t2": 5.5}, sync_timeout_s=4.0, policy="abort")
        mission_id = await _submit(a, task)
        t0 = agents["t0"].agent
        await _until(lambda: t0.queue.waiting_sync == 1, 30, "t0 waiting at barrier 1")
        a.pause()
        paused_at = time.time()
        try:
            async with httpx.AsyncClient(base_url=b.api, timeout=10) as api_b:
                watcher = asyncio.create_task(_watch(api_b, mission_id, 40))
                await asyncio.sleep(5.0)
                a.resume()
                resumed_at = time.time()
                seen = await watcher
        finally:
            a.resume()
        states = [r.get("state") for r in seen]
        assert seen and seen[-1]["state"] == "completed", seen[-1:]
        assert "aborted" not in states, "the shared record was downgraded by the old leader"
        assert seen[-1]["released_steps"] == [0, 1, 2]
        assert not any(p["excluded"] for p in seen[-1]["agents"]), seen[-1]["agents"]
        old = [e for e in await _events(a, mission_id=mission_id) if e["time"] >= paused_at]
        decided = [
            (e["kind"], e["message"], round(e["time"] - resumed_at, 3)) for e in old if e["kind"] in DECISIONS
        ]
        assert not decided, f"the old leader decided after its lease ran out: {decided}"
        assert any(e["kind"] == "mission_step_down" for e in old), [e["kind"] for e in old]
        takeovers = [e for e in await _events(b, mission_id=mission_id) if e["kind"] == "mission_takeover"]
        assert takeovers and takeovers[0]["time"] < resumed_at, "the standby led while a slept"
        alarms = await _events(a, kind="emergency_stale")  # its own silence is not the drones'
        assert not alarms, [e["message"] for e in alarms]
        async with httpx.AsyncClient(base_url=a.api, timeout=10) as api_a:  # the moved ones, once
            rows = (await api_a.get("/api/v1/agents", headers={"Authorization": f"Bearer {a.token}"})).json()
            fleet = {r["identity"]: r["daemon"] for r in (await api_a.get("/api/v1/cluster/fleet")).json()}
            info = (await api_a.get("/api/v1/cluster")).json()
        assert info["step_downs"] >= 1 and info["leading"] == [], info
        views = {r["identity"]: (r["connected"], r["peer"]) for r in rows}
        assert len(rows) == 3 and views["t0"] == views["t1"] == (True, "via gcs-b"), rows
        assert fleet == {"t0": "gcs-b", "t1": "gcs-b", "t2": "gcs-b"}, fleet


async def test_stalled_daemon_keeps_its_drones_in_the_mission(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """gcs-b (holding two drones, leading nothing) stalls 4.5 s mid-mission, shorter than its
    agents wait before moving (5 s): with lost_agent_policy continue, nobody is excluded."""
    links = {"t0": "gcs-a", "t1": "gcs-b", "t2": "gcs-b"}
    async with _served(tmp_path, nats_server.url, links, {}) as (serves, agents):
        a, b = serves["gcs-a"], serves["gcs-b"]
        task = _task({"t0": 3.0, "t1": 3.0, "t2": 3.0}, sync_timeout_s=30.0, policy="continue")
        mission_id = await _submit(a, task)
        t1 = agents["t1"].agent
        await _until(lambda: t1.queue.current_step == 1, 30, "t1 flying step 1")
        b.pause()
        try:
            async with httpx.AsyncClient(base_url=a.api, timeout=10) as api_a:
                watcher = asyncio.create_task(_watch(api_a, mission_id, 40))
                await asyncio.sleep(4.5)
                b.resume()
                seen = await watcher
        finally:
            b.resume()
        assert seen and seen[-1]["state"] == "completed", seen[-1:]
        excluded = [p["agent"] for r in seen for p in r["agents"] if p["excluded"]]
        assert not excluded, f"healthy drones excluded after a 4.5 s stall: {sorted(set(excluded))}"
        lost = await _events(b, kind="agent_lost") + await _events(b, kind="emergency_stale")
        assert not lost, f"b's own stall counted as its drones' silence: {[e['message'] for e in lost]}"
        assert seen[-1]["released_steps"] == [0, 1, 2]
