"""Missions over field-quality links (issue 26): daemon + 3 in-process agents + our simulator, each
agent behind its own fault proxy (and, for MAVLink loss, a relay in front of its vehicle), set to
one profile of tests/faults/links.py.

Per profile: the synchronized mission completes; every barrier is released once, in order, and
only after every drone finished that step (checked on the agents themselves when a release reaches
them); every agent runs each of its steps exactly once; an operator RTL then reaches each vehicle
within the profile's bound. The ``outage`` profile cuts drone-2's link for 30 s of vehicle time
while it flies its first leg.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from agent.runtime import Agent
from protocol.actions import Action
from tests.cooperation.rig import SPEEDUP, rig, wait_for
from tests.faults.common import released_steps
from tests.faults.links import PROFILES, LinkProfile, LinkRig
from tests.scenarios.scenarios import link_task, outage_on_first_leg, rtl_delivery

pytestmark = pytest.mark.slow

SYNC_STEPS = [0, 1, 2]
LAST_STEP = 3


class Observer:
    """What the agents themselves did: steps run, and at every release reaching one of them,
    whether every agent had finished that step (wraps instance methods; nothing changes)."""

    def __init__(self, agents: dict[str, Agent]) -> None:
        self.agents = agents
        self.ran: dict[str, list[int]] = {name: [] for name in agents}
        self.early: list[tuple[str, int, dict[str, int]]] = []  # (who got it, step, completed steps)
        for name, agent in agents.items():
            self._watch(name, agent)

    def _watch(self, name: str, agent: Agent) -> None:
        run, release = agent.executor.run, agent.queue.release

        async def traced_run(action: Action) -> None:
            self.ran[name].append(action.step)
            await run(action)

        def traced_release(mission_id: str, step: int) -> None:
            done = {n: a.queue.completed_step for n, a in self.agents.items()}
            if mission_id == agent.queue.mission_id and any(c < step for c in done.values()):
                self.early.append((name, step, done))
            release(mission_id, step)

        agent.executor.run = traced_run  # type: ignore[method-assign]
        agent.queue.release = traced_release  # type: ignore[method-assign]


@pytest.mark.parametrize("profile", list(PROFILES.values()), ids=list(PROFILES))
async def test_synchronized_mission_over_a_field_link(tmp_path: Path, profile: LinkProfile) -> None:
    async with (
        LinkRig(profile, seed=7) as links,
        rig(tmp_path, 3, **links.rig_options(SPEEDUP)) as r,
    ):
        watch = Observer(r.agents)
        mission_id = await r.daemon.missions.submit(link_task(r.names))
        if profile.outage_s:
            await outage_on_first_leg(r, links, "drone-2")
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 60, "the mission to end")
        progress = r.daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed", progress
        assert not any(a.excluded for a in progress.agents), progress
        assert released_steps(r.daemon, mission_id) == SYNC_STEPS
        assert watch.early == [], "a barrier was released before every drone finished its step"
        assert watch.ran == {n: [0, 1, 2, LAST_STEP] for n in r.names}, watch.ran
        reached = await rtl_delivery(r, "link profile test")
        late = {n: round(s, 2) for n, s in reached.items() if s > profile.rtl_bound_s}
        assert not late, f"RTL later than {profile.rtl_bound_s} s on {profile.name}: {late}"
        await wait_for(lambda: all(r.landed(n) for n in r.names), 60, "everyone landed")
        if profile.outage_s:
            assert links.proxies["drone-2"].stats["partition_stall"] == 1
        if profile.mavlink_loss:
            assert sum(relay.stats["up_dropped"] for relay in links.relays.values()) > 0
        if profile.spike_rate:
            assert sum(p.stats["up_spiked"] + p.stats["down_spiked"] for p in links.proxies.values()) > 0
