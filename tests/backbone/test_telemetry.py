"""Telemetry is logged to SQLite, survives outages (buffered reports), exports as flight logs."""

from __future__ import annotations

import asyncio
import csv
import itertools
import json
import sqlite3
import subprocess
import time
from pathlib import Path

from gcs.core.config import TelemetryConfig
from gcs.observe.telemetry import CSV_COLUMNS, split_flights
from gcs.storage.store import _MIGRATIONS, SCHEMA_VERSION, Store
from tests.backbone.helpers import (
    new_key,
    running_daemon,
    start_agent,
    stop_agents,
    survey_mission,
    telemetry_row,
)
from tests.support.polling import wait_for
from tests.support.processes import BIN


async def test_flight_is_logged_including_reports_buffered_during_an_outage(tmp_path: Path) -> None:
    key = new_key()
    daemon_cm = running_daemon(tmp_path, key)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    running = start_agent("logger", port, key, speedup=4.0)
    try:
        await wait_for(lambda: daemon.agents.session("logger") is not None, 10, "agent joins")
        mission_id = await daemon.missions.submit(survey_mission(["logger"], sync_legs=2))
        await wait_for(lambda: running.agent.queue.completed_step >= 1, 20, "first leg done")
        await daemon_cm.__aexit__(None, None, None)  # outage: the agent buffers its reports
        await wait_for(lambda: running.agent.link.buffered[0] >= 5, 10, "reports buffered")
        daemon_cm = running_daemon(tmp_path, key, listen_port=port)
        daemon = await daemon_cm.__aenter__()
        await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completes")
        await wait_for(lambda: running.autopilot.telemetry().landed, 10, "landed")
        samples = daemon.telemetry.history("logger", limit=100_000)
    finally:
        await running.kill()
        await daemon_cm.__aexit__(None, None, None)

    assert sum(s["buffered"] for s in samples) >= 5  # nothing recorded offline was lost
    times = [s["time"] for s in samples]
    assert times == sorted(times)
    flights = split_flights(samples)
    assert len(flights) == 1 and flights[0][0]["armed"] and not flights[0][-1]["armed"]
    assert max(s["alt_rel"] for s in flights[0]) > 4.0
    assert {s["mission_id"] for s in flights[0] if s["mission_id"]} == {mission_id}

    csv_dir = tmp_path / "flights"
    exported = subprocess.run(
        [BIN / "gcs", "log", "export", "--agent", "logger", "--data-dir", tmp_path, "--by-flight",
         "--out", csv_dir],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert exported.returncode == 0, exported.stderr
    (flight_file,) = sorted(csv_dir.glob("*.csv"))
    rows = list(csv.DictReader(flight_file.open()))
    assert tuple(rows[0].keys()) == CSV_COLUMNS
    assert len(rows) == len(flights[0])
    assert float(rows[-1]["alt_rel"]) < 0.5 and rows[-1]["armed"] == "0"

    geojson_file = tmp_path / "track.geojson"
    subprocess.run(
        [BIN / "gcs", "log", "export", "--agent", "logger", "--data-dir", tmp_path, "--format", "geojson",
         "--out", geojson_file],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    collection = json.loads(geojson_file.read_text())
    (feature,) = collection["features"]
    assert feature["geometry"]["type"] == "LineString" and len(feature["geometry"]["coordinates"]) > 10


async def test_downsampling_keeps_one_sample_per_period(tmp_path: Path) -> None:
    key = new_key()
    config = TelemetryConfig(period_s=0.5, flush_s=0.1)
    async with running_daemon(tmp_path, key, telemetry=config) as daemon:
        running = start_agent("sparse", daemon.listen_port, key)
        try:
            await wait_for(
                lambda: (s := daemon.agents.session("sparse")) and s.status_count >= 25, 10, "reports"
            )
            received = daemon.agents.session("sparse").status_count  # type: ignore[union-attr]
            kept = daemon.telemetry.history("sparse", limit=10_000)
        finally:
            await stop_agents([running])
    assert 2 <= len(kept) <= received / 3  # reports come every 0.1 s; one in five is kept
    gaps = [b["time"] - a["time"] for a, b in itertools.pairwise(kept)]
    assert min(gaps) >= 0.5


def test_a_replayed_row_is_stored_once(tmp_path: Path) -> None:
    """An agent replays until the daemon acknowledges it, so a replayed report may come twice: one row.
    Live rows are stored as before."""
    store = Store(tmp_path / "db.sqlite")
    replayed = (*telemetry_row("a", 5.0, 0.0)[:-1], 1)
    store.add_telemetry([replayed, replayed, telemetry_row("a", 6.0, 0.0)])
    store.add_telemetry([replayed, telemetry_row("a", 6.0, 1.0), (*telemetry_row("b", 5.0, 0.0)[:-1], 1)])
    assert [(r["agent"], r["time"]) for r in store.telemetry("a")] == [("a", 5.0), ("a", 6.0), ("a", 6.0)]
    assert len(store.telemetry("b")) == 1


async def test_replay_is_kept_until_stored_on_v2_and_forgotten_on_v1(tmp_path: Path) -> None:
    """v2: the replayed reports stay with the agent until the writer committed them (``replay_stored``);
    v1: the agent forgets them once sent, and the daemon sends it no acknowledgement."""
    key = new_key()
    slow = TelemetryConfig(flush_s=30.0)  # nothing is committed until the test flushes
    daemon_cm = running_daemon(tmp_path, key, telemetry=slow)
    daemon = await daemon_cm.__aenter__()
    port = daemon.listen_port
    v2 = start_agent("keeper", port, key)
    v1 = start_agent("forgetter", port, key, index=1)
    v1.agent.link.versions = [1]
    try:
        await wait_for(lambda: v2.agent.link.connected and v1.agent.link.connected, 10, "both join")
        assert (v2.agent.link.version, v1.agent.link.version) == (2, 1)
        await daemon_cm.__aexit__(None, None, None)
        await wait_for(
            lambda: v2.agent.link.buffered[0] >= 5 and v1.agent.link.buffered[0] >= 5, 10, "both buffer"
        )
        daemon_cm = running_daemon(tmp_path, key, listen_port=port, telemetry=slow)
        daemon = await daemon_cm.__aenter__()
        await wait_for(
            lambda: v2.agent.link.sessions == 2 and v1.agent.link.sessions == 2 and v2.agent.link.replayed,
            10,
            "both rejoin and replay",
        )
        await wait_for(lambda: v2.agent.link.buffered[0] == 0 and v1.agent.link.buffered[0] == 0, 10, "sent")
        link = v2.agent.link  # (reports from before its first join were replayed and acknowledged then)
        kept, acknowledged = link.unacknowledged, link.acknowledged
        assert kept == link.replayed - acknowledged and kept >= 5  # sent, not yet stored: kept
        assert v1.agent.link.unacknowledged == 0 and v1.agent.link.replayed >= 5
        await daemon.agents.drain_hooks()
        await asyncio.to_thread(daemon.telemetry.flush)  # the commit: now the daemon acknowledges
        await wait_for(lambda: link.unacknowledged == 0, 10, "the acknowledgement")
        assert link.acknowledged == acknowledged + kept and v1.agent.link.acknowledged == 0
    finally:
        await stop_agents([v2, v1])
        await daemon_cm.__aexit__(None, None, None)


def test_retention_prunes_old_samples(tmp_path: Path) -> None:
    store = Store(tmp_path / "db.sqlite")
    row = telemetry_row("a", 1.0, 0.0)
    now = time.time()
    store.add_telemetry([(*row[:2], now - 3600, *row[3:]), (*row[:2], now, *row[3:])])
    assert store.prune_telemetry(now - 60) == 1
    assert len(store.telemetry("a")) == 1


def test_version_1_database_is_migrated_without_losing_data(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    db = sqlite3.connect(path, isolation_level=None)
    db.executescript(f"BEGIN; {_MIGRATIONS[1]} PRAGMA user_version=1; COMMIT;")
    db.execute("INSERT INTO agents VALUES ('veteran', 7, 0, 0, '{}')")
    db.close()
    store = Store(path)
    assert store.known_agents() == {"veteran": 7}
    assert sqlite3.connect(path).execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert store.telemetry("veteran") == []
