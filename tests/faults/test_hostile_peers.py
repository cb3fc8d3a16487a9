"""Hostile and broken peers on both sides of the link while a real mission flies.

Daemon side: a garbage spewer, slow-loris clients and an authenticated flooder run at the same
time as a three-agent survey; the mission must complete and no honest agent may be dropped.
Agent side: corrupt frames injected by the fault proxy towards the agent must cost one
connection, never the agent process.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
import zlib
from pathlib import Path

from gcs.core.config import DaemonConfig
from protocol import auth
from protocol.packets import PROTOCOL_VERSION, Close, CloseReason, Position, RequestCid, StatusReport
from protocol.wire import FRAME_VERSION, HEADER, MAGIC, encode
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.faults.common import first_occurrences, record_releases, released_steps
from tests.faults.proxy import FaultProxy
from tests.support.polling import wait_for
from tests.support.raw_client import RawClient


def _status() -> StatusReport:
    return StatusReport(time=time.time(), position=Position(lat=47.0, lon=8.0, alt_rel=0.0, alt_amsl=400.0))


async def _drain_until_closed(client: RawClient, timeout: float) -> list[object]:
    """Everything the daemon sends until it closes (RST counts as closed); bounded in time and count."""
    bodies: list[object] = []
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(timeout):
            for _ in range(10_000):
                try:
                    frame = await client.receive(timeout)
                except ConnectionError:  # reset or broken pipe: closed all the same
                    return bodies
                if frame is None:
                    return bodies
                bodies.append(frame.body)
    raise AssertionError(f"still open after {timeout} s; got {bodies[-3:]}")


async def _garbage_spewer(port: int, rounds: int, rng: random.Random) -> int:
    """Connect, spew random bytes, expect a protocol_error close; returns how many were closed."""
    closed = 0
    for _ in range(rounds):
        client = await RawClient.connect(port)
        with contextlib.suppress(ConnectionError):
            await client.send_raw(b"X" + rng.randbytes(4095))  # never starts with the magic
        bodies = await _drain_until_closed(client, 3.0)
        if bodies:
            assert isinstance(bodies[-1], Close) and bodies[-1].reason == CloseReason.PROTOCOL_ERROR
        closed += 1
        client.close()
        await asyncio.sleep(0.05)
    return closed


async def _slow_loris(port: int, deadline_s: float) -> float:
    """Dribble a valid hello one byte per 100 ms; returns how long the daemon let it hang on."""
    hello = encode(
        RequestCid(identity="loris", protocol_version=PROTOCOL_VERSION, client_nonce=auth.new_nonce()), 1
    )
    client = await RawClient.connect(port)
    started = time.monotonic()
    for byte in hello[: int(deadline_s / 0.1)]:
        try:
            await client.send_raw(bytes([byte]))
        except ConnectionError:
            break
        if client.reader.at_eof():
            break
        await asyncio.sleep(0.1)
    bodies = await _drain_until_closed(client, deadline_s)
    assert bodies == [] or isinstance(bodies[-1], Close)
    client.close()
    return time.monotonic() - started


async def _flooder(port: int, key: str, seconds: float) -> tuple[int, list[object]]:
    """Authenticated agent sending status as fast as the socket takes it; returns (frames, replies)."""
    client = await RawClient.connect(port)
    await client.handshake("flooder", key)
    frame = encode(_status(), 3)
    chunk = frame * 50
    sent = 0
    replies: list[object] = []

    async def read_replies() -> None:
        for _ in range(10_000):
            try:
                got = await client.receive(seconds + 5)
            except ConnectionError:
                return
            if got is None:
                return
            replies.append(got.body)

    reader = asyncio.create_task(read_replies())
    stop_at = time.monotonic() + seconds
    try:
        while time.monotonic() < stop_at and not reader.done():
            client.writer.write(chunk)
            await asyncio.wait_for(client.writer.drain(), 5)
            sent += 50
    except (ConnectionError, TimeoutError):
        pass
    with contextlib.suppress(TimeoutError, ConnectionError):
        await asyncio.wait_for(reader, 5)
    client.close()
    return sent, replies


async def test_garbage_slow_loris_and_flood_while_a_mission_flies(tmp_path: Path) -> None:
    key = new_key()
    names = ["honest-1", "honest-2", "honest-3"]
    async with running_daemon(tmp_path, key, handshake_timeout_s=1.0) as daemon:
        agents = [start_agent(n, daemon.listen_port, key, i, speedup=4) for i, n in enumerate(names)]
        releases = [record_releases(a) for a in agents]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 3, 10, "three agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))
            garbage, lorises, flood = await asyncio.gather(
                _garbage_spewer(daemon.listen_port, 15, random.Random(11)),
                asyncio.gather(*(_slow_loris(daemon.listen_port, 4.0) for _ in range(8))),
                _flooder(daemon.listen_port, key, 3.0),
            )
            await wait_for(lambda: mission_id not in daemon.missions.active, 40, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
            assert released_steps(daemon, mission_id) == [0, 1, 2, 3]
            for seen in releases:
                assert first_occurrences(seen) == [0, 1, 2, 3]
            # Honest agents were never dropped, lost or cut off.
            for kind in ("agent_lost", "agent_disconnected", "agent_cut_off"):
                assert not [e for e in daemon.events.history(kind=kind) if e.agent in names], kind
            assert all(daemon.agents.session(n) is not None for n in names)
            assert garbage == 15
            assert all(held < 1.0 + 1.0 for held in lorises), lorises  # cut at the handshake timeout
            assert len(daemon.events.history(kind="handshake_timeout")) >= 8
            sent, replies = flood
            if "max_frames_per_s" in DaemonConfig.model_fields:
                cut = daemon.events.history(kind="agent_cut_off")
                assert [e.agent for e in cut] == ["flooder"] and "frames/s" in cut[0].message
                # The flooder reads while it writes and stops once the daemon closes, so the type-6
                # close arrives before any reset could overtake it.
                assert replies and isinstance(replies[-1], Close), replies[-3:]
                assert replies[-1].reason == CloseReason.PROTOCOL_ERROR and "frames/s" in replies[-1].message
                assert sent >= DaemonConfig().frame_burst
        finally:
            await stop_agents(agents)


async def test_byte_dribbler_counts_as_silent(tmp_path: Path) -> None:
    """docs/protocol.md: an agent with no *packet* for lost_after_s is lost. Bytes are not packets."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:  # lost after 1.0 s
        client = await RawClient.connect(daemon.listen_port)
        await client.handshake("dribbler", key)
        frame = encode(_status(), 3)
        with contextlib.suppress(ConnectionError):
            for byte in frame[:40]:  # 40 bytes over 2 s: no packet is ever completed
                await client.send_raw(bytes([byte]))
                await asyncio.sleep(0.05)
        assert daemon.events.history(kind="agent_lost", agent="dribbler")
        client.close()


