"""Shared state on a real nats-server: compare-and-set where daemons race, mirrors, leases."""

from __future__ import annotations

import asyncio
import time

from gcs.cluster.natsrun import NatsServer
from gcs.cluster.state import ClusterState
from tests.support.polling import wait_for


async def _state(server: NatsServer, name: str, ttl: float = 1.0) -> ClusterState:
    state = ClusterState([server.url], name, replicas=1, lease_ttl_s=ttl)
    await state.connect()
    return state


async def test_cid_assigned_once_when_daemons_race(nats_server: NatsServer) -> None:
    a, b = await _state(nats_server, "a"), await _state(nats_server, "b")
    try:
        names = [f"drone{i}" for i in range(6)]
        results = await asyncio.gather(*(a.assign_cid(n) for n in names), *(b.assign_cid(n) for n in names))
        by_a, by_b = results[:6], results[6:]
        assert by_a == by_b, "both daemons must see the same CID for each agent"
        assert sorted(by_a) == sorted(set(by_a)), "no CID given to two agents"
        assert await a.assign_cid("drone0") == by_a[0]  # stable on reconnect
    finally:
        await a.close()
        await b.close()


async def test_release_claimed_exactly_once(nats_server: NatsServer) -> None:
    a, b = await _state(nats_server, "a"), await _state(nats_server, "b")
    try:
        wins = await asyncio.gather(
            *(s.create("barriers", "m1.3.released", s.unique()) for s in (a, b, a, b))
        )
        assert sum(wins) == 1
        await wait_for(lambda: "m1.3.released" in b.mirror["barriers"], 20, "mirror update")
    finally:
        await a.close()
        await b.close()


async def test_lease_expires_and_one_standby_takes_it(nats_server: NatsServer) -> None:
    a, b, c = [await _state(nats_server, n, ttl=2.0) for n in "abc"]
    try:
        assert await a.take_lease("m1")
        assert not await b.take_lease("m1")
        assert await a.renew_lease("m1")
        renewed = time.monotonic()
        assert (await b.lease_holder("m1"))[0] == "a"
        deadline = renewed + 15  # a stops renewing: its lease ages out (bounded wait, slow CI)
        while time.monotonic() < deadline and (await b.lease_holder("m1"))[0] is not None:
            await asyncio.sleep(0.1)
        assert (await b.lease_holder("m1"))[0] is None
        assert time.monotonic() - renewed >= 1.0, "the lease outlived half its TTL"
        wins = await asyncio.gather(b.take_lease("m1"), c.take_lease("m1"))
        assert sum(wins) == 1
        assert not await a.renew_lease("m1"), "the old leader must learn it lost the lead"
    finally:
        for s in (a, b, c):
            await s.close()
