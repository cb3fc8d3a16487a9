"""A served connection over real TCP (and TLS): every connection reads into the daemon's one shared
buffer, a partial frame is kept per connection, and no task runs for an idle session."""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

from gcs.core.daemon import Daemon
from protocol.packets import PerformActions, Position, StatusReport
from protocol.session import ClientHandshake
from protocol.stream import client_handshake
from tests.backbone.helpers import new_key, running_daemon
from tests.link.common import BIG_FENCE, stall_outbox
from tests.support.pki import make_pki
from tests.support.polling import wait_for
from tests.support.raw_client import RawClient

T0 = time.time()  # report times near the daemon's clock (it refuses others)


def _report(t: float) -> StatusReport:
    return StatusReport(
        time=T0 + t,
        position=Position(lat=47.3, lon=8.5 + t * 1e-6, alt_rel=10.0, alt_amsl=500.0),
        mode="GUIDED",
    )


async def _until(value: Callable[[], int], expected: int, what: str) -> None:
    """Wait (bounded) until ``value()`` is ``expected``."""
    await wait_for(lambda: value() == expected, 5.0, what)


async def _compact_client(
    daemon: Daemon, identity: str, key: str, tls: ssl.SSLContext | None = None
) -> RawClient:
    """A raw client through the shared client handshake that negotiated the compact status body."""
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", daemon.listen_port, ssl=tls, server_hostname="gcs" if tls else None
    )
    client = RawClient(reader, writer)
    handshake = ClientHandshake(identity, bytes.fromhex(key), compact_status=True)
    accepted = await client_handshake(client.stream, handshake, timeout=5.0)
    assert accepted.compact_status
    return client


async def _split_at_every_offset(daemon: Daemon, key: str, tls: ssl.SSLContext | None = None) -> None:
    """Client a's frames are cut at every byte offset, each cut a read of its own, with client b's
    whole frames read through the same shared buffer between the two halves."""
    a = await _compact_client(daemon, "split-a", key, tls)
    b = await _compact_client(daemon, "split-b", key, tls)
    try:
        await wait_for(lambda: daemon.agents.session("split-b") is not None, 5.0, "both sessions served")
        session_a, session_b = daemon.agents.session("split-a"), daemon.agents.session("split-b")
        assert session_a is not None and session_b is not None
        conn_a = daemon.agents.table.owners[session_a.row]
        length = len(a.stream.frame(_report(0.5)))  # every report below encodes to this length
        whole = a.stream.frame(_report(0.5))  # sent whole ahead of each cut frame, in the same write
        for cut in range(1, length):
            t = 1.0 + cut
            frame = a.stream.frame(_report(t))
            assert len(frame) == length
            before_a, before_b = session_a.status_count, session_b.status_count
            await a.send_raw(whole + frame[:cut])  # one complete frame and the start of the next
            await _until(lambda: conn_a.decoder.pending_bytes, cut, f"{cut} bytes kept for a")
            await b.send_raw(b.stream.frame(_report(-t)))  # a whole frame of b's, read in between
            await _until(lambda: session_b.status_count, before_b + 1, f"b's frame at cut {cut}")
            await a.send_raw(frame[cut:])
            await _until(lambda: session_a.status_count, before_a + 2, f"a's frames at cut {cut}")
            assert conn_a.decoder.pending_bytes == 0
            assert session_a.status == _report(t), f"a's report cut at byte {cut}"
            assert session_b.status == _report(-t), f"b's report beside a's cut at byte {cut}"
        assert session_a.open and session_b.open
        assert not daemon.events.history(kind="protocol_error")
    finally:
        a.close()
        b.close()


async def test_a_frame_cut_at_every_byte_offset_is_put_together_per_connection(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_frames_per_s=10_000.0, frame_burst=10_000) as daemon:
        await _split_at_every_offset(daemon, key)


async def test_the_shared_read_buffer_serves_tls_connections_too(tmp_path: Path) -> None:
    """asyncio's TLS transport hands a buffered protocol the decrypted bytes the same way."""
    pki = make_pki(tmp_path)
    key = new_key()
    tls = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki["ca"]))
    overrides = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"]}
    async with running_daemon(
        tmp_path, key, max_frames_per_s=10_000.0, frame_burst=10_000, **overrides
    ) as daemon:
        await _split_at_every_offset(daemon, key, tls)


async def test_mutual_tls_sessions_are_served_by_the_shared_buffer(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    key = new_key()
    tls = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(pki["ca"]))
    tls.load_cert_chain(pki["client_cert"], pki["client_key"])
    overrides = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"], "tls_client_ca": pki["ca"]}
    async with running_daemon(tmp_path, key, **overrides) as daemon:
        client = await _compact_client(daemon, "drone-1", key, tls)
        try:
            await client.send_raw(b"".join(client.stream.frame(_report(float(t))) for t in range(1, 6)))
            await wait_for(
                lambda: (s := daemon.agents.session("drone-1")) is not None and s.status_count == 5,
                5.0,
                "five reports over mutual TLS",
            )
            session = daemon.agents.session("drone-1")
            assert session is not None and session.status == _report(5.0)
        finally:
            client.close()


