"""The fault proxy itself: each fault does what it says, at frame boundaries, and nothing else."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator

import pytest

from protocol.packets import Close, CloseReason, SyncSignal
from protocol.wire import FrameDecoder, encode
from tests.faults.proxy import RAW, FaultProxy, FrameSplitter
from tests.support.polling import wait_for


def sync(step: int) -> bytes:
    return encode(SyncSignal(mission_id="m", step=step, kind="finished"), step + 1)


class Sink:
    """Upstream that records every frame it receives (with arrival time) and can talk back."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int]] = []
        self.writers: list[asyncio.StreamWriter] = []
        self.eof = asyncio.Event()

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.writers.append(writer)
        decoder = FrameDecoder()
        for _ in range(10_000):
            try:
                data = await reader.read(65_536)
            except ConnectionError:
                break
            if not data:
                break
            for frame in decoder.feed(data):
                assert isinstance(frame.body, SyncSignal)
                self.frames.append((time.monotonic(), frame.body.step))
        self.eof.set()

    def steps(self) -> list[int]:
        return [s for _, s in self.frames]


@contextlib.asynccontextmanager
async def proxied(seed: int = 1) -> AsyncIterator[tuple[Sink, FaultProxy]]:
    sink = Sink()
    server = await asyncio.start_server(sink.handle, "127.0.0.1", 0)
    proxy = FaultProxy(server.sockets[0].getsockname()[1], seed=seed)
    await proxy.start()
    try:
        yield sink, proxy
    finally:
        await proxy.stop()
        server.close()


def test_splitter_cuts_at_frame_boundaries_and_passes_garbage_through() -> None:
    splitter = FrameSplitter()
    stream = sync(0) + sync(1) + sync(2)
    pieces = [stream[i : i + 7] for i in range(0, len(stream), 7)]  # frames split across reads
    frames = [f for piece in pieces for f in splitter.feed(piece)]
    assert [raw for _, _, raw in frames] == [sync(0), sync(1), sync(2)]
    assert [seq for _, seq, _ in frames] == [1, 2, 3]
    garbage = FrameSplitter()
    assert garbage.feed(b"GET / HTTP/1.1\r\n") == [(RAW, 0, b"GET / HTTP/1.1\r\n")]
    assert garbage.raw_mode


async def test_delay_and_jitter_keep_order() -> None:
    async with proxied() as (sink, proxy):
        proxy.up.delay_s, proxy.up.jitter_s = 0.15, 0.05
        _, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        sent_at = time.monotonic()
        writer.write(b"".join(sync(i) for i in range(20)))
        await wait_for(lambda: len(sink.frames) == 20, 3.0, "len(sink.frames) == 20", poll=0.01)
        assert sink.steps() == list(range(20))
        assert sink.frames[0][0] - sent_at >= 0.15
        writer.close()


async def test_drop_removes_whole_frames_of_the_chosen_type() -> None:
    async with proxied(seed=3) as (sink, proxy):
        proxy.up.drop_rate, proxy.up.drop_types = 0.5, frozenset({5})
        _, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(b"".join(sync(i) for i in range(100)))
        await wait_for(
            lambda: proxy.stats["up_dropped"] + len(sink.frames) == 100,
            3.0,
            'proxy.stats["up_dropped"] + len(sink.frames) == 100',
            poll=0.01,
        )
        assert 20 < proxy.stats["up_dropped"] < 80
        assert sink.steps() == sorted(sink.steps())  # survivors intact and in order
        writer.close()


async def test_reorder_swaps_neighbouring_frames() -> None:
    async with proxied(seed=5) as (sink, proxy):
        proxy.up.reorder_rate = 0.3
        _, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(b"".join(sync(i) for i in range(60)))
        await wait_for(lambda: len(sink.frames) == 60, 3.0, "len(sink.frames) == 60", poll=0.01)
        steps = sink.steps()
        assert sorted(steps) == list(range(60)) and steps != list(range(60))
        assert proxy.stats["up_reordered"] > 0
        writer.close()


async def test_half_open_swallows_one_direction_only() -> None:
    async with proxied() as (sink, proxy):
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        await wait_for(lambda: sink.writers, 3.0, "sink.writers", poll=0.01)
        proxy.half_open("up")
        writer.write(sync(1))
        sink.writers[0].write(encode(Close(reason=CloseReason.NORMAL), 1))
        decoder = FrameDecoder()
        data = await asyncio.wait_for(reader.read(65_536), 2.0)
        assert isinstance(next(iter(decoder.feed(data))).body, Close)  # down still flows
        await asyncio.sleep(0.1)
        assert sink.frames == [] and proxy.stats["up_swallowed"] == 1
        assert not writer.is_closing()  # nothing was closed
        proxy.heal()
        writer.write(sync(2))
        await wait_for(lambda: sink.steps() == [2], 3.0, "sink.steps() == [2]", poll=0.01)
        writer.close()


async def test_stall_partition_holds_bytes_and_delivers_them_after_healing() -> None:
    async with proxied() as (sink, proxy):
        _, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        await wait_for(lambda: sink.writers, 3.0, "sink.writers", poll=0.01)
        proxy.partition(0.3, "stall")
        started = time.monotonic()
        writer.write(sync(1) + sync(2))
        writer.write_eof()  # the FIN waits behind the data, as TCP would
        await wait_for(lambda: sink.eof.is_set(), 3.0, "sink.eof.is_set()", poll=0.01)
        assert sink.steps() == [1, 2]
        assert sink.frames[0][0] - started >= 0.29
        assert not proxy.partitioned


@pytest.mark.parametrize("mode", ["blackhole", "reset"])
async def test_blackhole_and_reset_partitions(mode: str) -> None:
    async with proxied() as (sink, proxy):
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        await wait_for(lambda: sink.writers, 3.0, "sink.writers", poll=0.01)
        proxy.partition(0.3, mode)  # type: ignore[arg-type]
        if mode == "reset":
            with contextlib.suppress(ConnectionError):
                assert await asyncio.wait_for(reader.read(10), 2.0) == b""
            _, refused_writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            await wait_for(lambda: proxy.stats["refused"] == 1, 3.0, 'proxy.stats["refused"] == 1', poll=0.01)
            refused_writer.close()
        else:
            writer.write(sync(1))
            await wait_for(
                lambda: proxy.stats["up_swallowed"] == 1, 3.0, 'proxy.stats["up_swallowed"] == 1', poll=0.01
            )
        await asyncio.sleep(0.35)
        _, again = await asyncio.open_connection("127.0.0.1", proxy.port)
        again.write(sync(7))
        await wait_for(lambda: 7 in sink.steps(), 3.0, "7 in sink.steps()", poll=0.01)
        assert 1 not in sink.steps()
        again.close()
        writer.close()
