"""The one place a body is rendered for the protocol version its session negotiated.

Version 1 treated every unknown field as an error (docs/protocol.md, section 1), so a version-1
peer must get exactly the fields of the version-1 text, at every depth, and nothing else. That is
kept as a list of what version 1 *has* (:data:`V1_FIELDS`, from the version-1 text of
docs/protocol.md) rather than of what later versions added: a field added tomorrow is left out
for a version-1 peer until someone decides it belongs to version 1, instead of cutting every
version-1 agent off (as ``source`` and ``await_release`` did).

One field's meaning cannot be dropped: ``await_release: k`` (a rejoining agent must wait at
barrier k before running on). For a version-1 agent the batch is rendered with what version 1
has for it, a leading ``hold`` of 0 s at step k with ``sync: true``: the agent reports ``finished``
for k again (a repeat the barrier ignores) and waits for the ``release`` of k before the rest.

Every frame to a peer goes through :func:`render` (via :func:`protocol.wire.encode`): the
daemon's outbox, its release burst and keepalives, the handshake stream, the agent's link.
"""

from __future__ import annotations

import json
from enum import Enum

from pydantic import BaseModel

from protocol.actions import GoBy, Goto, Hold, Land, ReturnToLaunch, SetSpeed, Takeoff, Waypoint, Waypoints
from protocol.packets import (
    ActionFailure,
    AgentParameters,
    Battery,
    Body,
    Camera,
    Capabilities,
    Close,
    FenceCircle,
    FenceVertex,
    Geofence,
    GeoPoint,
    Gps,
    PerformActions,
    Position,
    RequestCid,
    ResponseCid,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
    VelocityNed,
)

_ACTION = ("kind", "step", "sync", "timeout_s")

V1_FIELDS: dict[type[BaseModel], frozenset[str]] = {
    # type 0 and what it holds
    RequestCid: frozenset(
        {"identity", "protocol_version", "client_nonce", "capabilities", "home", "proof", "resume", "probe"}
    ),
    Capabilities: frozenset(
        {"vehicle_kind", "max_speed_mps", "endurance_s", "battery_wh", "camera", "autopilot"}
    ),
    Camera: frozenset({"hfov_deg", "vfov_deg", "resolution_px"}),
    GeoPoint: frozenset({"lat", "lon", "alt_amsl"}),
    Resume: frozenset({"mission_id", "completed_step", "waiting_step", "queue_depth"}),
    # type 1
    ResponseCid: frozenset(
        {"outcome", "server_nonce", "cid", "server_proof", "reason", "parameters", "server_time"}
    ),
    AgentParameters: frozenset(
        {
            "status_period_s",
            "link_range_m",
            "battery_low_pct",
            "battery_critical_pct",
            "battery_low_action",
            "battery_critical_action",
            "lost_link_timeout_s",
            "lost_link_action",
            "acceptance_radius_m",
        }
    ),
    # type 2 (version 1 had no ``failsafe`` or ``pilot``)
    StatusReport: frozenset(
        {
            "time",
            "vehicle_time",
            "position",
            "velocity",
            "heading_deg",
            "battery",
            "mode",
            "armed",
            "landed",
            "gps",
            "mission_id",
            "step",
            "completed_step",
            "queue_depth",
            "waiting_sync",
            "paused",
            "exceptions",
            "autopilot_link",
            "buffered",
            "failure",
        }
    ),
    Position: frozenset({"lat", "lon", "alt_rel", "alt_amsl"}),
    VelocityNed: frozenset({"vn", "ve", "vd"}),
    Battery: frozenset({"pct", "voltage_v", "current_a"}),
    Gps: frozenset({"fix", "satellites"}),
    ActionFailure: frozenset({"step", "kind", "reason", "time"}),
    # type 3
    SetParameters: frozenset({"geofence", "clear_geofence", "parameters"}),
    Geofence: frozenset({"circle", "polygon", "max_alt_m", "breach_action"}),
    FenceCircle: frozenset({"lat", "lon", "radius_m"}),
    FenceVertex: frozenset({"lat", "lon"}),
    # type 4 (version 1 had no ``source``, ``await_release`` or ``release_anchor``)
    PerformActions: frozenset({"mission_id", "mode", "actions", "reason"}),
    Takeoff: frozenset({*_ACTION, "alt"}),
    Goto: frozenset({*_ACTION, "lat", "lon", "alt", "speed"}),
    GoBy: frozenset({*_ACTION, "north", "east", "up", "speed"}),
    Land: frozenset({*_ACTION, "lat", "lon"}),
    ReturnToLaunch: frozenset({*_ACTION, "alt"}),
    Hold: frozenset({*_ACTION, "seconds"}),
    SetSpeed: frozenset({*_ACTION, "speed"}),
    Waypoints: frozenset({*_ACTION, "points", "speed"}),
    Waypoint: frozenset({"lat", "lon", "alt"}),
    # types 5 and 6
    SyncSignal: frozenset({"mission_id", "step", "kind"}),
    Close: frozenset({"reason", "message"}),
}
"""Every field of protocol version 1, per model, at every depth (docs/protocol.md, version 1)."""


class VersionError(TypeError):
    """A body holds a model this module has no version-1 form for (a bug: add it to V1_FIELDS)."""


def render(body: Body, version: int) -> bytes:
    """The JSON body of ``body`` as a peer speaking ``version`` must get it (UTF-8 bytes)."""
    if version >= 2:
        return body.model_dump_json(exclude_none=True).encode()
    return json.dumps(_v1(v1_form(body)), ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode()


def v1_form(body: Body) -> Body:
    """``body`` with the meaning of its later-version fields expressed in version-1 terms."""
    if isinstance(body, PerformActions) and body.await_release is not None:
        wait = Hold(step=body.await_release, sync=True, seconds=0.0)
        return body.model_copy(update={"actions": [wait, *body.actions], "await_release": None})
    return body


def _v1(value: object) -> object:
    """``value`` as plain JSON data holding only version-1 fields (None = absent, as in version 2)."""
    if isinstance(value, BaseModel):
        allowed = V1_FIELDS.get(type(value))
        if allowed is None:
            raise VersionError(f"{type(value).__name__} has no version-1 form (protocol/versions.py)")
        out: dict[str, object] = {}
        for name in type(value).model_fields:
            item = getattr(value, name)
            if name in allowed and item is not None:
                out[name] = _v1(item)
        return out
    if isinstance(value, (list, tuple)):
        return [_v1(item) for item in value]
    if isinstance(value, Enum):
        return value.value
    return value


__all__ = ["V1_FIELDS", "VersionError", "render", "v1_form"]
