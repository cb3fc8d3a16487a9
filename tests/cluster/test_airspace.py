"""Two drones linked to different daemons fly head-on on the simulator: one daemon decides the pair.

drone-1 is linked to daemon a (which holds the airspace lease and leads the mission), drone-2 to
daemon b. a's collision check sees drone-2 through the cluster and its orders for drone-2 pass b's
vehicle authority; then the operator sends drone-2 home through a's API (routed to b) in the
middle of the encounter, and nothing undoes that RTL.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.control.authority import Decision
from gcs.cooperation.intents import HoldIntent, ReleaseIntent
from gcs.cooperation.service import CooperationService
from gcs.core.daemon import Daemon
from protocol.actions import Hold, Land, Takeoff
from protocol.geo import ned_offset_m
from protocol.packets import CloseReason
from protocol.taskfile import AgentPlan, TaskFile
from tests.backbone.helpers import daemon_config, new_key, start_agent, stop_agents
from tests.cluster.simrig import spread_rig, two_daemons
from tests.cooperation.rig import HOME, SPACING_M, assert_pair_separated, head_on_task, wait_for

pytestmark = pytest.mark.slow


async def test_pair_across_daemons_is_kept_apart_and_operator_rtl_stands(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    async with spread_rig(tmp_path, nats_server.url, {"drone-1": "a", "drone-2": "b"}) as r:
        a, b = r.a, r.b
        assert a.cluster is not None and b.cluster is not None
        await wait_for(
            lambda: a.cluster.airspace() == "fleet" and b.cluster.airspace() == "none",  # type: ignore[union-attr]
            10,
            "a to decide the airspace",
        )
        mission_id = await a.missions.submit(head_on_task())

        def via_a(source: str) -> list[Decision]:
            return [
                d
                for d in b.authority.control("drone-2").decisions
                if d.source == source and d.accepted and "(via gcs-a)" in d.reason
            ]

        # a decides for drone-2 (the higher CID yields) and b's authority carries it out.
        await wait_for(lambda: via_a("collision"), 60, "a collision order for drone-2 applied by b")
        assert a.events.history(kind="collision_escape", agent="drone-2") or a.events.history(
            kind="collision_hold", agent="drone-2"
        )

        # The operator sends drone-2 home through a's API in the middle of the encounter.
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{a.http_port}", timeout=20) as api:
            reply = await api.post(
                "/api/v1/cluster/fleet/rtl",
                json={"agents": ["drone-2"], "reason": "test"},
                headers={"Authorization": "Bearer t"},
            )
        assert reply.status_code == 200 and reply.json()["delivered"] == ["drone-2"], reply.text

        await wait_for(lambda: mission_id not in a.missions.active, 90, "mission end")
        progress = a.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed", progress
        assert {row.agent: row.excluded for row in progress.agents} == {"drone-1": False, "drone-2": True}
        await wait_for(lambda: r.landed("drone-1") and r.landed("drone-2"), 60, "both landed")

        # Nothing but the operator commanded drone-2 after its RTL (b's authority, where it is linked).
        decisions = b.authority.control("drone-2").decisions
        rtl = [k for k, d in enumerate(decisions) if d.source == "operator" and d.command == "rtl"]
        assert rtl and decisions[rtl[0]].accepted, decisions
        undone = [
            d
            for d in decisions[rtl[0] + 1 :]
            if d.accepted and d.source != "operator" and d.command in ("hold", "release", "plan")
        ]
        assert not undone, undone
        # One decider: b never ran a collision decision of its own.
        assert not b.events.history(kind="collision_hold") and not b.events.history(kind="collision_escape")

        # Ground truth: never inside a 2 m x 1 m bubble of each other in the air; drone-2 came home.
        assert assert_pair_separated(r.truth) > 2.0
        state = r.fleet.vehicles[1].state  # drone-2 starts (and returns) SPACING_M east of HOME
        n, e = ned_offset_m(HOME[0], HOME[1], state.lat, state.lon)
        assert math.hypot(n, e - SPACING_M) < 5.0, f"drone-2 landed at {n:.1f} m N, {e:.1f} m E"


async def test_standby_decider_adopts_the_collision_holds_in_force(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """a (the decider) holds b's hovering drone; a stops; b takes the airspace, adopts the hold and
    releases it once nothing needs it: a decider's death never leaves a drone held for good."""
    key = new_key()
    a = Daemon(daemon_config(tmp_path / "a", key, cluster=nats_server.url, daemon_id="gcs-a"))
    await a.start()
    a_running = True
    b = Daemon(daemon_config(tmp_path / "b", key, cluster=nats_server.url, daemon_id="gcs-b"))
    await b.start()
    agent = start_agent("y", b.listen_port, key, 0)
    try:
        assert a.cluster is not None and b.cluster is not None
        await wait_for(lambda: a.agents.session("y") is not None, 10, "a to see y")
        task = _hover_task("y")
        await a.missions.submit(task)
        await wait_for(
            lambda: (s := b.agents.session("y")) and s.status and s.status.step == 1, 20, "y hovers"
        )
        coop_a = next(s for s in a.services if isinstance(s, CooperationService))
        await coop_a.apply([HoldIntent("y", "collision", "test: yield")])
        await wait_for(lambda: b.authority.is_held("y", "collision"), 10, "b's authority to hold y")
        assert b.cluster.airspace() == "none"
        await a.stop()
        a_running = False
        await wait_for(lambda: b.cluster.airspace() == "fleet", 10, "b to take the airspace")  # type: ignore[union-attr]
        await wait_for(lambda: not b.authority.is_held("y", "collision"), 15, "b to release the adopted hold")
        session = b.agents.session("y")
        await wait_for(lambda: session is not None and not session.status.paused, 10, "y to resume")  # type: ignore[union-attr]
        assert not a_running
    finally:
        await stop_agents([agent])
        await b.stop()
        if a_running:
            await a.stop()


