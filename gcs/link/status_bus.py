"""The status bus: the one place the link's agent events (status reports, joins, syncs, losts) enter.

Why one object: the hook lists services register on, the consumers that run them
(gcs/link/dispatch.py, one bounded queue and task per hook owner) and the barrier's direct path
used to be fields of the agent manager, spread over the frame handling, the status tick and the
liveness watch, and the order of the daemon's own observers rested on ``insert(0, ...)``. Here:

* **Synchronous observers** (:meth:`StatusBus.observe`) see every changed report inside the
  status tick (and every report handed over at once: failsafe, failure, replayed), before any
  consumer is queued, in the order :data:`OBSERVERS` declares, whatever order they registered in.
* **Asynchronous consumers** subscribe with handles (:meth:`StatusBus.subscriptions`) that carry
  their queue's limit, and a service's handles end together when its scope closes (as nats.py's
  subscriptions do). The plain hook lists stay for the code that appends to them.

Three kinds carry status reports: ``tick`` (each status tick's rows as columns, a
``StatusTick``), ``changes`` (the reports whose state changed) and ``status`` (every report,
built only if such a hook exists). ``join``, ``sync`` and ``lost`` are never dropped. What is
still to come (the cluster's remote reports entering here) is in docs/architecture.md,
"The agent link and the status bus".
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Any

from gcs.link.agents_table import StatusTick
from gcs.link.dispatch import ConsumerStats, HookDispatcher, HookKind, HookList
from gcs.link.session import (
    AgentSession,
    FinishedHook,
    JoinHook,
    LostHook,
    StatusHook,
    SyncHook,
    TickHook,
)
from protocol.packets import StatusReport

log = logging.getLogger("gcs.link.status_bus")

OBSERVERS: tuple[str, ...] = ("authority", "home")
"""The synchronous observers of a report, in the order they run: the vehicle authority first (it
knows of a failsafe, a pilot or a landing before any service decides on that report), then the
home latch (a drone that joined before its autopilot had a home gets the place it stands on)."""

Observer = Callable[[AgentSession, StatusReport], None]


class Subscription:
    """One hook on the bus: its kind, its owner's queue limit, and the way off (:meth:`unsubscribe`)."""

    __slots__ = ("_hooks", "capacity", "hook", "kind")

    def __init__(
        self, kind: HookKind, hook: Callable[..., Any], capacity: int | None, hooks: HookList[Any]
    ) -> None:
        self.kind, self.hook, self.capacity = kind, hook, capacity
        self._hooks = hooks

    @property
    def active(self) -> bool:
        return self.hook in self._hooks

    def unsubscribe(self) -> None:
        """Off the bus: events still queued for it are not delivered (gcs/link/dispatch.py)."""
        with contextlib.suppress(ValueError):
            self._hooks.remove(self.hook)