@contextlib.asynccontextmanager
async def deaf_peer(tmp_path: Path) -> AsyncIterator[tuple[Daemon, RawClient]]:
    """A daemon with a 1 s send timeout and a joined raw peer "deaf" that never reads."""
    key = new_key()
    # The raw peer sends no status: a long liveness limit keeps a loaded machine from losing it.
    async with running_daemon(tmp_path, key, send_timeout_s=1.0, lost_after_periods=400.0) as daemon:
        deaf = await RawClient.connect(daemon.listen_port)
        try:
            await deaf.handshake("deaf", key)
            await wait_for(lambda: daemon.agents.session("deaf") is not None, 5.0, "deaf joins")
            yield daemon, deaf
        finally:
            deaf.close()


async def test_an_idle_session_runs_no_task_and_a_stuck_peer_is_still_cut_off(tmp_path: Path) -> None:
    async with deaf_peer(tmp_path) as (daemon, _):
        session = daemon.agents.session("deaf")
        assert session is not None
        # Served and idle: the handshake task has ended and the outbox has no writer task.
        await wait_for(lambda: not daemon.agents._tasks, 5.0, "the handshake task ends")
        await wait_for(lambda: session.outbox._task is None, 5.0, "the writer task ends once idle")
        await stall_outbox(daemon, "deaf")  # it does not read: frames back up in its outbox
        assert session.outbox._task is not None, "a writer task while frames wait"
        stuck = asyncio.create_task(
            daemon.agents.send("deaf", PerformActions(mission_id="m", mode="pause", reason="x"))
        )
        assert await asyncio.wait_for(stuck, 10.0) is False
        await wait_for(lambda: daemon.agents.session("deaf") is None, 10.0, "the stuck peer is cut off")
        assert [e.agent for e in daemon.events.history(kind="agent_cut_off")] == ["deaf"]
        await wait_for(lambda: session.outbox._task is None, 5.0, "no writer task after the cut")
        await wait_for(lambda: not daemon.agents._tasks, 5.0, "the session's end has run")
        assert session.table is None, "its status row is free"


async def test_a_stuck_peer_that_only_gets_bursts_is_cut_off(tmp_path: Path) -> None:
    """Burst frames (barrier releases) are written past the queue; a peer that never drains them is
    cut off by the byte bound or the drain timeout, with no writer task while it was idle."""
    async with deaf_peer(tmp_path) as (daemon, _):
        for _ in range(2000):  # bounded: socket buffers fill long before
            if daemon.agents.session("deaf") is None:
                break
            daemon.agents.burst(["deaf"], BIG_FENCE)
            await asyncio.sleep(0.005)
        await wait_for(lambda: daemon.agents.session("deaf") is None, 10.0, "the stuck peer is cut off")
        assert [e.agent for e in daemon.events.history(kind="agent_cut_off")] == ["deaf"]


async def test_frames_pipelined_behind_the_proof_are_all_served(tmp_path: Path) -> None:
    """Hundreds of KiB sent with the proof, before the answer: the handshake's reader pauses the
    socket meanwhile; once the session is served every frame is ingested and reading resumes."""
    key = new_key()
    count = 2000  # ~300 KB: more than the handshake reader holds before it pauses the socket
    async with running_daemon(tmp_path, key, max_frames_per_s=10_000.0, frame_burst=10_000) as daemon:
        client = await RawClient.connect(daemon.listen_port)
        try:
            handshake = ClientHandshake("eager", bytes.fromhex(key), compact_status=True)
            await client.send(handshake.hello())
            challenge = await client.receive()
            assert challenge is not None
            proof = client.stream.frame(handshake.on_challenge(challenge.body))
            client.stream.compact_status = True  # offered; the answer will confirm it
            reports = b"".join(client.stream.frame(_report(float(t))) for t in range(1, count + 1))
            assert len(reports) > 256 << 10
            await client.send_raw(proof + reports)
            answer = await client.receive()
            assert answer is not None and handshake.on_answer(answer.body).compact_status
            await wait_for(
                lambda: (s := daemon.agents.session("eager")) is not None and s.status_count == count,
                10.0,
                f"all {count} pipelined reports",
            )
            session = daemon.agents.session("eager")
            assert session is not None and session.status == _report(float(count))
            await client.send_raw(client.stream.frame(_report(count + 1.0)))  # reading goes on
            await wait_for(lambda: session.status_count == count + 1, 5.0, "a report after them")
        finally:
            client.close()
