"""Per-agent outbound queue and writer: one bounded queue per session, a writer task while it has work.

Why: a peer that stops reading must only ever stall its own writer. Callers enqueue (``post``,
never blocks) or enqueue and wait for the frame to be written and drained (``send``); the writer
task owns the socket while it runs. A ``post`` to a peer with nothing queued, in flight or in its
transport goes to the socket at once (one ``send``, no task): a fleet-wide order is one pass of
sends, and a peer with a backlog queues as before. It is started when there is something to write or drain and
ends when the queue is empty and the socket drained, so an idle session costs no task (a fleet of
thousands mostly idles between keepalives: docs/performance.md, "Round 4: memory").

Two lanes: an *urgent* frame (operator/safety commands, close) is placed ahead of every queued
*normal* frame (mission traffic, geofence, parameters, keepalive, sync
releases), with one exception: type-4 frames (PerformActions) keep their relative order
whatever their lane, because the agent applies them in order (a ``replace`` cancels a
``pause``), so a pause overtaking the replace it was sent after would be lost. Normal frames
always keep their order among themselves.

The queue is bounded in frames and in bytes (queued plus the transport's own buffer); a peer
that overflows it, or whose socket does not drain within ``send_timeout_s``, is cut off: the
transport is aborted (what it holds is dropped, so the connection ends at once) and every waiting
``send`` resolves False.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from protocol.packets import PROTOCOL_VERSION, Body, Close, PacketType, PerformActions, packet_type_of
from protocol.wire import encode

log = logging.getLogger("gcs.link.outbox")

MAX_QUEUED_FRAMES = 1024
"""Frames waiting for one peer before it counts as stuck (a healthy peer has almost none)."""
MAX_BATCH_BYTES = 256 << 10
"""Frames written before one drain: a fan-out costs one drain per agent, not one per frame."""
_SEQ = struct.Struct(">I")
_SEQ_OFFSET = 4  # protocol.wire header: magic(2) version(1) type(1) seq(4) ...


def is_urgent(body: Body) -> bool:
    """The lane a frame goes in when the caller does not say: safety and operator commands first.

    Urgent: close, pause/resume, and a replace whose actions include a return or a landing.
    Everything else (missions, geofence, parameters, keepalive, sync releases) is normal.
    """
    if isinstance(body, Close):
        return True
    if isinstance(body, PerformActions):
        if body.mode in ("pause", "resume"):
            return True
        return body.mode == "replace" and any(a.kind in ("rtl", "land") for a in body.actions)
    return False


@dataclass(eq=False, slots=True)
class _Outgoing:
    frame: bytes
    ptype: int
    urgent: bool
    done: asyncio.Future[bool] | None = None


@dataclass(eq=False, slots=True)
class Outbox:
    """The outbound side of one session; its writer task runs only while there is work.

    ``on_cut_off(outbox, reason)`` is told when the peer is cut off (one shared callable for every
    session: nothing per agent).
    """

    writer: asyncio.StreamWriter
    identity: str
    send_timeout_s: float
    max_pending_bytes: int
    first_seq: int = 1
    version: int = PROTOCOL_VERSION  # the session's protocol version: a v1 peer gets v1 bodies
    max_frames: int = MAX_QUEUED_FRAMES
    on_cut_off: Callable[[Outbox, str], None] | None = None
    last_tx: float = field(default_factory=time.monotonic)
    written: int = 0
    open: bool = True
    cut_off_reason: str | None = None
    # A list, not a deque: an empty deque holds a 64-slot block (~600 B) per session; this queue is
    # almost always empty and never longer than max_frames.
    _queue: list[_Outgoing] = field(default_factory=list)
    _queued_bytes: int = 0
    _task: asyncio.Task[None] | None = None  # the writer, while there is something to write or drain
    _in_flight: list[_Outgoing] | None = None  # the batch being drained (the writer's)
    _drain_due: bool = False  # write_now wrote past the queue: the writer drains it
    _seq: int = 0
    _sock: socket.socket | None = None  # the plain TCP socket under the transport (None with TLS)
    _plain: asyncio.WriteTransport | None = None  # that socket's transport (a burst reads it per agent)

    def __post_init__(self) -> None:
        self._seq = self.first_seq
        transport = self.writer.transport
        sock = getattr(transport, "_sock", None)  # asyncio's selector TCP transport only
        if isinstance(sock, socket.socket) and sock.type == socket.SOCK_STREAM:
            self._sock = sock
            self._plain = transport

    def _wake(self) -> None:
        """Start the writer task unless it runs already (it ends by itself once idle)."""
        if self._task is None and self.open:
            self._task = asyncio.get_running_loop().create_task(self._run())

    @property
    def queued(self) -> int:
        """Frames waiting (not yet handed to the socket)."""
        return len(self._queue)

    @property
    def idle(self) -> bool:
        return not self._queue and not self._in_flight

    # --- enqueue --------------------------------------------------------------------------------

    def post(self, body: Body, urgent: bool | None = None) -> bool:
        """Queue ``body``; False (and the peer cut off if it overflowed) when it cannot be queued."""
        return self._enqueue(body, urgent, None)

    async def send(self, body: Body, urgent: bool | None = None, timeout: float | None = None) -> bool:
        """Queue ``body`` and wait until it is written and drained (True) or the peer is cut off (False).

        ``timeout`` bounds the wait; a frame not drained by then cuts the peer off, as a peer
        that does not take a frame within the send timeout is considered stuck.
        """
        done: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        if not self._enqueue(body, urgent, done):
            return False
        try:
            async with asyncio.timeout(timeout):
                return await asyncio.shield(done)
        except TimeoutError:
            self.cut_off(f"a frame was not written within {timeout:g} s")
            return False

    def write_now(self, frame: bytes, ptype: int, now: float | None = None) -> bool:
        """Write a pre-encoded normal-lane frame (any seq; it gets ours) to the socket right now.

        For a burst to many agents (a barrier release): one ``send`` per agent in one pass, no
        task switch per agent. When the transport holds nothing the frame goes straight to the
        plain TCP socket (``sock.send``: what ``transport.write`` would do, without its
        bookkeeping); what the kernel does not take, and every frame of a TLS session, goes
        through the transport, and the writer task is started to drain it (so a stuck peer is cut
        off as usual). When frames are already queued it queues behind them (order is kept).
        """
        if not self.open:
            return False
        if self._queue:
            return self._enqueue_frame(_Outgoing(frame, ptype, False))
        return self._write(frame, now)

    def take_direct(self, frame: bytes) -> tuple[socket.socket, bytearray] | None:
        """The plain TCP socket and ``frame`` stamped with our next seq, for the caller to ``send``
        itself, or None when it cannot go that way (closed, frames queued, bytes in the transport,
        TLS): then :meth:`write_now` it. The caller hands the result to :meth:`finish_direct` (a
        burst's sends on a helper thread: gcs/link/send_pool.py)."""
        sock = self._sock
        if sock is None or not self.open or self._queue:
            return None
        transport = self._plain  # (not self.writer.transport: one object fewer per agent of a burst)
        try:
            if transport is None or transport.get_write_buffer_size() or transport.is_closing():
                return None
        except (RuntimeError, AttributeError):
            return None
        self._seq += 1
        out = bytearray(frame)
        _SEQ.pack_into(out, _SEQ_OFFSET, self._seq % (1 << 32))
        return sock, out

    def finish_direct(self, out: bytearray, result: int | OSError, now: float) -> bool:
        """What the kernel did with a :meth:`take_direct` frame: the rest goes through the transport
        (its writer task drains it, cutting a stuck peer off), an error cuts the peer off."""
        if isinstance(result, OSError):
            self.cut_off(f"write failed: {result}")
            return False
        if result < len(out):
            transport = self.writer.transport
            try:
                transport.write(out[result:] if result else out)
                if transport.get_write_buffer_size():
                    self._drain_due = True
                    self._wake()
            except (OSError, RuntimeError, AttributeError) as exc:
                self.cut_off(f"write failed: {exc}")
                return False
        self.last_tx = now
        self.written += 1
        return True

    def _write(self, frame: bytes, now: float | None) -> bool:
        """Stamp our next seq into ``frame`` and hand it to the socket now (see :meth:`write_now`)."""
        transport = self.writer.transport  # straight to the transport: no per-agent layers in a burst
        try:
            waiting = transport.get_write_buffer_size()
            if len(frame) + waiting > self.max_pending_bytes:
                self.cut_off(
                    f"more than {self.max_pending_bytes} bytes waiting for a peer that does not read"
                )
                return False
            self._seq += 1
            out = bytearray(frame)
            _SEQ.pack_into(out, _SEQ_OFFSET, self._seq % (1 << 32))
            sent = 0
            sock = self._sock
            if sock is not None and not waiting and not transport.is_closing():
                try:
                    sent = sock.send(out)
                except (BlockingIOError, InterruptedError):  # the kernel's buffer is full
                    sent = 0  # (not contextlib.suppress: ~0.5 us a socket in a 1,000-socket burst)
            if sent < len(out):
                transport.write(out[sent:] if sent else out)
                if transport.get_write_buffer_size():  # the kernel did not take it all
                    self._drain_due = True  # the writer task drains it (and cuts a stuck peer off)
                    self._wake()
        except (OSError, RuntimeError, AttributeError) as exc:
            self.cut_off(f"write failed: {exc}")
            return False
        self.last_tx = now if now is not None else time.monotonic()
        self.written += 1
        return True

    def _enqueue(self, body: Body, urgent: bool | None, done: asyncio.Future[bool] | None) -> bool:
        if not self.open:
            return False
        frame = encode(body, 0, self.version)
        item = _Outgoing(frame, packet_type_of(body), is_urgent(body) if urgent is None else urgent, done)
        return self._enqueue_frame(item)

    def _enqueue_frame(self, item: _Outgoing) -> bool:
        if item.done is None and len(item.frame) <= self.max_pending_bytes and self._idle_link():
            # Nothing queued, in flight or in the transport: the frame goes out now (one ``send``),
            # not at the writer task's turn. A fleet-wide order to 2,000 agents is 2,000 sends in
            # one pass, not 2,000 tasks; a peer with a backlog still queues, so urgent frames
            # keep overtaking queued ones there.
            return self._write(item.frame, None)
        frame = item.frame
        if len(self._queue) >= self.max_frames:
            self.cut_off(f"more than {self.max_frames} frames waiting for a peer that does not read")
            return False
        if self._queued_bytes + _buffered(self.writer) > self.max_pending_bytes:
            self.cut_off(f"more than {self.max_pending_bytes} bytes waiting for a peer that does not read")
            return False
        if item.urgent:
            self._queue.insert(self._urgent_position(item.ptype), item)
        else:
            self._queue.append(item)
        self._queued_bytes += len(frame)
        self._wake()
        return True

    def _urgent_position(self, ptype: int) -> int:
        """After every queued urgent frame and, for a type-4 frame, after every queued type-4 frame."""
        keep_type4_order = ptype == PacketType.PERFORM_ACTIONS
        for index in range(len(self._queue) - 1, -1, -1):
            queued = self._queue[index]
            if queued.urgent or (keep_type4_order and queued.ptype == PacketType.PERFORM_ACTIONS):
                return index + 1
        return 0

    def _idle_link(self) -> bool:
        """Nothing waits for this peer: no queued or in-flight frame, an empty transport buffer."""
        if self._queue or self._in_flight or self._task is not None or not self.open:
            return False
        return _buffered(self.writer) == 0

    # --- writer ---------------------------------------------------------------------------------

    async def _run(self) -> None:
        """Write and drain until nothing is queued and nothing is left to drain, then end."""
        try:
            while self.open:
                if not self._queue:
                    if not self._drain_due:
                        return
                    self._drain_due = False
                    async with asyncio.timeout(self.send_timeout_s):
                        await self.writer.drain()
                    continue
                batch_bytes = 0
                self._in_flight = batch = []
                while self._queue and batch_bytes < MAX_BATCH_BYTES:
                    item = self._queue.pop(0)
                    self._queued_bytes -= len(item.frame)
                    self._seq += 1
                    frame = bytearray(item.frame)
                    _SEQ.pack_into(frame, _SEQ_OFFSET, self._seq % (1 << 32))
                    self.writer.write(frame)
                    batch_bytes += len(frame)
                    batch.append(item)
                self.last_tx = time.monotonic()
                async with asyncio.timeout(self.send_timeout_s):
                    await self.writer.drain()
                self.written += len(batch)
                for item in batch:
                    if item.done is not None and not item.done.done():
                        item.done.set_result(True)
                self._in_flight = None
        except TimeoutError:
            self.cut_off(f"socket did not drain within {self.send_timeout_s:g} s")
        except (OSError, ConnectionError, RuntimeError) as exc:
            self.cut_off(f"write failed: {exc}")
        finally:
            self._task = None
            if not self.open:
                self._fail_pending()

    def cut_off(self, reason: str) -> None:
        """Abort the transport and fail every waiting frame (idempotent)."""
        if not self.open:
            return
        self.open = False
        self.cut_off_reason = reason
        log.warning("send to %s failed: %s", self.identity, reason)
        with contextlib.suppress(Exception):  # aborted: a close would wait for the stuck bytes to drain
            self.writer.transport.abort()
        self._fail_pending()
        if self.on_cut_off is not None:
            self.on_cut_off(self, reason)

    def close(self) -> None:
        """The session ended for another reason: stop quietly, fail what is still waiting."""
        self.open = False
        self._fail_pending()

    def _fail_pending(self) -> None:
        for item in [*(self._in_flight or ()), *self._queue]:
            if item.done is not None and not item.done.done():
                item.done.set_result(False)
        self._in_flight = None
        self._queue.clear()
        self._queued_bytes = 0

    async def wait_closed(self, timeout: float = 2.0) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
            await asyncio.wait([self._task], timeout=timeout)


def _buffered(writer: asyncio.StreamWriter) -> int:
    with contextlib.suppress(Exception):
        return int(writer.transport.get_write_buffer_size())
    return 0


__all__ = ["MAX_QUEUED_FRAMES", "Outbox", "is_urgent"]
