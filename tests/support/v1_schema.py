"""A strict decoder of what a protocol-version-1 agent may receive, written from the v1 text alone.

Standard library only, no fleetgcs imports: it is what a third party who read the version-1
docs/protocol.md would write. Version 1 treats every unknown field as an error, at any depth, and
parses strictly (no coercion, no NaN/Infinity, no duplicate keys), so everything the daemon sends
to a version-1 agent must pass :func:`check_v1_body`; anything else raises :class:`V1Violation`
naming the packet type and the path of the offending field.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from typing import Any

Check = Callable[[Any, str], None]


class V1Violation(AssertionError):
    """A body a strict version-1 receiver rejects (an unknown field, a wrong type or range...)."""


def _fail(where: str, why: str) -> None:
    raise V1Violation(f"{where}: {why}")


def integer(lo: int | None = None, hi: int | None = None) -> Check:
    def check(value: Any, where: str) -> None:
        if type(value) is not int:
            _fail(where, f"{value!r} is not an int")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            _fail(where, f"{value} outside {lo}..{hi}")

    return check


def number(lo: float | None = None, hi: float | None = None, *, above: float | None = None) -> Check:
    def check(value: Any, where: str) -> None:
        if type(value) not in (int, float) or not math.isfinite(value):
            _fail(where, f"{value!r} is not a finite number")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            _fail(where, f"{value} outside {lo}..{hi}")
        if above is not None and value <= above:
            _fail(where, f"{value} not above {above}")

    return check


def boolean(value: Any, where: str) -> None:
    if type(value) is not bool:
        _fail(where, f"{value!r} is not a bool")


def text(max_len: int | None = None, min_len: int = 0, pattern: str | None = None) -> Check:
    def check(value: Any, where: str) -> None:
        if type(value) is not str:
            _fail(where, f"{value!r} is not a string")
        if len(value) < min_len or (max_len is not None and len(value) > max_len):
            _fail(where, f"length {len(value)} outside {min_len}..{max_len}")
        if pattern is not None and not re.fullmatch(pattern, value):
            _fail(where, f"{value!r} does not match {pattern}")

    return check


def one_of(*values: str) -> Check:
    def check(value: Any, where: str) -> None:
        if value not in values or type(value) is not str:
            _fail(where, f"{value!r} is not one of {values}")

    return check


def listing(item: Check, min_len: int = 0, max_len: int | None = None) -> Check:
    def check(value: Any, where: str) -> None:
        if type(value) is not list:
            _fail(where, f"{value!r} is not a list")
        if len(value) < min_len or (max_len is not None and len(value) > max_len):
            _fail(where, f"{len(value)} entries, expected {min_len}..{max_len}")
        for index, entry in enumerate(value):
            item(entry, f"{where}[{index}]")

    return check


def obj(fields: dict[str, Check], required: tuple[str, ...] = ()) -> Check:
    """An object of exactly these fields (version 1: an unknown one is an error); no nulls."""

    def check(value: Any, where: str) -> None:
        if type(value) is not dict:
            _fail(where, f"{value!r} is not an object")
        for name in required:
            if name not in value:
                _fail(where, f"required field {name!r} missing")
        for name, entry in value.items():
            if name not in fields:
                _fail(where, f"unknown field {name!r}")
            fields[name](entry, f"{where}.{name}")

    return check


LAT, LON = number(-90, 90), number(-180, 180)
HEX_NONCE = text(128, 32, r"[0-9a-f]+")
HEX_MAC = text(64, 64, r"[0-9a-f]+")
REACTION = one_of("report", "rtl", "land", "hold")
PARAMETERS = obj(
    {
        "status_period_s": number(0.02, 60),
        "link_range_m": number(above=0),
        "battery_low_pct": number(0, 100),
        "battery_critical_pct": number(0, 100),
        "battery_low_action": REACTION,
        "battery_critical_action": REACTION,
        "lost_link_timeout_s": number(above=0),
        "lost_link_action": one_of("continue", "hold", "rtl", "land"),
        "acceptance_radius_m": number(above=0),
    }
)
GEOFENCE = obj(
    {
        "circle": obj({"lat": LAT, "lon": LON, "radius_m": number(above=0)}, ("lat", "lon", "radius_m")),
        "polygon": listing(obj({"lat": LAT, "lon": LON}, ("lat", "lon")), 3, 500),
        "max_alt_m": number(above=0),
        "breach_action": REACTION,
    }
)
_COMMON = {"kind": text(), "step": integer(0), "sync": boolean, "timeout_s": number(above=0)}
SPEED = number(above=0, hi=100)
ACTIONS: dict[str, Check] = {
    "takeoff": obj({**_COMMON, "alt": number(above=0)}, ("kind", "step", "alt")),
    "goto": obj(
        {**_COMMON, "lat": LAT, "lon": LON, "alt": number(), "speed": SPEED},
        ("kind", "step", "lat", "lon", "alt"),
    ),
    "go_by": obj(
        {**_COMMON, "north": number(), "east": number(), "up": number(), "speed": SPEED},
        ("kind", "step", "north", "east", "up"),
    ),
    "land": obj({**_COMMON, "lat": LAT, "lon": LON}, ("kind", "step")),
    "rtl": obj({**_COMMON, "alt": number(2, 3000)}, ("kind", "step")),
    "hold": obj({**_COMMON, "seconds": number(0)}, ("kind", "step", "seconds")),
    "set_speed": obj({**_COMMON, "speed": SPEED}, ("kind", "step", "speed")),
    "waypoints": obj(
        {
            **_COMMON,
            "points": listing(obj({"lat": LAT, "lon": LON, "alt": number()}, ("lat", "lon", "alt")), 1, 2000),
            "speed": SPEED,
        },
        ("kind", "step", "points"),
    ),
}


def action(value: Any, where: str) -> None:
    kind = value.get("kind") if type(value) is dict else None
    if not isinstance(kind, str) or kind not in ACTIONS:
        _fail(where, f"unknown action kind {kind!r}")
        return
    ACTIONS[kind](value, where)
    if kind == "land" and ("lat" in value) != ("lon" in value):
        _fail(where, "land needs both lat and lon or neither")


BODIES: dict[int, Check] = {
    1: obj(
        {
            "outcome": one_of("challenge", "accepted", "refused"),
            "server_nonce": HEX_NONCE,
            "cid": integer(1, 65535),
            "server_proof": HEX_MAC,
            "reason": text(512),
            "parameters": PARAMETERS,
            "server_time": number(),
        },
        ("outcome",),
    ),
    3: obj({"geofence": GEOFENCE, "clear_geofence": boolean, "parameters": PARAMETERS}),
    4: obj(
        {
            "mission_id": text(64, 1),
            "mode": one_of("append", "replace", "pause", "resume"),
            "actions": listing(action, 0, 10_000),
            "reason": text(200),
        },
        ("mission_id",),
    ),
    5: obj(
        {"mission_id": text(64, 1), "step": integer(0), "kind": one_of("finished", "release")},
        ("mission_id", "step", "kind"),
    ),
    6: obj(
        {
            "reason": one_of("normal", "refused", "protocol_error", "replaced", "shutdown"),
            "message": text(512),
        },
        ("reason",),
    ),
}
"""Every packet type a daemon sends to an agent, as the version-1 text defines it."""


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        raise V1Violation(f"duplicate key in {keys}")
    return dict(pairs)


def _constant(name: str) -> Any:
    raise V1Violation(f"{name} is not JSON")


def check_v1_body(ptype: int, payload: bytes) -> dict[str, Any]:
    """Parse and check one body a version-1 agent received; the body, or V1Violation."""
    if ptype not in BODIES:
        raise V1Violation(f"packet type {ptype} is not one a daemon sends in version 1")
    try:
        body = json.loads(payload.decode("utf-8"), object_pairs_hook=_pairs, parse_constant=_constant)
    except ValueError as exc:
        raise V1Violation(f"type {ptype}: not UTF-8 JSON: {exc}") from None
    BODIES[ptype](body, f"type {ptype}")
    if ptype == 4 and body.get("mode") in ("pause", "resume") and body.get("actions"):
        raise V1Violation(f"type 4: mode {body['mode']!r} carries no actions")
    return body


__all__ = ["BODIES", "V1Violation", "check_v1_body"]
