"""Load benchmark: how big a fleet one daemon carries on this machine, and what an agent costs.

Run: python bench/bench_load.py [--quick]
Prints a table; writes bench/results/load.json. About 3-4 minutes on 2 cores.

Set-up, all on loopback: the daemon (an in-process ``gcs.core.daemon.Daemon``, with its SQLite store
and telemetry recorder, as ``gcs serve`` runs it) lives in its own process. Synthetic agents are
lightweight protocol clients (real handshake, then pre-templated status frames; no simulator)
hosted many per process in worker processes, so client cost does not land on the daemon's core.

Measured:

* **fleet search**: status at 10 Hz from N agents for a few seconds; a size passes with zero loss
  (every frame sent was ingested, no agent dropped) and p99 ingest latency (agent timestamp to the
  report written into the daemon's status table) under 50 ms; the latency to a status hook
  (behind the status tick and the hook queues) is printed beside it. Doubling, then bisection.
* **sync barrier**: N agents (streaming status at 10 Hz) all send ``finished`` for a step; latency
  from the daemon receiving the last arrival to the last agent receiving its release (and the part
  inside the daemon: to the release burst written to every socket). Two modes, paired barrier by
  barrier in one fleet: with the release beacon (protocol/beacon.py: one UDP broadcast on the
  loopback broadcast address, then the TCP burst; each agent listens on its own UDP socket, acts
  on a beacon only when the mission's hash chain proves it, and is released by whichever comes
  first) and TCP only (``--no-beacon``: TCP only, without the beacon barriers). A beacon's
  arrival is the later of its kernel receive stamp and the return of the daemon's ``sendto``:
  the kernel stamps a broadcast once, before cloning it to every socket, and on loopback the
  clones are made inside that ``sendto`` (see ``barrier_trial``).
* **memory per agent**: daemon RSS delta over the fleet trial divided by N.
* **throughput vs bare asyncio**: the same pre-encoded status frames flooded by the same clients
  into (a) a bare asyncio sink that only splits frames by header, (b) asyncio plus the full
  ``FrameDecoder`` (CRC, a decoded report per frame), (c) the daemon (frames written into its
  status table, its ingest counter). Ratio = daemon / bare.
* **agent footprint**: one ``agent run`` process at 10 Hz status with one vehicle (memory backend;
  MAVLink backend against ``sitl run`` too): RSS and CPU share. By default this venv's ``agent``;
  ``--agent-bin DIR`` another install's, e.g. the agent-only venv ``bench/agent_venv.sh`` builds
  from the wheel (as a companion computer has it: byte-compiled, no ground station).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import json
import multiprocessing as mp
import os
import platform
import random
import resource
import secrets
import socket
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from array import array
from collections.abc import Sequence
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from protocol.beacon import ReleaseVerifier

RESULTS = Path(__file__).resolve().parent / "results"
BIN = Path(sys.executable).parent
RUSAGE_THREAD = getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)  # Linux: this thread alone
P99_LIMIT_MS = 50.0
STATUS_HZ = 10.0
DAEMON_OVERRIDES: dict[str, Any] = {}  # DaemonConfig fields from --daemon-config (JSON)
PROFILE: dict[str, str | None] = {"path": None}  # --profile: cProfile the daemon over a fleet trial
CLIENT = {"compact": True}  # synthetic agents offer (and then send) the compact status body; --json: v1


# --- /proc helpers --------------------------------------------------------------------------------


def rss_kb(pid: int | str = "self") -> int:
    """Resident set size of a process in KiB (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def percentile(values: Sequence[float], p: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(p * len(ordered)))]


# --- the server process: daemon, or a bare asyncio sink ------------------------------------------


def server_main(
    kind: str, conn: Connection, key_hex: str, extra: dict[str, Any], profile: str | None = None
) -> None:
    """Entry point of the server process; answers commands on ``conn`` until 'stop'."""
    import logging

    slow_ms = os.environ.get("BENCH_SLOW_CALLBACK_MS")  # diagnosis: log every loop stall longer than this
    if slow_ms:
        logging.basicConfig(level=logging.WARNING)
        for name in ("gcs", "fleetgcs"):
            logging.getLogger(name).setLevel(logging.CRITICAL)
    else:
        logging.disable(logging.CRITICAL)  # per-agent events would flood stderr; the numbers are the output
    asyncio.run(_server(kind, conn, key_hex, extra, profile), debug=bool(slow_ms))


