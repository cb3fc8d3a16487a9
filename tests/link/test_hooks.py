"""Hooks run off the read path: slow or failing hooks hurt only their own consumer."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from gcs.link.dispatch import HookDispatcher, HookKind, HookList
from gcs.link.session import AgentSession
from gcs.observe.metrics import DaemonMetrics
from protocol.packets import Resume, StatusReport
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.support.polling import wait_for


class SlowJoins:
    """A service whose join hook takes longer than the whole handshake budget."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.seen: list[tuple[str, bool]] = []

    async def on_join(self, session: AgentSession, resume: Resume | None) -> None:
        await asyncio.sleep(self.seconds)
        self.seen.append((session.identity, resume is not None))


async def test_slow_join_hook_does_not_break_joining_or_rejoining(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, handshake_timeout_s=1.0) as daemon:
        slow = SlowJoins(seconds=2.5)  # longer than the 1 s handshake budget
        daemon.agents.on_join.append(slow.on_join)
        first = start_agent("rejoiner", daemon.listen_port, key)
        other = start_agent("bystander", daemon.listen_port, key, index=1)
        second = None
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 5, "both agents join")
            await daemon.missions.submit(survey_mission(["rejoiner"], sync_legs=4))
            await wait_for(lambda: first.agent.queue.completed_step >= 0, 20, "takeoff done")
            await first.kill()  # the companion restarts: it comes back without its queue
            second = start_agent("rejoiner", daemon.listen_port, key)
            # The mission runner's own join hook re-sends the queue while the slow hook still sleeps.
            await wait_for(
                lambda: daemon.events.history(kind="mission_resent", agent="rejoiner"), 2.0, "re-send"
            )
            assert len(slow.seen) < 3, "the test needs the slow hook to still be busy here"
            session = daemon.agents.session("rejoiner")
            assert session is not None
            before = session.status_count
            await asyncio.sleep(3.0)  # well past the handshake budget and the slow hook's calls
            assert session.open and daemon.agents.session("rejoiner") is session, "no reconnect loop"
            assert session.status_count > before + 10
            joins = [e.agent for e in daemon.events.history(kind="agent_joined")]
            assert joins.count("rejoiner") == 2 and joins.count("bystander") == 1, joins
            assert not daemon.events.history(kind="handshake_timeout")
            assert await daemon.agents.drain_hooks(timeout=10.0)
            assert [name for name, _ in slow.seen].count("rejoiner") == 2
        finally:
            await stop_agents([a for a in (first, second, other) if a is not None])


