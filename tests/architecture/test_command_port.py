"""One command port by construction (issue 24): nothing but the authority's command port reaches an
agent's link with an order, a geofence, parameters or a barrier release.

* a service's context and an extension have no method that sends to an agent (introspection, and
  an extension that tries fails with a clear error);
* a geofence an extension sends is the fence the daemon's emergency monitor checks;
* a cluster-forwarded ``append`` is arbitrated like any order: refused while a higher source holds
  the drone (once on one daemon through the port, once across two daemons on NATS).
"""

from __future__ import annotations

import asyncio
import dataclasses
from pathlib import Path
from typing import Any

import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.core.context import AgentRecord, AgentsView, ServiceContext
from gcs.extensions import Extension, ExtensionError
from gcs.link.agents import AgentManager
from protocol.actions import Hold
from protocol.packets import FenceCircle, Geofence, PerformActions, SetParameters, SyncSignal
from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent, stop_agents
from tests.cluster.simrig import two_daemons
from tests.support.polling import wait_for

SENDERS = {"post", "send", "burst", "write_now", "outbox", "send_all_now"}
"""Names through which a part could put a frame on an agent's link."""

FENCE = Geofence(circle=FenceCircle(lat=HOME[0], lon=HOME[1], radius_m=80.0))


def _append(source: Any = "mission") -> PerformActions:
    return PerformActions(
        mission_id="forwarded", mode="append", actions=[Hold(step=0, seconds=600.0)], source=source
    )


class Intruder(Extension):
    """An extension that tries every way around the command port, and the one way through it."""

    name = "intruder"

    def __init__(self, options: dict[str, Any] | None = None) -> None:
        super().__init__(options)
        self.tries: dict[str, str] = {}

    async def attempt(self, agent: str) -> bool:
        ctx = self.context
        assert ctx is not None
        for name in ("post", "send", "burst"):
            try:
                getattr(ctx.agents, name)(agent, SyncSignal(mission_id="m", step=0, kind="release"))
            except AttributeError as exc:
                self.tries[name] = str(exc)
        for label, body in (
            ("order", _append()),
            ("release", SyncSignal(mission_id="m", step=0, kind="release")),
        ):
            try:
                await self.send(agent, body)
            except ExtensionError as exc:
                self.tries[label] = str(exc)
        return await self.send(agent, SetParameters(geofence=FENCE))


def create_intruder(options: dict[str, Any]) -> Intruder:
    return Intruder(options)


def _public(obj: object) -> set[str]:
    return {name for name in dir(obj) if not name.startswith("_")}


def test_a_service_context_has_no_send_side() -> None:
    """The context's agents are a read-only view; no field of the context is the agent manager."""
    assert not _public(AgentsView) & SENDERS
    assert not _public(AgentRecord) & SENDERS  # what ctx.agents.session() is typed as
    assert {"session", "connected", "on_status", "on_join", "on_lost"} <= _public(AgentsView)
    fields = {f.name: f.type for f in dataclasses.fields(ServiceContext)}
    assert fields["agents"] == "AgentsView"
    assert "AgentManager" not in fields.values()
    assert not _public(ServiceContext) & SENDERS
    assert not _public(Extension) & (SENDERS - {"send"})  # Extension.send goes through the port


async def test_an_extension_cannot_go_around_the_port_and_its_fence_is_the_daemons(tmp_path: Path) -> None:
    key = new_key()
    extension = "tests.architecture.test_command_port:create_intruder"
    async with running_daemon(tmp_path, key, extensions=[extension]) as daemon:
        agents = [start_agent("d1", daemon.listen_port, key, 0)]
        try:
            await wait_for(lambda: daemon.agents.session("d1") is not None, 10, "d1 to join")
            intruder = next(s for s in daemon.services if isinstance(s, Intruder))
            assert intruder.context is not None
            ctx = intruder.context
            assert isinstance(ctx.agents, AgentsView) and not isinstance(ctx.agents, AgentManager)
            for value in (getattr(ctx, f.name) for f in dataclasses.fields(ctx)):
                assert not isinstance(value, AgentManager)
                if value is not ctx.commands:  # the port itself is the one way through
                    assert not _public(value) & {"post", "burst", "write_now"}, type(value)
            assert daemon.geofences == {}

            assert await intruder.attempt("d1")
            assert set(intruder.tries) == {"post", "send", "burst", "order", "release"}, intruder.tries
            assert "Extension.command" in intruder.tries["order"]
            assert "SyncSignal" in intruder.tries["release"]
            # the fence sent by the extension is what the emergency monitor checks
            assert daemon.geofences == {"d1": FENCE}
            assert ctx.geofences["d1"] == FENCE
            agent = agents[0].agent
            await wait_for(lambda: agent.monitor.geofence == FENCE, 5, "d1 to install the fence")
        finally:
            await stop_agents(agents)


