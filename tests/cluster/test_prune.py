"""Finished missions' keys leave the shared buckets a while after the mission ends, in bounded rounds."""

from __future__ import annotations

import json
import time

from gcs.cluster.housekeeping import prune_round
from gcs.cluster.natsrun import NatsServer
from gcs.cluster.state import ClusterState
from tests.support.polling import wait_for


async def _state(server: NatsServer, name: str) -> ClusterState:
    state = ClusterState([server.url], name, replicas=1, lease_ttl_s=3.0)
    await state.connect()
    return state


def _mission(mission_id: str, state: str, finished: float | None) -> dict[str, object]:
    return {"id": mission_id, "name": mission_id, "task": "{}", "state": state, "created": 0.0,
            "finished": finished, "result": None, "paused": False, "leader": "a"}  # fmt: skip


async def _messages(state: ClusterState, bucket: str) -> int:
    assert state.js is not None
    info = await state.js.stream_info(f"KV_fleet_{bucket}")
    return int(info.state.messages)


async def test_finished_mission_keys_are_pruned_in_bounded_rounds(nats_server: NatsServer) -> None:
    a, b = await _state(nats_server, "a"), await _state(nats_server, "b")
    try:
        now = time.time()
        a.put_json("missions", "m-old", _mission("m-old", "completed", now - 100.0))
        a.put_json("missions", "m-new", _mission("m-new", "completed", now - 1.0))
        a.put_json("missions", "m-run", _mission("m-run", "running", None))
        for mission in ("m-old", "m-new", "m-run"):
            for agent in ("d1", "d2", "d3"):
                a.put_json("progress", f"{mission}.{agent}", {"completed": 3, "excluded": False})
                a.put_json("barriers", f"{mission}.1.arrived.{agent}", {"t": 1})
            a.put_json("barriers", f"{mission}.1.released", {"t": 1})
        await a.flush_writes()
        await a.create("leases", "m-old", a.unique())
        await wait_for(lambda: len(b.mirror["progress"]) == 9, 10, "b's mirror to load")

        assert await prune_round(a, after_s=50.0, now=now, budget=4) == 4  # bounded
        assert await prune_round(a, after_s=50.0, now=now, budget=4) == 3  # the rest of m-old's 7 keys
        old = [k for bucket in ("progress", "barriers") for k in a.mirror[bucket] if k.startswith("m-old.")]
        assert not old
        await wait_for(
            lambda: not any(k.startswith("m-old.") for k in b.mirror["progress"] | b.mirror["barriers"]),
            10,
            "the purges to reach b's mirror",
        )
        await a.flush_writes()
        assert json.loads(a.mirror["missions"]["m-old"])["pruned"] == now
        before = await _messages(a, "progress")
        assert await prune_round(a, after_s=50.0, now=now) == 1  # step 2: markers and lease go
        await a.flush_writes()
        assert await _messages(a, "progress") == before - 3, "the purge markers are gone too"
        assert (await a.lease_holder("m-old"))[0] is None
        assert json.loads(a.mirror["missions"]["m-old"])["tidy"] is True
        assert await prune_round(a, after_s=50.0, now=now) == 0  # nothing left to do
        # the young finished mission and the running one keep every key; the record stays
        assert sum(k.startswith("m-new.") for k in a.mirror["progress"]) == 3
        assert sum(k.startswith("m-run.") for k in a.mirror["barriers"]) == 4
        assert "m-old" in a.mirror["missions"]
    finally:
        await a.close()
        await b.close()
