"""Divergence monitor: the flown track against the planned leg -> corrections or a replan (pure).

It never acts on a drone that waits at a barrier, is paused or held, returns or lands, is in an
emergency, or is under a higher source's order: those are not flying their plan leg, so a
difference from the leg is expected (the issue saw a drone moved 31 m while it waited at a
barrier).
"""

from __future__ import annotations

from gcs.cooperation.config import DivergenceConfig
from gcs.cooperation.divergence import divergence_may_act, leg_error
from gcs.cooperation.intents import EventIntent, HoldIntent, Intent, ReleaseIntent, ReplaceIntent
from gcs.cooperation.tracking import TrackedAgent
from protocol.packets import StatusReport


def _may_act(agent: TrackedAgent, status: StatusReport, held_or_outranked: bool) -> bool:
    """Is the drone flying a plan leg that divergence may correct right now?"""
    if agent.plan is None or agent.judge is None:
        return False
    return divergence_may_act(
        status,
        held=held_or_outranked,
        emergency=agent.emergency is not None,
        detour=agent.detour_step is not None,
    )


class DivergenceMonitor:
    def __init__(self, config: DivergenceConfig, vehicle_time_scale: float) -> None:
        self.config = config
        self.vehicle_time_scale = vehicle_time_scale

    def on_status(
        self, agent: TrackedAgent, status: StatusReport, held_or_outranked: bool, now: float
    ) -> list[Intent]:
        blocked = not _may_act(agent, status, held_or_outranked)
        if agent.plan is not None:
            agent.plan.stop_clock(blocked, status.time)
        if blocked:
            return []
        plan, judge = agent.plan, agent.judge
        assert plan is not None and judge is not None
        leg = plan.leg(status.waiting_sync)
        if leg is None:
            return []
        cfg = self.config
        here = agent.position
        pos = (here.lat, here.lon, here.alt_rel)
        error = leg_error(leg, pos, cfg.lookahead_m)
        elapsed = (status.time - plan.segment_started) * self.vehicle_time_scale
        verdict, detail = judge.judge(leg, error, elapsed, now, plan.replans < cfg.max_replans_per_step)
        data = {"cross_track_m": round(error.cross_track_m, 2), "step": leg.step}
        ident = agent.ident
        if verdict == "lag":
            return [EventIntent("divergence_lag", detail, ident, "warning", data)]
        if verdict == "correct":
            reason = "divergence correction"
            return [
                EventIntent(
                    "divergence_correction",
                    f"{detail}: pause + resume re-issues the leg target",
                    ident,
                    "warning",
                    data,
                ),
                HoldIntent(ident, "divergence", reason),
                ReleaseIntent(ident, "divergence", reason),
            ]
        if verdict == "replan":
            detour = plan.detour(status, error.rejoin, agent.completed)
            if detour is None:
                return []
            plan.replans += 1
            agent.detour_step = detour[0].step
            return [
                EventIntent(
                    "divergence_replan",
                    f"{detail}: re-planned the rest from here via a rejoin point on the planned leg",
                    ident,
                    "warning",
                    {**data, "rejoin": list(error.rejoin), "actions": len(detour)},
                ),
                ReplaceIntent(ident, "divergence", detour, detail, "replan"),
            ]
        return []
