"""The release burst's sends on two threads (gcs/link/send_pool.py), on real loopback TCP sockets:
each socket gets its own bytes exactly once, in a burst large enough for the helper thread; a
socket that fails or is full gives its result back instead of raising, and the thread stops."""

from __future__ import annotations

import contextlib
import socket

import pytest

from gcs.link.send_pool import POOL_MIN, SendPool

pytestmark = pytest.mark.timeout(60)


def _pairs(count: int) -> tuple[list[socket.socket], list[socket.socket]]:
    server = socket.create_server(("127.0.0.1", 0), backlog=count)
    try:
        far = [socket.create_connection(server.getsockname()) for _ in range(count)]
        near = [server.accept()[0] for _ in range(count)]
    finally:
        server.close()
    for sock in near:
        sock.setblocking(False)
    return near, far


def _read(sock: socket.socket, size: int, timeout: float = 5.0) -> bytes:
    sock.settimeout(timeout)
    data = b""
    for _ in range(100):  # bounded: a frame of a few bytes comes in one or two reads
        if len(data) >= size:
            break
        data += sock.recv(size - len(data))
    return data


def test_a_large_burst_reaches_every_socket_once() -> None:
    near, far = _pairs(POOL_MIN + 44)
    pool = SendPool()
    try:
        jobs = [(sock, bytearray(f"frame-{i:05d}".encode())) for i, sock in enumerate(near)]
        results = pool.send_all(jobs)
        assert results == [len(data) for _, data in jobs]
        assert pool._thread is not None and pool._thread.is_alive()  # the helper took part
        for i, sock in enumerate(far):
            assert _read(sock, 11) == f"frame-{i:05d}".encode()
            sock.setblocking(False)
            with pytest.raises(BlockingIOError):  # exactly once: nothing more behind it
                sock.recv(1)
    finally:
        pool.close()
        for sock in [*near, *far]:
            sock.close()
    assert pool._thread is None


def test_a_failed_or_full_socket_gives_its_result_back() -> None:
    near, far = _pairs(POOL_MIN)
    pool = SendPool()
    try:
        broken = near[3]
        broken.close()  # its send raises (bad descriptor): a result, not an exception
        full = near[7]
        full.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        for _ in range(10_000):  # fill its send buffer (the far end never reads)
            try:
                full.send(b"x" * 65_536)
            except BlockingIOError:
                break
        jobs = [(sock, bytearray(b"release")) for sock in near]
        results = pool.send_all(jobs)
        assert isinstance(results[3], OSError)
        taken = results[7]
        assert isinstance(taken, int) and 0 <= taken < 7  # the kernel took nothing (or a part)
        assert all(r == 7 for i, r in enumerate(results) if i not in (3, 7))
    finally:
        pool.close()
        for sock in [*near, *far]:
            with contextlib.suppress(OSError):
                sock.close()


def test_a_small_burst_runs_on_the_callers_thread() -> None:
    near, far = _pairs(8)
    pool = SendPool()
    try:
        assert pool.send_all([(sock, bytearray(b"go")) for sock in near]) == [2] * 8
        assert pool._thread is None  # no thread started
        assert all(_read(sock, 2) == b"go" for sock in far)
    finally:
        for sock in [*near, *far]:
            sock.close()


def test_a_burst_whose_jobs_are_taken_by_the_sending_thread() -> None:
    """``take_and_send``: each job is taken once, right before its send, by whichever thread sends
    it; a job ``take`` refuses (None) is not sent and comes back as None for the caller to send."""
    near, far = _pairs(POOL_MIN + 44)
    pool = SendPool()
    taken_by: dict[int, int] = {}

    def take(index: int, sock: socket.socket) -> tuple[socket.socket, bytearray] | None:
        assert index not in taken_by  # once
        taken_by[index] = 1
        return None if index % 5 == 0 else (sock, bytearray(f"frame-{index:05d}".encode()))

    try:
        jobs = list(enumerate(near))
        taken, results = pool.take_and_send(jobs, take)
        assert sorted(taken_by) == list(range(len(near)))
        for i, (job, result) in enumerate(zip(taken, results, strict=True)):
            if i % 5 == 0:
                assert job is None and result is None
            else:
                assert job is not None and job[0] is near[i] and result == 11
        for i, sock in enumerate(far):
            sock.setblocking(False)
            if i % 5 == 0:
                with pytest.raises(BlockingIOError):  # refused by take: nothing was sent
                    sock.recv(1)
            else:
                assert _read(sock, 11) == f"frame-{i:05d}".encode()
    finally:
        pool.close()
        for sock in [*near, *far]:
            sock.close()