async def _server(
    kind: str, conn: Connection, key_hex: str, extra: dict[str, Any], profile: str | None = None
) -> None:
    import cProfile
    import gc

    gc_pauses: dict[int, list[float]] = {0: [], 1: [], 2: []}
    gc_started = [0.0]
    gc_runs: list[tuple[float, float]] = []  # (wall start, seconds) of the newest collections

    def gc_watch(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            gc_started[0] = time.perf_counter()
        else:
            took = time.perf_counter() - gc_started[0]
            gc_pauses[info["generation"]].append(took)
            gc_runs.append((time.time() - took, took))
            del gc_runs[:-1000]

    gc.callbacks.append(gc_watch)
    if os.environ.get("BENCH_TRACEMALLOC"):  # diagnosis: where the daemon's memory goes (slow)
        import tracemalloc

        tracemalloc.start(int(os.environ["BENCH_TRACEMALLOC"]))
    if os.environ.get("BENCH_GC"):  # diagnosis: e.g. "freeze" or "off"
        import gc

        gc.freeze()
        if os.environ["BENCH_GC"] == "off":
            gc.disable()
        if os.environ["BENCH_GC"] == "threshold":
            gc.set_threshold(2000, 10, 1_000_000)
    if os.environ.get("BENCH_SLOW_CALLBACK_MS"):
        asyncio.get_running_loop().slow_callback_duration = float(os.environ["BENCH_SLOW_CALLBACK_MS"]) / 1000
    from gcs.core.config import DaemonConfig
    from gcs.core.daemon import Daemon

    if os.environ.get("BENCH_STEP_BUDGET_S"):  # diagnosis: the hook consumers' time slice
        import gcs.link.dispatch

        gcs.link.dispatch.STEP_BUDGET_S = float(os.environ["BENCH_STEP_BUDGET_S"])
    if os.environ.get("BENCH_STATUS_TICK_S"):  # diagnosis: the status tick
        import importlib

        try:  # the status tick is a part of its own since issue 24 (gcs/link/status_tick.py)
            tick_module = importlib.import_module("gcs.link.status_tick")
        except ImportError:
            tick_module = importlib.import_module("gcs.link.agents")
        tick_module.STATUS_TICK_S = float(os.environ["BENCH_STATUS_TICK_S"])
    if os.environ.get("BENCH_POOL_MIN"):  # diagnosis: from how many sockets a burst takes two threads
        import gcs.link.send_pool as send_pool

        send_pool.POOL_MIN = int(os.environ["BENCH_POOL_MIN"])
    from protocol.taskfile import TaskFile
    from protocol.wire import HEADER, HEADER_SIZE, FrameDecoder

    probe: Any = None
    released: dict[int, float] = {}  # step -> when the daemon's release burst was written
    burst_started: dict[int, float] = {}  # step -> when the release burst began
    burst_cpu: dict[int, tuple[float, int, int]] = {}  # step -> the loop thread in the burst: CPU
    # time (thread_time), then its voluntary (it waited: the GIL, a lock) and involuntary
    # (preempted) context switches
    completed: dict[int, float] = {}  # step -> when the mission runner found the barrier complete
    # step -> (sendto began, returned, sent, the thread's CPU seconds in it: the rest it was off the CPU)
    beacon_sent: dict[int, tuple[float, float, bool, float]] = {}
    beacon_sender: Any = None  # the daemon's gcs.link.beacon.BeaconSender (release_beacon configured)
    release_parts: dict[int, list[float]] = {}  # step -> [row began, row done, event began, event done]
    # Arrays of doubles, not lists of floats: this process's RSS is the daemon's memory figure, and a
    # list costs 32 B per report (2-3 KiB per agent over a trial), an array 8.
    latencies = array("d")  # agent timestamp -> written into the daemon's status table
    hook_latencies = array("d")  # agent timestamp -> a status hook (behind the status tick)
    arrivals: dict[int, float] = {}
    counter = {"frames": 0}
    daemon: Daemon | None = None
    server: asyncio.base_events.Server | None = None
    data_dir = tempfile.TemporaryDirectory()

    release_path = ["new"]
    if kind == "daemon":
        overrides: dict[str, Any] = {}
        if "max_frames_per_s" in DaemonConfig.model_fields:  # the flood trial must not be rate limited
            overrides.update(max_frames_per_s=1e9, frame_burst=1_000_000_000)
        if "enroll_burst" in DaemonConfig.model_fields:  # every bench client connects from 127.0.0.1
            overrides.update(max_handshakes_per_source=64, enroll_burst=1_000_000)
        overrides.update(extra)  # --daemon-config, e.g. to switch a service off and see what it costs
        if "release_beacon" not in DaemonConfig.model_fields:  # a tree before the beacon: TCP only
            overrides.pop("release_beacon", None)
        settings: dict[str, Any] = dict(
            listen_port=0,
            http_host=None,  # {"http_host": "127.0.0.1", "http_port": 0} turns the API (and live hub) on
            data_dir=Path(data_dir.name),
            fleet_key_hex=key_hex,
            max_agents=20_000,
            status_period_s=1.0 / STATUS_HZ,
            lost_after_periods=600,
            handshake_timeout_s=60,
        )
        settings.update(overrides)
        config = DaemonConfig(**settings)
        daemon = Daemon(config)

        async def on_tick(tick: Any) -> None:  # the newest report of each agent, as columns
            hook_latencies.extend((time.time() - tick.cols["time"]).tolist())

        from protocol.packets import StatusReport, SyncSignal

        # The frame handling: the manager's frame ingest (gcs/link/ingest.py) since issue 24, the
        # manager itself before (paired trials against an older tree).
        frames = getattr(daemon.agents, "frames", None)
        handle_owner, handle_name = (daemon.agents, "_handle") if frames is None else (frames, "handle")
        handle = getattr(handle_owner, handle_name)
        unpack_time = struct.Struct("<d").unpack_from

        def stamp_ingest(payload: bytes) -> None:  # every compact report the ingest writes into the table
            latencies.append(time.time() - unpack_time(payload, 4)[0])

        probe = stamp_ingest

        def handle_and_stamp(session: Any, frame: Any) -> None:
            if isinstance(frame.body, SyncSignal):  # stamped as the frame loop gets it, before any hook
                arrivals[frame.body.step] = time.time()  # the last one wins: the barrier's last arrival
            elif isinstance(frame.body, StatusReport):  # the decoded path (JSON clients)
                latencies.append(time.time() - frame.body.time)
            handle(session, frame)

        # The "release_path" command picks the TCP burst of the next releases ("old": before issue 29).
        bursts = {"new": daemon.agents.burst, "old": _legacy_burst(daemon.agents)}

        def burst_and_stamp(identities: list[str], body: Any) -> int:
            usage = resource.getrusage(RUSAGE_THREAD)
            started, cpu = time.time(), time.thread_time()
            is_release = isinstance(body, SyncSignal) and body.kind == "release"
            sent = bursts[release_path[0] if is_release else "new"](identities, body)
            if isinstance(body, SyncSignal) and body.kind == "release":
                released[body.step] = time.time()  # every member's socket written
                after = resource.getrusage(RUSAGE_THREAD)
                burst_cpu[body.step] = (  # wall time beyond the CPU time: off the CPU
                    time.thread_time() - cpu,
                    after.ru_nvcsw - usage.ru_nvcsw,
                    after.ru_nivcsw - usage.ru_nivcsw,
                )
                burst_started[body.step] = started
            return sent

        # The release part of the runner (gcs/missions/releases.py, split out in issue 24), or the
        # runner itself in older trees (paired trials): its own calls look the method up on it.
        releases = getattr(daemon.missions, "_releases", None)
        if releases is not None or hasattr(daemon.missions, "_release_now"):
            name = "release_now" if releases is not None else "_release_now"
            owner = releases if releases is not None else daemon.missions
            release = getattr(owner, name)

            def release_and_stamp(mission: Any, step: int) -> None:
                completed.setdefault(step, time.time())
                release(mission, step)

            setattr(owner, name, release_and_stamp)
            if os.environ.get("BENCH_RELEASE_PARTS"):  # diagnosis: where storing a release goes
                _stamp_release_parts(daemon.missions, release_parts)
        else:  # the code before issue 16's round 4 (paired trials against an older tree)
            release_async = daemon.missions._release

            async def release_async_and_stamp(mission: Any, step: int) -> None:
                completed.setdefault(step, time.time())
                await release_async(mission, step)

            daemon.missions._release = release_async_and_stamp  # type: ignore[method-assign]
        setattr(handle_owner, handle_name, handle_and_stamp)
        daemon.agents.burst = burst_and_stamp  # type: ignore[method-assign]
        daemon.agents.ingest_probe = probe
        daemon.agents.on_status_tick.append(on_tick)
        await daemon.start()
        port = daemon.listen_port
        beacon_sender = getattr(daemon.missions, "beacon", None)
        if beacon_sender is not None:
            send_beacon = beacon_sender.send

            def send_beacon_and_stamp(mission_id: str, step: int, value: bytes) -> bool:
                started, cpu = time.time(), time.thread_time()
                sent = bool(send_beacon(mission_id, step, value))
                # Returned: the loopback fan-out is done (and the readers it woke may have run).
                beacon_sent[step] = (started, time.time(), sent, time.thread_time() - cpu)
                return sent

            beacon_sender.send = send_beacon_and_stamp
    else:

        async def sink(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            decoder = FrameDecoder()
            buffer = bytearray()
            for _ in range(100_000_000):
                data = await reader.read(65_536)
                if not data:
                    break
                if kind == "decode":
                    counter["frames"] += sum(1 for _ in decoder.feed(data))
                    continue
                buffer += data
                offset = 0
                while len(buffer) - offset >= HEADER_SIZE:
                    length = HEADER.unpack_from(buffer, offset)[4]
                    if len(buffer) - offset < HEADER_SIZE + length:
                        break
                    offset += HEADER_SIZE + length
                    counter["frames"] += 1
                del buffer[:offset]
            writer.close()

        server = await asyncio.start_server(sink, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]

    loop = asyncio.get_running_loop()
    baseline: Any = None
    if os.environ.get("BENCH_TRACEMALLOC"):
        import tracemalloc

        baseline = tracemalloc.take_snapshot()
    objects_before = _object_counts() if os.environ.get("BENCH_OBJECTS") else None
    maps_before = _rss_by_mapping() if os.environ.get("BENCH_SMAPS") else None
    conn.send(("ready", port, rss_kb()))
    cpu_mark = time.process_time()
    profiler = cProfile.Profile() if profile else None
    marks: dict[str, float] = {}
    for _ in range(1_000_000):
        command, *args = await loop.run_in_executor(None, conn.recv)
        if command == "reset":  # (latency=True): False = count ingested frames only (flood trial)
            counter["latency"] = int(args[0]) if args else 1
            counter["rss_at_reset_kb"] = rss_kb()  # every agent connected, none reporting yet
            if daemon is not None:
                daemon.agents.ingest_probe = probe if counter["latency"] else None
                counter["ingest0"] = daemon.agents.ingest_frames
            for pauses in gc_pauses.values():
                pauses.clear()
            del latencies[:]
            del hook_latencies[:]
            counter["frames"] = 0
            cpu_mark = time.process_time()
            marks = _service_marks(daemon)
            if profiler is not None:
                profiler.enable()
            conn.send("ok")
        elif command == "stats":
            if os.environ.get("BENCH_TRACEMALLOC"):
                import tracemalloc

                group = os.environ.get("BENCH_TRACEMALLOC_BY", "lineno")
                top = tracemalloc.take_snapshot().compare_to(baseline, group)[
                    : int(os.environ.get("BENCH_TRACEMALLOC_TOP", "30"))
                ]
                print("\n".join(str(stat) for stat in top), file=sys.stderr, flush=True)
                grown = sum(
                    stat.size_diff for stat in tracemalloc.take_snapshot().compare_to(baseline, group)
                )
                print(
                    f"traced memory grew by {grown / 1024:.0f} KiB since ready", file=sys.stderr, flush=True
                )
            if objects_before is not None:  # diagnosis: live objects per type per agent, since ready
                agents = max(1, len(daemon.agents.sessions) if daemon else 1)
                counts, sizes = _object_counts()
                counts.subtract(objects_before[0])
                sizes.subtract(objects_before[1])
                lines = [
                    f"{sizes[name] / agents:8.0f} B {n / agents:7.2f}  {name}"
                    for name, n in counts.most_common(60)
                    if n > 0
                ]
                total = sum(sizes.values()) / agents
                print(
                    f"objects per agent ({total:.0f} B, shallow sizes of GC-tracked objects):\n"
                    + "\n".join(sorted(lines, reverse=True)),
                    file=sys.stderr,
                    flush=True,
                )
            if maps_before is not None:  # diagnosis: which mappings the RSS grew in (heap, anonymous, files)
                grown_maps = _rss_by_mapping()
                grown_maps.subtract(maps_before)
                print(
                    f"RSS growth by mapping (KiB): {dict(grown_maps.most_common(8))}",
                    file=sys.stderr,
                    flush=True,
                )
            if os.environ.get("BENCH_MALLOCSTATS"):  # diagnosis: pymalloc's arenas, used and free bytes
                sys._debugmallocstats()  # to stderr
            if os.environ.get("BENCH_TRIM"):  # diagnosis: how much of the RSS is memory malloc keeps free
                import ctypes

                before = rss_kb()
                ctypes.CDLL("libc.so.6").malloc_trim(0)
                print(f"malloc_trim: RSS {before} -> {rss_kb()} KiB", file=sys.stderr, flush=True)
            if profiler is not None and profile:
                profiler.disable()
                profiler.dump_stats(profile)
            if daemon is None:
                received = counter["frames"]
            elif counter["latency"]:
                received = len(latencies)
            else:  # the bench's own per-frame stamp is off: the daemon's ingest counter
                received = daemon.agents.ingest_frames - counter["ingest0"]
            connected = len(daemon.agents.connected()) if daemon else 0
            conn.send(
                {
                    "services_us": _service_costs(daemon, marks),
                    "events": _event_kinds(daemon),
                    "gc_pauses": {
                        f"gen{g}": f"{len(p)} max {max(p, default=0) * 1000:.1f} ms"
                        for g, p in gc_pauses.items()
                    },
                    "received": received,
                    "hook_seen": len(hook_latencies),
                    "p50_ms": percentile(latencies, 0.50) * 1000,
                    "p99_ms": percentile(latencies, 0.99) * 1000,
                    "max_ms": max(latencies, default=float("nan")) * 1000,
                    "hook_p50_ms": percentile(hook_latencies, 0.50) * 1000,
                    "hook_p99_ms": percentile(hook_latencies, 0.99) * 1000,
                    "connected": connected,
                    "rss_kb": rss_kb(),
                    "rss_at_reset_kb": counter.get("rss_at_reset_kb", 0),
                    "cpu_s": time.process_time() - cpu_mark,
                }
            )
        elif command == "submit":
            assert daemon is not None
            mission_id = await daemon.missions.submit(TaskFile.model_validate_json(args[0]))
            conn.send(mission_id)
        elif command == "events":
            conn.send(_event_kinds(daemon))
        elif command == "arrival":
            step = args[0]
            begin, end = arrivals.get(step), released.get(step)
            in_release = (  # collections that ran between the last arrival and the burst's end
                sum(took for at, took in gc_runs if at + took >= begin and at <= end)
                if begin is not None and end is not None
                else 0.0
            )
            conn.send(
                (
                    begin,
                    completed.get(step),
                    burst_started.get(step),
                    end,
                    in_release,
                    beacon_sent.get(step),
                    burst_cpu.get(step),
                )
            )
        elif command == "parts":  # BENCH_RELEASE_PARTS: step -> barrier complete -> first send, in parts
            parts = {}
            for step, (row_at, row_done, event_at, event_done) in release_parts.items():
                mark = beacon_sent.get(step)
                first_send = mark[0] if mark is not None else burst_started.get(step)
                if step in completed and first_send is not None:
                    parts[step] = (
                        row_at - completed[step],  # gc off, the write lock (the telemetry writer's row)
                        row_done - row_at,  # the release row
                        event_done - event_at,  # the event (its row, the subscribers)
                        first_send - event_done,  # the commit, and to the first send
                    )
            conn.send(parts)
        elif command == "release_path":  # ("new" | "old"): the TCP burst the next releases take
            if daemon is not None:
                release_path[0] = args[0]
            conn.send(release_path[0] if daemon is not None else None)
        elif command == "http":  # the API's port and token (http_host set in the daemon's overrides)
            if profiler is not None:  # --only-rtl --profile: the fleet RTLs that follow
                profiler.enable()
            conn.send((daemon.http_port, daemon.api_token) if daemon is not None else (None, None))
        elif command == "beacon":  # (on): the release beacon for the next releases, or TCP only
            if daemon is not None and beacon_sender is not None:
                # None is the runner's own "not configured" path; the mission keeps its chain.
                daemon.missions.beacon = beacon_sender if args[0] else None
            conn.send(beacon_sender is not None)
        elif command == "stop":
            if profiler is not None and profile:
                profiler.disable()
                profiler.dump_stats(profile)
            break
    stop_note = "clean"
    if daemon is not None and beacon_sender is not None:
        daemon.missions.beacon = beacon_sender  # switched off for a TCP-only step: the daemon closes it
    if daemon is not None:
        try:  # bounded: a stuck service must not hang the benchmark (see docs/performance.md)
            await asyncio.wait_for(daemon.stop(), 10.0)
        except TimeoutError:
            stop_note = "daemon.stop() timed out"
    if server is not None:
        server.close()
    data_dir.cleanup()
    conn.send(stop_note)


def _legacy_burst(manager: Any) -> Any:
    """The TCP release burst as it was before issue 29 (``AgentManager.burst`` and
    ``Outbox.write_now`` at 66afb5f), kept here so one run pairs it barrier by barrier with the
    daemon's current burst (``--no-old-release`` leaves it out)."""
    from gcs.link.outbox import _SEQ, _SEQ_OFFSET
    from protocol.packets import packet_type_of
    from protocol.wire import encode

    def write_now(box: Any, frame: bytes, ptype: int, now: float) -> bool:
        if not box.open:
            return False
        if box._queue:
            return bool(box._enqueue_frame(type(box._queue[0])(frame, ptype, False)))
        transport = box.writer.transport
        try:
            waiting = transport.get_write_buffer_size()
            if len(frame) + waiting > box.max_pending_bytes:
                box.cut_off(f"more than {box.max_pending_bytes} bytes waiting for a peer that does not read")
                return False
            box._seq += 1
            out = bytearray(frame)
            _SEQ.pack_into(out, _SEQ_OFFSET, box._seq % (1 << 32))
            sent = 0
            sock = box._sock
            if sock is not None and not waiting and not transport.is_closing():
                try:
                    sent = sock.send(out)
                except (BlockingIOError, InterruptedError):
                    sent = 0
            if sent < len(out):
                transport.write(out[sent:] if sent else out)
                if transport.get_write_buffer_size():
                    box._drain_due = True
                    box._wake()
        except (OSError, RuntimeError, AttributeError) as exc:
            box.cut_off(f"write failed: {exc}")
            return False
        box.last_tx = now
        box.written += 1
        return True

    def burst(identities: list[str], body: Any) -> int:
        frames: dict[int, bytes] = {}
        ptype = packet_type_of(body)
        sent = 0
        now = time.monotonic()
        for identity in identities:
            session = manager.session(identity)
            if session is None:
                continue
            if identity in manager.remote:
                sent += session.post(body)
                continue
            frame = frames.get(session.version)
            if frame is None:
                frame = frames[session.version] = encode(body, 0, session.version)
            if write_now(session.outbox, frame, ptype, now):
                sent += 1
        return sent

    return burst


def _stamp_release_parts(missions: Any, parts: dict[int, list[float]]) -> None:
    """Time the writes inside a release (``BENCH_RELEASE_PARTS=1``): the row and the event."""
    core = getattr(missions, "_core", None)  # the runner's shared core (issue 24), or older trees' runner
    store, events = (core.store, core.events) if core is not None else (missions._store, missions._events)
    record, publish = store.record_release, events.publish

    def record_and_stamp(mission_id: str, step: int) -> None:
        began = time.time()
        record(mission_id, step)
        parts[step] = [began, time.time()]

    def publish_and_stamp(kind: str, *args: Any, **kwargs: Any) -> Any:
        began = time.time()
        event = publish(kind, *args, **kwargs)
        step = (kwargs.get("data") or {}).get("step")
        if kind == "sync_released" and step in parts:
            parts[step] += [began, time.time()]
        return event

    store.record_release = record_and_stamp
    events.publish = publish_and_stamp


def _object_counts() -> tuple[collections.Counter[str], collections.Counter[str]]:
    """Live objects the collector tracks, and their shallow bytes, per type (``BENCH_OBJECTS=1``)."""
    import gc

    gc.unfreeze()  # frozen objects are not listed (the daemon freezes a large fleet's heap)
    gc.collect()
    counts: collections.Counter[str] = collections.Counter()
    sizes: collections.Counter[str] = collections.Counter()
    for o in gc.get_objects():
        name = type(o).__qualname__
        counts[name] += 1
        sizes[name] += sys.getsizeof(o)
    return counts, sizes


def _rss_by_mapping() -> collections.Counter[str]:
    """This process's RSS in KiB per kind of mapping (``BENCH_SMAPS=1``): [heap], anonymous by size, files."""
    rss: collections.Counter[str] = collections.Counter()
    name = "?"
    for line in Path("/proc/self/smaps").read_text().splitlines():
        fields = line.split()
        if "-" in fields[0] and len(fields) >= 5:  # a mapping's header line
            start, end = (int(x, 16) for x in fields[0].split("-"))
            size = (end - start) >> 10
            kind = "1MiB (pymalloc arena)" if size == 1024 else ">1MiB" if size > 1024 else "<1MiB"
            name = fields[5] if len(fields) > 5 else f"anon {kind}"
            if name.startswith("/"):
                name = "files"
        elif fields[0] == "Rss:":
            rss[name] += int(fields[1])
    return rss


def _service_marks(daemon: Any) -> dict[str, float]:
    """Busy seconds and event counts so far: ingest (decode + record) and each hook consumer."""
    if daemon is None:
        return {}
    marks = {
        "ingest": daemon.agents.ingest_busy_s,
        "ingest#": float(daemon.agents.ingest_frames),
        "status tick": daemon.agents.tick_busy_s,
    }
    for s in daemon.agents.hook_stats():
        marks[s.name], marks[s.name + "#"] = s.busy_s, float(s.delivered)
    return marks


def _event_kinds(daemon: Any) -> dict[str, int]:
    """How many events of each kind the daemon logged (what its services decided during the trial)."""
    if daemon is None:
        return {}
    kinds: dict[str, int] = {}
    for event in daemon.events.history(limit=100_000):
        kinds[event.kind] = kinds.get(event.kind, 0) + 1
    return kinds


def _service_costs(daemon: Any, marks: dict[str, float]) -> dict[str, float]:
    """Microseconds of event-loop time per status report, per service, since ``marks``."""
    now = _service_marks(daemon)
    reports = max(1.0, now.get("ingest#", 0.0) - marks.get("ingest#", 0.0))
    return {
        name: round((busy - marks.get(name, 0.0)) * 1e6 / reports, 2)
        for name, busy in now.items()
        if not name.endswith("#")
    }


# --- worker processes: many synthetic agents each -------------------------------------------------


GRID_M = 40.0  # synthetic vehicles hover on a grid this far apart (a real fleet is not stacked on one point)


class StatusTemplate:
    """A real type-2 body serialised once; each frame only splices in a fresh timestamp.

    ``compact``: the binary body (protocol/status_binary.py, time at body offset 4), else JSON.
    """

    def __init__(self, index: int = 0, compact: bool = False) -> None:
        from protocol import status_binary
        from protocol.geo import offset_latlon
        from protocol.packets import Battery, Gps, Position, StatusReport

        lat, lon = offset_latlon(47.397742, 8.545594, GRID_M * (index // 50), GRID_M * (index % 50))
        report = StatusReport(
            time=0.0,
            position=Position(lat=lat, lon=lon, alt_rel=12.3, alt_amsl=500.3),
            battery=Battery(pct=87.5, voltage_v=12.1, current_a=14.2),
            gps=Gps(fix=3, satellites=14),  # a healthy fleet: without a fix the emergency monitor returns it
            mode="GUIDED",
            armed=True,
            landed=False,
        )
        self.compact = compact
        if compact:
            self.binary = bytearray(status_binary.encode(report))
            return
        body = report.model_dump_json(exclude_none=True)
        head, tail = body.split('"time":0.0', 1)
        self.head, self.tail = (head + '"time":').encode(), tail.encode()

    def frame(self, seq: int, now: float) -> bytes:
        from protocol.wire import HEADER, MAGIC, STATUS_COMPACT

        if self.compact:
            _TIME.pack_into(self.binary, 4, now)
            body = bytes(self.binary)
            ptype = STATUS_COMPACT
        else:
            body = self.head + repr(now).encode() + self.tail
            ptype = 2
        return HEADER.pack(MAGIC, 1, ptype, seq & 0xFFFFFFFF, len(body), zlib.crc32(body)) + body


_TIME = struct.Struct("<d")


class Client:
    """One synthetic agent: a socket, a sequence counter and the releases it received.

    With ``beacon_port`` it also listens for release beacons (protocol/beacon.py) on its own UDP
    socket bound to the loopback broadcast address, as an agent does on its LAN, and offers
    ``release_beacon`` in the handshake; it accepts a beacon only when the mission's
    :class:`~protocol.beacon.ReleaseVerifier` (from the anchor in the mission's type-4 frames)
    proves it.
    """

    def __init__(self, identity: str, index: int, compact: bool, beacon_port: int | None = None) -> None:
        self.identity = identity
        self.template = StatusTemplate(index, compact)
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.stream: Any = None  # protocol.stream.FramedStream once the handshake is done
        self.seq = 0
        self.sent = 0
        self.closed = False
        self.releases: dict[int, float] = {}  # step -> kernel receive time of its TCP release
        self.beacons: dict[int, float] = {}  # step -> kernel receive time of its verified beacon
        self.beacon_read: dict[int, float] = {}  # step -> when this process read that beacon
        self.read_at: dict[int, float] = {}  # step -> when this process first read either
        self.release_event = asyncio.Event()
        self.order_at: float | None = None  # kernel receive time of the newest fleet return order (type 4)
        self.order_event = asyncio.Event()
        self.verifiers: dict[str, ReleaseVerifier] = {}  # mission id -> its chain's check
        self.rejected = 0  # datagrams on the beacon port that were not a verified, new release
        self.udp = _beacon_socket(beacon_port) if beacon_port is not None else None

    def write(self, frame: bytes) -> None:
        assert self.writer is not None
        self.seq += 1
        self.writer.write(frame)


def worker_main(
    conn: Connection,
    port: int,
    key_hex: str,
    identities: list[str],
    authenticate: bool,
    compact: bool,
    beacon_port: int | None = None,
) -> None:
    asyncio.run(_worker(conn, port, key_hex, identities, authenticate, compact, beacon_port))


async def _handshake(client: Client, key: bytes) -> None:
    """The shared client handshake (protocol/session.py over protocol/stream.py)."""
    from protocol.session import ClientHandshake
    from protocol.stream import client_handshake

    stream = client.stream
    hello = ClientHandshake(
        client.identity, key, compact_status=client.template.compact, release_beacon=client.udp is not None
    )
    accepted = await client_handshake(stream, hello, timeout=60.0)
    assert accepted.compact_status == client.template.compact, accepted
    client.seq = stream.seq


SO_TIMESTAMPNS = 35  # Linux SO_TIMESTAMPNS(_OLD): the kernel stamps each received segment (CLOCK_REALTIME)
CMSG_SPACE_16 = socket.CMSG_SPACE(16)  # room for one timespec
BEACON_HOST = "127.255.255.255"  # loopback broadcast: one datagram reaches every socket bound to it


def _kernel_stamp(ancillary: list[tuple[int, int, bytes]], default: float) -> float:
    """The ``SO_TIMESTAMPNS`` receive time in a ``recvmsg`` answer (CLOCK_REALTIME), else ``default``."""
    for level, kind, value in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(value) >= 16:
            seconds, nanos = struct.unpack_from("qq", value)
            return float(seconds + nanos * 1e-9)
    return default


def _beacon_socket(port: int) -> socket.socket:
    """The agent's own beacon socket (agent/beacon.py: ``SO_REUSEADDR`` on the loopback broadcast
    address, so every agent of the host gets its copy), with ``SO_TIMESTAMPNS`` to stamp arrivals
    as the TCP path does."""
    from agent.beacon import beacon_socket

    try:
        sock = beacon_socket((BEACON_HOST, port))
    except OSError as exc:
        raise RuntimeError(f"cannot listen for beacons on {BEACON_HOST}:{port}: {exc}") from None
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    return sock


def read_beacons(client: Client) -> None:
    """Read what waits on the client's beacon socket; a release counts only when its chain proves it.

    Non-blocking and bounded (64 datagrams a call). The stamp kept is the kernel's receive time;
    see :func:`barrier_trial` for why the orchestrator also takes the daemon's ``sendto`` return.
    """
    from protocol.beacon import MAX_BEACON_BYTES, BeaconError, decode_beacon

    sock = client.udp
    if sock is None:
        return
    space = CMSG_SPACE_16
    for _ in range(64):
        try:
            data, ancillary, _flags, _addr = sock.recvmsg(MAX_BEACON_BYTES + 1, space)
        except OSError:  # nothing more waiting (BlockingIOError), or the socket is closed
            return
        read = time.time()
        try:
            beacon = decode_beacon(data)
        except BeaconError:
            client.rejected += 1
            continue
        verifier = client.verifiers.get(beacon.mission_id)
        if verifier is None or not verifier.accept(beacon.step, beacon.value):
            client.rejected += 1  # a forgery, a replay, or a mission this agent has no anchor of
            continue
        client.beacons.setdefault(beacon.step, _kernel_stamp(ancillary, read))
        client.beacon_read.setdefault(beacon.step, read)
        client.read_at.setdefault(beacon.step, read)
        client.release_event.set()


async def _client_reader(client: Client) -> None:
    """Drain what the daemon sends; note releases and closes.

    A release is stamped twice: when the kernel put its bytes into this agent's socket (the
    ``SO_TIMESTAMPNS`` receive timestamp, CLOCK_REALTIME like the daemon's ``time.time()``), and
    when this process got round to reading them. One worker process hosts hundreds of agents, so
    the second stamp also counts the worker's own queue of sockets to read (a real fleet has one
    agent per machine); the first is when the release reached the agent. Reading goes through
    ``recvmsg`` on a duplicate of the socket (the transport's own reading is paused).
    """
    from gcs.cooperation.returns import RETURN_PREFIX
    from protocol.beacon import ReleaseVerifier
    from protocol.packets import Close, PerformActions, SyncSignal
    from protocol.wire import ProtocolError

    stream = client.stream
    assert stream is not None and client.writer is not None
    transport = client.writer.transport
    loop = asyncio.get_running_loop()
    ended = loop.create_future()

    def note(frames: Any, kernel: float, read: float) -> None:
        for frame in frames:
            body = frame.body
            if isinstance(body, SyncSignal) and body.kind == "release":
                client.releases.setdefault(body.step, kernel)
                client.read_at.setdefault(body.step, read)
                client.release_event.set()
            elif (
                isinstance(body, PerformActions)
                and body.release_anchor
                and body.mission_id not in client.verifiers
            ):
                client.verifiers[body.mission_id] = ReleaseVerifier(bytes.fromhex(body.release_anchor))
            elif isinstance(body, PerformActions) and body.mission_id.startswith(RETURN_PREFIX):
                if client.order_at is None:  # the fleet RTL's order (reset by the orchestrator)
                    client.order_at = kernel
                    client.order_event.set()
            elif isinstance(body, Close):
                client.closed = True

    now = time.time()
    note(list(stream.backlog), now, now)
    stream.backlog.clear()
    transport.pause_reading()  # type: ignore[attr-defined]  # a socket transport: it reads too
    buffered: bytearray = stream.reader._buffer  # read before the pause
    if buffered:
        leftover = bytes(buffered)
        buffered.clear()
        note(list(stream.decoder.feed(leftover)), now, now)
    raw = socket.socket(fileno=os.dup(transport.get_extra_info("socket").fileno()))
    raw.setblocking(False)
    raw.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    space = CMSG_SPACE_16

    def readable() -> None:
        try:
            data, ancillary, _flags, _addr = raw.recvmsg(65_536, space)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data, ancillary = b"", []
        read = time.time()
        if not data:
            if not ended.done():
                ended.set_result(None)
            return
        try:
            note(list(stream.decoder.feed(data)), _kernel_stamp(ancillary, read), read)
        except ProtocolError:
            if not ended.done():
                ended.set_result(None)

    loop.add_reader(raw.fileno(), readable)
    try:
        await ended
    finally:
        loop.remove_reader(raw.fileno())
        raw.close()
        client.closed = True


async def _worker(
    conn: Connection,
    port: int,
    key_hex: str,
    identities: list[str],
    authenticate: bool,
    compact: bool,
    beacon_port: int | None = None,
) -> None:
    from protocol.packets import SyncSignal
    from protocol.stream import FramedStream
    from protocol.wire import encode

    key = bytes.fromhex(key_hex)
    clients = [Client(name, int(name.rsplit("-", 1)[1]), compact, beacon_port) for name in identities]
    loop = asyncio.get_running_loop()
    for c in clients:  # beacons are read as they come, in this loop, like the TCP releases
        if c.udp is not None:
            loop.add_reader(c.udp.fileno(), read_beacons, c)
    status_task: asyncio.Future[Any] | None = None
    cpu_mark = time.process_time()
    readers: list[asyncio.Task[None]] = []
    gate = asyncio.Semaphore(32)

    async def connect(client: Client) -> bool:
        from protocol.session import Refused

        async with gate:
            for attempt in range(20):  # a `busy` refusal (too many handshakes at once) is retried
                try:
                    client.reader, client.writer = await asyncio.open_connection("127.0.0.1", port)
                    client.stream = FramedStream(client.reader, client.writer)
                    if authenticate:
                        await asyncio.wait_for(_handshake(client, key), 60)
                except Refused as exc:
                    if exc.action != "retry" or attempt == 19:
                        client.closed = True
                        return False
                    await asyncio.sleep(0.2 + random.random() * 0.5)
                    continue
                except Exception:  # timed out, reset: this one client is lost, the bench goes on
                    client.closed = True
                    return False
                readers.append(asyncio.create_task(_client_reader(client)))
                return True
            return False

    async def status_loop(client: Client, period: float, stop_at: float) -> None:
        next_at = time.monotonic() + random.random() * period
        for _ in range(10_000_000):
            await asyncio.sleep(max(0.0, next_at - time.monotonic()))
            if time.monotonic() >= stop_at or client.closed:
                return
            client.write(client.template.frame(client.seq + 1, time.time()))
            client.sent += 1
            next_at += period

    async def flood(client: Client, stop_at: float) -> None:
        chunk = b"".join(client.template.frame(i, time.time()) for i in range(20))
        assert client.writer is not None
        with contextlib.suppress(ConnectionError, TimeoutError):
            for _ in range(100_000_000):
                if time.monotonic() >= stop_at or client.closed:
                    return
                client.writer.write(chunk)
                client.sent += 20
                await asyncio.wait_for(client.writer.drain(), 10)

    for _ in range(1_000_000):
        command, *args = await loop.run_in_executor(None, conn.recv)
        if command == "connect":
            results = await asyncio.gather(*(connect(c) for c in clients))
            conn.send(sum(results))
        elif command == "status":  # (rate_hz, seconds): runs in the background; 'sent' collects
            rate, seconds = args
            cpu_mark = time.process_time()
            for c in clients:
                c.sent = 0
            stop_at = time.monotonic() + seconds
            status_task = asyncio.ensure_future(
                asyncio.gather(*(status_loop(c, 1.0 / rate, stop_at) for c in clients))
            )
            conn.send("started")
        elif command == "sent":
            if status_task is not None:
                await status_task
            conn.send(
                {
                    "sent": sum(c.sent for c in clients),
                    "closed": sum(c.closed for c in clients),
                    "cpu_s": time.process_time() - cpu_mark,
                }
            )
        elif command == "flood":
            for c in clients:
                c.sent = 0
            stop_at = time.monotonic() + args[0]
            await asyncio.gather(*(flood(c, stop_at) for c in clients))
            conn.send({"sent": sum(c.sent for c in clients), "closed": sum(c.closed for c in clients)})
        elif command == "finish":  # (mission_id, step, timeout): all send 'finished', wait for releases
            mission_id, step, timeout = args
            for c in clients:
                c.write(encode(SyncSignal(mission_id=mission_id, step=step, kind="finished"), c.seq + 1))
            deadline = time.monotonic() + timeout
            for c in clients:  # the TCP release always comes (a beacon only ever comes first)
                while step not in c.releases and time.monotonic() < deadline and not c.closed:
                    c.release_event.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(c.release_event.wait(), max(0.01, deadline - time.monotonic()))
            for c in clients:  # a beacon in a socket not yet read still counts at its kernel stamp
                read_beacons(c)
            conn.send(
                [
                    (c.releases.get(step), c.read_at.get(step), c.beacons.get(step), c.beacon_read.get(step))
                    for c in clients
                ]
            )
        elif command == "orders_reset":  # before a fleet RTL: forget the previous one's orders
            for c in clients:
                c.order_at = None
                c.order_event.clear()
            conn.send("ok")
        elif command == "orders":  # (timeout): wait for every client's fleet RTL order; their stamps
            deadline = time.monotonic() + args[0]
            for c in clients:
                while c.order_at is None and time.monotonic() < deadline and not c.closed:
                    c.order_event.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(c.order_event.wait(), max(0.01, deadline - time.monotonic()))
            conn.send([c.order_at for c in clients])
        elif command == "rejected":  # datagrams on the beacon port not taken as a release
            conn.send(sum(c.rejected for c in clients))
        elif command == "close":
            if status_task is not None:
                for c in clients:
                    c.closed = True  # status loops end at their next tick
                with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                    await asyncio.wait_for(status_task, 2.0)
            for c in clients:
                if c.writer is not None:
                    c.writer.transport.abort()  # RST: a flood backlog in the server's buffers is discarded
                if c.udp is not None:
                    loop.remove_reader(c.udp.fileno())
                    c.udp.close()
            for task in readers:
                task.cancel()
            conn.send("closed")
            return


# --- orchestration --------------------------------------------------------------------------------


class Harness:
    """One server process and ``workers`` client processes hosting ``agents`` clients between them.

    ``beacon_port``: the daemon sends release beacons to the loopback broadcast address on this
    UDP port, and every client listens there and offers ``release_beacon``.
    """

    def __init__(
        self,
        kind: str,
        agents: int,
        workers: int = 2,
        authenticate: bool = True,
        beacon_port: int | None = None,
        overrides: dict[str, Any] | None = None,
    ) -> None:
        self.ctx = mp.get_context("spawn")
        self.key_hex = secrets.token_hex(32)
        self.kind, self.agents = kind, agents
        self.server_conn, child = self.ctx.Pipe()
        extra = {**DAEMON_OVERRIDES, **(overrides or {})}
        if beacon_port is not None:
            extra["release_beacon"] = f"{BEACON_HOST}:{beacon_port}"
        self.server = self.ctx.Process(
            target=server_main,
            args=(kind, child, self.key_hex, extra, PROFILE["path"]),
            daemon=True,
        )
        self.server.start()
        child.close()  # a server that dies then ends recv() with EOFError instead of hanging it
        if not self.server_conn.poll(120):  # bounded: a server that died at start (bad config) never answers
            self.server.kill()
            raise RuntimeError(f"the server process did not start (exit code {self.server.exitcode})")
        ready, self.port, self.base_rss_kb = self.server_conn.recv()
        assert ready == "ready"
        names = [f"load-{i}" for i in range(agents)]
        self.worker_conns: list[Connection] = []
        self.workers: list[Any] = []
        for w in range(workers):
            share = names[w::workers]
            if not share:
                continue
            parent, child = self.ctx.Pipe()
            proc = self.ctx.Process(
                target=worker_main,
                args=(child, self.port, self.key_hex, share, authenticate, CLIENT["compact"], beacon_port),
                daemon=True,
            )
            proc.start()
            child.close()
            self.worker_conns.append(parent)
            self.workers.append(proc)
        self.identities = names
        self.stop_note = "not stopped"

    def server_call(self, *command: Any) -> Any:
        self.server_conn.send(command)
        return self.server_conn.recv()

    def workers_call(self, *command: Any) -> list[Any]:
        for conn in self.worker_conns:
            conn.send(command)
        return [conn.recv() for conn in self.worker_conns]

    def connect(self) -> int:
        return sum(self.workers_call("connect"))

    def close(self) -> None:
        """Stop workers, then the server; bounded: a stuck process is killed after 20 s."""
        for conn in self.worker_conns:
            with contextlib.suppress(Exception):
                conn.send(("close",))
                if conn.poll(20):
                    conn.recv()
        with contextlib.suppress(Exception):
            self.server_conn.send(("stop",))
            if self.server_conn.poll(30):
                self.stop_note = self.server_conn.recv()
        for proc in [*self.workers, self.server]:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()


def fleet_trial(agents: int, seconds: float) -> dict[str, Any]:
    """N agents at 10 Hz for ``seconds``: loss, ingest latency, daemon RSS and CPU."""
    harness = Harness("daemon", agents)
    try:
        connected = harness.connect()
        time.sleep(0.5)
        harness.server_call("reset")
        harness.workers_call("status", STATUS_HZ, seconds)
        sent_rows = harness.workers_call("sent")
        time.sleep(1.0)  # let the last frames in flight arrive
        stats = harness.server_call("stats")
    finally:
        harness.close()
    sent = sum(r["sent"] for r in sent_rows)
    dropped = agents - min(connected, stats["connected"]) + sum(r["closed"] for r in sent_rows)
    loss = (sent - stats["received"]) / sent if sent else 1.0
    row = {
        "agents": agents,
        "seconds": seconds,
        "sent": sent,
        "received": stats["received"],
        "loss": max(0.0, loss),
        "dropped_agents": dropped,
        "ingest_msgs_per_s": stats["received"] / seconds,
        "latency_p50_ms": stats["p50_ms"],
        "latency_p99_ms": stats["p99_ms"],
        "latency_max_ms": stats["max_ms"],
        "hook_seen": stats["hook_seen"],
        "hook_latency_p50_ms": stats["hook_p50_ms"],
        "hook_latency_p99_ms": stats["hook_p99_ms"],
        "daemon_cpu_share": stats["cpu_s"] / (seconds + 1.0),
        "client_workers_cpu_share": sum(r["cpu_s"] for r in sent_rows) / seconds,
        "daemon_rss_mb": stats["rss_kb"] / 1024,
        "rss_per_agent_kb": (stats["rss_kb"] - harness.base_rss_kb) / agents,
        # Connected, before any status: the sessions alone, without what a loaded trial leaves queued.
        "rss_per_connected_agent_kb": (stats["rss_at_reset_kb"] - harness.base_rss_kb) / agents,
        "services_us_per_report": stats["services_us"],
        "events": stats["events"],
        "gc_pauses": stats["gc_pauses"],
    }
    row["passed"] = bool(
        stats["received"] >= sent and dropped == 0 and stats["p99_ms"] < P99_LIMIT_MS and connected == agents
    )
    return row


def fleet_search(seconds: float, start: int, budget_s: float) -> tuple[list[dict[str, Any]], int]:
    """Double from ``start`` until a size fails, then bisect twice; returns (trials, largest passing)."""
    trials: list[dict[str, Any]] = []
    began = time.monotonic()
    size, best, worst = start, 0, 0
    for _ in range(8):
        row = fleet_trial(size, seconds)
        trials.append(row)
        _print_fleet(row)
        if row["passed"]:
            best = size
            size *= 2
        else:
            worst = size
            break
        if time.monotonic() - began > budget_s:
            break
    for _ in range(2):
        if not worst or worst - best <= max(50, best // 10) or time.monotonic() - began > budget_s:
            break
        size = (best + worst) // 2
        row = fleet_trial(size, seconds)
        trials.append(row)
        _print_fleet(row)
        if row["passed"]:
            best = size
        else:
            worst = size
    return trials, best


def _print_fleet(row: dict[str, Any]) -> None:
    print(
        f"  {row['agents']:>6} agents  {row['ingest_msgs_per_s']:8.0f} msg/s  loss {row['loss']:6.2%}  "
        f"dropped {row['dropped_agents']:>3}  p50 {row['latency_p50_ms']:7.2f} ms  "
        f"p99 {row['latency_p99_ms']:8.2f} ms  (hooks p99 {row['hook_latency_p99_ms']:6.1f} ms, "
        f"{row['hook_seen'] / max(1, row['received']):4.0%} seen)  cpu {row['daemon_cpu_share']:4.0%} "
        f"(clients {row['client_workers_cpu_share']:4.0%})  rss/agent {row['rss_per_agent_kb']:6.1f} KiB "
        f"(connected {row['rss_per_connected_agent_kb']:4.1f})  "
        f"{'PASS' if row['passed'] else 'fail'}  (full gc: {row['gc_pauses']['gen2']})",
        flush=True,
    )


class _BarrierStats:
    """One release mode's samples over a barrier trial (all in seconds)."""

    def __init__(self, mode: str) -> None:
        self.mode = mode
        self.per_step: list[float] = []  # last arrival -> the last member released (see barrier_trial)
        self.per_agent: list[float] = []
        self.read_step: list[float] = []  # last arrival -> the last member's process read a release
        self.to_barrier: list[float] = []  # last arrival -> the mission runner found the barrier complete
        self.in_daemon: list[float] = []  # last arrival -> the burst written to every member's socket
        self.writing: list[float] = []  # the burst itself (every member's socket written)
        self.writing_cpu: list[float] = []  # of which the loop's thread was on the CPU
        self.waits: list[float] = []  # the loop's thread's voluntary context switches in the burst
        self.preempted: list[float] = []  # and involuntary ones
        self.storing: list[float] = []  # barrier complete -> the first send (the release stored first)
        self.gc_in_release: list[float] = []  # gc between the last arrival and the burst's end
        self.per_step_read: list[float] = []  # as per_step, a beacon's arrival bounded by its read too
        self.sendto: list[float] = []  # the daemon's beacon sendto (on loopback: the whole fan-out)
        self.sendto_cpu: list[float] = []  # of which the daemon's thread was on the CPU
        self.to_beacon: list[float] = []  # last arrival -> the beacon's sendto returned
        self.stamp_early: list[float] = []  # sendto returned - the latest kernel stamp of the beacon
        self.members = 0
        self.heard = 0  # members that got a verified beacon
        self.beacon_first = 0  # members released by the beacon before their TCP release

    def add(self, stamps: list[tuple[Any, Any, Any, Any]], daemon: tuple[Any, ...]) -> str:
        """One barrier's stamps and the daemon's; '' or why the barrier failed.

        Per member: its TCP release's kernel stamp, its first read of a release, its verified
        beacon's kernel stamp and when its process read that beacon.
        """
        last_arrival, complete, started, written, gc_s, beacon, cpu = daemon
        self.gc_in_release.append(gc_s)
        if self.mode != "beacon" and beacon is not None:  # the runner must read its sender at each release
            return "a beacon went out on a TCP-only barrier (the bench's switch did not hold)"
        if last_arrival is None or any(tcp is None for tcp, _, _, _ in stamps):
            return f"{sum(tcp is None for tcp, _, _, _ in stamps)} not released"
        released, released_read = [], []
        for tcp, _, heard, heard_read in stamps:
            at = at_read = tcp
            if heard is not None and beacon is not None:
                # The kernel stamps a broadcast once, before it is cloned to every socket; on
                # loopback the clones are made inside the daemon's sendto, so a member's copy is
                # there no later than sendto's return: the later of the two is its arrival.
                arrival = max(heard, beacon[1])
                self.heard += 1
                if arrival < tcp:
                    self.beacon_first += 1
                    at = arrival
                # The return also counts time the daemon was off the CPU after the fan-out; the
                # member's own read of the copy is an upper bound as hard (printed beside).
                at_read = min(tcp, max(heard, min(beacon[1], heard_read)))
            released.append(at)
            released_read.append(at_read)
        self.members += len(stamps)
        self.per_step.append(max(released) - last_arrival)
        self.per_step_read.append(max(released_read) - last_arrival)
        self.per_agent += [t - last_arrival for t in released]
        self.read_step.append(max(read for _, read, _, _ in stamps) - last_arrival)
        if complete is not None:
            self.to_barrier.append(complete - last_arrival)
        if written is not None:
            self.in_daemon.append(written - last_arrival)
            self.writing.append(written - started)
            if cpu is not None:
                self.writing_cpu.append(cpu[0])
                self.waits.append(cpu[1])
                self.preempted.append(cpu[2])
        first_send = beacon[0] if beacon is not None else started
        if complete is not None and first_send is not None:
            self.storing.append(first_send - complete)
        if beacon is not None:
            self.sendto.append(beacon[1] - beacon[0])
            self.sendto_cpu.append(beacon[3])
            self.to_beacon.append(beacon[1] - last_arrival)
            heard_at = [h for _, _, h, _ in stamps if h is not None]
            if heard_at:
                self.stamp_early.append(beacon[1] - max(heard_at))
        return ""

    def row(self, agents: int, failed: str) -> dict[str, Any]:
        ms = {
            name: (percentile(values, 0.5) * 1000, percentile(values, 0.99) * 1000)
            for name, values in (
                ("last_release", self.per_step),
                ("last_release_read_bound", self.per_step_read),
                ("per_agent_release", self.per_agent),
                ("last_read", self.read_step),
                ("to_barrier", self.to_barrier),
                ("daemon_release", self.in_daemon),
                ("burst_write", self.writing),
                ("burst_cpu", self.writing_cpu),
                ("store_release", self.storing),
                ("beacon_sendto", self.sendto),
                ("beacon_sendto_cpu", self.sendto_cpu),
                ("to_beacon", self.to_beacon),
                ("beacon_stamp_before_return", self.stamp_early),
            )
        }
        return {
            "mode": self.mode,
            "agents": agents,
            "steps": len(self.gc_in_release),
            **{f"{name}_p{p}_ms": v[i] for name, v in ms.items() for i, p in ((0, 50), (1, 99))},
            "last_release_max_ms": max(self.per_step, default=float("nan")) * 1000,
            "burst_switches_p50": {
                "voluntary": percentile(self.waits, 0.5),
                "involuntary": percentile(self.preempted, 0.5),
            },
            "gc_in_release_ms": {
                "releases with a collection": sum(1 for g in self.gc_in_release if g > 0),
                "max": max(self.gc_in_release, default=0.0) * 1000,
            },
            "released_steps": len(self.per_step),
            "beacon_heard_share": self.heard / self.members if self.members else 0.0,
            "released_by_beacon_share": self.beacon_first / self.members if self.members else 0.0,
            "failed": failed,
        }


def barrier_trial(
    agents: int, steps: int, beacon: bool = True, old_path: bool = True
) -> list[dict[str, Any]]:
    """Release latency of barriers with ``agents`` members streaming status at 10 Hz.

    ``old_path``: one more mode, TCP only through the daemon's burst as it was before issue 29
    (``_legacy_burst``), paired barrier by barrier with the others ("tcp_old").

    ``beacon``: the daemon sends release beacons (``release_beacon`` to the loopback broadcast
    address on a port free for this run) and every member listens, and the barriers take the
    modes in turn in the same fleet: released with the beacon (then the TCP burst), by the TCP
    burst only (the runner's sender set to None for them, the daemon's own path when no beacon
    is configured), and by the old burst; the last two swap places every other round
    (:func:`_mode_index`). ``steps`` barriers per mode; the rows are paired barrier by barrier,
    so machine load hits all alike. Without ``beacon``: TCP only, no UDP sockets, as before the
    beacon.

    A member's release is the earlier of its TCP release (the kernel's receive stamp) and its
    verified beacon. For a beacon the kernel's stamp is taken once, before the datagram is cloned
    to every listening socket, so it under-reports the fan-out; on loopback the fan-out is done
    inside the daemon's ``sendto``, so a beacon's arrival is the later of its stamp and the moment
    that ``sendto`` returned (the bench wraps the daemon's ``BeaconSender.send``).
    """
    from protocol.actions import Goto, Land, Takeoff
    from protocol.taskfile import AgentPlan, TaskFile

    modes = [_BarrierStats("beacon"), _BarrierStats("tcp")] if beacon else [_BarrierStats("tcp")]
    if old_path:
        modes.append(_BarrierStats("tcp_old"))
    beacon_port = None
    if beacon:
        from gcs.link.beacon import free_udp_port  # (not at the top: paired trials run older trees too)

        beacon_port = free_udp_port()
    harness = Harness("daemon", agents, beacon_port=beacon_port)
    failed = ""
    rejected = 0
    try:
        assert harness.connect() == agents
        total = steps * len(modes)
        actions: list[Any] = [Takeoff(step=0, alt=5.0, sync=True)]
        actions += [Goto(step=k, lat=47.3978, lon=8.5456, alt=5.0, sync=True) for k in range(1, total)]
        actions.append(Land(step=total))
        task = TaskFile(
            name="bench-barrier",
            sync_timeout_s=600,
            plans=[AgentPlan(agent=name, actions=list(actions)) for name in harness.identities],
        )
        harness.workers_call("status", STATUS_HZ, 3600.0)  # a 3-D fix first: submit waits for one
        time.sleep(0.5)
        mission_id = harness.server_call("submit", task.model_dump_json())
        time.sleep(0.5 + agents / 2000)  # the type-4 batches reach everyone
        for step in range(total):
            stats = modes[_mode_index(step, len(modes))]
            if beacon and not harness.server_call("beacon", stats.mode == "beacon"):
                failed = "the daemon has no beacon sender (release_beacon not configured?)"
                break
            harness.server_call("release_path", "old" if stats.mode == "tcp_old" else "new")
            stamps = [t for row in harness.workers_call("finish", mission_id, step, 30.0) for t in row]
            why = stats.add(stamps, harness.server_call("arrival", step))
            if why:
                # Overloaded (the cooperation service then treats late reports as stale and
                # takes the drones over): count it and stop, the numbers so far stand.
                failed = f"step {step} ({stats.mode}): {why}; daemon events {harness.server_call('events')}"
                break
            time.sleep(0.05)
        rejected = sum(harness.workers_call("rejected"))
        if os.environ.get("BENCH_RELEASE_PARTS"):
            _print_release_parts(harness.server_call("parts"), [stats.mode for stats in modes])
    finally:
        harness.close()
    rows = [stats.row(agents, failed) for stats in modes]
    for row in rows:
        row["beacon_datagrams_rejected"] = rejected  # by the members' verifiers: 0 unless forged or replayed
    return rows


def _mode_index(step: int, count: int) -> int:
    """Which mode a barrier step runs in: in turn, the last two swapping places every other round
    (TCP now and TCP before each follow the other as often: the one right after a beacon barrier
    meets clients still busy with it)."""
    cycle, slot = divmod(step, count)
    if count >= 2 and cycle % 2 and slot >= count - 2:
        slot = 2 * count - 3 - slot
    return slot


def _print_release_parts(parts: dict[int, tuple[float, ...]], modes: list[str]) -> None:
    """Barrier complete -> first send, in parts, p50 / p99 per mode (``BENCH_RELEASE_PARTS=1``)."""
    names = ("gc off + write lock", "release row", "event", "commit -> first send")
    for index, mode in enumerate(modes):
        rows = [v for step, v in parts.items() if _mode_index(step, len(modes)) == index]
        cols = [[row[i] for row in rows] for i in range(len(names))]
        print(
            f"  {mode:>6} barrier complete -> first send, in parts (p50 / p99 ms): "
            + ", ".join(
                f"{name} {percentile(col, 0.5) * 1000:.3f} / {percentile(col, 0.99) * 1000:.3f}"
                for name, col in zip(names, cols, strict=True)
            ),
            flush=True,
        )


def _print_barrier(row: dict[str, Any]) -> None:
    beacon = ""
    if row["mode"] == "beacon":
        beacon = (
            f"; released by the beacon first: {row['released_by_beacon_share']:.1%} of members "
            f"(heard it: {row['beacon_heard_share']:.1%}, "
            f"datagrams rejected: {row['beacon_datagrams_rejected']}); "
            f"the daemon's beacon sendto p50 {row['beacon_sendto_p50_ms']:.3f} ms "
            f"p99 {row['beacon_sendto_p99_ms']:.3f} ms "
            f"(on the CPU p50 {row['beacon_sendto_cpu_p50_ms']:.3f} ms "
            f"p99 {row['beacon_sendto_cpu_p99_ms']:.3f} ms), arrival -> sendto returned "
            f"p50 {row['to_beacon_p50_ms']:.3f} ms p99 {row['to_beacon_p99_ms']:.3f} ms "
            f"(the kernel's stamp p50 {row['beacon_stamp_before_return_p50_ms']:.3f} ms before that return); "
            f"last release with a beacon's arrival bounded by its member's read too "
            f"p50 {row['last_release_read_bound_p50_ms']:.2f} ms "
            f"p99 {row['last_release_read_bound_p99_ms']:.2f} ms"
        )
    print(
        f"  {row['mode']:>6} {row['agents']:>6} agents  last arrival -> last release "
        f"p50 {row['last_release_p50_ms']:7.2f} ms  "
        f"p99 {row['last_release_p99_ms']:7.2f} ms  (max {row['last_release_max_ms']:.2f} ms; "
        f"per agent p50 {row['per_agent_release_p50_ms']:.2f} ms; in the daemon, arrival -> barrier "
        f"complete p50 {row['to_barrier_p50_ms']:.2f} ms p99 {row['to_barrier_p99_ms']:.2f} ms, "
        f"stored -> first send p50 {row['store_release_p50_ms']:.2f} ms "
        f"p99 {row['store_release_p99_ms']:.2f} ms, -> burst written "
        f"p50 {row['daemon_release_p50_ms']:.2f} ms p99 {row['daemon_release_p99_ms']:.2f} ms, "
        f"of which the burst p50 {row['burst_write_p50_ms']:.2f} ms p99 {row['burst_write_p99_ms']:.2f} ms "
        f"(the loop's thread on the CPU p50 {row['burst_cpu_p50_ms']:.2f} ms "
        f"p99 {row['burst_cpu_p99_ms']:.2f} ms; its context switches p50 {row['burst_switches_p50']}); "
        f"read by the clients' processes p50 {row['last_read_p50_ms']:.2f} ms "
        f"p99 {row['last_read_p99_ms']:.2f} ms; {row['released_steps']} barriers; "
        f"gc in releases {row['gc_in_release_ms']}{beacon})"
        + (f"  STOPPED: {row['failed']}" if row["failed"] else ""),
        flush=True,
    )


def _print_barrier_rows(rows: list[dict[str, Any]]) -> None:
    """Each mode's line, then the paired ratio when both modes ran."""
    for row in rows:
        _print_barrier(row)
    by_mode = {row["mode"]: row for row in rows}
    for one, other, what in (("beacon", "tcp", "beacon / TCP only"), ("tcp", "tcp_old", "TCP now / before")):
        if one in by_mode and other in by_mode:
            b, t = by_mode[one], by_mode[other]
            print(
                f"  {b['agents']:>13} agents  {what} (paired barriers): "
                f"p50 {b['last_release_p50_ms']:.2f} / {t['last_release_p50_ms']:.2f} ms "
                f"= {b['last_release_p50_ms'] / t['last_release_p50_ms']:.2f}, "
                f"p99 {b['last_release_p99_ms']:.2f} / {t['last_release_p99_ms']:.2f} ms "
                f"= {b['last_release_p99_ms'] / t['last_release_p99_ms']:.2f}; the burst itself p50 "
                f"{b['burst_write_p50_ms']:.2f} / {t['burst_write_p50_ms']:.2f} ms",
                flush=True,
            )


def throughput_trial(kind: str, clients: int, seconds: float) -> dict[str, Any]:
    """Clients flood pre-encoded status frames; frames/s the server side absorbed."""
    harness = Harness(kind, clients, authenticate=kind == "daemon")
    try:
        assert harness.connect() == clients
        harness.server_call("reset", False)
        started = time.monotonic()
        rows = harness.workers_call("flood", seconds)
        elapsed = time.monotonic() - started
        time.sleep(0.5)
        stats = harness.server_call("stats")
    finally:
        harness.close()
    return {
        "server": kind,
        "server_stop": harness.stop_note,
        "clients": clients,
        "sent": sum(r["sent"] for r in rows),
        "received": stats["received"],
        "frames_per_s": stats["received"] / (elapsed + 0.5),
        "server_cpu_share": stats["cpu_s"] / (elapsed + 0.5),
    }


def fleet_rtl_trial(agents: int, repeats: int, status_hz: float = STATUS_HZ) -> dict[str, Any]:
    """``POST /api/v1/fleet/rtl`` to N airborne agents streaming status: to the last one's order.

    Per repeat: from just before the request is written (the orchestrator's ``time.time()``) to
    the kernel receive stamp of the return order (type 4, a ``return-`` mission) in the last
    agent's socket; also the first agent's and the HTTP answer. Every agent reports armed and in
    the air at its own spot, so each gets a deconflicted return program through the authority.
    """
    import http.client

    harness = Harness("daemon", agents, overrides={"http_host": "127.0.0.1", "http_port": 0})
    last: list[float] = []
    first: list[float] = []
    answered: list[float] = []
    delivered: list[int] = []
    failed = ""
    try:
        assert harness.connect() == agents
        harness.workers_call("status", status_hz, 3600.0)
        time.sleep(1.0 / status_hz + 1.0 + agents / 2000)  # every agent's first reports are in
        port, token = harness.server_call("http")
        api = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
        headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
        for repeat in range(repeats):
            harness.workers_call("orders_reset")
            started = time.time()
            try:
                api.request(
                    "POST", "/api/v1/fleet/rtl", body=json.dumps({"reason": "bench"}), headers=headers
                )
                answer = api.getresponse()
                payload = answer.read()
            except (TimeoutError, OSError) as exc:
                failed = f"repeat {repeat}: no HTTP answer ({exc!r}, timeout 60 s)"
                break
            answered.append(time.time() - started)
            if answer.status != 200:
                failed = f"repeat {repeat}: HTTP {answer.status} {payload[:200]!r}"
                break
            delivered.append(len(json.loads(payload)["delivered"]))
            stamps = [t for row in harness.workers_call("orders", 30.0) for t in row]
            if any(t is None for t in stamps):
                failed = f"repeat {repeat}: {sum(t is None for t in stamps)} agents got no order within 30 s"
                break
            last.append(max(stamps) - started)
            first.append(min(stamps) - started)
            time.sleep(0.3)
        api.close()
    finally:
        harness.close()
    ms = {
        name: (percentile(values, 0.5) * 1000, percentile(values, 0.99) * 1000)
        for name, values in (("last_order", last), ("first_order", first), ("http_answer", answered))
    }
    return {
        "agents": agents,
        "repeats": len(last),
        "first_repeat_ms": last[0] * 1000 if last else float("nan"),  # the API's first request: cold
        "delivered": delivered,
        **{f"{name}_p{p}_ms": v[i] for name, v in ms.items() for i, p in ((0, 50), (1, 99))},
        "failed": failed,
    }


def _print_fleet_rtl(row: dict[str, Any]) -> None:
    print(
        f"  {row['agents']:>6} agents  POST /api/v1/fleet/rtl -> the last agent's order "
        f"p50 {row['last_order_p50_ms']:8.2f} ms  p99 {row['last_order_p99_ms']:8.2f} ms  "
        f"(the first agent's p50 {row['first_order_p50_ms']:.2f} ms; the HTTP answer "
        f"p50 {row['http_answer_p50_ms']:.2f} ms p99 {row['http_answer_p99_ms']:.2f} ms; "
        f"{row['repeats']} repeats, the first {row['first_repeat_ms']:.1f} ms: FastAPI builds its routes "
        f"at the first request; delivered {sorted(set(row['delivered']))})"
        + (f"  STOPPED: {row['failed']}" if row["failed"] else ""),
        flush=True,
    )


def floor_trial(agents: int, rounds: int) -> dict[str, Any]:
    """bench_burst_floor's TCP floor at ``agents`` sockets: a bare ``sock.send`` each (no daemon)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_burst_floor import floor

    return {"agents": agents, **floor(agents, rounds, "tcp")}


def agent_footprint(backend: str, seconds: float, agent_bin: Path = BIN) -> dict[str, Any]:
    """RSS and CPU share of one `agent run` at 10 Hz status beside one vehicle.

    ``agent_bin``: the ``bin`` folder whose ``agent`` runs (``--agent-bin``: an agent-only venv
    installed from the wheel, as a companion computer has it; by default this venv's).
    """
    harness = Harness("daemon", 0, workers=0)
    sitl: subprocess.Popen[str] | None = None
    agent: subprocess.Popen[bytes] | None = None
    try:
        with tempfile.TemporaryDirectory() as tmp:
            key_file = Path(tmp) / "fleet.key"
            key_file.write_text(harness.key_hex)
            if backend == "memory":
                connection = "47.397742,8.545594,488"
            else:
                sitl = subprocess.Popen(
                    [BIN / "sitl", "run", "--vehicles", "1", "--base-port", "0", "--speedup", "1"],
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                )
                assert sitl.stdout is not None
                line = sitl.stdout.readline()
                if not line.startswith("SITL READY"):
                    raise RuntimeError(f"sitl did not start: {line!r}")
                connection = line.split()[2]
            agent = subprocess.Popen(
                [
                    agent_bin / "agent",
                    "run",
                    "--gcs",
                    f"127.0.0.1:{harness.port}",
                    "--id",
                    "pi-1",
                    "--key-file",
                    key_file,
                    "--autopilot-backend",
                    backend,
                    "--autopilot",
                    connection,
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                # another venv's agent runs its own install (a PYTHONPATH to a tree would replace it)
                env=None if agent_bin == BIN else {k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
            )
            time.sleep(4.0)  # connect, handshake, settle
            if agent.poll() is not None:
                raise RuntimeError(f"agent exited with {agent.returncode}")
            harness.server_call("reset")
            cpu0, t0 = cpu_seconds(agent.pid), time.monotonic()
            time.sleep(seconds)
            cpu = cpu_seconds(agent.pid) - cpu0
            elapsed = time.monotonic() - t0
            stats = harness.server_call("stats")
            sitl_cpu = cpu_seconds(sitl.pid) if sitl else None
            return {
                "backend": backend,
                "seconds": elapsed,
                "status_per_s": stats["received"] / elapsed,
                "rss_mb": rss_kb(agent.pid) / 1024,
                "cpu_share_of_one_core": cpu / elapsed,
                "sitl_cpu_s_total": sitl_cpu,
            }
    finally:
        for proc in (agent, sitl):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
        harness.close()


def machine() -> dict[str, Any]:
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    fields = dict(line.split(":", 1) for line in lscpu.splitlines() if ":" in line)
    mem_kb = next(
        int(line.split()[1])
        for line in Path("/proc/meminfo").read_text().splitlines()
        if line.startswith("MemTotal")
    )
    return {
        "cpu": fields.get("Model name", "?").strip(),
        "cpus": os.cpu_count(),
        "ram_gib": round(mem_kb / 1024 / 1024, 1),
        "python": platform.python_version(),
        "kernel": platform.release(),
    }


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="tiny sizes and short windows: checks every row prints (smoke run)",
    )
    parser.add_argument("--seconds", type=float, default=4.0, help="fleet trial window")
    parser.add_argument("--start", type=int, default=250, help="first fleet size of the search")
    parser.add_argument(
        "--daemon-config",
        default="{}",
        help='JSON DaemonConfig overrides, e.g. {"telemetry":{"enabled":false}}',
    )
    parser.add_argument("--only-fleet", type=int, help="just one fleet trial of this size (diagnosis)")
    parser.add_argument("--only-barrier", type=int, help="just the barrier trial with this many agents")
    parser.add_argument("--only-rtl", type=int, help="just the fleet RTL fan-out with this many agents")
    parser.add_argument(
        "--only-agent",
        choices=["memory", "mavlink"],
        help="just the agent footprint (RSS, CPU share) with this backend",
    )
    parser.add_argument(
        "--agent-bin",
        type=Path,
        default=BIN,
        help="the bin folder of the agent measured (an agent-only venv, e.g. from bench/agent_venv.sh)",
    )
    parser.add_argument(
        "--barrier-steps", type=int, default=40, help="barriers per barrier trial and mode (p99 over them)"
    )
    parser.add_argument("--rtl-repeats", type=int, default=20, help="fleet RTLs per fan-out trial")
    parser.add_argument(
        "--rtl-status-hz", type=float, default=STATUS_HZ, help="with --only-rtl: the agents' status rate"
    )
    parser.add_argument(
        "--rtl-agents", type=int, nargs="+", default=[1000, 2000], help="fleet sizes of the RTL fan-out"
    )
    parser.add_argument(
        "--no-beacon",
        action="store_true",
        help="barrier trials over TCP only (no release beacon, no paired beacon barriers)",
    )
    parser.add_argument(
        "--no-old-release",
        action="store_true",
        help="no paired barriers through the TCP burst as it was before issue 29 ('tcp_old')",
    )
    parser.add_argument("--json", action="store_true", help="clients send JSON status bodies (v1 agents)")
    parser.add_argument(
        "--profile", help="with --only-fleet or --only-rtl: write the daemon's cProfile stats here"
    )
    return parser.parse_args()


def _print_floor(row: dict[str, Any]) -> None:
    print(
        f"  {row['agents']:>6} sockets  loopback TCP send floor (bare sock.send each, no daemon) "
        f"p50 {row['p50_ms']:7.2f} ms  p99 {row['p99_ms']:7.2f} ms  ({row['rounds']} bursts)",
        flush=True,
    )


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} / {five:.2f} / {fifteen:.2f} (1 / 5 / 15 min) on {os.cpu_count()} CPUs"


def _barriers_and_floor(args: argparse.Namespace) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The barrier trials (beacon, TCP only, TCP before issue 29; paired) and the send floor at each size."""
    print("\nsync barrier release latency (agents streaming status at 10 Hz):", flush=True)
    barriers, floors = [], []
    for n in (10, 50) if args.quick else (10, 100, 1000):
        rows = barrier_trial(
            n,
            3 if args.quick else args.barrier_steps,
            beacon=not args.no_beacon,
            old_path=not args.no_old_release,
        )
        barriers += rows
        _print_barrier_rows(rows)
        if n >= 50:
            floors.append(floor_trial(n, 5 if args.quick else args.barrier_steps))
            _print_floor(floors[-1])
    return barriers, floors


def _footprints(
    quick: bool, backends: Sequence[str] = ("memory", "mavlink"), agent_bin: Path = BIN
) -> list[dict[str, Any]]:
    print(f"\nagent footprint (one `agent run`, one vehicle, status at 10 Hz; {_load()}):", flush=True)
    footprint = []
    for backend in backends:
        try:
            row = agent_footprint(backend, 2.0 if quick else 10.0, agent_bin)
        except (RuntimeError, OSError) as exc:
            print(f"  {backend}: not measured ({exc})")
            continue
        footprint.append(row)
        print(
            f"  {backend:>8}: RSS {row['rss_mb']:6.1f} MiB  "
            f"CPU {row['cpu_share_of_one_core']:6.1%} of one core  "
            f"({row['status_per_s']:.1f} status/s received)",
            flush=True,
        )
    return footprint


def _summary(out: dict[str, Any], best: int) -> None:
    """The figures issue 29 asks for, one line each (every row of a full run, also of --quick)."""
    trials = out["fleet_trials"]
    best_row = next((t for t in trials if t["agents"] == best), None)
    print(f"\n{out['load_at_start']} at the start; {_load()} at the end")
    print(f"largest fleet sustained (the knee): {best} agents at {STATUS_HZ:g} Hz")
    if best_row:
        print(f"daemon memory at the knee: {best_row['rss_per_agent_kb']:.1f} KiB RSS per agent")
        costs = best_row["services_us_per_report"]
        print(
            "event-loop time per status report at the knee (us): "
            + ", ".join(f"{name} {us:.1f}" for name, us in costs.items())
            + f"; total {sum(costs.values()):.1f}"
        )
    floors = {row["agents"]: row for row in out["send_floor"]}
    for row in out["barriers"]:
        floor = floors.get(row["agents"])
        print(
            f"barrier release at {row['agents']} agents ({row['mode']}): "
            f"p50 {row['last_release_p50_ms']:.2f} ms, p99 {row['last_release_p99_ms']:.2f} ms"
            + (f", {row['released_by_beacon_share']:.0%} by the beacon" if row["mode"] == "beacon" else "")
            + (
                f"; send floor p50 {floor['p50_ms']:.2f} ms, p99 {floor['p99_ms']:.2f} ms"
                if floor and row["mode"] != "beacon"
                else ""
            )
        )
    for row in out["fleet_rtl"]:
        print(
            f"fleet RTL to the last of {row['agents']} agents: p50 {row['last_order_p50_ms']:.2f} ms, "
            f"p99 {row['last_order_p99_ms']:.2f} ms ({row['repeats']} repeats)"
            + (f" STOPPED: {row['failed']}" if row["failed"] else "")
        )
    print(f"daemon / bare asyncio flood ratio: {out['summary']['daemon_over_bare_asyncio_throughput']:.3f}")
    for row in out["agent_footprint"]:
        print(
            f"agent RSS ({row['backend']} backend): {row['rss_mb']:.1f} MiB, "
            f"CPU {row['cpu_share_of_one_core']:.1%} of one core"
        )
    print(f"wall {out['wall_s']:.0f} s")


def main() -> int:
    args = _arguments()
    DAEMON_OVERRIDES.update(json.loads(args.daemon_config))
    CLIENT["compact"] = not args.json
    PROFILE["path"] = args.profile
    load_at_start = _load()
    print(load_at_start, flush=True)
    if args.only_fleet:
        row = fleet_trial(args.only_fleet, args.seconds)
        _print_fleet(row)
        print(f"  event-loop us per report: {row['services_us_per_report']}")
        print(f"  events: {row['events']}")
        print(f"  gc pauses: {row['gc_pauses']}")
        return 0
    if args.only_barrier:
        rows = barrier_trial(
            args.only_barrier, args.barrier_steps, beacon=not args.no_beacon, old_path=not args.no_old_release
        )
        _print_barrier_rows(rows)
        _print_floor(floor_trial(args.only_barrier, args.barrier_steps))
        print(json.dumps(rows, indent=1))
        return 0
    if args.only_rtl:
        _print_fleet_rtl(fleet_rtl_trial(args.only_rtl, args.rtl_repeats, args.rtl_status_hz))
        return 0
    if args.only_agent:
        _footprints(args.quick, [args.only_agent], args.agent_bin)
        return 0
    began = time.monotonic()
    seconds = 2.0 if args.quick else args.seconds
    info = machine()
    print(f"machine: {info}")

    print(
        f"\nfleet search: status at {STATUS_HZ:g} Hz, pass = zero loss and p99 < {P99_LIMIT_MS:g} ms",
        flush=True,
    )
    trials, best = fleet_search(seconds, 50 if args.quick else args.start, 1 if args.quick else 120)
    barriers, floors = _barriers_and_floor(args)

    print("\nfleet-wide safety order: POST /api/v1/fleet/rtl to the last agent's type-4 order:", flush=True)
    fleet_rtl = []
    for n in [20] if args.quick else args.rtl_agents:
        fleet_rtl.append(fleet_rtl_trial(n, 2 if args.quick else args.rtl_repeats))
        _print_fleet_rtl(fleet_rtl[-1])

    print("\nthroughput, the same status frames flooded by 20 clients:", flush=True)
    flood_s = 1.0 if args.quick else 4.0
    throughput = {kind: throughput_trial(kind, 20, flood_s) for kind in ("bare", "decode", "daemon")}
    for kind, row in throughput.items():
        print(
            f"  {kind:>7}  {row['frames_per_s']:9.0f} frames/s  server cpu {row['server_cpu_share']:4.0%}",
            flush=True,
        )
    ratio = throughput["daemon"]["frames_per_s"] / throughput["bare"]["frames_per_s"]
    print(f"  daemon / bare asyncio = {ratio:.3f}")
    footprint = _footprints(args.quick, agent_bin=args.agent_bin)

    best_row = next((t for t in trials if t["agents"] == best), None)
    out = {
        "machine": info,
        "load_at_start": load_at_start,
        "quick": args.quick,
        "summary": {
            "client_status_body": "compact" if CLIENT["compact"] else "json",
            "max_fleet_zero_loss_p99_under_50ms": best,
            "rss_per_agent_kb_at_max": best_row["rss_per_agent_kb"] if best_row else None,
            "daemon_over_bare_asyncio_throughput": ratio,
        },
        "fleet_trials": trials,
        "barriers": barriers,
        "send_floor": floors,
        "fleet_rtl": fleet_rtl,
        "throughput": throughput,
        "agent_footprint": footprint,
        "wall_s": time.monotonic() - began,
    }
    _summary(out, best)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / ("load_quick.json" if args.quick else "load.json")).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
