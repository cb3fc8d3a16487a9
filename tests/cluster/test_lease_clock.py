"""Fencing on a real nats-server: a lease judged by the holder's own clock, writes and forwarded
orders under an older lease token refused once a newer leader stamped the mission record."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import nats.js.errors
import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.cluster.node import AIRSPACE_LEASE, ClusterNode
from gcs.cluster.state import ClusterState
from gcs.cluster.store import ClusterStore
from gcs.core.config import DaemonConfig


async def _state(server: NatsServer, name: str, ttl: float) -> ClusterState:
    state = ClusterState([server.url], name, replicas=1, lease_ttl_s=ttl)
    await state.connect()
    return state


def _record(leader: str, state: str = "running") -> dict[str, object]:
    return {"id": "m1", "name": "m1", "task": "{}", "state": state, "created": 0.0,
            "finished": None, "result": None, "paused": False, "leader": leader}  # fmt: skip


async def _until(predicate: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if await predicate():
            return
        await asyncio.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


async def test_stale_leader_writes_are_refused(nats_server: NatsServer) -> None:
    a, b = await _state(nats_server, "a", 1.0), await _state(nats_server, "b", 1.0)
    try:
        assert await a.take_lease("m1")
        a.put_fenced("missions", "m1", _record("a"), "m1")
        await a.flush_writes()
        assert a.leases.valid("m1")

        # a "sleeps": its clock gives the lease up before NATS does, then NATS expires it.
        async def ran_out() -> bool:
            return not a.leases.valid("m1")

        await _until(ran_out, 5, "a's lease to run out by a's clock")

        async def expired() -> bool:
            return (await b.lease_holder("m1"))[0] is None

        await _until(expired, 15, "the lease to expire in NATS")
        assert await b.take_lease("m1")
        assert await b.leases.stamp("m1")
        # Decisions a made under its old token, written after b stamped the record: refused.
        a.put_fenced("missions", "m1", _record("a", "aborted"), "m1")
        a.put_fenced("progress", "m1.x", {"completed": 5, "excluded": True}, "m1")
        await a.flush_writes()
        stored = json.loads((await b.kv["missions"].get("m1")).value or b"{}")
        assert stored["state"] == "running" and stored["leader"] == "b", stored
        with pytest.raises(nats.js.errors.KeyNotFoundError):
            await b.kv["progress"].get("m1.x")
        assert a.leases.refused == 2
        assert json.loads(a.mirror["missions"]["m1"])["state"] == "running", "a's mirror shows the truth"
        assert not await a.leases.confirm("m1"), "a steps down when it wakes"
        assert a.leases.token("m1") is None
        b.put_fenced("missions", "m1", {**stored, "state": "completed"}, "m1")
        await b.flush_writes()
        assert json.loads((await a.kv["missions"].get("m1")).value or b"{}")["state"] == "completed"
    finally:
        await a.close()
        await b.close()


async def test_lease_renewed_in_time_stays_valid(nats_server: NatsServer) -> None:
    """A holder past its local validity that nobody replaced renews once (compare-and-set on its
    own last revision) and may decide; the other daemon never held it meanwhile."""
    a = await _state(nats_server, "a", 2.0)
    try:
        assert await a.take_lease("m1")
        held = a.leases.held["m1"]
        held.valid_until = time.monotonic() - 0.01  # as after missed rounds, the key still ours
        assert await a.leases.confirm("m1")
        assert a.leases.valid("m1") and a.leases.token("m1") == held.token
    finally:
        await a.close()


def test_forwarded_order_with_an_older_token_is_refused(tmp_path: Path) -> None:
    config = DaemonConfig(cluster=["nats://127.0.0.1:4222"], daemon_id="gcs-b", data_dir=tmp_path)
    node = ClusterNode(config)  # not started: the check reads the mission record's mirror only
    node.state.mirror["missions"]["m1"] = json.dumps({**_record("gcs-b"), "lease": 20}).encode()
    assert node.forwarder.stale_order({"mission": "m1", "lease": "20"}) is None
    assert "older than 20" in (node.forwarder.stale_order({"mission": "m1", "lease": "12"}) or "")
    assert node.forwarder.stale_order({"airspace": "9"}) is None
    assert "stale airspace decider" in (node.forwarder.stale_order({"airspace": "5"}) or "")
    assert node.forwarder.stale_order({"lease": "x", "mission": "m1"}) == "bad lease header"
    node.store.close()


async def test_airspace_decided_only_while_the_lease_is_good_here(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """The airspace decider's scope follows its lease by its own clock: when its rounds stop
    (they fail, or it was paused) it stops deciding before NATS gives the lease to another."""
    config = DaemonConfig(
        cluster=[nats_server.url], daemon_id="gcs-a", data_dir=tmp_path, cluster_lease_ttl_s=2.0
    )
    node = ClusterNode(config)
    await node.state.connect()
    try:
        assert await node.state.renew_lease(AIRSPACE_LEASE)
        node.leadership.airspace_held = True  # what its last successful lease round concluded
        assert node.airspace() == "fleet"
        node.state.leases.held[AIRSPACE_LEASE].valid_until = time.monotonic() - 0.01  # rounds missed
        assert node.airspace() == "none"
    finally:
        await node.state.close()
        node.store.close()


async def test_a_mission_just_submitted_is_led_before_its_lease_write_ran(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """The submitting daemon's lease take is queued behind earlier writes; a status report handled
    before it ran must wait for it, not step the new mission down."""
    state = await _state(nats_server, "a", 2.0)
    store = ClusterStore(tmp_path / "a.sqlite", state)
    try:
        store.add_mission("m2", "m2", "{}", ["x"])
        assert state.leases.token("m2") is None, "the take is still queued"
        assert await state.leases.confirm("m2")
        await state.flush_writes()
        stored = json.loads((await state.kv["missions"].get("m2")).value or b"{}")
        assert stored["lease"] == state.leases.token("m2") and stored["leader"] == "a", stored
    finally:
        await state.close()
        store.close()
