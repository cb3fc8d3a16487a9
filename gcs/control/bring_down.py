"""Bring drones down: the one use case behind the operator's RTL/land, an extension's ``rtl``/``land``,
a cooperation monitor's return (emergency, connectivity) and the cluster's forwarded fleet command.

The order matters and is the same for every caller: ask the vehicle authority first (a refusal is
recorded and the drone keeps its mission), take the drone out of its mission (so its landing does
not count as finishing it; in a cluster the daemon leading that mission is told), then start the
deconflicted return at the asker's priority (altitude layers, landing in sequence).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from gcs.missions.runner import MissionRejected

if TYPE_CHECKING:
    from gcs.control.authority import Owner, VehicleAuthority
    from gcs.cooperation.return_coordinator import ReturnCoordinator
    from gcs.missions.runner import MissionRunner

Kind = Literal["rtl", "land"]


@dataclass
class Descent:
    """What a bring-down did: who the authority let ``owner`` command, who got a return program,
    which missions were aborted (left with nobody flying)."""

    allowed: list[str] = field(default_factory=list)
    delivered: list[str] = field(default_factory=list)
    aborted: list[str] = field(default_factory=list)


class BringDown:
    """Withdraw from the mission, then return or land, through the authority (see the module doc)."""

    def __init__(
        self,
        authority: VehicleAuthority,
        missions: MissionRunner,
        returns: ReturnCoordinator,
        records_after: Callable[[], AbstractContextManager[None]] = contextlib.nullcontext,
    ) -> None:
        """``records_after``: a block whose events are stored when it ends (the daemon's
        ``EventBus.deferred``), so every drone's order is on its link before the records are."""
        self._authority = authority
        self._missions = missions
        self._returns = returns
        self._records_after = records_after

    async def __call__(
        self,
        targets: list[str],
        kind: Kind,
        owner: Owner,
        why: str,
        *,
        abort_emptied: bool = False,
        on_allowed: Callable[[str], None] | None = None,
    ) -> Descent:
        """Bring ``targets`` down on behalf of ``owner``.

        ``abort_emptied``: a mission all of whose flying members are targets is aborted (their
        drones hold, then get the return) instead of withdrawing them one by one (the operator's
        fleet command). ``on_allowed`` is told of each target the authority allowed, before its
        withdrawal (the cooperation service forgets its collision picture of it).
        """
        descent = Descent()
        with self._records_after():
            for ident in targets:
                if self._authority.request(ident, owner, kind, why)[0]:  # refusals recorded there
                    descent.allowed.append(ident)
                    if on_allowed is not None:
                        on_allowed(ident)
        if not descent.allowed:
            return descent
        descent.aborted = await self._leave_missions(descent.allowed, owner, why, abort_emptied)
        with self._records_after():  # every order written in one pass, then the ~2 events a drone
            descent.delivered = self._returns.start(descent.allowed, kind, owner, why)
        return descent

    async def _leave_missions(
        self, targets: list[str], owner: Owner, why: str, abort_emptied: bool
    ) -> list[str]:
        """Take the targets out of their missions; a target in none led here is withdrawn anyway
        (in a cluster the mission's leader is told, gcs/missions/runner.py ``withdraw_elsewhere``)."""
        missions, wanted, left, aborted = self._missions, set(targets), set(), []
        for mission_id in list(missions.active):
            mission = missions.active.get(mission_id)
            members = set(missions.members(mission)) if mission is not None else set()
            inside = members & wanted
            if not inside:
                continue
            left |= inside
            if abort_emptied and members <= wanted:
                with contextlib.suppress(MissionRejected):
                    await missions.abort(mission_id, why, owner, "hold")
                    aborted.append(mission_id)
            else:
                for ident in sorted(inside):
                    await missions.withdraw(ident, why)
        for ident in targets:
            if ident not in left:
                await missions.withdraw(ident, why)
        return aborted


__all__ = ["BringDown", "Descent"]
