"""The served connection's frames: rate-checked, recorded and handed on, with nothing awaited.

Why apart from the handshake and the tick: this is the hot path. Each ``buffer_updated`` of a
served connection (gcs/link/connection.py) lands here (:meth:`FrameIngest.ingest`): a compact
status body (``compact_status``, negotiated by the session layer) is CRC- and rate-checked, its
layout checked whole (``status_binary.check_layout``: lengths, UTF-8, no stray bytes; a bad one
closes the session) and copied as it is into the agent's row of the fleet status table
(gcs/link/agents_table.py), for the status tick (gcs/link/status_tick.py). JSON status, failsafe
or failure reports, replayed status, ``finished`` and close are decoded and handled at once
(:meth:`FrameIngest.handle`), behind the agent's report still waiting for the tick, so each
consumer sees one agent's events in the order they arrived.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from gcs.core.config import DaemonConfig
from gcs.link.agents_table import MAX_BODY, ROW_BYTES, StatusTable
from gcs.link.connection import Connection
from gcs.link.rates import RateLimited, TokenBucket
from gcs.link.session import AgentSession
from gcs.link.status_bus import StatusBus
from gcs.link.status_limits import refusal
from gcs.link.status_tick import StatusTicker
from gcs.observe.events import EventBus
from protocol.packets import Close, PacketType, StatusReport, SyncSignal
from protocol.status_binary import BUFFERED, HAS_TAIL, StatusBodyError, check_layout
from protocol.wire import COMPACT, STATUS_COMPACT, Frame, ProtocolError, decode_body

log = logging.getLogger("gcs.link.ingest")

_SLOW_FLAGS = 0x80 | HAS_TAIL | BUFFERED  # a compact body with these is decoded at once (rare or bad)


def safety_news(report: StatusReport, last: StatusReport | None, received: float) -> StatusReport | None:
    """What an implausible report still says that must not be lost: the vehicle's own failsafe or an
    action's failure (a lower-priority order must not undo a failsafe because one number glitched).
    The measured values (time, position, velocity, counters) are the last plausible report's, or
    none (no position) without one; the state flags and the safety news are the report's own.
    None when the report carries no such news (it is then only dropped)."""
    if (report.failsafe is None and report.failure is None) or report.buffered:
        return None
    kept = last if last is not None else StatusReport(time=received, position=None)
    return report.model_copy(
        update={
            "time": kept.time,
            "vehicle_time": kept.vehicle_time,
            "position": kept.position,
            "velocity": kept.velocity,
            "step": kept.step,
            "completed_step": kept.completed_step,
            "waiting_sync": kept.waiting_sync,
            "queue_depth": kept.queue_depth,
        }
    )


class FrameIngest:
    """Records what a served connection's frames say and hands it to the status tick or the bus."""

    def __init__(
        self, config: DaemonConfig, events: EventBus, table: StatusTable, ticker: StatusTicker, bus: StatusBus
    ) -> None:
        self.config = config
        self._events = events
        self._table = table
        self._ticker = ticker
        self._bus = bus
        self.probe: Callable[[bytes], None] | None = None  # benchmarks: sees each table write
        self.frames = 0  # frames recorded by the frame loops
        self.busy_s = 0.0  # event-loop time recording them took (checks, record, publish)

    def take(self, conn: Connection, frame: Frame, now: float) -> None:
        """The rate limit of a decoded frame (live frames and replayed status have separate budgets).

        Live frames and replayed (``buffered``) status reports are counted in separate buckets,
        so an agent catching up after an outage is not cut off for it (docs/protocol.md).
        """
        session = conn.session
        assert session is not None  # only served connections get here
        session.last_rx = now  # complete packets count as life, stray bytes do not
        replayed = isinstance(frame.body, StatusReport) and frame.body.buffered
        bucket = conn.live
        if replayed:
            if conn.replay is None:  # only an agent that replays status needs this budget (full at first)
                conn.replay = TokenBucket(self.config.replay_frames_per_s, self.config.replay_burst)
            bucket = conn.replay
        if not bucket.take(now):
            raise self.over_budget(replayed)

    def over_budget(self, replayed: bool) -> RateLimited:
        """The refusal of a frame over its budget (live frames, or replayed status reports)."""
        kind = "replayed status reports" if replayed else "frames"
        rate, burst = (
            (self.config.replay_frames_per_s, self.config.replay_burst)
            if replayed
            else (self.config.max_frames_per_s, self.config.frame_burst)
        )
        return RateLimited(f"more than {rate:g} {kind}/s (burst {burst}); cut off")

    def ingest(self, conn: Connection, data: bytes | memoryview) -> bool:
        """Every frame ``data`` completes; False once the session is over.

        The hot path: a compact status body without tail (not replayed) is copied into the
        session's table row as it is, nothing decoded. Anything else is decoded and handled
        (:meth:`handle`) at once, behind the reports already received.
        """
        started = time.perf_counter()
        session, table, ticker, frames = conn.session, self._table, self._ticker, 0
        assert session is not None  # only served connections get here
        probe = self.probe
        try:
            for ptype, seq, payload in conn.decoder.split(data):
                frames += 1
                now = time.monotonic()
                size = len(payload)
                if (
                    ptype == STATUS_COMPACT
                    and size <= MAX_BODY
                    and size > 1
                    and not payload[1] & _SLOW_FLAGS
                    and session.compact_status
                ):
                    session.last_rx = now
                    if not conn.live.take(now):
                        raise self.over_budget(replayed=False)
                    try:  # the whole variable part, before a byte reaches the table (fixed: the tick)
                        check_layout(payload)
                    except StatusBodyError as exc:
                        raise conn.decoder.fail(ProtocolError(str(exc), packet_type=ptype)) from None
                    row = session.row
                    start = row * ROW_BYTES
                    buf = table.buf
                    buf[start : start + size] = payload
                    buf[start + MAX_BODY] = size
                    table.objects[row] = None
                    table.dirty[row] = 1
                    table.rx[row] = time.time()
                    session.status_count += 1
                    if not ticker.due:
                        ticker.schedule(now)
                    if probe is not None:
                        probe(payload)
                    continue
                try:
                    body = decode_body(ptype, payload)
                except ProtocolError as exc:
                    raise conn.decoder.fail(exc) from None
                frame = Frame(PacketType(ptype & ~COMPACT), seq, body, ptype == STATUS_COMPACT)
                self.take(conn, frame, now)
                self.handle(session, frame)
                if not session.open:
                    return False
            return True
        finally:
            self.frames += frames
            self.busy_s += time.perf_counter() - started

    def handle(self, session: AgentSession, frame: Frame) -> None:
        """Record what a decoded frame says and hand it to the hook consumers; nothing is awaited here."""
        body = frame.body
        if isinstance(body, StatusReport):
            if frame.compact and not session.compact_status:
                raise ProtocolError("compact status body (type 0x82) sent without negotiating it")
            received = time.time()
            reason = refusal(body, received, self._table.limits, replayed=body.buffered)
            if reason is not None:
                salvaged = safety_news(body, session.status, received)
                if salvaged is None or refusal(salvaged, received, self._table.limits) is not None:
                    session.status_count += 1
                    self._ticker.refused(session, reason)
                    return
                self._ticker.refused(
                    session, f"{reason}; its failsafe/failure kept with the last plausible values"
                )
                body = salvaged
            self.exception_events(session, body)
            session.status_count += 1
            if body.buffered:  # history: it never overwrites the newer live state; in order, at once
                session.replayed_count += 1
                self._ticker.flush(session)
                self._bus.hand_over([(session, body)])
                return
            urgent = body.failsafe is not None or body.failure is not None or body.pilot is not None
            if urgent:  # safety news goes to the hooks now, behind the report still waiting for the tick
                self._ticker.flush(session)
            self._table.put_report(session.row, body, time.time())
            if urgent:
                self._ticker.flush(session)
            elif not self._ticker.due:
                self._ticker.schedule(time.monotonic())
        elif isinstance(body, SyncSignal):
            if body.kind != "finished":
                raise ProtocolError("agents may only send 'finished' sync signals")
            self.finished(session, body)
        elif isinstance(body, Close):
            self._events.publish(
                "agent_closed",
                f"agent closed its session: {body.reason.value} {body.message}",
                agent=session.identity,
            )
            session.close_transport()
        else:
            raise ProtocolError(
                f"type {frame.packet_type.value} ({frame.packet_type.name}) "
                "is not valid from an agent after the handshake"
            )

    def finished(self, session: AgentSession, signal: SyncSignal) -> None:
        """A 'finished' sync signal: to the barrier at once, then to every ``on_sync`` hook.

        The last arrival of a barrier releases it from here, in this ``buffer_updated`` call (no
        hook queue and no task switch in between): ``on_finished`` records the arrival and, when
        it completes the barrier, persists and bursts the release. Not while the consumer of its
        owner still holds a join or lost of the agent (``on_finished`` itself declines while the
        agent's newest report carries a failsafe or a failure): then the owner's ``on_sync`` hook
        takes the arrival, in order. A plain status report still waiting for the tick (flushed
        below, for the other hooks) says nothing the barrier depends on.
        """
        direct = self._bus.may_finish_now(session.identity)
        if direct is not None:
            try:
                direct(session, signal)
            except Exception:  # a bug costs this arrival (as a failing hook would), not the session
                log.exception("barrier arrival of %s failed", session.identity)
        self._ticker.publish("sync", session.identity, session, signal)

    def exception_events(self, session: AgentSession, status: StatusReport) -> None:
        """Turn exceptions that appear in a status report into events (once each, bounded).

        At most ``max_exception_events`` per agent per minute are published; beyond that they
        are counted, with one warning per suppressed run, so an agent cycling through new names
        cannot fill the database.
        """
        if not status.exceptions and not session.exception_names:
            return  # the common case: nothing raised before or now
        before = session.exception_names
        names = frozenset(e.split(":", 1)[0] for e in status.exceptions)
        session.exception_names = names
        if session.exception_budget is None:
            cap = self.config.max_exception_events
            session.exception_budget = TokenBucket(cap / 60.0, cap)
        now = time.monotonic()
        for text in status.exceptions:
            name = text.split(":", 1)[0]
            if name in before:
                continue
            if not session.exception_budget.take(now):
                session.exceptions_suppressed += 1
                if session.exceptions_suppressed == 1 or session.exceptions_suppressed % 1000 == 0:
                    self._events.publish(
                        "agent_exceptions_suppressed",
                        f"more than {self.config.max_exception_events} new exceptions a minute; "
                        f"{session.exceptions_suppressed} not logged",
                        severity="warning",
                        agent=session.identity,
                    )
                continue
            if name not in before:
                self._events.publish(
                    "agent_exception",
                    text,
                    severity="warning",
                    agent=session.identity,
                    data={"exception": name},
                )


__all__ = ["FrameIngest", "safety_news"]
