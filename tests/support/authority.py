"""A vehicle authority on a recording link, and terse status reports, for the pure authority units."""

from __future__ import annotations

from gcs.control.authority import VehicleAuthority
from protocol.packets import Body, PerformActions, StatusReport


class Link:
    """Records what the authority posts (the real AgentManager.post queues it per agent)."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, PerformActions, bool]] = []

    def post(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        assert isinstance(body, PerformActions)
        self.sent.append((identity, body, bool(urgent)))
        return True

    def modes(self) -> list[str]:
        return [f"{b.mode}:{b.source}" for _, b, _ in self.sent]


def authority() -> tuple[VehicleAuthority, Link, list[tuple[str, str, str, bool, str]], dict[str, str]]:
    link = Link()
    decisions: list[tuple[str, str, str, bool, str]] = []
    persisted: dict[str, str] = {}

    def persist(agent: str, owner: str, reason: str | None) -> None:
        if reason is None:
            persisted.pop(f"{agent}/{owner}", None)
        else:
            persisted[f"{agent}/{owner}"] = reason

    auth = VehicleAuthority(link, lambda *d: decisions.append(d), persist)
    return auth, link, decisions, persisted


def status(**fields: object) -> StatusReport:
    base: dict[str, object] = {"time": 1.0, "armed": True, "landed": False}
    base.update(fields)
    return StatusReport.model_validate(base)
