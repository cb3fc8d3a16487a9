"""No two airspace deciders, and no two leaders of a mission, at any instant.

Each daemon records its decisions with their lease term (gcs/cluster/decisions.py): spans of
time.monotonic(), one clock for every process of this host. Two real `gcs serve --cluster`
daemons on a real three-node `nats-server` cluster fly a mission; the airspace decider (and
mission leader) is paused 5 s (SIGSTOP) and resumed, then the NATS node the decider of that moment
is connected to is killed. From both daemons' records: the two decided, each in its turn, and
never at once (docs/cluster.md, "Fencing").
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import httpx
import pytest

from gcs.cluster.decisions import FILE_NAME, overlaps, read_spans
from gcs.cluster.natsrun import NatsCluster
from tests.cluster.served import cluster_info, hold_task, served_cluster, submit, until, watch

pytestmark = pytest.mark.slow

LINKS = {"d0": "gcs-a", "d1": "gcs-b", "d2": "gcs-b"}
REPLICATED = {"FLEETGCS_CLUSTER_REPLICAS": "3"}


async def test_one_decider_across_a_pause_and_a_nats_node_loss(
    tmp_path: Path, nats_cluster: NatsCluster
) -> None:
    async with served_cluster(tmp_path, nats_cluster.urls, LINKS, {}, env=REPLICATED) as (serves, agents):
        a, b = serves["gcs-a"], serves["gcs-b"]
        assert (await cluster_info(a))["airspace"] == "gcs-a"
        task = hold_task({n: [1.0] * 14 for n in LINKS}, sync_timeout_s=60.0, policy="continue", name="one")
        mission_id = await submit(a, task)
        d1 = agents["d1"].agent
        await until(lambda: (d1.queue.waiting_sync or 0) >= 2, 40, "the mission at its second barrier")
        a.pause()
        try:
            await asyncio.sleep(5.0)
        finally:
            a.resume()
        await until(lambda: (d1.queue.waiting_sync or 0) >= 8, 60, "the mission at its eighth barrier")
        info = {s.name: await cluster_info(s) for s in (a, b)}
        decider = info["gcs-b"]["airspace"] or "gcs-b"  # the one deciding now (b since a's pause)
        url = info[decider]["connected_url"]
        next(s for s in nats_cluster.servers if s.url == url).kill()
        async with httpx.AsyncClient(base_url=b.api, timeout=10) as api:
            records = await watch(api, mission_id, 90)
        assert records and records[-1]["state"] == "completed", records[-1:]
    # both daemons stopped: every span is written
    spans = read_spans(tmp_path / "gcs-a" / FILE_NAME) + read_spans(tmp_path / "gcs-b" / FILE_NAME)
    airspace = [s for s in spans if s["kind"] == "airspace"]
    assert {s["daemon"] for s in airspace} == {"gcs-a", "gcs-b"}, "both decided, each in its turn"
    assert all(s["scope"] == "fleet" for s in airspace), [s for s in airspace if s["scope"] != "fleet"]
    assert not overlaps(spans, "airspace"), overlaps(spans, "airspace")[:3]
    led = {s["daemon"] for s in spans if s["kind"] == f"mission:{mission_id}"}
    assert led == {"gcs-a", "gcs-b"}, led
    assert not overlaps(spans, "mission:"), overlaps(spans, "mission:")[:3]