async def test_a_forwarded_append_is_arbitrated_by_the_authority(tmp_path: Path) -> None:
    """The holder's side of a cluster-forwarded ``append``: through the port, refused under an
    operator hold (nothing reaches the agent's queue), accepted once the hold is released."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent("d1", daemon.listen_port, key, 0)]
        try:
            await wait_for(lambda: daemon.agents.session("d1") is not None, 10, "d1 to join")
            queue = agents[0].agent.queue
            assert daemon.authority.hold("d1", "operator", "test: operator holds")[0]
            await wait_for(lambda: queue.paused, 5, "d1 paused")
            ok, why = daemon.commands.forwarded("d1", _append("extension"), "gcs-x")
            assert not ok and "outranked by operator hold" in why, why
            last = daemon.authority.control("d1").decisions[-1]
            assert (last.command, last.accepted, last.source) == ("append", False, "extension"), last
            await asyncio.sleep(0.5)  # bounded: what was refused must not arrive late either
            assert queue.depth == 0

            assert daemon.authority.release("d1", "operator", "test: released")[0]
            await wait_for(lambda: not queue.paused, 5, "d1 resumed")
            ok, why = daemon.commands.forwarded("d1", _append("extension"), "gcs-x")
            assert ok, why
            await wait_for(lambda: queue.busy or queue.depth > 0, 5, "the append to reach d1")
        finally:
            await stop_agents(agents)


async def test_a_cluster_append_is_refused_where_the_drone_is_linked(
    tmp_path: Path, nats_server: NatsServer
) -> None:
    """a forwards an ``append`` to y, linked to b and held there by b's operator: b's vehicle
    authority refuses it and a hears why (before the port, b posted it to y regardless)."""
    key = new_key()
    async with two_daemons(tmp_path, nats_server.url, key) as (a, b):
        assert a.cluster is not None and b.cluster is not None
        agent = start_agent("y", b.listen_port, key, 0)
        try:
            await wait_for(lambda: a.cluster.holder("y") == "gcs-b", 15, "a to see y on b")  # type: ignore[union-attr]
            assert b.authority.hold("y", "operator", "test: b's operator")[0]
            await wait_for(lambda: agent.agent.queue.paused, 5, "y paused")
            a.cluster.forward("y", _append("extension"), False)
            await wait_for(lambda: a.cluster.refusals, 10, "a to hear b's answer")  # type: ignore[union-attr]
            refusal = a.cluster.refusals[-1]
            assert refusal["command"] == "extension append" and refusal["daemon"] == "gcs-b", refusal
            assert "outranked by operator hold" in refusal["reason"], refusal
            last = b.authority.control("y").decisions[-1]
            assert (last.command, last.accepted) == ("append", False), last
            assert agent.agent.queue.depth == 0
        finally:
            await stop_agents([agent])


@pytest.mark.parametrize("body", [SyncSignal(mission_id="m", step=0, kind="finished")])
def test_the_port_refuses_what_no_daemon_forwards(body: SyncSignal) -> None:
    """Only orders, type-3 bodies and releases are forwarded; anything else is refused by name."""
    from gcs.control.authority import VehicleAuthority
    from gcs.control.command_port import CommandPort

    class Closed:
        def post(self, identity: str, body: object, *, urgent: bool | None = None) -> bool:
            raise AssertionError("nothing may be sent")

        def burst(self, identities: list[str], body: object) -> int:
            raise AssertionError("nothing may be sent")

    port = CommandPort(Closed(), VehicleAuthority(Closed(), lambda *_: None))
    ok, why = port.forwarded("d1", body, "gcs-x")
    assert not ok and "SyncSignal is not forwarded" in why
