"""The liveness watch: keepalives to quiet links, and agents marked lost when they fall silent.

Why apart: it is the link's one periodic task; it reads the registry, writes keepalives through
the sender's burst and publishes ``lost`` on the status bus, and nothing calls into it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from gcs.core.config import DaemonConfig
from gcs.link.sessions import SessionRegistry
from gcs.link.status_bus import StatusBus
from gcs.link.status_tick import StatusTicker
from gcs.observe.events import EventBus
from protocol.packets import Body, SetParameters

STALL_S = 1.0  # the liveness loop woke this much late: we were paused or starved, not the agents silent


class Liveness:
    """Keeps quiet links alive and marks silent agents lost (:meth:`watch`, until cancelled)."""

    def __init__(
        self,
        config: DaemonConfig,
        registry: SessionRegistry,
        burst: Callable[[list[str], Body], int],
        ticker: StatusTicker,
        bus: StatusBus,
        events: EventBus,
    ) -> None:
        self.config = config
        self._registry = registry
        self._burst = burst
        self._ticker = ticker  # a lost is published behind the agent's report waiting for the tick
        self._bus = bus
        self._events = events

    async def watch(self) -> None:
        """Mark agents lost when silent (or gone) for longer than ``lost_after_s``; runs until cancelled."""
        period = max(0.05, min(self.config.status_period_s, self.config.keepalive_s) / 2)
        keepalive = SetParameters()  # an empty type 3 changes nothing: it only proves we are here
        while True:
            asked = time.monotonic() + period
            await asyncio.sleep(period)
            now = time.monotonic()
            # Woken late (paused, starved): their packets wait unread in the sockets. Judge
            # nobody on this pass; the next one comes after those reads.
            stalled = now - asked > STALL_S
            due = [
                s.identity
                for s in self._registry.connected()
                if s.outbox.idle and now - s.last_tx >= self.config.keepalive_s
            ]
            if due:  # encoded once, written in one pass: a stuck peer never delays this loop
                # At most about twice a pass's fair share, so a fleet that joined at once does
                # not get all its keepalives in the same pass every second (one long stall).
                share = 2 * len(self._registry.sessions) * period / self.config.keepalive_s
                self._burst(due[: max(64, int(share))], keepalive)
            for identity, session in list(self._registry.sessions.items()):
                if (
                    stalled
                    or identity in self._registry.lost
                    or now - session.last_rx <= self.config.lost_after_s
                ):
                    continue
                self._registry.lost.add(identity)
                session.close_transport()
                self._events.publish(
                    "agent_lost",
                    f"no packet for {now - session.last_rx:.1f} s (limit {self.config.lost_after_s:.1f} s)",
                    severity="warning",
                    agent=identity,
                )
                self._ticker.publish("lost", identity, identity)
            await self._bus.prune()


__all__ = ["Liveness"]
