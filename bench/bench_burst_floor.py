"""The floor under a barrier release on this machine: one small frame to N loopback sockets.

Run: python bench/bench_burst_floor.py [--agents 100 1000] [--rounds 40]

What the daemon's release cannot beat, measured the way ``bench_load.py`` measures the release,
for both ways a release travels:

* **TCP**: N TCP connections on loopback, their far ends drained by two worker processes (as the
  load bench's clients are), and per round one 60-byte frame written with a bare ``sock.send`` to
  every near end in a tight loop, no asyncio, no protocol. The latency runs from just before the
  first send to the kernel's receive timestamp (``SO_TIMESTAMPNS``) of the last frame, as the load
  bench stamps a release.
* **broadcast** (the release beacon, protocol/beacon.py): N UDP sockets bound to the loopback
  broadcast address and one port (``SO_REUSEADDR``), split between the two processes, and per
  round one 60-byte ``sendto`` to that address. The kernel stamps a broadcast once, before it
  clones it to every socket, so the stamp under-reports the fan-out; on loopback the clones are
  made inside the ``sendto``, so the latency is to the later of the last stamp and the return of
  the ``sendto`` (printed apart too), as the load bench takes a beacon's arrival.

Printed beside the daemon's figures (``bench_load.py --only-barrier N``) it says how much of a
release is the daemon and how much is the kernel's loopback delivery.
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

from gcs.link.beacon import LOOPBACK_BROADCAST, free_udp_port

FRAME = b"\x00" * 60
TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
SCM_TIMESTAMPNS = TIMESTAMPNS


def _open(kind: str, port: int, count: int) -> list[socket.socket]:
    """``count`` receiving sockets: TCP connections to ``port``, or UDP sockets on the broadcast port."""
    socks = []
    for _ in range(count):
        if kind == "tcp":
            sock = socket.create_connection(("127.0.0.1", port))
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((LOOPBACK_BROADCAST, port))
        sock.setsockopt(socket.SOL_SOCKET, TIMESTAMPNS, 1)
        sock.setblocking(False)
        socks.append(sock)
    return socks


def _drain(conn: Connection, kind: str, port: int, count: int, rounds: int) -> None:
    """Open ``count`` sockets; per round, the latest kernel receive time among them."""
    socks = _open(kind, port, count)
    selector = selectors.DefaultSelector()
    for sock in socks:
        selector.register(sock, selectors.EVENT_READ)
    conn.send("connected")
    for _ in range(rounds):
        got, latest = 0, 0.0
        deadline = time.monotonic() + 10.0
        while got < count * len(FRAME) and time.monotonic() < deadline:
            for key, _ in selector.select(1.0):
                ready = key.fileobj
                assert isinstance(ready, socket.socket)
                try:
                    data, ancillary, _, _ = ready.recvmsg(4096, socket.CMSG_SPACE(16))
                except BlockingIOError:
                    continue
                got += len(data)
                for level, kind_, payload in ancillary:
                    if level == socket.SOL_SOCKET and kind_ == SCM_TIMESTAMPNS:
                        seconds, nanos = struct.unpack("qq", payload[:16])
                        latest = max(latest, seconds + nanos / 1e9)
        conn.send(latest if got == count * len(FRAME) else None)
    for sock in socks:
        sock.close()


def _percentiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    if not ordered:
        return {"p50_ms": float("nan"), "p99_ms": float("nan")}
    pick = lambda q: ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1000  # noqa: E731
    return {"p50_ms": pick(0.5), "p99_ms": pick(0.99)}


def floor(agents: int, rounds: int, kind: str = "tcp") -> dict[str, float]:
    """p50/p99 (ms) of first send -> last arrival over ``rounds`` bursts to ``agents`` sockets.

    ``kind`` "tcp": one ``send`` per socket; "broadcast": one ``sendto`` for all (arrival = the
    later of the last kernel stamp and the ``sendto``'s return; ``sendto_*`` and ``stamp_*`` apart).
    """
    server: socket.socket | None = None
    sender: socket.socket | None = None
    near: list[socket.socket] = []
    if kind == "tcp":
        server = socket.create_server(("127.0.0.1", 0), backlog=agents)
        port = server.getsockname()[1]
    else:
        sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sender.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        port = free_udp_port()  # a port free for this run
    ctx = mp.get_context("spawn")
    pipes, workers = [], []
    for share in (agents // 2, agents - agents // 2):
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_drain, args=(child, kind, port, share, rounds), daemon=True)
        proc.start()
        pipes.append(parent)
        workers.append(proc)
    if server is not None:
        near = [server.accept()[0] for _ in range(agents)]
        for sock in near:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
    latencies: list[float] = []
    sendtos: list[float] = []
    stamps: list[float] = []
    try:
        for pipe in pipes:
            assert pipe.poll(60) and pipe.recv() == "connected"
        for _ in range(rounds):
            time.sleep(0.05)
            started = time.time()
            if sender is not None:
                sender.sendto(FRAME, (LOOPBACK_BROADCAST, port))
            else:
                for sock in near:
                    sock.send(FRAME)
            returned = time.time()
            last = [pipe.recv() if pipe.poll(15) else None for pipe in pipes]
            if all(t is not None for t in last):
                stamp = max(t for t in last if t is not None)
                if sender is not None:
                    sendtos.append(returned - started)
                    stamps.append(stamp - started)
                    stamp = max(stamp, returned)
                latencies.append(stamp - started)
    finally:
        for sock in near:
            sock.close()
        for owned in (server, sender):
            if owned is not None:
                owned.close()
        for proc in workers:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
    row = {**_percentiles(latencies), "rounds": len(latencies)}
    if sender is not None:
        row.update({f"sendto_{k}": v for k, v in _percentiles(sendtos).items()})
        row.update({f"stamp_{k}": v for k, v in _percentiles(stamps).items()})
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[100, 1000])
    parser.add_argument("--rounds", type=int, default=40)
    args = parser.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)  # one descriptor per near-end socket
    wanted = max(args.agents) + 64
    if soft < wanted and (hard == resource.RLIM_INFINITY or hard >= wanted):
        resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
    print("first send -> last arrival (two receiving processes):")
    for n in args.agents:
        tcp = floor(n, args.rounds, "tcp")
        print(
            f"  {n:>6} sockets  TCP, a bare sock.send each        p50 {tcp['p50_ms']:6.2f} ms  "
            f"p99 {tcp['p99_ms']:6.2f} ms  ({tcp['rounds']} bursts)",
            flush=True,
        )
        udp = floor(n, args.rounds, "broadcast")
        print(
            f"  {n:>6} sockets  one broadcast sendto for all     p50 {udp['p50_ms']:6.2f} ms  "
            f"p99 {udp['p99_ms']:6.2f} ms  ({udp['rounds']} datagrams; the sendto p50 "
            f"{udp['sendto_p50_ms']:.3f} ms p99 {udp['sendto_p99_ms']:.3f} ms; the kernel's stamp alone "
            f"p50 {udp['stamp_p50_ms']:.3f} ms p99 {udp['stamp_p99_ms']:.3f} ms)",
            flush=True,
        )


if __name__ == "__main__":
    main()
