"""The floor under a barrier release on this machine: one small frame to N loopback sockets.

Run: python bench/bench_burst_floor.py [--agents 100 1000] [--rounds 40]

What the daemon's release cannot beat, measured the way ``bench_load.py`` measures the release:
N TCP connections on loopback, their far ends drained by two worker processes (as the load
bench's clients are), and per round one 60-byte frame written with a bare ``sock.send`` to every
near end in a tight loop, no asyncio, no protocol. The latency runs from just before the first
send to the kernel's receive timestamp (``SO_TIMESTAMPNS``) of the last frame, as the load bench
stamps a release. Printed beside the daemon's figures (``bench_load.py --only-barrier N``) it
says how much of a release is the daemon and how much is the kernel's loopback delivery.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import selectors
import socket
import struct
import time
from multiprocessing.connection import Connection

FRAME = b"\x00" * 60
TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SCM_TIMESTAMPNS = TIMESTAMPNS


def _drain(conn: Connection, port: int, count: int, rounds: int) -> None:
    """Connect ``count`` sockets; per round, the latest kernel receive time among them."""
    socks = []
    for _ in range(count):
        sock = socket.create_connection(("127.0.0.1", port))
        sock.setsockopt(socket.SOL_SOCKET, TIMESTAMPNS, 1)
        sock.setblocking(False)
        socks.append(sock)
    selector = selectors.DefaultSelector()
    for sock in socks:
        selector.register(sock, selectors.EVENT_READ)
    conn.send("connected")
    for _ in range(rounds):
        got, latest = 0, 0.0
        deadline = time.monotonic() + 10.0
        while got < count * len(FRAME) and time.monotonic() < deadline:
            for key, _ in selector.select(1.0):
                sock = key.fileobj
                assert isinstance(sock, socket.socket)
                try:
                    data, ancillary, _, _ = sock.recvmsg(4096, socket.CMSG_SPACE(16))
                except BlockingIOError:
                    continue
                got += len(data)
                for level, kind, payload in ancillary:
                    if level == socket.SOL_SOCKET and kind == SCM_TIMESTAMPNS:
                        seconds, nanos = struct.unpack("qq", payload[:16])
                        latest = max(latest, seconds + nanos / 1e9)
        conn.send(latest if got == count * len(FRAME) else None)
    for sock in socks:
        sock.close()


def floor(agents: int, rounds: int) -> dict[str, float]:
    """p50/p99 (ms) of first send -> last kernel receive over ``rounds`` bursts to ``agents`` sockets."""
    server = socket.create_server(("127.0.0.1", 0), backlog=agents)
    port = server.getsockname()[1]
    ctx = mp.get_context("spawn")
    pipes, workers = [], []
    for share in (agents // 2, agents - agents // 2):
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_drain, args=(child, port, share, rounds), daemon=True)
        proc.start()
        pipes.append(parent)
        workers.append(proc)
    near = [server.accept()[0] for _ in range(agents)]
    for sock in near:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
    try:
        for pipe in pipes:
            assert pipe.poll(60) and pipe.recv() == "connected"
        latencies: list[float] = []
        for _ in range(rounds):
            time.sleep(0.05)
            started = time.time()
            for sock in near:
                sock.send(FRAME)
            last = [pipe.recv() if pipe.poll(15) else None for pipe in pipes]
            if all(t is not None for t in last):
                latencies.append(max(t for t in last if t is not None) - started)
    finally:
        for sock in near:
            sock.close()
        server.close()
        for proc in workers:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
    latencies.sort()
    if not latencies:
        return {"p50_ms": float("nan"), "p99_ms": float("nan"), "rounds": 0}
    pick = lambda q: latencies[min(len(latencies) - 1, int(q * len(latencies)))] * 1000  # noqa: E731
    return {"p50_ms": pick(0.5), "p99_ms": pick(0.99), "rounds": len(latencies)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--rounds", type=int, default=40)
    args = parser.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)  # one descriptor per near-end socket
    wanted = max(args.agents) + 64
    if soft < wanted and (hard == resource.RLIM_INFINITY or hard >= wanted):
        resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
    print("bare sock.send burst, first send -> last kernel receive (two draining processes):")
    for n in args.agents:
        row = floor(n, args.rounds)
        print(
            f"  {n:>6} sockets  p50 {row['p50_ms']:6.2f} ms  p99 {row['p99_ms']:6.2f} ms"
            f"  ({row['rounds']} bursts)"
        )


if __name__ == "__main__":
    main()