async def test_slow_and_failing_status_hooks_do_not_stop_other_agents(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        stuck = asyncio.Event()
        slow_calls: list[str] = []

        async def slow_status(session: AgentSession, status: StatusReport) -> None:
            slow_calls.append(session.identity)
            await stuck.wait()  # never returns during the test: this consumer is stuck

        async def failing_status(session: AgentSession, status: StatusReport) -> None:
            raise RuntimeError("a buggy extension")

        daemon.agents.on_status.append(slow_status)
        daemon.agents.on_status.append(failing_status)
        names = ["s-1", "s-2", "s-3"]
        agents = [start_agent(n, daemon.listen_port, key, index=i) for i, n in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 3, 5, "three agents")
            await asyncio.sleep(1.0)
            counts = {n: daemon.agents.session(n).status_count for n in names}  # type: ignore[union-attr]
            logged = daemon.telemetry.history("s-2", limit=100_000)
            await asyncio.sleep(1.5)
            for name in names:
                session = daemon.agents.session(name)
                assert session is not None and session.status_count > counts[name] + 8, name
            # The telemetry recorder (another consumer) kept logging every agent.
            assert len(daemon.telemetry.history("s-2", limit=100_000)) > len(logged) + 8
            assert len(slow_calls) == 1, "the slow hook is still in its first call"
            stats = {s.name: s for s in daemon.agents.hook_stats()}
            assert stats["slow_status"].queued > 20  # everything since waits for it, in order
            assert stats["failing_status"].failed > 20 and stats["failing_status"].queued < 10
            assert all(s.failed == 0 for n, s in stats.items() if n != "failing_status")
            scrape = DaemonMetrics(daemon).render().decode()
            assert 'fleetgcs_hook_events_total{consumer="failing_status",outcome="failed"}' in scrape
            assert 'fleetgcs_hook_queue_depth{consumer="slow_status"}' in scrape
        finally:
            stuck.set()
            await stop_agents(agents)


async def test_consumer_coalesces_statuses_but_never_drops_syncs() -> None:
    """Pure dispatcher: a full queue keeps the newest status per agent and every other event."""
    seen: list[tuple[str, str, int]] = []
    gate = asyncio.Event()

    class Service:
        async def on_status(self, agent: str, n: int) -> None:
            await gate.wait()
            seen.append(("status", agent, n))

        async def on_sync(self, agent: str, n: int) -> None:
            seen.append(("sync", agent, n))

    service = Service()
    hooks: dict[HookKind, HookList[object]] = {
        "join": HookList(),
        "status": HookList([service.on_status]),
        "sync": HookList([service.on_sync]),
        "lost": HookList(),
    }
    dispatcher = HookDispatcher(hooks, capacity=4)  # type: ignore[arg-type]
    dispatcher.publish("status", "a", "a", 0)
    await asyncio.sleep(0.01)  # the consumer takes status 0 and blocks in it
    for n in range(1, 4):
        dispatcher.publish("status", "a", "a", n)
    dispatcher.publish("status", "b", "b", 1)  # queue full now: a1 a2 a3 b1
    dispatcher.publish("status", "a", "a", 4)  # a3 is a's latest: coalesced into it
    dispatcher.publish("sync", "a", "a", 5)  # never dropped
    dispatcher.publish("status", "a", "a", 6)  # a's latest is the sync: the oldest status goes
    (stats,) = dispatcher.stats()
    assert (stats.coalesced, stats.dropped, stats.overflow) == (1, 1, 1)
    gate.set()
    assert await dispatcher.drain(timeout=5.0)
    assert seen == [
        ("status", "a", 0),
        ("status", "a", 2),
        ("status", "a", 4),
        ("status", "b", 1),
        ("sync", "a", 5),
        ("status", "a", 6),
    ]
    await dispatcher.close()


async def test_drain_hooks_waits_for_follow_up_work() -> None:
    done: list[float] = []

    async def hook(_: str) -> None:
        await asyncio.sleep(0.2)
        done.append(time.monotonic())

    hooks: dict[HookKind, HookList[object]] = {
        "join": HookList(),
        "status": HookList(),
        "sync": HookList(),
        "lost": HookList([hook]),
    }
    dispatcher = HookDispatcher(hooks)  # type: ignore[arg-type]
    for name in ("a", "b", "c"):
        dispatcher.publish("lost", name, name)
    assert not await dispatcher.drain(timeout=0.1)
    assert await dispatcher.drain(timeout=5.0)
    assert len(done) == 3
    await dispatcher.close()


async def test_a_removed_hook_gets_no_queued_events() -> None:
    """A service that stops (removes its hooks) is not called for events queued before."""
    gate = asyncio.Event()
    calls: list[int] = []

    async def first(n: int) -> None:
        await gate.wait()
        calls.append(n)

    async def second(n: int) -> None:
        calls.append(-n)

    lost: HookList[object] = HookList([first, second])
    hooks: dict[HookKind, HookList[object]] = {
        "join": HookList(),
        "status": HookList(),
        "sync": HookList(),
        "lost": lost,
    }
    dispatcher = HookDispatcher(hooks)  # type: ignore[arg-type]
    for n in (1, 2, 3):
        dispatcher.publish("lost", "a", n)
    await asyncio.sleep(0.01)  # first is inside its call for 1; second has run all three
    lost.remove(first)
    gate.set()
    assert await dispatcher.drain(timeout=5.0)
    assert calls == [-1, -2, -3, 1]  # 2 and 3 were queued for first after it was removed
    await dispatcher.close()
