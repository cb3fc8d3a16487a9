"""Synchronization barriers (CoUAS 2.2.5), as pure bookkeeping: no I/O, no clock.

A mission has one barrier per sync step. Its members are the mission's agents that are not
excluded. An arrival ("finished step k") is idempotent; when every member has arrived the
barrier releases, and a late or repeated arrival at a released step is answered with a release
at once (that is how an agent that reconnects after a daemon restart gets unstuck).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(slots=True)
class BarrierSet:
    """All barriers of one mission."""

    members: set[str]
    sync_steps: list[int]
    released: set[int] = field(default_factory=set)
    arrivals: dict[int, set[str]] = field(default_factory=dict)

    def arrive(self, agent: str, step: int) -> bool:
        """Record ``agent`` finished ``step``; True when this completes (or already completed) the barrier."""
        if step not in self.sync_steps:
            raise ValueError(
                f"step {step} is not a sync step of this mission (sync steps: {self.sync_steps})"
            )
        if step in self.released:
            return True
        self.arrivals.setdefault(step, set()).add(agent)
        return self.is_complete(step)

    def is_complete(self, step: int) -> bool:
        return self.members <= self.arrivals.get(step, set())

    def exclude(self, agent: str) -> list[int]:
        """Drop ``agent`` from every future barrier; returns the pending steps this completes."""
        self.members.discard(agent)
        return [s for s in self.pending_steps() if self.arrivals.get(s) and self.is_complete(s)]

    def pending_steps(self) -> list[int]:
        """Steps with at least one arrival that are not yet released, in order."""
        return sorted(s for s, who in self.arrivals.items() if who and s not in self.released)

    def missing(self, step: int) -> set[str]:
        return self.members - self.arrivals.get(step, set())

    def mark_released(self, step: int) -> None:
        self.released.add(step)
