"""A daemon killed right after an agent rejoined loses none of the agent's buffered telemetry.

Real `gcs serve` processes (SIGKILLed) on one data directory, real TCP, an in-process agent on the
memory backend. The agent is offline for some seconds (buffering its status reports), rejoins and replays
them, and the daemon is killed 0.5 s later: before its telemetry writer committed the replay
(its batch interval is set to 10 s here, so without the acknowledgement the loss is certain, not
1 run in 2). The agent keeps the replay until a daemon acknowledges it stored it (type 3
`replay_stored`, docs/protocol.md section 2), so it replays it again to the restarted daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import signal
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest

from tests.backbone.helpers import RunningAgent, start_agent
from tests.support.polling import wait_for
from tests.support.processes import serve_daemon, wait_ready

NAME = "rejoin-1"
SLOW_FLUSH = {"FLEETGCS_TELEMETRY__FLUSH_S": "10"}  # the replay waits up to 10 s for its commit
MAX_GAP_S = 1.0  # status every 0.1 s: a second without a stored row is a hole


async def _start(data_dir: Path, ready: Path, listen: str) -> tuple[subprocess.Popen[bytes], int]:
    proc = serve_daemon(data_dir, ready, listen, env=SLOW_FLUSH)
    try:
        agent_port, _ = await asyncio.to_thread(wait_ready, ready, proc, 120.0)  # a loaded CI machine
    except BaseException:
        proc.kill()  # never ready: do not leave it running
        proc.wait(timeout=10)
        raise
    return proc, agent_port


def _kill(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGKILL)  # no shutdown code runs: what is not committed is gone
    proc.wait(timeout=10)


def _stored_times(db_path: Path) -> list[float]:
    with contextlib.closing(sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)) as db:
        return [r[0] for r in db.execute("SELECT time FROM telemetry WHERE agent=? ORDER BY time", (NAME,))]


def _holes(times: list[float], start: float, end: float) -> list[tuple[float, float]]:
    """(length, from) of every stretch of [start, end] longer than MAX_GAP_S without a stored row."""
    covered = [start] + [t for t in times if start < t < end] + [end]
    return [(b - a, a) for a, b in itertools.pairwise(covered) if b - a > MAX_GAP_S]


@pytest.mark.slow
async def test_daemon_killed_after_a_rejoin_loses_no_buffered_status(tmp_path: Path) -> None:
    data_dir, ready = tmp_path / "gcs", tmp_path / "ready"
    db_path = data_dir / "fleetgcs.sqlite"
    procs: list[subprocess.Popen[bytes]] = []
    running: RunningAgent | None = None
    try:
        first, port = await _start(data_dir, ready, "127.0.0.1:0")
        procs.append(first)
        key = (data_dir / "fleet.key").read_text().strip()
        running = start_agent(NAME, port, key)
        link = running.agent.link
        await wait_for(lambda: link.connected and link.version == 2, 20, "the agent joins on version 2")
        await asyncio.sleep(0.5)

        _kill(first)
        offline_from = time.time()
        await wait_for(lambda: link.buffered[0] >= 25, 10, "status reports buffered offline")
        second, _ = await _start(data_dir, ready, f"127.0.0.1:{port}")
        procs.append(second)
        await wait_for(lambda: link.sessions == 2 and link.buffered[0] == 0, 20, "the rejoin and its replay")
        offline_until = time.time()
        await asyncio.sleep(0.5)
        _kill(second)  # 0.5 s after the rejoin: the replay is received, not yet committed

        third, _ = await _start(data_dir, ready, f"127.0.0.1:{port}")
        procs.append(third)
        await wait_for(lambda: link.sessions == 3, 20, "the second rejoin")
        with contextlib.suppress(AssertionError):  # the stored rows are checked below, whatever came
            await wait_for(
                lambda: not _holes(_stored_times(db_path), offline_from, offline_until),
                30,
                "the offline period stored",
                poll=0.5,
            )
        times = _stored_times(db_path)  # committed rows (WAL), read while the daemon runs
        gaps = _holes(times, offline_from, offline_until)
        assert not gaps, (
            f"stored telemetry of {NAME} has {len(gaps)} hole(s) over the "
            f"{offline_until - offline_from:.1f} s offline period (longest {max(gaps)[0]:.1f} s)"
        )
        assert len(times) == len(set(times)), "a replayed report was stored twice"
        await wait_for(lambda: link.unacknowledged == 0 and link.acknowledged > 0, 10, "the acknowledgement")
    finally:
        if running is not None:
            await running.kill()
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
