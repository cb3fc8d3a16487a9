"""Two daemons sharing a fleet through NATS: a 3-drone mission on the simulator, agents split across them."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from gcs.cluster.natsrun import NatsServer
from gcs.core.daemon import Daemon
from gcs.observe.live import LiveHub
from tests.backbone.helpers import mission_ended, survey_mission
from tests.cluster.simrig import spread_rig
from tests.cooperation.rig import wait_for

pytestmark = pytest.mark.slow

LINKS = {"drone-1": "a", "drone-2": "b", "drone-3": "b"}


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
    async with spread_rig(tmp_path, nats_server.url, LINKS) as r:
        a, b = r.a, r.b
        names = list(LINKS)
        cids = {n: a.agents.session(n).cid for n in names}  # type: ignore[union-attr]
        assert sorted(cids.values()) == sorted(set(cids.values()))
        assert {n: b.agents.session(n).cid for n in names} == cids  # type: ignore[union-attr]
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{b.http_port}") as api:
            fleet = (await api.get("/api/v1/cluster/fleet")).json()
            assert {row["identity"]: row["daemon"] for row in fleet} == {
                n: f"gcs-{d}" for n, d in LINKS.items()
            }
            listed = (await api.get("/api/v1/agents")).json()  # what the dashboard lists
            assert sorted(a["identity"] for a in listed) == names
            hub = next(s for s in b.services if isinstance(s, LiveHub))
            await wait_for(lambda: "drone-1" in hub.history, 20, "drone-1 in b's live history (dashboard)")
        task = survey_mission(names, sync_legs=2)
        mission_id = await a.missions.submit(task)
        await wait_for(lambda: b.missions.led_elsewhere(mission_id), 20, "b to see a's mission")
        stored = await mission_ended(a, mission_id, 90, "mission end")
        assert stored.state == "completed", stored
        sync_steps = task.plans[0].sync_steps()
        assert _released((a, b), mission_id) == sync_steps, "every barrier released exactly once"
        assert a.store.released_steps(mission_id) == set(sync_steps)
        await wait_for(lambda: all(r.landed(n) for n in names), 30, "every vehicle landed")
        # b's plans for its agents came from a through b's authority (a mission order, via gcs-a).
        for name in ("drone-2", "drone-3"):
            plans = [
                d
                for d in b.authority.control(name).decisions
                if d.source == "mission" and d.command == "plan" and "(via gcs-a)" in d.reason
            ]
            assert plans, b.authority.control(name).decisions
