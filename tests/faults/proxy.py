"""A loopback TCP fault proxy that sits between agents and the daemon and acts at frame boundaries.

Why frame-aware: the faults we care about are the ones a real link produces to whole packets
(late, lost, out of order, a silent peer). Cutting frames in half would only test the decoder,
which the fuzzer already does. Bytes are split with the protocol's own header
(:data:`protocol.wire.HEADER`); a stream that is not fleetgcs framing (garbage, HTTP) is passed
through raw, so abuse tests can run through the proxy too.

Each proxied connection has two directions, ``up`` (client/agent -> daemon) and ``down``
(daemon -> agent). Per direction: a reader task splits frames and queues them (bounded queue:
back-pressure reaches the sender like a real socket), and a writer task delivers them at
``arrival + delay + jitter`` in order, unless a fault says otherwise.

Faults (change them at any time from the test, they apply to every connection):

* ``proxy.up.delay_s`` / ``jitter_s``: latency per frame (order kept, as TCP does);
* ``spike_rate`` / ``spike_s``: a frame (and, order kept, every frame queued behind it) is held
  ``spike_s`` longer, as TCP's retransmission of a lost segment does (head-of-line blocking);
* ``drop_rate`` (+ ``drop_types``): whole frames vanish (not TCP-faithful; status reports are
  idempotent, so the protocol must ride through lost ones);
* ``reorder_rate`` (+ ``reorder_types``): a frame is held back and sent after the next one (or
  alone after ``reorder_hold_s`` if no next frame comes);
* ``half_open(direction)``: that direction swallows frames, the connection stays open;
* ``partition(duration, mode)``: both directions at once. ``stall`` holds bytes and FINs and
  delivers them after healing (what TCP does across a real outage: the peer sees silence, not a
  close); ``blackhole`` discards them; ``reset`` aborts every connection (RST) and refuses new
  ones until the partition ends.

An on-path forger without the key: ``impersonate(script, ...)`` has the proxy itself answer the
next connections, one script each, instead of the daemon: a script is a list of answers, one per
frame the client sends (each answer a list of bodies), after which the connection is closed. Later
connections reach the daemon again.

Every loop is bounded in count (``MAX_READS``) and every wait in time (``max_stall_s``).
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Literal

from protocol.packets import Body
from protocol.wire import DEFAULT_MAX_BODY, HEADER, HEADER_SIZE, MAGIC, Frame, decode_one, encode

Direction = Literal["up", "down"]
PartitionMode = Literal["stall", "blackhole", "reset"]

RAW = -1  # packet type recorded for bytes that are not fleetgcs framing
MAX_READS = 10_000_000  # per direction and connection; a test never gets near it
READ_CHUNK = 65_536


@dataclass
class DirectionFaults:
    """What one direction does to the frames passing through it (mutable at any time)."""

    delay_s: float = 0.0
    jitter_s: float = 0.0
    spike_rate: float = 0.0  # fraction of frames held back by a retransmission timeout
    spike_s: float = 0.0  # how long such a frame is held (every later frame waits behind it)
    drop_rate: float = 0.0
    drop_types: frozenset[int] | None = None  # None: every type may be dropped
    reorder_rate: float = 0.0
    reorder_types: frozenset[int] | None = None  # None: every type may be held back
    reorder_hold_s: float = 0.05  # a held frame goes out alone if no next frame comes by then
    swallow: bool = False  # half-open: frames vanish, the connection stays open


@dataclass(frozen=True, slots=True)
class FrameRecord:
    """One frame seen by the proxy, and what the proxy did with it."""

    time: float
    connection: int
    direction: Direction
    packet_type: int
    seq: int
    size: int
    action: Literal["forwarded", "dropped", "swallowed", "injected"]
    raw: bytes

    def decode(self) -> Frame:
        """The decoded frame (raises ProtocolError for raw or corrupt bytes)."""
        return decode_one(self.raw)


class FrameSplitter:
    """Cuts a byte stream at fleetgcs frame boundaries; falls back to raw pass-through on non-framing."""

    def __init__(self, max_body: int = DEFAULT_MAX_BODY) -> None:
        self.max_body = max_body
        self.raw_mode = False
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[tuple[int, int, bytes]]:
        """Return ``(packet_type, seq, bytes)`` for every complete frame (or raw chunk) in ``data``."""
        if self.raw_mode:
            return [(RAW, 0, data)]
        self._buffer += data
        out: list[tuple[int, int, bytes]] = []
        for _ in range(len(self._buffer) // HEADER_SIZE + 1):  # at most one frame per header's worth
            buf = self._buffer
            if (len(buf) >= 2 and buf[:2] != MAGIC) or (len(buf) == 1 and buf[:1] != MAGIC[:1]):
                return self._go_raw(out)
            if len(buf) < HEADER_SIZE:
                break
            _, _, ptype, seq, length, _ = HEADER.unpack_from(buf)
            if length > self.max_body:
                return self._go_raw(out)
            end = HEADER_SIZE + length
            if len(buf) < end:
                break
            out.append((ptype & 0x7F, seq, bytes(buf[:end])))  # 0x82 (compact status) is type 2
            del buf[:end]
        return out

    def flush(self) -> bytes:
        """Bytes of an incomplete frame left at end of stream."""
        rest = bytes(self._buffer)
        self._buffer.clear()
        return rest

    def _go_raw(self, out: list[tuple[int, int, bytes]]) -> list[tuple[int, int, bytes]]:
        self.raw_mode = True
        if self._buffer:
            out.append((RAW, 0, bytes(self._buffer)))
            self._buffer.clear()
        return out


Script = list[list[Body]]  # per frame the client sends, the bodies the forger answers with
Queued = tuple[float, int, int, bytes]  # (arrival time, packet type, seq, bytes); None = end of stream


@dataclass(eq=False)
class ProxiedConnection:
    """One agent connection through the proxy: the client side and the upstream (daemon) side."""

    id: int
    client_writer: asyncio.StreamWriter
    upstream_writer: asyncio.StreamWriter
    tasks: list[asyncio.Task[None]] = field(default_factory=list)
    closed: bool = False

    def abort(self) -> None:
        """RST both sides (SO_LINGER 0 semantics via transport.abort)."""
        self.closed = True
        for writer in (self.client_writer, self.upstream_writer):
            with contextlib.suppress(Exception):
                writer.transport.abort()


class FaultProxy:
    """``async with FaultProxy(daemon_port) as proxy:`` then point agents at ``proxy.port``."""

    def __init__(
        self,
        upstream_port: int,
        upstream_host: str = "127.0.0.1",
        *,
        seed: int = 0,
        max_connections: int = 256,
        max_stall_s: float = 60.0,
        queue_frames: int = 1024,
        record_limit: int = 20_000,
    ) -> None:
        self.upstream = (upstream_host, upstream_port)
        self.up = DirectionFaults()
        self.down = DirectionFaults()
        self.max_connections = max_connections
        self.max_stall_s = max_stall_s
        self.queue_frames = queue_frames
        self.records: deque[FrameRecord] = deque(maxlen=record_limit)
        self.stats: Counter[str] = Counter()
        self.connections: dict[int, ProxiedConnection] = {}
        self._rng = random.Random(seed)
        self._server: asyncio.base_events.Server | None = None
        self._next_id = 0
        self._open = asyncio.Event()  # set = traffic flows; cleared during a stall partition
        self._open.set()
        self._partition: PartitionMode | None = None
        self._partition_timer: asyncio.TimerHandle | None = None
        self._handlers: set[asyncio.Task[None]] = set()
        self._scripts: deque[Script] = deque()
        self.port = 0

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self) -> FaultProxy:
        self._server = await asyncio.start_server(self._on_client, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def stop(self) -> None:
        if self._partition_timer is not None:
            self._partition_timer.cancel()
        self._open.set()
        if self._server is not None:
            self._server.close()
        for conn in list(self.connections.values()):
            conn.abort()
        tasks = [t for c in self.connections.values() for t in c.tasks] + list(self._handlers)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=2.0)
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)

    async def __aenter__(self) -> FaultProxy:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # --- controls -------------------------------------------------------------------------------

    def faults(self, direction: Direction) -> DirectionFaults:
        return self.up if direction == "up" else self.down

    def half_open(self, direction: Direction) -> None:
        """Stop forwarding ``direction`` (frames are swallowed); nothing is closed."""
        self.faults(direction).swallow = True

    def partition(self, duration_s: float, mode: PartitionMode = "stall") -> None:
        """Cut both directions of every connection for ``duration_s`` (then heal by itself)."""
        if self._partition_timer is not None:
            self._partition_timer.cancel()
        self._partition = mode
        self.stats[f"partition_{mode}"] += 1
        if mode == "stall":
            self._open.clear()
        elif mode == "reset":
            self.reset_all()
        self._partition_timer = asyncio.get_running_loop().call_later(duration_s, self.heal)

    async def partition_for(self, duration_s: float, mode: PartitionMode = "stall") -> None:
        """:meth:`partition` and wait until it has healed."""
        self.partition(duration_s, mode)
        await asyncio.sleep(duration_s + 0.01)

    @property
    def partitioned(self) -> bool:
        return self._partition is not None

    def heal(self) -> None:
        """End a partition and every half-open direction; latency/drop settings stay."""
        if self._partition_timer is not None:
            self._partition_timer.cancel()
            self._partition_timer = None
        self._partition = None
        self.up.swallow = self.down.swallow = False
        self._open.set()

    def reset_all(self) -> None:
        """Abort (RST) every current connection."""
        for conn in list(self.connections.values()):
            conn.abort()
        self.stats["resets"] += 1

    def impersonate(self, *scripts: Script) -> None:
        """The next ``len(scripts)`` connections are answered by the proxy (a forger), one script each."""
        self._scripts.extend(scripts)

    @property
    def forging(self) -> int:
        """Scripts not played yet."""
        return len(self._scripts)

    def inject(self, direction: Direction, data: bytes) -> int:
        """Write ``data`` into every open connection in ``direction`` (between frames); returns how many."""
        count = 0
        for conn in list(self.connections.values()):
            writer = conn.upstream_writer if direction == "up" else conn.client_writer
            if conn.closed or writer.is_closing():
                continue
            writer.write(data)
            self._record(conn.id, direction, RAW, 0, data, "injected")
            count += 1
        return count

    def frames(
        self, direction: Direction, packet_type: int | None = None, action: str = "forwarded"
    ) -> list[FrameRecord]:
        """Recorded frames of one direction (optionally one type) that met ``action``."""
        return [
            r
            for r in self.records
            if r.direction == direction
            and r.action == action
            and (packet_type is None or r.packet_type == packet_type)
        ]

    # --- plumbing -------------------------------------------------------------------------------

    def _record(self, conn: int, direction: Direction, ptype: int, seq: int, raw: bytes, action: str) -> None:
        self.stats[f"{direction}_{action}"] += 1
        self.records.append(
            FrameRecord(time.monotonic(), conn, direction, ptype, seq, len(raw), action, raw)  # type: ignore[arg-type]
        )

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._handlers.add(task)
        try:
            await self._serve_client(reader, writer)
        except asyncio.CancelledError:
            writer.transport.abort()  # proxy stopping; top of the task, so nothing else to unwind
        finally:
            if task is not None:
                self._handlers.discard(task)

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self._scripts:
            await self._forge(self._scripts.popleft(), reader, writer)
            return
        if self._partition == "reset" or len(self.connections) >= self.max_connections:
            self.stats["refused"] += 1
            writer.transport.abort()
            return
        if self._partition == "stall":  # like a SYN retried until the path is back
            try:
                await asyncio.wait_for(self._open.wait(), self.max_stall_s)
            except TimeoutError:
                writer.transport.abort()
                return
        try:
            up_reader, up_writer = await asyncio.wait_for(asyncio.open_connection(*self.upstream), 5.0)
        except (OSError, TimeoutError):
            self.stats["upstream_unreachable"] += 1
            writer.transport.abort()
            return
        self._next_id += 1
        conn = ProxiedConnection(self._next_id, writer, up_writer)
        self.connections[conn.id] = conn
        self.stats["connections"] += 1
        try:
            await asyncio.gather(
                self._direction(conn, "up", reader, up_writer),
                self._direction(conn, "down", up_reader, writer),
            )
        finally:
            conn.closed = True
            for w in (writer, up_writer):
                with contextlib.suppress(Exception):
                    w.close()
            self.connections.pop(conn.id, None)

    async def _forge(
        self, script: Script, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Answer the client with ``script`` (frame for frame), then close: the daemon never hears of it."""
        self._next_id += 1
        conn, splitter, seq = self._next_id, FrameSplitter(), 0
        self.stats["forged"] += 1
        try:
            for answer in script:
                for _ in range(64):  # reads until one whole frame from the client
                    frames = splitter.feed(await asyncio.wait_for(reader.read(READ_CHUNK), self.max_stall_s))
                    for ptype, fseq, raw in frames:
                        self._record(conn, "up", ptype, fseq, raw, "swallowed")
                    if frames:
                        break
                for body in answer:
                    seq += 1
                    data = encode(body, seq, 2)
                    writer.write(data)
                    self._record(conn, "down", data[3], seq, data, "injected")
                await asyncio.wait_for(writer.drain(), 5.0)
        except (ConnectionError, OSError, TimeoutError):
            pass
        finally:
            writer.close()

    async def _direction(
        self,
        conn: ProxiedConnection,
        direction: Direction,
        src: asyncio.StreamReader,
        dst: asyncio.StreamWriter,
    ) -> None:
        """One direction: a reader that splits frames and a writer that delivers them, faults applied."""
        queue: asyncio.Queue[Queued | None] = asyncio.Queue(self.queue_frames)
        reader_task = asyncio.create_task(self._read_side(conn, direction, src, queue))
        writer_task = asyncio.create_task(self._write_side(conn, direction, dst, queue))
        conn.tasks += [reader_task, writer_task]
        try:
            await asyncio.gather(reader_task, writer_task)
        except (ConnectionError, OSError, TimeoutError):
            conn.abort()
        finally:
            for task in (reader_task, writer_task):
                task.cancel()

    async def _read_side(
        self,
        conn: ProxiedConnection,
        direction: Direction,
        src: asyncio.StreamReader,
        queue: asyncio.Queue[Queued | None],
    ) -> None:
        splitter = FrameSplitter()
        try:
            for _ in range(MAX_READS):
                data = await src.read(READ_CHUNK)
                if not data:
                    break
                arrival = time.monotonic()
                for ptype, seq, raw in splitter.feed(data):
                    await queue.put((arrival, ptype, seq, raw))
            rest = splitter.flush()
            if rest:
                await queue.put((time.monotonic(), RAW, 0, rest))
        except (ConnectionError, OSError):
            conn.abort()
        await queue.put(None)

    async def _write_side(
        self,
        conn: ProxiedConnection,
        direction: Direction,
        dst: asyncio.StreamWriter,
        queue: asyncio.Queue[Queued | None],
    ) -> None:
        faults = self.faults(direction)
        held: tuple[int, int, bytes] | None = None
        last_due = 0.0
        for _ in range(MAX_READS):
            if held is None:
                item = await queue.get()
            else:
                try:
                    item = await asyncio.wait_for(queue.get(), faults.reorder_hold_s)
                except TimeoutError:
                    await self._deliver(conn, direction, dst, *held)
                    held = None
                    continue
            await self._wait_open(conn)
            if item is None:
                break
            arrival, ptype, seq, raw = item
            if faults.swallow or self._partition == "blackhole":
                self._record(conn.id, direction, ptype, seq, raw, "swallowed")
                continue
            eligible = faults.drop_types is None or ptype in faults.drop_types
            if eligible and faults.drop_rate > 0 and self._rng.random() < faults.drop_rate:
                self._record(conn.id, direction, ptype, seq, raw, "dropped")
                continue
            due = arrival + faults.delay_s + self._rng.uniform(0.0, faults.jitter_s)
            if faults.spike_rate > 0 and self._rng.random() < faults.spike_rate:
                due += faults.spike_s
                self.stats[f"{direction}_spiked"] += 1
            due = max(last_due, due)
            last_due = due
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            await self._wait_open(conn)
            reorderable = faults.reorder_types is None or ptype in faults.reorder_types
            if held is None and reorderable and self._rng.random() < faults.reorder_rate:
                held = (ptype, seq, raw)  # goes out right after the next frame
                continue
            await self._deliver(conn, direction, dst, ptype, seq, raw)
            if held is not None:
                await self._deliver(conn, direction, dst, *held)
                self.stats[f"{direction}_reordered"] += 1
                held = None
        if held is not None:
            await self._deliver(conn, direction, dst, *held)
        if not conn.closed and dst.can_write_eof():
            with contextlib.suppress(OSError, RuntimeError):
                dst.write_eof()  # half-close: the peer sees the same FIN the source sent

    async def _wait_open(self, conn: ProxiedConnection) -> None:
        if self._open.is_set():
            return
        try:
            await asyncio.wait_for(self._open.wait(), self.max_stall_s)
        except TimeoutError:
            conn.abort()
            raise ConnectionError("stalled longer than max_stall_s") from None

    async def _deliver(
        self,
        conn: ProxiedConnection,
        direction: Direction,
        dst: asyncio.StreamWriter,
        ptype: int,
        seq: int,
        raw: bytes,
    ) -> None:
        if conn.closed:
            raise ConnectionError("connection aborted")
        dst.write(raw)
        await asyncio.wait_for(dst.drain(), 10.0)
        self._record(conn.id, direction, ptype, seq, raw, "forwarded")
