"""The agent checks what it is told: limits of its own, refusals reported to the daemon, and
releases for barriers it has not reached ignored."""

from __future__ import annotations

import asyncio
from pathlib import Path

from agent.config import SanityLimits
from protocol.actions import Goto, Hold, Takeoff
from protocol.geo import offset_latlon
from protocol.packets import PerformActions, SyncSignal
from tests.backbone.helpers import HOME, new_key, running_daemon, start_agent
from tests.support.polling import wait_for


async def test_absurd_orders_are_refused_and_reported(tmp_path: Path) -> None:
    key = new_key()
    limits = SanityLimits(max_queue_actions=50)
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("careful", daemon.listen_port, key, limits=limits)
        try:
            await wait_for(lambda: (s := daemon.agents.session("careful")) and s.status, 10, "joined")
            far_lat, far_lon = offset_latlon(HOME[0], HOME[1], 1_000_000.0, 0.0)  # 1000 km north
            orders = [
                [Takeoff(step=0, alt=9999.0)],
                # Refused at its first action: nothing of it flies (a batch is flown up to the
                # first action that would cross; tests/protocol_v2/test_agent_limits.py).
                [Goto(step=0, lat=far_lat, lon=far_lon, alt=5.0), Takeoff(step=1, alt=5.0)],
                [Hold(step=0, seconds=86_000.0)],
                [Hold(step=i, seconds=1.0) for i in range(51)],
            ]
            for number, actions in enumerate(orders):
                daemon.agents.post(
                    "careful", PerformActions(mission_id=f"m{number}", mode="replace", actions=actions)
                )
                await wait_for(
                    lambda n=number: (
                        (s := daemon.agents.session("careful")) is not None
                        and s.status is not None
                        and s.status.mission_id == f"m{n}"
                        and s.status.failure is not None
                        and "refused by the agent" in s.status.failure.reason
                    ),
                    10,
                    f"refusal {number} reported",
                )
            reasons = [
                e.message for e in daemon.events.history(kind="agent_exception", agent="careful", limit=100)
            ]
            assert any("command_refused" in r and "max_alt_m" in r for r in reasons), reasons
            t = running.autopilot.telemetry()
            assert t.landed and not t.armed  # nothing was flown
            assert running.agent.queue.depth == 0
        finally:
            await running.kill()


async def test_a_release_for_a_barrier_not_reached_is_ignored(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("patient", daemon.listen_port, key)
        try:
            await wait_for(lambda: daemon.agents.session("patient") is not None, 10, "joined")
            plan = [Hold(step=0, seconds=0.2, sync=True), Hold(step=1, seconds=0.2, sync=True)]
            daemon.agents.post("patient", PerformActions(mission_id="m", mode="replace", actions=plan))
            daemon.agents.post("patient", SyncSignal(mission_id="m", step=1, kind="release"))  # early
            queue = running.agent.queue
            await wait_for(lambda: queue.waiting_sync == 0, 10, "waiting at barrier 0")
            daemon.agents.post("patient", SyncSignal(mission_id="m", step=0, kind="release"))
            await wait_for(lambda: queue.waiting_sync == 1, 10, "waiting at barrier 1")
            await asyncio.sleep(1.0)  # the hold is 0.2 s: an early release remembered would have let it go
            assert queue.waiting_sync == 1 and queue.completed_step == 1
            daemon.agents.post("patient", SyncSignal(mission_id="m", step=1, kind="release"))
            await wait_for(lambda: queue.waiting_sync is None and queue.completed_step == 1, 10, "released")
        finally:
            await running.kill()