async def _agent_through_proxy_gets(tmp_path: Path, poison: bytes) -> None:
    """Inject ``poison`` towards a flying agent; it must drop that connection, reconnect and finish."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        running = start_agent("target", proxy.port, key, speedup=4)
        try:
            await wait_for(lambda: daemon.agents.session("target") is not None, 10, "agent joins")
            mission_id = await daemon.missions.submit(survey_mission(["target"], sync_legs=3))
            await wait_for(lambda: running.agent.queue.current_step >= 1, 20, "flying")
            assert proxy.inject("down", poison) == 1
            await wait_for(lambda: running.agent.link.sessions >= 2, 5, "agent reconnects")
            assert not running.task.done(), running.task
            await wait_for(lambda: mission_id not in daemon.missions.active, 30, "mission end")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
        finally:
            await stop_agents([running])


async def test_agent_survives_a_corrupt_frame_from_the_link(tmp_path: Path) -> None:
    frame = bytearray(encode(Close(reason=CloseReason.NORMAL, message="x"), 99))
    frame[-1] ^= 0xFF  # CRC mismatch
    await _agent_through_proxy_gets(tmp_path, bytes(frame))


async def test_agent_survives_a_frame_with_a_huge_integer(tmp_path: Path) -> None:
    body = b'{"parameters":{"status_period_s":' + b"1" * 5000 + b"}}"
    poison = HEADER.pack(MAGIC, FRAME_VERSION, 3, 99, len(body), zlib.crc32(body)) + body
    await _agent_through_proxy_gets(tmp_path, poison)
