"""Daemon storage and enrollment safety: damaged or vanished databases, file modes, per-agent keys,
bounded exception events (while an agent flies)."""

from __future__ import annotations

import json
import stat
import subprocess
import time
from pathlib import Path

import pytest

from gcs.storage.store import Store, StoreError
from protocol.packets import StatusReport
from protocol.session import ClientHandshake, Refused
from protocol.stream import open_client
from tests.backbone.helpers import new_key, running_daemon, start_agent
from tests.faults.common import hover_mission
from tests.support.polling import wait_for
from tests.support.processes import BIN


def test_database_files_are_private_and_a_vanished_database_is_not_replaced(tmp_path: Path) -> None:
    db = tmp_path / "data" / "fleetgcs.sqlite"
    store = Store(db)
    assert store.cid_for("drone-1", {}) == 1
    store.close()
    assert stat.S_IMODE(db.parent.stat().st_mode) == 0o700
    assert stat.S_IMODE(db.stat().st_mode) == 0o600
    db.unlink()
    with pytest.raises(StoreError, match="missing but a database existed there"):
        Store(db)
    fresh = Store(db, allow_new=True)  # the operator said so
    assert fresh.cid_of("drone-1") is None
    fresh.close()


def test_damaged_database_stops_gcs_serve_at_start_with_one_line(tmp_path: Path) -> None:
    data = tmp_path / "data"
    Store(data / "fleetgcs.sqlite").close()
    (data / "fleetgcs.sqlite").write_bytes(b"this is not SQLite" * 300)
    with pytest.raises(StoreError, match="damaged"):
        Store(data / "fleetgcs.sqlite")
    result = subprocess.run(
        [BIN / "gcs", "serve", "--data-dir", data, "--listen", "127.0.0.1:0", "--http", "none"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    assert "cannot start" in result.stderr and "damaged" in result.stderr
    assert "Traceback" not in result.stderr


async def test_keygen_issues_per_agent_keys_that_the_daemon_accepts(tmp_path: Path) -> None:
    keys_file = tmp_path / "agents.json"
    made = subprocess.run(
        [BIN / "gcs", "keygen", "--agent", "drone-1", "--agent", "drone-2", "--agent-keys", keys_file],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    printed = dict(line.split() for line in made.stdout.splitlines())
    assert json.loads(keys_file.read_text()) == printed and set(printed) == {"drone-1", "drone-2"}
    assert stat.S_IMODE(keys_file.stat().st_mode) == 0o600
    again = subprocess.run(
        [BIN / "gcs", "keygen", "--agent", "drone-1", "--agent-keys", keys_file],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert again.stdout.split() == ["drone-1", printed["drone-1"]]  # kept unless --rotate
    fleet_key = new_key()
    async with running_daemon(
        tmp_path, fleet_key, agent_keys_file=keys_file, allow_unlisted_agents=False
    ) as daemon:
        own = ClientHandshake("drone-1", bytes.fromhex(printed["drone-1"]))
        stream, accepted = await open_client("127.0.0.1", daemon.listen_port, own)
        assert accepted.cid == 1
        await stream.close()
        with pytest.raises(Refused) as caught:  # the fleet key does not open a listed identity
            await open_client(
                "127.0.0.1", daemon.listen_port, ClientHandshake("drone-2", bytes.fromhex(fleet_key))
            )
        assert caught.value.code == "wrong_key"


async def test_exception_events_are_bounded_per_agent(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_exception_events=20) as daemon:
        flying = start_agent("steady", daemon.listen_port, key)
        try:
            await wait_for(lambda: (s := daemon.agents.session("steady")) and s.status, 10, "agent joined")
            mission_id = await daemon.missions.submit(hover_mission("steady", seconds=60.0))
            stream, _ = await open_client(
                "127.0.0.1", daemon.listen_port, ClientHandshake("noisy", bytes.fromhex(key))
            )
            for i in range(50):  # 50 reports, each with 32 names never seen before: 1600 "new" exceptions
                names = [f"n{i}_{j}: x" for j in range(32)]
                await stream.send(StatusReport(time=time.time(), exceptions=names))
            session = daemon.agents.session("noisy")
            await wait_for(lambda: session is not None and session.status_count == 50, 10, "reports in")
            assert session is not None and session.open
            logged = daemon.events.history(kind="agent_exception", agent="noisy", limit=10_000)
            assert 20 <= len(logged) <= 25  # the bucket refills at 20/min during the test
            assert daemon.events.history(kind="agent_exceptions_suppressed", agent="noisy")
            steady = daemon.agents.session("steady")
            assert steady is not None and steady.open and mission_id in daemon.missions.active
            await stream.close()
        finally:
            await flying.kill()
