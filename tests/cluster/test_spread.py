"""Two daemons sharing a fleet through NATS: a mission flown by agents split across them."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.daemon import Daemon
from gcs.live import LiveHub
from tests.backbone.helpers import (
    daemon_config,
    new_key,
    start_agent,
    stop_agents,
    survey_mission,
    wait_for,
)

pytestmark = pytest.mark.slow


@contextlib.asynccontextmanager
async def two_daemons(
    tmp_path: Path, servers: str, key: str, **overrides: object
) -> AsyncIterator[tuple[Daemon, Daemon]]:
    daemons = []
    try:
        for name in ("a", "b"):
            config = daemon_config(
                tmp_path / name,
                key,
                cluster=servers,
                daemon_id=f"gcs-{name}",
                http_host="127.0.0.1",
                http_port=0,
                api_token="t",
                **overrides,
            )
            daemon = Daemon(config)
            await daemon.start()
            daemons.append(daemon)
        yield daemons[0], daemons[1]
    finally:
        for daemon in reversed(daemons):
            await daemon.stop()


def _released(daemons: tuple[Daemon, ...], mission_id: str) -> list[int]:
    steps: list[int] = []
    for daemon in daemons:
        steps += [
            int(e.data["step"])
            for e in daemon.store.events(kind="sync_released", limit=1000)
            if e.mission_id == mission_id
        ]
    return sorted(steps)


async def test_mission_spread_over_two_daemons(tmp_path: Path, nats_server: NatsServer) -> None:
    key = new_key()
    async with two_daemons(tmp_path, nats_server.url, key) as (a, b):
        agents = [
            start_agent("d0", a.listen_port, key, 0),
            start_agent("d1", b.listen_port, key, 1),
            start_agent("d2", b.listen_port, key, 2),
        ]
        try:
            await wait_for(
                lambda: all(a.agents.session(n) and b.agents.session(n) for n in ("d0", "d1", "d2")),
                10,
                "every agent visible from both daemons",
            )
            cids = {n: a.agents.session(n).cid for n in ("d0", "d1", "d2")}  # type: ignore[union-attr]
            assert sorted(cids.values()) == sorted(set(cids.values()))
            assert {n: b.agents.session(n).cid for n in cids} == cids  # type: ignore[union-attr]
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{b.http_port}") as api:
                fleet = (await api.get("/api/v1/cluster/fleet")).json()
                assert {row["identity"]: row["daemon"] for row in fleet} == {
                    "d0": "gcs-a",
                    "d1": "gcs-b",
                    "d2": "gcs-b",
                }
                listed = (await api.get("/api/v1/agents")).json()  # what the dashboard lists
                assert sorted(a["identity"] for a in listed) == ["d0", "d1", "d2"]
                hub = next(s for s in b.services if isinstance(s, LiveHub))
                await wait_for(lambda: "d0" in hub.history, 5, "d0 in b's live history (dashboard)")
            task = survey_mission(["d0", "d1", "d2"], sync_legs=2)
            mission_id = await a.missions.submit(task)
            await wait_for(lambda: b.missions.led_elsewhere(mission_id), 5, "b to see a's mission")
            await wait_for(
                lambda: (m := a.store.mission(mission_id)) is not None and m.state != "running",
                60,
                "mission end",
                poll=0.1,
            )
            stored = a.store.mission(mission_id)
            assert stored is not None and stored.state == "completed", stored
            sync_steps = task.plans[0].sync_steps()
            assert _released((a, b), mission_id) == sync_steps, "every barrier released exactly once"
            assert a.store.released_steps(mission_id) == set(sync_steps)
        finally:
            await stop_agents(agents)
