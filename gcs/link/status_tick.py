"""The status tick: the newest report of every agent that sent one, screened and published in one batch.

Why a class of its own: the frame handling (gcs/link/ingest.py) only copies compact bodies into
the fleet status table (gcs/link/agents_table.py) and marks their rows dirty; at most every
``STATUS_TICK_S`` this tick reads the dirty rows as NumPy columns, screens them (the protocol's
ranges, the plausibility bounds of gcs/link/status_limits.py) and publishes them on the status
bus (gcs/link/status_bus.py) three ways: a ``StatusTick`` of columns, the reports whose state
changed, every report (only if such hooks exist). A rarer event of an agent (a sync, a lost, a
failsafe) is published behind that agent's report still waiting for the tick (:meth:`publish`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from gcs.link.agents_table import StatusTable, StatusTick
from gcs.link.dispatch import HookKind
from gcs.link.session import AgentSession
from gcs.link.status_bus import StatusBus
from gcs.link.status_limits import ImplausibleStatus
from gcs.observe.events import EventBus
from protocol.packets import PacketType, StatusReport
from protocol.status_binary import ARMED, LANDED, StatusBodyError
from protocol.wire import ProtocolError

log = logging.getLogger("gcs.link.status_tick")

STATUS_TICK_S = 0.01
"""Status reports reach the hooks in one batch per tick: the newest per agent since the last tick,
at most every 10 ms (sooner after a quiet spell: once the event loop has run what it had ready).
Failsafe, failure, replayed status, sync signals and closes are handed over at once."""
TICK_SLICE = 128
"""A tick's rows reach the tick hooks in slices of this many: a consumer yields between two
slices once its step budget is spent (gcs/link/dispatch.py), so a whole fleet's tick never holds the
loop for one service, and its loop time is counted without what ran in between."""
FREEZE_MIN_AGENTS = 200  # smaller fleets: full collections are short anyway (and tests run many daemons)
REFUSAL_EVENT_S = 10.0
"""At most one ``status_refused`` event per agent this often (the first at once): an agent whose
every report is implausible must not fill the event log at its status rate."""


class StatusTicker:
    """Runs the status tick over the fleet status table and publishes what it finds on the bus."""

    def __init__(
        self, table: StatusTable, bus: StatusBus, sessions: Mapping[str, AgentSession], events: EventBus
    ) -> None:
        self.table = table
        self._bus = bus
        self._sessions = sessions  # the registry's (a rarer event flushes its agent's waiting report)
        self._events = events
        self.status_tick_s = STATUS_TICK_S
        self.due = False  # a tick is scheduled (the ingest's hot path reads this)
        self._last_tick = 0.0
        self._frozen_at = 0  # fleet size at the last gc.freeze() (0: none by this ticker)
        self.tick_count = 0
        self.tick_busy_s = 0.0  # event-loop time of the status ticks (decode dirty rows, publish)

    def schedule(self, now: float) -> None:
        """The first report since the last tick: the next tick runs ``status_tick_s`` after the last
        one, or when the event loop has run the callbacks it has ready if that was longer ago."""
        self.due = True
        loop = asyncio.get_running_loop()
        delay = self._last_tick + self.status_tick_s - now
        if delay > 0:
            loop.call_later(delay, self._run)
        else:
            loop.call_soon(self._run)

    def _run(self) -> None:
        self.due = False
        self._last_tick = time.monotonic()
        try:
            self.tick()
        except Exception:  # a bug must cost one tick, never the status flow
            log.exception("status tick failed")

    def tick(self) -> int:
        """Hand the newest report of every agent that sent one since the last tick to the status
        hooks, as one batch; how many. Rows are screened first (:meth:`screen`): a body that breaks
        the protocol's ranges ends its session, an implausible report is dropped, the rest go on.
        """
        started = time.perf_counter()
        table = self.table
        rows = table.take_dirty()
        if not len(rows):
            return 0
        cols = table.columns(rows)
        changed = table.changed(rows)
        keep, sessions, reports = self.screen(rows, cols)
        if len(keep) != len(rows):  # (whole rows: cols[keep] would drop mode and mission)
            cols, changed, rows = table.pick(cols, keep), changed[keep], rows[keep]
        # On the ground and disarmed the authority drops automatic holds with every report, as
        # before (a hold placed on a landed drone ends at its next report, not at a change).
        changed |= (cols["flags"] & (LANDED | ARMED)) == LANDED
        tick = StatusTick(sessions, cols, table.arrivals(rows), reports)
        if sessions and not self._bus.closed:
            hooks = self._bus
            decoded = np.fromiter((r is not None for r in reports), dtype=bool, count=len(reports))
            if hooks.has("status"):  # every report as an object: built here (the API's and extensions' view)
                hooks.publish_batch([(s, tick.report(i)) for i, s in enumerate(sessions)])
            if hooks.observing or hooks.has("changes"):  # a changed state (or a report that came decoded)
                moved = np.flatnonzero(changed | decoded).tolist()  # (decoded: before building any here)
                pairs = [(sessions[i], tick.report(i)) for i in moved]
                hooks.observed(pairs)  # the synchronous observers, in their declared order, first
                hooks.publish_batch(pairs, "changes")
            for start in range(0, len(sessions), TICK_SLICE):  # the consumers yield between slices
                hooks.publish_tick(
                    tick.slice(start, start + TICK_SLICE), min(TICK_SLICE, len(sessions) - start)
                )
        self._freeze_heap(len(table))
        self.tick_count += 1
        self.tick_busy_s += time.perf_counter() - started
        return len(sessions)

    def screen(
        self, rows: np.ndarray[Any, np.dtype[np.intp]], cols: np.ndarray[Any, Any]
    ) -> tuple[list[int], list[AgentSession], list[StatusReport | None]]:
        """Which of a tick's ``rows`` go to the hooks: their indexes, sessions and reports (None:
        built on demand from the columns).

        Every row is checked at once on the columns (the schema's ranges, ``StatusTable.check``,
        and the plausibility bounds, gcs/link/status_limits.py); only a row that fails is looked at on
        its own (the reference decoder and :func:`~gcs.link.status_limits.refusal` name what is wrong),
        so one bad row costs only itself: a body out of the protocol's ranges closes that session
        (``protocol_error``), an implausible report is dropped with a ``status_refused`` event.
        """
        table = self.table
        ok = table.check(cols) & table.plausible(cols, rows)
        owners, objects = table.owners, table.objects
        keep: list[int] = []
        sessions: list[AgentSession] = []
        reports: list[StatusReport | None] = []
        for i, (row, passed) in enumerate(zip(rows.tolist(), ok.tolist(), strict=True)):
            conn = owners[row]
            if conn is None:
                continue
            report = objects[row]  # came decoded and checked (JSON), or an API call decoded it already
            if not passed and report is None:
                try:  # the reference decoder and the plausibility bounds name what is wrong
                    report = table.report(row)
                except StatusBodyError as exc:
                    conn.finish(ProtocolError(str(exc), packet_type=PacketType.STATUS))
                    continue
                except ImplausibleStatus as exc:
                    table.unsee(row)  # its next accepted report counts as a change
                    self.refused(conn.session, str(exc))
                    continue
            keep.append(i)
            sessions.append(conn.session)
            reports.append(report)
        return keep, sessions, reports

    def refused(self, session: AgentSession, reason: str) -> None:
        """An implausible status report of ``session`` was dropped: counted, and a ``status_refused``
        event (warning) naming the agent and the reason, at most one per :data:`REFUSAL_EVENT_S`."""
        session.refused_count += 1
        now = time.monotonic()
        if now - session.refused_event_at < REFUSAL_EVENT_S:
            return
        since = session.refused_count - session.refused_reported
        session.refused_event_at, session.refused_reported = now, session.refused_count
        more = f" ({since} refused since the last such event)" if since > 1 else ""
        self._events.publish(
            "status_refused",
            f"status report refused: {reason}{more}",
            severity="warning",
            agent=session.identity,
            data={"refused": session.refused_count},
        )

    def _freeze_heap(self, agents: int) -> None:
        """Keep the per-agent state of a large fleet out of the full garbage collections.

        A full collection scans every tracked object; with thousands of agents that took 50-170
        ms of event loop (docs/performance.md). When the fleet has grown by a quarter (from
        ``FREEZE_MIN_AGENTS`` agents on), what is alive is frozen (``gc.freeze``): per-report
        garbage is still freed by reference counting and by the young generations. When it has
        shrunk by a quarter the heap is unfrozen, so the state of agents that left is collected.
        """
        if agents < FREEZE_MIN_AGENTS and not self._frozen_at:
            return
        if agents >= max(FREEZE_MIN_AGENTS, self._frozen_at * 1.25):
            gc.freeze()
            self._frozen_at = agents
        elif agents < self._frozen_at * 0.75:
            gc.unfreeze()
            self._frozen_at = agents if agents >= FREEZE_MIN_AGENTS else 0

    def flush(self, session: AgentSession) -> None:
        """Hand the session's report waiting for the tick to the hooks now (before a rarer event)."""
        table = session.table
        if table is None or not table.dirty[session.row]:
            return
        table.clean(session.row)
        table.unsee(session.row)
        try:
            report = table.report(session.row)
        except StatusBodyError as exc:
            raise ProtocolError(str(exc), packet_type=PacketType.STATUS) from None
        except ImplausibleStatus as exc:
            self.refused(session, str(exc))
            return
        session._status = report
        self._bus.hand_over([(session, report)])

    def publish(self, kind: HookKind, agent: str, *args: object) -> None:
        """Publish a non-status event behind the agent's report still waiting for the tick."""
        session = self._sessions.get(agent)
        if session is not None:
            with contextlib.suppress(ProtocolError):
                self.flush(session)
        self._bus.publish(kind, agent, *args)


__all__ = ["STATUS_TICK_S", "TICK_SLICE", "StatusTicker"]
