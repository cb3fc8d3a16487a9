"""Who holds a drone's link, and what the holder says back (docs/cluster.md, "Commands").

Three daemons on one NATS: a drone's link moves from a to b; before and after, every view of every
daemon (GET agents, the stream, the cluster fleet, ``gcs agents``) shows it once, connected, at
the daemon holding its link (tests/cluster/views.py), and a's late messages (sent under the older
epoch of its registry record) change nothing at c. Two daemons: b's operator holds b's drone;
a's mission submit is refused naming the drone and b's order, a command a forwards is refused by
b's vehicle authority and a hears why, and the cluster API answers per drone.
"""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.cluster.node import RemoteSession
from gcs.missions.runner import MissionRejected
from protocol.actions import Hold, Land, Takeoff
from protocol.packets import CloseReason, StatusReport
from protocol.taskfile import AgentPlan, TaskFile
from protocol.wire import encode
from tests.backbone.helpers import new_key, start_agent, stop_agents
from tests.cluster.simrig import cluster_daemons, two_daemons
from tests.cluster.views import every_view_shows
from tests.support.polling import wait_for


def _hover_task(name: str) -> TaskFile:
    actions = [Takeoff(step=0, alt=5.0, sync=True), Hold(step=1, seconds=600.0), Land(step=2)]
    return TaskFile(name="hover", plans=[AgentPlan(agent=name, actions=actions)])  # type: ignore[arg-type]


async def test_the_registry_epoch_decides_the_holder_across_three_daemons(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    key = new_key()
    async with cluster_daemons(tmp_path, nats_server.url, key, ("a", "b", "c")) as (a, b, c):
        assert a.cluster is not None and b.cluster is not None and c.cluster is not None
        agent = start_agent("y", a.listen_port, key, 0, daemons=[f"127.0.0.1:{b.listen_port}"])
        try:
            await wait_for(lambda: c.cluster.holder("y") == "gcs-a", 15, "c to see y on a")  # type: ignore[union-attr]
            first = c.cluster.link_epoch("y")
            assert first is not None and first[1] == "gcs-a" and first[0] > 0
            await wait_for(
                lambda: (s := c.agents.session("y")) is not None and s.status, 10, "y's status at c"
            )
            old_status = c.agents.session("y").status  # type: ignore[union-attr]
            assert isinstance(old_status, StatusReport)
            await every_view_shows((a, b, c), {"y": "gcs-a"}, "before the move")

            assert a._server is not None
            a._server.close()  # a stops taking agents: y's link moves to b
            await a.agents.sessions["y"].close(CloseReason.SHUTDOWN, "test: link moves")
            await wait_for(lambda: (s := b.agents.sessions.get("y")) is not None and s.open, 15, "y on b")
            for daemon in (a, b, c):
                await wait_for(
                    lambda d=daemon: d.cluster.holder("y") == "gcs-b", 10, "every daemon: b holds y"
                )  # type: ignore[misc]
            moved = c.cluster.link_epoch("y")
            assert moved is not None and moved[0] > first[0]
            # Shown once, at b, by every view of every daemon: a's closed session is not shown.
            await every_view_shows((a, b, c), {"y": "gcs-b"}, "after the move")

            # a's late news about y (a status and a "lost", under the old epoch) changes nothing at c.
            nc = a.cluster.state.nc
            assert nc is not None
            old = {"daemon": "gcs-a", "cid": "1", "rev": str(first[0]), "level": "0"}
            dropped = c.cluster.stale_dropped
            await nc.publish("fleet.status.y", encode(old_status, 0), headers=old)
            await nc.publish("fleet.up.y", b"", headers={**old, "kind": "lost"})
            await nc.flush()
            await wait_for(lambda: c.cluster.stale_dropped >= dropped + 2, 10, "c to drop a's stale messages")  # type: ignore[union-attr]
            remote = c.agents.remote.get("y")
            assert isinstance(remote, RemoteSession) and remote.open and remote.daemon == "gcs-b"
            assert c.cluster.holder("y") == "gcs-b"
            rows = {row["identity"]: row for row in c.cluster.fleet()}
            assert rows["y"]["daemon"] == "gcs-b" and rows["y"]["connected"]
        finally:
            await stop_agents([agent])


async def test_the_holders_refusals_reach_the_sender(tmp_path: Path, nats_server: NatsServer) -> None:
    key = new_key()
    async with two_daemons(tmp_path, nats_server.url, key) as (a, b):
        assert a.cluster is not None and b.cluster is not None
        agent = start_agent("y", b.listen_port, key, 0)
        stopped = False
        try:
            await wait_for(lambda: a.cluster.holder("y") == "gcs-b", 15, "a to see y on b")  # type: ignore[union-attr]
            assert a.cluster.remote_blocker("y") is None
            b.authority.hold("y", "operator", "test: b's operator")
            await wait_for(lambda: a.cluster.remote_blocker("y") is not None, 10, "a to see b's hold")  # type: ignore[union-attr]

            # A mission submitted on a is refused like a local refusal, naming the drone and b's order.
            refused = r"agent y is under operator hold \(test: b's operator\) control at gcs-b"
            with pytest.raises(MissionRejected, match=refused):
                await a.missions.submit(_hover_task("y"))
            assert not a.missions.active

            # A collision hold a forwards is refused by b's vehicle authority; a hears why.
            a.authority.hold("y", "collision", "test: yield")
            await wait_for(lambda: a.events.history(kind="command_refused", agent="y"), 10, "a to hear")
            refusal = a.cluster.refusals[-1]
            assert refusal["daemon"] == "gcs-b" and refusal["command"] == "collision pause", refusal
            assert "outranked by operator hold" in refusal["reason"], refusal
            assert a.cluster.remote_level("y") >= 60  # the airspace decider sees it outranked
            assert not b.authority.is_held("y", "collision")
            # a's own record takes the refused hold back: it says what y was actually told.
            assert not a.authority.is_held("y", "collision")
            last = a.authority.control("y").decisions[-1]
            assert not last.accepted and last.command == "hold" and "refused by gcs-b" in last.detail, last

            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{a.http_port}", timeout=20) as api:
                auth = {"Authorization": "Bearer t"}
                reply = await api.post(
                    "/api/v1/cluster/fleet/rtl", json={"agents": ["y", "ghost"]}, headers=auth
                )
                assert reply.status_code == 200, reply.text
                body = reply.json()
                assert body["delivered"] == ["y"] and list(body["refused"]) == ["ghost"], body
                assert "no daemon" in body["refused"]["ghost"]

                await stop_agents([agent])  # y's link ends; the registry still names b
                stopped = True
                await wait_for(
                    lambda: "y" not in b.agents.sessions or not b.agents.sessions["y"].open, 10, "b loses y"
                )
                reply = await api.post("/api/v1/cluster/fleet/hold", json={"agents": ["y"]}, headers=auth)
                assert reply.status_code == 200, reply.text
                body = reply.json()
                assert body["delivered"] == [] and "not linked to gcs-b" in body["refused"]["y"], body
        finally:
            if not stopped:
                await stop_agents([agent])
