"""What a monitor decides: intents, applied by the cooperation service through the vehicle authority.

Monitors (collision, emergency, divergence, connectivity) are pure deciders: they read the fleet
picture and return a list of these; they never send packets. The service hands each intent to
:class:`gcs.control.authority.VehicleAuthority` (which may refuse it: a lower source never undoes a
higher one) or to the event log.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from gcs.control.authority import Owner
from protocol.actions import Action


@dataclass(frozen=True)
class HoldIntent:
    ident: str
    owner: Owner
    reason: str


@dataclass(frozen=True)
class ReleaseIntent:
    ident: str
    owner: Owner
    reason: str


@dataclass(frozen=True)
class ReplaceIntent:
    """New actions for the drone (an escape, a detour, a return toward the fleet)."""

    ident: str
    owner: Owner
    actions: list[Action]
    reason: str
    order: str


@dataclass(frozen=True)
class EndOrderIntent:
    """The owner's order (an escape, a detour) is done: lower sources may act again."""

    ident: str
    owner: Owner
    reason: str


@dataclass(frozen=True)
class ReturnIntent:
    """Take the drone out of its mission and bring it down (deconflicted RTL or land)."""

    ident: str
    owner: Owner
    action: Literal["rtl", "land"]
    reason: str


@dataclass(frozen=True)
class EventIntent:
    kind: str
    message: str
    agent: str | None = None
    severity: Literal["info", "warning", "error"] = "info"
    data: dict[str, Any] = field(default_factory=dict)


Intent = HoldIntent | ReleaseIntent | ReplaceIntent | EndOrderIntent | ReturnIntent | EventIntent

__all__ = [
    "EndOrderIntent",
    "EventIntent",
    "HoldIntent",
    "Intent",
    "ReleaseIntent",
    "ReplaceIntent",
    "ReturnIntent",
]
