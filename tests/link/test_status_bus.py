"""The status bus (gcs/link/status_bus.py): the synchronous observers run inside the status tick in
the order the bus declares, before any consumer sees the report; a subscription's handle carries
its queue's limit, and a scope's subscriptions all end when it closes."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcs.link.agents_table import StatusTable
from gcs.link.status_bus import StatusBus
from gcs.link.status_limits import UNBOUNDED
from gcs.link.status_tick import StatusTicker
from gcs.observe.events import EventBus
from gcs.storage.store import Store
from protocol.packets import Resume, StatusReport
from tests.support.status_reports import report_at
from tests.support.status_table import stored_like_ingest


class Owner:
    """A table row's owner as the tick reads it: the served connection, whose session is the agent."""

    def __init__(self, identity: str) -> None:
        self.identity = identity
        self.session = self
        self.open = True


async def test_observers_run_in_the_declared_order_inside_the_tick_before_any_consumer(
    tmp_path: Path,
) -> None:
    bus = StatusBus(observers=("authority", "home"))
    seen: list[tuple[str, str]] = []

    def home(session: Owner, report: StatusReport) -> None:
        seen.append(("home", session.identity))

    def authority(session: Owner, report: StatusReport) -> None:
        seen.append(("authority", session.identity))
        if session.identity == "a-0":
            raise RuntimeError("a failing observer costs its own call only")

    bus.observe("home", home)  # registered first, runs second: the declared order decides
    bus.observe("authority", authority)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="not a declared observer"):
        bus.observe("cooperation", home)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="registered already"):
        bus.observe("home", home)  # type: ignore[arg-type]

    class Service:
        async def on_changes(self, session: Owner, report: StatusReport) -> None:
            seen.append(("consumer", session.identity))

    service = Service()
    bus.subscribe("changes", service.on_changes)
    store = Store(tmp_path / "bus.db")
    try:
        table = StatusTable(limits=UNBOUNDED)
        ticker = StatusTicker(table, bus, {}, EventBus(store))
        for name in ("a-0", "a-1"):
            stored_like_ingest(table, table.attach(Owner(name)), report_at(1.0, armed=True))
        assert ticker.tick() == 2
        # Inside the tick, synchronously: every observer in order for each report, no consumer yet.
        assert seen == [("authority", "a-0"), ("home", "a-0"), ("authority", "a-1"), ("home", "a-1")]
        assert await bus.drain(10.0)
        assert seen[4:] == [("consumer", "a-0"), ("consumer", "a-1")]
        # A report handed over at once (failsafe, failure, replayed) meets the observers first too.
        urgent = report_at(2.0, armed=True)
        bus.hand_over([(Owner("a-2"), urgent)])  # type: ignore[list-item]
        assert seen[6:8] == [("authority", "a-2"), ("home", "a-2")]
        assert await bus.drain(10.0)
        assert seen[8:] == [("consumer", "a-2")]
    finally:
        await bus.close()
        store.close()


async def test_subscriptions_carry_their_limit_and_end_together_with_their_scope() -> None:
    bus = StatusBus()
    got: list[tuple[str, str]] = []

    class Service:
        async def on_join(self, session: str, resume: Resume | None) -> None:
            got.append(("join", session))

        async def on_lost(self, identity: str) -> None:
            got.append(("lost", identity))

    service = Service()
    try:
        with bus.subscriptions() as scope:
            join = scope.subscribe("join", service.on_join, capacity=3)
            lost = scope.subscribe("lost", service.on_lost)
            assert join.active and lost.active and join.capacity == 3 and lost.capacity is None
            for k in range(5):  # published at once, before the consumer runs: 5 queued, limit 3
                bus.publish("join", f"a-{k}", f"a-{k}", None)
            bus.publish("lost", "a-0", "a-0")
            assert await bus.drain(10.0)
            assert got == [*(("join", f"a-{k}") for k in range(5)), ("lost", "a-0")]  # joins never dropped
            (stats,) = bus.stats()  # one owner, one consumer: the handle's limit is its queue's
            assert stats.name == "Service" and stats.overflow == 3 and stats.dropped == 0
        assert not join.active and not lost.active
        assert not bus.on_join and not bus.on_lost
        bus.publish("join", "a-9", "a-9", None)
        bus.publish("lost", "a-9", "a-9")
        assert await bus.drain(10.0)
        assert len(got) == 6  # nothing reaches a closed scope's hooks
        await bus.prune()
        assert bus.stats() == []  # its consumer is gone with them
    finally:
        await bus.close()
