"""A three-node NATS cluster loses a node mid-mission: the daemons carry on, the fleet stays whole.

Also: either daemon's API shows the whole fleet and routes an operator command to the daemon
holding the drone's link (applied there through its vehicle authority).
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsCluster
from tests.backbone.helpers import mission_ended, new_key, start_agent, stop_agents, survey_mission
from tests.cluster.simrig import two_daemons
from tests.support.polling import wait_for

pytestmark = pytest.mark.slow


async def test_nats_node_killed_mid_mission(tmp_path: Path, nats_cluster: NatsCluster) -> None:
    key = new_key()
    async with two_daemons(tmp_path, nats_cluster.urls, key, cluster_replicas=3) as (a, b):
        agents = [
            start_agent("f0", a.listen_port, key, 0, speedup=4.0),
            start_agent("f1", b.listen_port, key, 1, speedup=4.0),
            start_agent("f2", b.listen_port, key, 2, speedup=4.0),
        ]
        names = ["f0", "f1", "f2"]
        try:
            for daemon in (a, b):
                await wait_for(
                    lambda d=daemon: all(d.agents.session(n) for n in names), 15, "fleet on both daemons"
                )
            task = survey_mission(names, sync_legs=4, name="nats-failover")
            mission_id = await a.missions.submit(task)
            await wait_for(lambda: 1 in a.store.released_steps(mission_id), 30, "first releases")
            nats_cluster.servers[0].kill()
            stored = await mission_ended(a, mission_id, 60, "mission end after the NATS node died")
            assert stored.state == "completed", stored
            steps = set(task.plans[0].sync_steps())
            await wait_for(lambda: b.store.released_steps(mission_id) == steps, 30, "b's mirror to follow")
            for daemon in (a, b):
                async with httpx.AsyncClient(
                    base_url=f"http://127.0.0.1:{daemon.http_port}", timeout=20
                ) as api:
                    fleet = {r["identity"]: r for r in (await api.get("/api/v1/cluster/fleet")).json()}
                    assert sorted(fleet) == names
                    assert fleet["f0"]["daemon"] == "gcs-a" and fleet["f1"]["daemon"] == "gcs-b"
            # an operator hold for f0 (linked to a) given through b's API lands in a's authority
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{b.http_port}", timeout=20) as api:
                reply = await api.post(
                    "/api/v1/cluster/fleet/hold",
                    json={"agents": ["f0", "f1"], "reason": "test"},
                    headers={"Authorization": "Bearer t"},
                )
                assert reply.status_code == 200, reply.text
                assert sorted(reply.json()["delivered"]) == ["f0", "f1"], reply.text
                assert reply.json()["refused"] == {}, reply.text
            assert a.authority.is_held("f0", "operator") and not b.authority.is_held("f0", "operator")
            assert b.authority.is_held("f1", "operator")
        finally:
            await stop_agents(agents)
