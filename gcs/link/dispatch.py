"""Hook dispatch: the frame loop hands reports off; one consumer task per hook owner runs the hooks.

Why: a hook awaited on the read path lets one slow service stall every agent's link (and a slow
``on_join`` inside the handshake budget put agents into a reconnect loop). Here the frame loop
and the liveness watch only *publish* (no await); every registered hook is served by the
consumer of its owner (the object a bound-method hook belongs to, or the function itself), so
the hooks of one service (say ``MissionRunner._on_join`` / ``_on_status`` / ``_on_sync`` /
``_on_lost``) see one agent's events in the order they happened, as they did when they ran in
the frame loop, and a slow or failing service delays only itself.

Status reports arrive in batches (``publish_batch``: the agent manager hands over everything the
frame loops received in one event-loop iteration at once), so a report costs each consumer one
list entry, not one queue item and one task switch. A consumer runs its queue in steps of
``STEP_BUDGET_S`` and then yields, so with thousands of connections it still gets its share of
the loop and a backlog never stalls it.

Each consumer's queue is bounded (``capacity`` events, a batch counting its reports). When it is
full, a status report is coalesced with the same agent's status still waiting (a status carries
full state), or else the oldest waiting status (a whole batch, for batches) is dropped; joins,
syncs and losts are never dropped (their rate is bound by the agent count and the per-agent
frame limit), they are counted as ``overflow`` instead. Everything is counted per consumer
(``stats()``, exported by gcs/observe/metrics.py), including the loop time its hooks took (``busy_s``).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, Self, SupportsIndex, TypeVar

log = logging.getLogger("gcs.link.dispatch")

HookKind = Literal["join", "status", "changes", "tick", "sync", "lost"]
_BATCHED: frozenset[str] = frozenset(("status", "changes", "tick"))  # may be dropped when a queue is full
Hook = Callable[..., Awaitable[None]]
StatusBatch = list[tuple[Any, Any]]  # (session, report) pairs, in arrival order

DEFAULT_CAPACITY = 10_000
STEP_BUDGET_S = 0.005
"""A consumer with a backlog runs hooks for this long before letting the loop go round. The
frames are read in protocol callbacks (``buffer_updated``) (no read task per connection to compete with),
so a short slice keeps every socket read close to its arrival while several consumers work
through a status batch of the whole fleet."""
SLOW_HOOK_S = 0.5  # a hook call longer than this is logged (once per consumer per minute)


_H = TypeVar("_H")


class HookList(list[_H]):
    """A plain list of hooks (services append and remove as before) that counts its changes.

    The dispatcher caches which consumer serves each hook and checks "still registered?" by
    comparing versions instead of searching the list for every event.
    """

    version: int = 0

    def _changed(self) -> None:
        self.version += 1

    def append(self, hook: _H) -> None:
        super().append(hook)
        self._changed()

    def extend(self, hooks: Iterable[_H]) -> None:
        super().extend(hooks)
        self._changed()

    def insert(self, index: SupportsIndex, hook: _H) -> None:
        super().insert(index, hook)
        self._changed()

    def remove(self, hook: _H) -> None:
        super().remove(hook)
        self._changed()

    def pop(self, index: SupportsIndex = -1) -> _H:
        hook = super().pop(index)
        self._changed()
        return hook

    def clear(self) -> None:
        super().clear()
        self._changed()

    def __setitem__(self, index: Any, value: Any) -> None:
        super().__setitem__(index, value)
        self._changed()

    def __delitem__(self, index: Any) -> None:
        super().__delitem__(index)
        self._changed()

    def __iadd__(self, hooks: Iterable[_H]) -> Self:  # type: ignore[override,misc]
        self.extend(hooks)
        return self


@dataclass(eq=False, slots=True)
class _Item:
    kind: HookKind
    hook: Hook
    agent: str  # "" for a batch
    args: tuple[Any, ...]
    version: int  # of the hook list when published: unchanged means still registered
    live: bool = True
    batch: StatusBatch | None = None  # a status batch: hook(session, report) for each pair
    size: int = 1  # reports it stands for (a batch: its pairs; a tick: its rows)


@dataclass(frozen=True, slots=True)
class ConsumerStats:
    name: str
    queued: int
    delivered: int
    coalesced: int
    dropped: int
    overflow: int
    failed: int
    busy_s: float = 0.0  # time spent in this consumer's hooks (event-loop time), for benchmarks


@dataclass(eq=False)
class Consumer:
    """One owner's hooks: a bounded queue and the task that runs them in order."""

    name: str
    owner: object
    lists: Mapping[HookKind, HookList[Hook]]
    capacity: int = DEFAULT_CAPACITY
    delivered: int = 0
    coalesced: int = 0
    dropped: int = 0
    overflow: int = 0
    failed: int = 0
    busy_s: float = 0.0
    _queue: collections.deque[_Item] = field(default_factory=collections.deque)
    _size: int = 0  # live items in the queue
    _latest: dict[str, _Item] = field(default_factory=dict)  # agent -> its newest queued item
    _wakeup: asyncio.Event = field(default_factory=asyncio.Event)
    _idle: asyncio.Event = field(default_factory=asyncio.Event)
    _awake: bool = False  # the task is running or already woken: no Event calls per event
    _task: asyncio.Task[None] | None = None
    _last_slow_log: float = 0.0

    def holds(self, agent: str) -> bool:
        """Whether an event of ``agent`` (a join, sync or lost; not a status batch) waits here."""
        return agent in self._latest

    def __post_init__(self) -> None:
        self._idle.set()
        self._task = asyncio.create_task(self._run(), name=f"hooks-{self.name}")

    @property
    def queued(self) -> int:
        return self._size

    def offer_batch(self, item: _Item) -> None:
        """Queue one status batch or tick (shared, never changed, by every consumer it goes to)."""
        size = item.size
        for _ in range(len(self._queue)):
            if self._size + size <= self.capacity:
                break
            dropped = self._drop_oldest_status()
            if not dropped:
                break
            self.dropped += dropped
        self._queue.append(item)
        self._size += size
        if not self._awake:
            self._awake = True
            self._idle.clear()
            self._wakeup.set()

    def offer(self, item: _Item) -> None:
        if self._size >= self.capacity:
            if item.kind == "status":
                latest = self._latest.get(item.agent)
                if latest is not None and latest.kind == "status" and latest.hook == item.hook:
                    latest.args = item.args  # the newer report replaces the one still waiting
                    self.coalesced += 1
                    return
                self.dropped += self._drop_oldest_status()
            else:
                self.overflow += 1
        self._queue.append(item)
        self._size += 1
        self._latest[item.agent] = item
        if not self._awake:
            self._awake = True
            self._idle.clear()
            self._wakeup.set()

    def _drop_oldest_status(self) -> int:
        """Drop the oldest waiting status (or status batch); how many reports went."""
        for queued in self._queue:
            if queued.live and queued.kind in _BATCHED:
                queued.live = False
                if queued.batch is not None or queued.kind == "tick":
                    self._size -= queued.size
                    return queued.size
                self._size -= 1
                if self._latest.get(queued.agent) is queued:
                    del self._latest[queued.agent]
                return 1
        return 0

    async def _run(self) -> None:
        queue, latest, lists = self._queue, self._latest, self.lists
        step_started = started = time.monotonic()
        while True:
            if not queue:
                self._awake = False
                self._idle.set()
                self._wakeup.clear()
                await self._wakeup.wait()
                step_started = started = time.monotonic()
                continue
            item = queue.popleft()
            if not item.live:
                continue
            if item.batch is not None or item.kind == "tick":
                self._size -= item.size
            else:
                self._size -= 1
                if latest.get(item.agent) is item:
                    del latest[item.agent]
            hooks = lists[item.kind]
            if item.version != hooks.version and item.hook not in hooks:
                continue  # the service removed its hook (stopped) after the event was queued
            if item.batch is None:
                await self._call(item.kind, item.hook, item.args)
            else:  # a whole fleet's batch can take longer than a step: yield inside it too
                for index, pair in enumerate(item.batch):
                    await self._call(item.kind, item.hook, pair)
                    if index & 15 == 15 and time.monotonic() - step_started > STEP_BUDGET_S:
                        self.busy_s += time.monotonic() - started
                        await asyncio.sleep(0)
                        step_started = started = time.monotonic()
            now = time.monotonic()
            self.busy_s += now - started
            if now - started > SLOW_HOOK_S and started - self._last_slow_log > 60.0:
                self._last_slow_log = started
                log.warning(
                    "%s hook of %s took %.2f s (%d queued)", item.kind, self.name, now - started, self._size
                )
            started = now
            if now - step_started > STEP_BUDGET_S:
                await asyncio.sleep(0)
                step_started = started = time.monotonic()

    async def _call(self, kind: HookKind, hook: Hook, args: tuple[Any, ...]) -> None:
        try:
            await hook(*args)
            self.delivered += 1
        except asyncio.CancelledError:
            raise
        except Exception:  # a failing hook costs its own event, never the consumer
            self.failed += 1
            if self.failed <= 10 or self.failed % 1000 == 0:
                log.exception("%s hook of %s failed (%d failures)", kind, self.name, self.failed)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.wait([self._task], timeout=2.0)

    def stats(self) -> ConsumerStats:
        return ConsumerStats(
            self.name,
            self._size,
            self.delivered,
            self.coalesced,
            self.dropped,
            self.overflow,
            self.failed,
            self.busy_s,
        )


