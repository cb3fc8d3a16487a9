"""Fleet events (agent joined/lost, exceptions, sync releases, mission results): logged, stored, streamed."""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Literal

from pydantic import BaseModel

from gcs.store import Store

log = logging.getLogger("gcs.events")

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


class EventBus:
    """Persists each event, then hands it to every subscriber queue (slow subscribers drop, not block)."""

    def __init__(self, store: Store, subscriber_queue_size: int = 1000) -> None:
        self._store = store
        self._subscribers: set[asyncio.Queue[Event]] = set()
        self._queue_size = subscriber_queue_size

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
        stored = self._store.add_event(kind, severity, message, agent, mission_id, data)
        event = Event(
            id=stored.id,
            time=stored.time,
            kind=kind,
            severity=severity,
            agent=agent,
            mission_id=mission_id,
            message=message,
            data=stored.data,
        )
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
        return event

    def subscribe(self) -> asyncio.Queue[Event]:
        queue: asyncio.Queue[Event] = asyncio.Queue(self._queue_size)
        self._subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[Event]) -> None:
        self._subscribers.discard(queue)

    def history(
        self, since_id: int = 0, kind: str | None = None, agent: str | None = None, limit: int = 500
    ) -> list[Event]:
        return [
            Event(
                id=e.id,
                time=e.time,
                kind=e.kind,
                severity=e.severity,
                agent=e.agent,
                mission_id=e.mission_id,
                message=e.message,
                data=e.data,
            )
            for e in self._store.events(since_id, kind, agent, limit)
        ]
