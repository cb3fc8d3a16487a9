"""A barrier release against a real daemon and real TCP agents: one burst, journaled first.

The agents are the stdlib agent of docs/protocol.md on blocking sockets in threads, so they
observe the daemon from outside its event loop. The test holds the store's write lock while the
last agent arrives: the release must reach every agent anyway (it no longer waits for the
database), each agent must find it in the release journal when it hears it (durable before it is
sent), and the release row and its event must be in the database once the lock is free.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.backbone.helpers import new_key, running_daemon, survey_mission
from tests.protocol_v2.stdlib_agent import StdlibAgent
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(120)

AGENTS = 12
HOLD_S = 0.4  # how long the test keeps the write lock once every agent has sent 'finished'


def _persisted(db_path: str, mission_id: str, step: int) -> tuple[bool, bool]:
    """(release row, sync_released event) as another process would read them right now."""
    db = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10)
    try:
        row = db.execute(
            "SELECT 1 FROM releases WHERE mission_id=? AND step=?", (mission_id, step)
        ).fetchone()
        event = db.execute(
            "SELECT 1 FROM events WHERE kind='sync_released' AND mission_id=?", (mission_id,)
        ).fetchone()
        return row is not None, event is not None
    finally:
        db.close()


def _journaled(db_path: str, mission_id: str, step: int) -> bool:
    """The release is a line of the release journal beside the database (gcs/missions/release_journal.py)."""
    entries = [json.loads(line) for line in Path(db_path + "-releases").read_text().splitlines()]
    return any(entry["m"] == mission_id and entry["s"] == step for entry in entries)


def _await_release(agent: StdlibAgent, mission_id: str, step: int, db_path: str, out: dict[str, Any]) -> None:
    """Read frames until the release of ``step``; note when it came and whether it was journaled then."""
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            ptype, body = agent.receive()
        except TimeoutError:
            continue
        if ptype == 5 and body.get("kind") == "release" and body.get("mission_id") == mission_id:
            out[agent.identity] = (time.time(), body["step"], _journaled(db_path, mission_id, step))
            return


async def test_a_release_reaches_every_member_in_one_burst_journaled_first(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [StdlibAgent(daemon.listen_port, f"burst-{i:02d}", key) for i in range(AGENTS)]
        bursts: list[tuple[list[str], int, bool]] = []
        burst = daemon.agents.burst

        def spy(identities: list[str], body: Any) -> int:  # the real burst, recorded
            sent = burst(identities, body)
            if getattr(body, "kind", None) == "release":
                bursts.append((list(identities), sent, asyncio.current_task() is None))
            return sent

        daemon.agents.burst = spy  # type: ignore[method-assign]
        try:
            for agent in agents:
                await asyncio.to_thread(agent.handshake)
                agent.status()  # a 3-D fix: the mission may start
            identities = [a.identity for a in agents]
            await wait_for(
                lambda: all((s := daemon.agents.session(i)) and s.status for i in identities), 10, "fix"
            )
            mission_id = await daemon.missions.submit(survey_mission(identities, sync_legs=1))
            db_path = str(daemon.store.path)
            for agent in agents[:-1]:
                agent.send(5, {"mission_id": mission_id, "step": 0, "kind": "finished"})
            mission = daemon.missions.active[mission_id]
            await wait_for(lambda: len(mission.barriers.arrivals.get(0, ())) == AGENTS - 1, 10, "arrivals")

            received: dict[str, Any] = {}
            readers = [
                threading.Thread(
                    target=_await_release, args=(a, mission_id, 0, db_path, received), daemon=True
                )
                for a in agents
            ]
            locked, unlocked_at = threading.Event(), [0.0]

            def hold_the_write_lock() -> None:
                with daemon.store.write_lock:
                    locked.set()
                    agents[-1].send(5, {"mission_id": mission_id, "step": 0, "kind": "finished"})
                    time.sleep(HOLD_S)  # the daemon's loop blocks on the lock to persist meanwhile
                    unlocked_at[0] = time.time()

            holder = threading.Thread(target=hold_the_write_lock, daemon=True)
            for reader in readers:
                reader.start()
            holder.start()
            await asyncio.to_thread(locked.wait, 10)
            await asyncio.to_thread(holder.join, 20)
            for reader in readers:
                await asyncio.to_thread(reader.join, 20)

            assert sorted(received) == sorted(identities), (
                f"not released to {set(identities) - set(received)}"
            )
            assert len(bursts) == 1, bursts
            members, sent, outside_tasks = bursts[0]
            assert sorted(members) == sorted(identities) and sent == AGENTS
            assert outside_tasks, "the release was sent from a hook task, not from the last arrival's frame"
            for identity, (at, step, journaled) in received.items():
                assert step == 0
                assert journaled, f"{identity} got the release before it was journaled"
                assert at < unlocked_at[0], f"{identity} got the release only once the database was free"
            await wait_for(
                lambda: all(_persisted(db_path, mission_id, 0)), 10, "release row and event stored"
            )
            assert daemon.store.released_steps(mission_id) == {0}
        finally:
            for agent in agents:
                agent.close()
            await asyncio.sleep(0.2)