class HookDispatcher:
    """Publishes agent events to the consumer of every hook registered for their kind."""

    def __init__(self, hooks: Mapping[HookKind, HookList[Hook]], capacity: int = DEFAULT_CAPACITY) -> None:
        self._hooks = hooks  # the manager's own lists: services append/remove hooks at any time
        self.capacity = capacity
        self._consumers: dict[int, Consumer] = {}
        self._names: collections.Counter[str] = collections.Counter()
        self._routes: dict[HookKind, tuple[int, list[tuple[Hook, Consumer]]]] = {}
        self._limits: dict[int, tuple[object, int]] = {}  # owner id -> (owner, its queue's capacity)

    def limit(self, hook: Callable[..., object], capacity: int) -> None:
        """The queue capacity of ``hook``'s owner's consumer (a subscription's limit; else ``capacity``)."""
        owner = _owner(hook)
        self._limits[id(owner)] = (owner, capacity)
        consumer = self._consumers.get(id(owner))
        if consumer is not None and consumer.owner is owner:
            consumer.capacity = capacity

    def publish(self, kind: HookKind, agent: str, *args: Any) -> None:
        """Queue ``hook(*args)`` for every hook of ``kind``; never blocks, never raises for a hook."""
        for hook, consumer in self._route(kind):
            consumer.offer(_Item(kind, hook, agent, args, self._hooks[kind].version))

    def publish_batch(self, batch: StatusBatch, kind: HookKind = "status") -> None:
        """Queue ``hook(session, report)`` for every pair of ``batch`` and every hook of ``kind``."""
        if batch:
            version = self._hooks[kind].version
            for hook, consumer in self._route(kind):
                consumer.offer_batch(_Item(kind, hook, "", (), version, batch=batch, size=len(batch)))

    def publish_tick(self, tick: Any, size: int) -> None:
        """Queue ``hook(tick)`` for every tick hook (one call per tick: the service reads its columns)."""
        version = self._hooks["tick"].version
        for hook, consumer in self._route("tick"):
            consumer.offer_batch(_Item("tick", hook, "", (tick,), version, size=size))

    def queued_for(self, hook: Callable[..., object], agent: str) -> bool:
        """Whether the consumer of ``hook``'s owner still holds a join, sync or lost of ``agent``
        (status batches not counted): a caller may act for that owner on the agent's next event
        right away without overtaking one of those."""
        owner = _owner(hook)
        consumer = self._consumers.get(id(owner))
        return consumer is not None and consumer.owner is owner and consumer.holds(agent)

    def has(self, kind: HookKind) -> bool:
        """Whether any hook of ``kind`` is registered (the status tick builds reports only for them)."""
        return bool(self._hooks[kind])

    def _route(self, kind: HookKind) -> list[tuple[Hook, Consumer]]:
        """(hook, its consumer) for every hook of ``kind``, cached until the hook list changes."""
        version = self._hooks[kind].version
        route = self._routes.get(kind)
        if route is None or route[0] != version:
            route = self._routes[kind] = (version, [(h, self._consumer(h)) for h in self._hooks[kind]])
        return route[1]

    def _consumer(self, hook: Hook) -> Consumer:
        owner = _owner(hook)
        consumer = self._consumers.get(id(owner))
        if consumer is None or consumer.owner is not owner:
            bound = hasattr(hook, "__self__")
            base = type(owner).__name__ if bound else str(getattr(hook, "__name__", "hook"))
            self._names[base] += 1
            name = base if self._names[base] == 1 else f"{base}#{self._names[base]}"
            limit = self._limits.get(id(owner))
            capacity = limit[1] if limit is not None and limit[0] is owner else self.capacity
            consumer = Consumer(name, owner, self._hooks, capacity)
            self._consumers[id(owner)] = consumer
        return consumer

    def consumers(self) -> list[Consumer]:
        return list(self._consumers.values())

    def stats(self) -> list[ConsumerStats]:
        return [c.stats() for c in self._consumers.values()]

    async def drain(self, timeout: float = 10.0) -> bool:
        """Wait until every consumer has run everything queued (hooks may queue more: waits for that too).

        True when all are idle at once, False after ``timeout`` seconds.
        """
        deadline = time.monotonic() + timeout
        while True:
            busy = [c for c in self._consumers.values() if not c._idle.is_set()]
            if not busy:
                await asyncio.sleep(0)  # let a hook's follow-up publish land, then check again
                if all(c._idle.is_set() for c in self._consumers.values()):
                    return True
                continue
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            try:
                async with asyncio.timeout(remaining):
                    await busy[0]._idle.wait()
            except TimeoutError:
                return False

    async def prune(self) -> None:
        """Stop idle consumers whose owner has no hook registered any more."""
        live = {id(_owner(hook)) for hooks in self._hooks.values() for hook in hooks}
        for key in [k for k in self._limits if k not in live]:  # an unsubscribed owner's limit
            del self._limits[key]
        idle = [k for k, c in self._consumers.items() if k not in live and c._idle.is_set()]
        stopped = [c for c in (self._consumers.pop(k, None) for k in idle) if c is not None]
        if stopped:
            self._routes.clear()
        for consumer in stopped:
            await consumer.stop()

    async def close(self) -> None:
        consumers, self._consumers = list(self._consumers.values()), {}
        self._routes.clear()
        for consumer in consumers:
            await consumer.stop()


def _owner(hook: Callable[..., object]) -> object:
    """The object a bound-method hook belongs to, else the callable itself."""
    return hook.__self__ if hasattr(hook, "__self__") else hook


__all__ = ["ConsumerStats", "HookDispatcher", "HookKind", "HookList", "StatusBatch"]
