"""The agent manager: the agent link's composition, one part per job.

Every agent connection is owned here, but each job is a part of its own (docs/architecture.md,
"The agent link and the status bus"):

* admission (gcs/link/admission.py): the handshake, who may join (gcs/link/preauth.py), serving
  and ending a session; one protocol object per connection (gcs/link/connection.py);
* the frame ingest (gcs/link/ingest.py): nothing is awaited on the read path, a compact status
  body is copied into the fleet status table (gcs/link/agents_table.py);
* the status tick (gcs/link/status_tick.py): the dirty rows screened and published;
* the status bus (gcs/link/status_bus.py): the hook lists and their consumers;
* the sessions registry (gcs/link/sessions.py) and the liveness watch (gcs/link/liveness.py);
* the sender (gcs/link/sender.py): ``post``, ``send``, ``burst``, handed to the vehicle
  authority and the command port only (gcs/core/daemon.py).

This class wires them and keeps the surface the daemon, the authority, the command port, the
cluster node and the tests use.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from gcs.core.config import DaemonConfig
from gcs.link.admission import Admission, certificate_identities, source_of
from gcs.link.agents_table import StatusTable
from gcs.link.connection import Connection
from gcs.link.dispatch import ConsumerStats
from gcs.link.ingest import FrameIngest
from gcs.link.keys import KeyRing
from gcs.link.liveness import Liveness
from gcs.link.preauth import PreAuthLimits
from gcs.link.sender import LinkSender
from gcs.link.session import AgentSession, FinishedHook, JoinHook, LostHook, StatusHook, SyncHook, TickHook
from gcs.link.sessions import RetireRefused, SessionRegistry
from gcs.link.status_bus import StatusBus
from gcs.link.status_limits import StatusLimits
from gcs.link.status_tick import StatusTicker
from gcs.observe.events import EventBus
from gcs.storage.store import Store
from protocol.packets import Body, CloseReason

READ_BUFFER_BYTES = 256 << 10
"""Every served connection reads into the manager's one buffer of this size (asyncio's own read size)."""


class AgentManager:
    """Owns every agent connection; other services talk to agents only through it."""

    def __init__(
        self,
        config: DaemonConfig,
        store: Store,
        events: EventBus,
        keys: KeyRing,
        assign_cid: Callable[[str], Awaitable[int]] | None = None,
    ) -> None:
        self.config = config
        self.bus = StatusBus()
        self.table = StatusTable(limits=StatusLimits(max_clock_skew_s=config.max_clock_skew_s))
        self.registry = SessionRegistry(events)
        self.ticker = StatusTicker(self.table, self.bus, self.registry.sessions, events)
        self.frames = FrameIngest(config, events, self.table, self.ticker, self.bus)
        self.admission = Admission(
            config, store, events, keys, self.registry, self.frames, self.ticker, assign_cid
        )
        self.sender = LinkSender(self.registry)
        self.liveness = Liveness(config, self.registry, self.burst, self.ticker, self.bus, events)
        # The surface other code reads: the registry's and the bus's own objects.
        self.sessions: dict[str, AgentSession] = self.registry.sessions
        self.lost: set[str] = self.registry.lost
        self.remote: dict[str, AgentSession] = self.registry.remote  # cluster mode: linked elsewhere
        self.on_join = self.bus.on_join
        self.on_status = self.bus.on_status
        self.on_status_changes = self.bus.on_status_changes
        self.on_status_tick = self.bus.on_status_tick
        self.on_sync = self.bus.on_sync
        self.on_lost = self.bus.on_lost
        self.pre_auth: PreAuthLimits = self.admission.pre_auth
        self.read_buffer = memoryview(bytearray(READ_BUFFER_BYTES))  # every connection reads into it
        self.take_frames = self.frames.ingest  # a served connection's reads (gcs/link/connection.py)
        self._tasks: set[asyncio.Task[None]] = set()  # handshakes and session ends under way

    # --- settings and counters other code reads or sets -----------------------------------------

    @property
    def on_finished(self) -> FinishedHook | None:
        """The barrier's direct path (gcs/missions/runner.py), on the status bus."""
        return self.bus.on_finished

    @on_finished.setter
    def on_finished(self, hook: FinishedHook | None) -> None:
        self.bus.on_finished = hook

    @property
    def accepting(self) -> bool:
        """False: handshakes are refused with code ``starting``."""
        return self.admission.accepting

    @accepting.setter
    def accepting(self, value: bool) -> None:
        self.admission.accepting = value

    @property
    def assign_cid(self) -> Callable[[str], Awaitable[int]] | None:
        return self.admission.assign_cid

    @property
    def status_tick_s(self) -> float:
        return self.ticker.status_tick_s

    @status_tick_s.setter
    def status_tick_s(self, value: float) -> None:
        self.ticker.status_tick_s = value

    @property
    def ingest_probe(self) -> Callable[[bytes], None] | None:
        """Benchmarks: sees each compact body written into the table."""
        return self.frames.probe

    @ingest_probe.setter
    def ingest_probe(self, probe: Callable[[bytes], None] | None) -> None:
        self.frames.probe = probe

    @property
    def ingest_frames(self) -> int:
        return self.frames.frames

    @property
    def ingest_busy_s(self) -> float:
        return self.frames.busy_s

    @property
    def tick_count(self) -> int:
        return self.ticker.tick_count

    @property
    def tick_busy_s(self) -> float:
        return self.ticker.tick_busy_s

    # --- queries (the registry) -----------------------------------------------------------------

    def session(self, identity: str) -> AgentSession | None:
        """The agent's open session here, else its session at another daemon of the cluster."""
        return self.registry.session(identity)

    def connected(self) -> list[AgentSession]:
        return self.registry.connected()

    def link(self, identity: str) -> AgentSession | None:
        """The session every view shows for ``identity`` (:meth:`SessionRegistry.link`)."""
        return self.registry.link(identity)

    def holder(self, identity: str) -> str | None:
        """The daemon holding ``identity``'s link, None on one daemon (:meth:`SessionRegistry.holder`)."""
        return self.registry.holder(identity)

    def fleet(self) -> list[AgentSession]:
        """Every agent once, where its link is (:meth:`SessionRegistry.fleet`)."""
        return self.registry.fleet()

    def retire(self, identity: str, mission: str | None = None) -> AgentSession:
        """Take a disconnected agent off the fleet list (:meth:`SessionRegistry.retire`)."""
        return self.registry.retire(identity, mission)

    # --- the send side (the authority and the command port only) --------------------------------

    async def send(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` and wait until it is written and drained (:class:`LinkSender`)."""
        return await self.sender.send(identity, body, urgent=urgent)

    def post(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` without waiting; False if it is not connected (or overflowed)."""
        return self.sender.post(identity, body, urgent=urgent)

    def burst(self, identities: list[str], body: Body) -> int:
        """Send ``body`` to every connected agent of ``identities`` in one pass; how many got it."""
        return self.sender.burst(identities, body)

    # --- connections (the ConnectionHost of gcs/link/connection.py) -----------------------------

    def connection(self) -> Connection:
        """The protocol factory of the agent listener (``loop.create_server``): one object per connection."""
        return Connection(self)

    async def handle_connection(self, conn: Connection) -> None:
        """The connection's one task, for its handshake only (:class:`Admission`)."""
        await self.admission.handle_connection(conn)

    async def end(self, conn: Connection, exc: BaseException | None) -> None:
        """A served session is over (``exc``: what ended it)."""
        await self.admission.end(conn, exc)

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run ``coro`` as a task the manager waits for on shutdown (a handshake, a session's end)."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # --- lifecycle ------------------------------------------------------------------------------

    async def watch_liveness(self) -> None:
        """Keepalives and lost agents (:class:`Liveness`); runs until cancelled."""
        await self.liveness.watch()

    async def close_all(self, reason: CloseReason, message: str) -> None:
        sessions = self.connected()
        await asyncio.gather(*(s.close(reason, message) for s in sessions))
        deadline = time.monotonic() + 2.0  # closed transports end every session; a moment to clean up
        while (self._tasks or self.admission.serving) and time.monotonic() < deadline:
            if self._tasks:
                await asyncio.wait(list(self._tasks), timeout=max(0.0, deadline - time.monotonic()))
            else:  # a transport's connection_lost (which ends its session) is still to come
                await asyncio.sleep(0.01)
        await self.bus.close()  # a tick still scheduled must not start new consumers
        self.sender.close()

    def tick(self) -> int:
        """Run the status tick now (:meth:`StatusTicker.tick`); how many reports it handed over."""
        return self.ticker.tick()

    async def drain_hooks(self, timeout: float = 10.0) -> bool:
        """Wait until every hook consumer has handled everything queued; False after ``timeout``.

        For tests and services that need "everything received so far has been seen by the hooks".
        """
        self.ticker.tick()
        return await self.bus.drain(timeout)

    def hook_stats(self) -> list[ConsumerStats]:
        """Per consumer: queued, delivered, coalesced, dropped, overflow, failed (for metrics)."""
        return self.bus.stats()


__all__ = [
    "AgentManager",
    "AgentSession",
    "FinishedHook",
    "JoinHook",
    "LostHook",
    "RetireRefused",
    "StatusHook",
    "SyncHook",
    "TickHook",
    "certificate_identities",
    "source_of",
]