class Subscriptions:
    """One owner's subscriptions, ended together: ``close()`` (a service's ``stop``) or a ``with`` block."""

    def __init__(self, bus: StatusBus) -> None:
        self._bus = bus
        self.handles: list[Subscription] = []

    def subscribe(
        self, kind: HookKind, hook: Callable[..., Any], capacity: int | None = None
    ) -> Subscription:
        """``hook`` on every event of ``kind``; ``capacity`` bounds its owner's queue (events, a
        batch counting its reports; the dispatcher's default without one)."""
        handle = self._bus.subscribe(kind, hook, capacity)
        self.handles.append(handle)
        return handle

    def close(self) -> None:
        """Every handle of this scope unsubscribed (newest first)."""
        handles, self.handles = self.handles, []
        for handle in reversed(handles):
            handle.unsubscribe()

    def __enter__(self) -> Subscriptions:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class StatusBus:
    """The hook lists of every kind, their consumers, and the barrier's direct path."""

    def __init__(self, observers: Sequence[str] = OBSERVERS) -> None:
        self._order = tuple(observers)  # the declared order of the synchronous observers
        self._observers: dict[str, Observer] = {}
        self._observing: tuple[Observer, ...] = ()  # registered ones, in the declared order
        # Plain lists to the services that append/remove hooks; HookList only counts changes.
        self.on_join: HookList[JoinHook] = HookList()
        self.on_status: HookList[StatusHook] = HookList()  # every report (built for them: costs ~6 us each)
        self.on_status_changes: HookList[StatusHook] = HookList()  # reports whose state changed (STATE_BYTES)
        self.on_status_tick: HookList[TickHook] = HookList()  # each tick's reports as columns (StatusTick)
        self.on_sync: HookList[SyncHook] = HookList()
        self.on_lost: HookList[LostHook] = HookList()
        # The barrier's direct path (gcs/missions/runner.py): a 'finished' is handed to it from the frame's
        # buffer_updated, before the on_sync hooks get it, unless its owner's consumer still holds
        # a join, sync or lost of that agent (gcs/link/ingest.py).
        self.on_finished: FinishedHook | None = None
        self._lists: dict[HookKind, HookList[Any]] = {
            "join": self.on_join,
            "status": self.on_status,
            "changes": self.on_status_changes,
            "tick": self.on_status_tick,
            "sync": self.on_sync,
            "lost": self.on_lost,
        }
        self._hooks = HookDispatcher(self._lists)
        self.closed = False  # after close(): a tick still scheduled must not start new consumers

    # --- synchronous observers (in the declared order, inside the tick) -------------------------

    def observe(self, name: str, observer: Observer) -> None:
        """Run ``observer(session, report)`` on every changed or handed-over report, synchronously,
        at its place in the declared order (``observers``); an undeclared name is refused."""
        if name not in self._order:
            raise ValueError(f"{name!r} is not a declared observer {self._order}")
        if name in self._observers:
            raise ValueError(f"observer {name!r} is registered already")
        self._observers[name] = observer
        self._observing = tuple(self._observers[n] for n in self._order if n in self._observers)

    @property
    def observing(self) -> bool:
        return bool(self._observing)

    def observed(self, pairs: list[tuple[AgentSession, StatusReport]]) -> None:
        """Each report through every observer in the declared order; a failing observer costs its
        own call (logged), never the tick or the observers after it."""
        for session, report in pairs:
            for observer in self._observing:
                try:
                    observer(session, report)
                except Exception:
                    log.exception("status observer failed for %s", session.identity)

    # --- asynchronous consumers -----------------------------------------------------------------

    def subscribe(
        self, kind: HookKind, hook: Callable[..., Any], capacity: int | None = None
    ) -> Subscription:
        """``hook`` on every event of ``kind``, run by its owner's consumer; the handle unsubscribes it."""
        if capacity is not None:
            self._hooks.limit(hook, capacity)
        hooks = self._lists[kind]
        hooks.append(hook)
        return Subscription(kind, hook, capacity, hooks)

    def subscriptions(self) -> Subscriptions:
        """A scope of subscriptions that end together (a service's ``stop``)."""
        return Subscriptions(self)

    # --- publishing (the link's parts) ----------------------------------------------------------

    def publish(self, kind: HookKind, agent: str, *args: object) -> None:
        """One agent event to every hook of ``kind`` (the caller has flushed the agent's waiting report)."""
        if not self.closed:
            self._hooks.publish(kind, agent, *args)

    def publish_batch(
        self, pairs: list[tuple[AgentSession, StatusReport]], kind: HookKind = "status"
    ) -> None:
        """``(session, report)`` pairs to every hook of ``kind`` (``status`` or ``changes``)."""
        if not self.closed:
            self._hooks.publish_batch(pairs, kind)

    def publish_tick(self, tick: StatusTick, size: int) -> None:
        """One slice of a status tick to every tick hook."""
        if not self.closed:
            self._hooks.publish_tick(tick, size)

    def hand_over(self, pairs: list[tuple[AgentSession, StatusReport]]) -> None:
        """Reports handed over outside the tick (rare packets): to the observers, then to every kind
        of status hook."""
        if not self.closed:
            if self._observing:
                self.observed(pairs)
            self._hooks.publish_batch(pairs)
            self._hooks.publish_batch(pairs, "changes")
            if self._hooks.has("tick"):
                self._hooks.publish_tick(StatusTick.of_reports(pairs, time.time()), len(pairs))

    def has(self, kind: HookKind) -> bool:
        """Whether any hook of ``kind`` is registered (the tick builds reports only for them)."""
        return self._hooks.has(kind)

    def may_finish_now(self, agent: str) -> FinishedHook | None:
        """The barrier's direct path, if it may take ``agent``'s arrival now: its owner's consumer
        holds no join, sync or lost of the agent that the arrival would overtake."""
        direct = self.on_finished
        if direct is None or self.closed or self._hooks.queued_for(direct, agent):
            return None
        return direct

    # --- the consumers --------------------------------------------------------------------------

    async def drain(self, timeout: float = 10.0) -> bool:
        """Wait until every consumer has run everything queued; False after ``timeout``."""
        return await self._hooks.drain(timeout)

    def stats(self) -> list[ConsumerStats]:
        """Per consumer: queued, delivered, coalesced, dropped, overflow, failed (for metrics)."""
        return self._hooks.stats()

    async def prune(self) -> None:
        """Stop idle consumers whose owner has no hook registered any more."""
        await self._hooks.prune()

    async def close(self) -> None:
        """No more events; every consumer stopped."""
        self.closed = True
        await self._hooks.close()


__all__ = ["OBSERVERS", "Observer", "StatusBus", "Subscription", "Subscriptions"]
