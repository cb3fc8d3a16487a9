"""Fleet events (agent joined/lost, exceptions, sync releases, mission results): logged, stored, streamed."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Iterator
from typing import Any, Literal

from pydantic import BaseModel

from gcs.storage.store import Store, StoredEvent

log = logging.getLogger("gcs.observe.events")

Severity = Literal["info", "warning", "error"]


class Event(BaseModel):
    """One event as the API and subscribers see it."""

    id: int
    time: float
    kind: str
    severity: str
    agent: str | None = None
    mission_id: str | None = None
    message: str
    data: dict[str, Any] = {}


def _as_event(stored: StoredEvent) -> Event:
    """A stored event as the API and subscribers see it."""
    return Event(
        id=stored.id,
        time=stored.time,
        kind=stored.kind,
        severity=stored.severity,
        agent=stored.agent,
        mission_id=stored.mission_id,
        message=stored.message,
        data=stored.data,
    )


_Pending = tuple[float, str, Severity, str, str | None, str | None, dict[str, Any] | None]
"""A deferred event: (time, kind, severity, message, agent, mission id, data)."""


class EventBus:
    """Persists each event, then hands it to every subscriber queue (slow subscribers drop, not block)."""

    def __init__(self, store: Store, subscriber_queue_size: int = 1000) -> None:
        self._store = store
        self._subscribers: set[asyncio.Queue[Event]] = set()
        self._queue_size = subscriber_queue_size
        self._deferring = 0  # depth of deferred() blocks
        self._pending: list[_Pending] = []

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """Events published inside are stored (one transaction) and handed out when the block ends.

        Why: a fleet-wide safety order records two events per drone; stored with a commit each
        on the event loop, before the next drone's order, they put ~4,000 commits between the
        operator's RTL and the last of 2,000 drones. Inside, :meth:`publish` returns the event with
        id 0 (its id comes with the store); each keeps the time it was published at.
        """
        self._deferring += 1
        try:
            yield
        finally:
            self._deferring -= 1
            if not self._deferring and self._pending:
                pending, self._pending = self._pending, []
                self._flush(pending)

    def _flush(self, pending: list[_Pending]) -> None:
        with self._store.atomic():
            stored = [
                self._store.add_event(kind, severity, message, agent, mission_id, data, at=at)
                for at, kind, severity, message, agent, mission_id, data in pending
            ]
        for event in stored:
            self._hand_out(_as_event(event))

    def publish(
        self,
        kind: str,
        message: str,
        *,
        severity: Severity = "info",
        agent: str | None = None,
        mission_id: str | None = None,
        data: dict[str, Any] | None = None,
    ) -> Event:
        if self._deferring:
            at = time.time()
            self._pending.append((at, kind, severity, message, agent, mission_id, data))
            return Event(
                id=0,
                time=at,
                kind=kind,
                severity=severity,
                agent=agent,
                mission_id=mission_id,
                message=message,
                data=data or {},
            )
        event = _as_event(self._store.add_event(kind, severity, message, agent, mission_id, data))
        self._hand_out(event)
        return event

    def _hand_out(self, event: Event) -> None:
        """Log the stored event and give it to every subscriber that has room."""
        kind, severity, agent, message = event.kind, event.severity, event.agent, event.message
        log.log(
            logging.WARNING if severity != "info" else logging.INFO,
            "%s%s: %s",
            kind,
            f" [{agent}]" if agent else "",
            message,
        )
        for queue in self._subscribers:
            if queue.full():
                continue
            queue.put_nowait(event)

    def subscribe(self) -> asyncio.Queue[Event]:
        queue: asyncio.Queue[Event] = asyncio.Queue(self._queue_size)
        self._subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[Event]) -> None:
        self._subscribers.discard(queue)

    def history(
        self, since_id: int = 0, kind: str | None = None, agent: str | None = None, limit: int = 500
    ) -> list[Event]:
        return [_as_event(e) for e in self._store.events(since_id, kind, agent, limit)]