def _hover_task(name: str, **options: Any) -> TaskFile:
    actions = [Takeoff(step=0, alt=5.0, sync=True), Hold(step=1, seconds=600.0), Land(step=2)]
    plans = [AgentPlan(agent=name, actions=actions)]  # type: ignore[arg-type]
    return TaskFile(name="hover", plans=plans, **options)


async def test_release_reaches_a_drone_whose_link_moved_while_held(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """y is held by a (the decider, leading y's mission) while linked to a, then its link moves to
    b: a re-asserts its hold through b when y joins there; when a declares its own link to y lost,
    y (alive on b) keeps both its place in the mission and a's hold; a's release ends the pause
    through b."""
    key = new_key()
    async with two_daemons(tmp_path, nats_server.url, key) as (a, b):
        agent = start_agent("y", a.listen_port, key, 0, daemons=[f"127.0.0.1:{b.listen_port}"])
        try:
            await wait_for(lambda: b.agents.session("y") is not None, 10, "b to see y")
            mission_id = await a.missions.submit(_hover_task("y", lost_agent_policy="continue"))
            await wait_for(lambda: _status(a, "y") is not None and _status(a, "y").step == 1, 20, "y hovers")
            coop_a = next(s for s in a.services if isinstance(s, CooperationService))
            await coop_a.apply([HoldIntent("y", "collision", "test: yield")])
            await wait_for(lambda: _status(a, "y").paused, 10, "y to pause")
            session = a.agents.sessions["y"]
            assert a._server is not None
            a._server.close()  # a stops taking agents: y's link moves to b
            await session.close(CloseReason.SHUTDOWN, "test: link moves")
            await wait_for(lambda: (s := b.agents.sessions.get("y")) is not None and s.open, 15, "y on b")
            await wait_for(lambda: _status(b, "y") is not None and _status(b, "y").paused, 10, "y still held")
            await wait_for(lambda: b.authority.is_held("y", "collision"), 10, "a's hold re-asserted at b")
            await wait_for(lambda: "y" in a.agents.lost, 10, "a to declare its own link to y lost")
            assert await a.agents.drain_hooks(), "a's lost hooks to run"
            assert a.authority.is_held("y", "collision"), (
                "the decider keeps its hold of a drone alive elsewhere"
            )
            mission = a.missions.active.get(mission_id)
            assert mission is not None and "y" not in mission.excluded, "lost on a only: still flying it"
            await coop_a.apply([ReleaseIntent("y", "collision", "test: clear")])
            await wait_for(lambda: not _status(b, "y").paused, 10, "y to resume through b")
        finally:
            await stop_agents([agent])


def _status(daemon: Daemon, name: str) -> Any:
    session = daemon.agents.session(name)
    return session.status if session else None
