"""One authenticated agent connection as the daemon holds it (:class:`AgentSession`) and the hook types.

Why apart from the manager: every part of the link (admission, ingest, the status tick, the
registry, the sender) and every service reads sessions; none of them needs the manager for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from gcs.link.agents_table import MAX_BODY, ROW_BYTES, StatusTable, StatusTick
from gcs.link.outbox import Outbox
from gcs.link.rates import TokenBucket
from gcs.link.status_limits import ImplausibleStatus
from protocol.packets import (
    PROTOCOL_VERSION,
    Body,
    Capabilities,
    Close,
    CloseReason,
    GeoPoint,
    Resume,
    StatusReport,
    SyncSignal,
)
from protocol.session import Code
from protocol.status_binary import StatusBodyError

REASON_CODES = {
    CloseReason.NORMAL: Code.NORMAL,
    CloseReason.REPLACED: Code.REPLACED,
    CloseReason.SHUTDOWN: Code.SHUTDOWN,
    CloseReason.PROTOCOL_ERROR: Code.PROTOCOL_ERROR,
}


@dataclass(eq=False, slots=True)
class AgentSession:
    """One authenticated connection of one agent identity.

    Outbound frames go through the session's :class:`~gcs.link.outbox.Outbox` (its own bounded queue
    and a writer task while it has work), so a peer that does not read stalls only itself.
    """

    identity: str
    cid: int
    capabilities: Capabilities
    home: GeoPoint | None
    writer: asyncio.StreamWriter
    peer: str
    outbox: Outbox
    connected_at: float = field(default_factory=time.time)
    last_rx: float = field(default_factory=time.monotonic)
    _status: StatusReport | None = field(default=None, repr=False)  # as of the last status tick
    status_count: int = 0
    replayed_count: int = 0  # buffered status reports received (counted apart from live ones)
    open: bool = True
    version: int = PROTOCOL_VERSION
    exception_names: frozenset[str] = frozenset()
    exception_budget: TokenBucket | None = None
    exceptions_suppressed: int = 0
    compact_status: bool = False  # negotiated: status may come as the compact binary body
    refused_count: int = 0  # implausible status reports dropped (gcs/link/status_limits.py)
    refused_reported: int = 0  # of them, counted in a status_refused event already
    refused_event_at: float = -math.inf  # monotonic time of its last status_refused event
    release_beacon: bool = False  # v2 offer: the agent listens for release beacons (protocol/beacon.py)
    row: int = -1  # its row in the manager's status table while the session is served
    table: StatusTable | None = field(default=None, repr=False)

    @property
    def status(self) -> StatusReport | None:
        """The newest live status report: decoded on demand from the status table (the tick builds
        reports only for the hooks that want objects), cached until the next report."""
        table = self.table
        if table is not None and table.buf[self.row * ROW_BYTES + MAX_BODY]:
            with contextlib.suppress(StatusBodyError, ImplausibleStatus):  # the tick refuses it
                self._status = table.report(self.row)
        return self._status

    @status.setter
    def status(self, report: StatusReport | None) -> None:
        self._status = report

    @property
    def last_tx(self) -> float:
        """When a frame was last handed to the socket (monotonic)."""
        return self.outbox.last_tx

    def post(self, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue one packet without waiting; False if the session is closed or its queue overflowed.

        ``urgent=None`` picks the lane from the packet (:func:`gcs.link.outbox.is_urgent`).
        """
        if not self.open:
            return False
        return self.outbox.post(body, urgent)

    async def send(
        self,
        body: Body,
        timeout: float | None = None,
        max_pending: int | None = None,
        *,
        urgent: bool | None = None,
    ) -> bool:
        """Send one packet and wait until it is written and drained; False (session cut off) if not.

        ``timeout`` bounds the whole wait (queue included); ``max_pending`` is kept for callers
        of the old signature, the session's outbox has its own byte bound.
        """
        del max_pending
        if not self.open:
            return False
        return await self.outbox.send(body, urgent, timeout)

    async def close(
        self, reason: CloseReason, message: str, timeout: float = 1.0, *, code: Code | None = None
    ) -> None:
        """Tell the peer why (urgent, bounded wait), then close the transport."""
        if self.outbox.open:
            self.open = False  # no new frames from here on; the close itself still goes out
            code = code or REASON_CODES.get(reason)
            body = Close(reason=reason, message=message[:500], code=code.value if code else None)
            await self.outbox.send(body, True, timeout)
        self.close_transport()

    def close_transport(self) -> None:
        self.open = False
        self.outbox.close()
        with contextlib.suppress(Exception):
            self.writer.close()


JoinHook = Callable[[AgentSession, Resume | None], Awaitable[None]]
StatusHook = Callable[[AgentSession, StatusReport], Awaitable[None]]
TickHook = Callable[[StatusTick], Awaitable[None]]
SyncHook = Callable[[AgentSession, SyncSignal], Awaitable[None]]
FinishedHook = Callable[[AgentSession, SyncSignal], bool]
LostHook = Callable[[str], Awaitable[None]]


__all__ = [
    "AgentSession",
    "FinishedHook",
    "JoinHook",
    "LostHook",
    "StatusHook",
    "SyncHook",
    "TickHook",
]
