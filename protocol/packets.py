"""Bodies of the seven packet types (CoUAS Table 2), as pydantic models.

Each body travels as a UTF-8 JSON object inside one frame (see :mod:`protocol.wire`). Models
forbid unknown fields so that a typo in *our* code is an error; on the wire, the decoder drops
unknown fields outside commands before validating (docs/protocol.md, "must ignore"), so that
adding an optional field is not a breaking change. What a version-1 peer gets of each body is
decided in one place, :mod:`protocol.versions` (its list of the version-1 fields).
Units: degrees (lat/lon/heading), metres, m/s, seconds, volts, amperes, percent.
"""

from __future__ import annotations

import enum
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from protocol.actions import Action, AltitudeRel, Latitude, Longitude
from protocol.geo import distance_m, point_in_polygon

PROTOCOL_VERSION = 2
"""The newest protocol version this code speaks (the session version is negotiated, see
:mod:`protocol.session`)."""
SUPPORTED_VERSIONS: tuple[int, ...] = (1, 2)
"""Every protocol version this code speaks, oldest first."""

Identity = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")]
HexNonce = Annotated[str, Field(min_length=32, max_length=128, pattern=r"^[0-9a-f]+$")]
HexAnchor = Annotated[str, Field(min_length=32, max_length=32, pattern=r"^[0-9a-f]+$")]
HexMac = Annotated[str, Field(min_length=64, max_length=64, pattern=r"^[0-9a-f]+$")]
Finite = Annotated[float, Field(allow_inf_nan=False)]
MissionId = Annotated[str, Field(min_length=1, max_length=64)]


class PacketType(enum.IntEnum):
    """The packet type byte of the frame header."""

    REQUEST_CID = 0
    RESPONSE_CID = 1
    STATUS = 2
    SET_PARAMETERS = 3
    PERFORM_ACTIONS = 4
    SYNC = 5
    CLOSE = 6


Code = Annotated[str, Field(min_length=1, max_length=32, pattern=r"^[a-z][a-z0-9_]*$")]
"""A refusal or close code (v2); the known ones and what they mean are in :mod:`protocol.session`."""


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --- type 0: request connection ID -------------------------------------------------------------


class Camera(_Body):
    """What the planner needs to know about the payload camera."""

    hfov_deg: Annotated[float, Field(gt=0.0, lt=180.0)]
    vfov_deg: Annotated[float, Field(gt=0.0, lt=180.0)]
    resolution_px: tuple[Annotated[int, Field(gt=0)], Annotated[int, Field(gt=0)]]


class Capabilities(_Body):
    """The vehicle's abilities, used by planners to divide work by capability."""

    vehicle_kind: Literal["multicopter", "fixed_wing", "vtol", "rover", "other"] = "multicopter"
    max_speed_mps: Annotated[float, Field(gt=0.0, le=100.0)] = 10.0
    endurance_s: Annotated[float, Field(gt=0.0, le=172_800.0)] = 1200.0
    battery_wh: Annotated[float, Field(gt=0.0, le=100_000.0)] | None = None
    camera: Camera | None = None
    autopilot: str = Field(default="unknown", max_length=64)


class GeoPoint(_Body):
    """A lat/lon position with altitude above mean sea level."""

    lat: Latitude
    lon: Longitude
    alt_amsl: Finite = 0.0


class Resume(_Body):
    """What the agent still holds from an earlier session, so the daemon can resume it."""

    mission_id: MissionId
    completed_step: int = Field(ge=-1)
    waiting_step: int | None = Field(default=None, ge=0, description="sync step awaiting release")
    queue_depth: int = Field(ge=0)


class RequestCid(_Body):
    """Type 0. Sent twice in a handshake: first without ``proof`` (hello), then with it.

    ``proof`` = hex HMAC-SHA256(key, "fleetgcs-agent-v1|" identity "|" server_nonce "|"
    client_nonce), where server_nonce is the challenge of the type-1 reply to the hello.

    ``probe`` (optional, default false) asks only for authentication: a check such as
    ``agent doctor`` gets an ``accepted`` without a CID and never becomes a fleet member.

    ``compact_status`` (optional, v2 only, in the request with ``proof``) offers the compact binary
    status body (protocol/status_binary.py, frame type byte 0x82); the agent uses it only once
    the accepting type 1 says so.

    ``release_beacon`` (optional, v2 only) says the agent listens for barrier releases as UDP
    datagrams (protocol/beacon.py); the daemon then sends it each mission's chain anchor with the
    mission's actions (``PerformActions.release_anchor``).
    """

    identity: Identity
    protocol_version: int = Field(ge=1, le=255, description="the highest version the agent speaks")
    versions: list[Annotated[int, Field(ge=1, le=255)]] | None = Field(
        default=None,
        min_length=1,
        max_length=16,
        description="v2: every version the agent speaks; absent = [protocol_version] (a v1 agent)",
    )
    client_nonce: HexNonce
    capabilities: Capabilities = Capabilities()
    home: GeoPoint | None = None
    proof: HexMac | None = None
    resume: Resume | None = None
    probe: bool = False
    compact_status: bool | None = Field(default=None, description="v2: offers the compact status body (0x82)")
    release_beacon: bool | None = Field(
        default=None, description="v2: the agent listens for release beacons (protocol/beacon.py)"
    )


# --- type 1: response with connection ID -------------------------------------------------------


class AgentParameters(_Body):
    """Parameter settings the daemon pushes to an agent (absent field = unchanged)."""

    status_period_s: Annotated[float, Field(ge=0.02, le=60.0)] | None = None
    link_range_m: Annotated[float, Field(gt=0.0, le=100_000.0)] | None = None
    battery_low_pct: Annotated[float, Field(ge=0.0, le=100.0)] | None = None
    battery_critical_pct: Annotated[float, Field(ge=0.0, le=100.0)] | None = None
    battery_low_action: Literal["report", "rtl", "land", "hold"] | None = None
    battery_critical_action: Literal["report", "rtl", "land", "hold"] | None = None
    lost_link_timeout_s: Annotated[float, Field(gt=0.0, le=3600.0)] | None = None
    lost_link_action: Literal["continue", "hold", "rtl", "land"] | None = None
    acceptance_radius_m: Annotated[float, Field(gt=0.0, le=1000.0)] | None = None


class ResponseCid(_Body):
    """Type 1. ``challenge`` answers a hello; ``accepted`` or ``refused`` answers a proof.

    On ``accepted``, ``server_proof`` = hex HMAC-SHA256(key, "fleetgcs-daemon-v1|" identity "|"
    client_nonce "|" server_nonce) lets the agent check it talks to a daemon holding its key.
    ``compact_status`` (v2, on ``accepted``, only when the request with proof offered it) lets the
    agent send its status reports in the compact binary body.
    """

    outcome: Literal["challenge", "accepted", "refused"]
    server_nonce: HexNonce | None = None
    cid: int | None = Field(default=None, ge=1, le=65_535)
    server_proof: HexMac | None = None
    reason: str | None = Field(default=None, max_length=512)
    parameters: AgentParameters | None = None
    server_time: Finite | None = None
    protocol_version: int | None = Field(
        default=None, ge=1, le=255, description="v2: the version the session speaks (with challenge/accepted)"
    )
    code: Code | None = Field(default=None, description="v2: with refused, what the agent should do")
    retry_after_s: Annotated[float, Field(ge=0.0, le=86_400.0, allow_inf_nan=False)] | None = Field(
        default=None, description="v2: with a retry code, wait at least this long"
    )
    lost: bool | None = Field(
        default=None, description="v2: with accepted, true when the daemon had marked this agent lost"
    )
    compact_status: bool | None = Field(
        default=None, description="v2: with accepted, the agent may send the compact status body (0x82)"
    )
    refusal_proof: HexMac | None = Field(
        default=None,
        description="v2: with refused, after the agent proved its key: the daemon proves the refusal",
    )


# --- type 2: status report ---------------------------------------------------------------------


class Position(_Body):
    lat: Latitude
    lon: Longitude
    alt_rel: Finite
    alt_amsl: Finite


class VelocityNed(_Body):
    vn: Finite = 0.0
    ve: Finite = 0.0
    vd: Finite = 0.0


class Battery(_Body):
    pct: Annotated[float, Field(ge=0.0, le=100.0)] | None = None
    voltage_v: Annotated[float, Field(ge=0.0, le=1000.0)] | None = None
    current_a: Annotated[float, Field(ge=-1000.0, le=1000.0)] | None = None


class Gps(_Body):
    fix: int = Field(default=0, ge=0, le=8)
    satellites: int = Field(default=0, ge=0, le=255)


class ActionFailure(_Body):
    """The action of the report's mission that failed last; the agent then holds, queue empty.

    It stays in every report until the agent starts another action, so the daemon sees it even
    across a lost report; ``time`` (agent clock) tells a repeated failure of the same step apart.
    """

    step: int = Field(ge=0)
    kind: str = Field(max_length=32)
    reason: str = Field(max_length=300, description="the autopilot's words, e.g. a refusal")
    time: Finite


class StatusReport(_Body):
    """Type 2. Sent every status period; ``seq`` of the frame orders them."""

    time: Finite = Field(description="agent wall clock, UNIX seconds")
    vehicle_time: Finite | None = Field(
        default=None,
        ge=0.0,
        description="the autopilot's own clock (seconds since its boot) at this position; a simulator's "
        "sim time, so records stay right when it runs faster than real time or falls behind",
    )
    position: Position | None = Field(
        default=None, description="None until the vehicle has reported a 3-D fix (no position yet)"
    )
    velocity: VelocityNed = VelocityNed()
    heading_deg: Annotated[float, Field(ge=0.0, le=360.0)] = 0.0
    battery: Battery = Battery()
    mode: str = Field(default="UNKNOWN", max_length=32)
    armed: bool = False
    landed: bool = True
    gps: Gps = Gps()
    mission_id: MissionId | None = None
    step: int = Field(default=-1, ge=-1, description="step being executed, -1 idle")
    completed_step: int = Field(default=-1, ge=-1, description="last completed step of mission_id")
    queue_depth: int = Field(default=0, ge=0)
    waiting_sync: int | None = Field(default=None, ge=0)
    paused: bool = Field(default=False, description="held by a type-4 pause until resumed")
    exceptions: list[Annotated[str, Field(max_length=200)]] = Field(default_factory=list, max_length=32)
    autopilot_link: bool = True
    buffered: bool = Field(default=False, description="recorded while the daemon link was down")
    failure: ActionFailure | None = None
    failsafe: str | None = Field(
        default=None,
        max_length=200,
        description="the agent's own failsafe in force ('name: reaction'), latched until landed or an "
        "operator command; while set the agent refuses lower-priority type-4 orders",
    )
    pilot: str | None = Field(
        default=None,
        max_length=32,
        description="v2: the mode a pilot (RC transmitter or another ground station) put the vehicle in, "
        "a mode change the agent did not command; while set the agent sends nothing that moves the "
        "vehicle and refuses every type-4 order but the operator's release (docs/cooperation.md)",
    )


# --- type 3: set geofence (and the other parameter settings) -----------------------------------


class FenceCircle(_Body):
    lat: Latitude
    lon: Longitude
    radius_m: Annotated[float, Field(gt=0.0, le=100_000.0)]


class FenceVertex(_Body):
    lat: Latitude
    lon: Longitude


class Geofence(_Body):
    """An inclusion fence: a circle and/or a polygon, with an altitude ceiling above home."""

    circle: FenceCircle | None = None
    polygon: list[FenceVertex] | None = Field(default=None, min_length=3, max_length=500)
    max_alt_m: Annotated[float, Field(gt=0.0, le=10_000.0)] | None = None
    breach_action: Literal["report", "rtl", "land", "hold"] = "rtl"

    def violation(self, lat: float, lon: float, alt_rel: float) -> str | None:
        """Why a position is outside this fence, or None when inside every part of it."""
        if self.max_alt_m is not None and alt_rel > self.max_alt_m:
            return f"altitude {alt_rel:.1f} m above the ceiling {self.max_alt_m:.1f} m"
        if self.circle is not None:
            off = distance_m(lat, lon, self.circle.lat, self.circle.lon)
            if off > self.circle.radius_m:
                return f"{off:.1f} m from the fence centre, radius {self.circle.radius_m:.1f} m"
        if self.polygon is not None and not point_in_polygon(
            lat, lon, [(v.lat, v.lon) for v in self.polygon]
        ):
            return "outside the fence polygon"
        return None


class SetParameters(_Body):
    """Type 3. Installs a geofence (``clear_geofence`` removes it) and/or other settings."""

    geofence: Geofence | None = None
    clear_geofence: bool | None = Field(default=None, description="true: remove the fence (absent = false)")
    parameters: AgentParameters | None = None
    replay_stored: Finite | None = Field(
        default=None,
        description="v2: the agent's replayed (buffered) status reports with time <= this are stored "
        "durably by the daemon; the agent may forget them (docs/protocol.md section 2)",
    )


# --- type 4: perform action(s) -----------------------------------------------------------------


CommandSource = Literal[
    "operator",
    "daemon_emergency",
    "collision",
    "connectivity",
    "divergence",
    "extension",
    "mission",
    "returns",
]
"""Who in the daemon issued a type-4 packet (docs/cooperation.md gives the priority order)."""


class PerformActions(_Body):
    """Type 4. ``append`` adds to the agent's FIFO queue; ``replace`` empties it first.

    ``pause`` stops the vehicle where it is and keeps the queue (the interrupted action resumes
    where it left off); ``resume`` continues. Both carry no actions. ``reason`` says who paused
    (operator, collision avoidance...), for the agent's log and status. ``source`` says which
    daemon authority level sent it: an agent in its own failsafe obeys only ``operator``.
    ``await_release`` makes the agent wait at that (already finished) sync step until the
    daemon releases it before it runs ``actions``: a rejoining agent never runs ahead.
    ``release_anchor`` (v2, only to an agent that offered ``release_beacon``): hex anchor of the
    mission's release chain, with which the agent checks release beacons (protocol/beacon.py).
    """

    mission_id: MissionId
    mode: Literal["append", "replace", "pause", "resume"] = "append"
    actions: list[Action] = Field(default_factory=list, max_length=10_000)
    reason: str | None = Field(default=None, max_length=200)
    source: CommandSource | None = None
    await_release: int | None = Field(default=None, ge=0)
    release_anchor: HexAnchor | None = Field(
        default=None, description="v2: the mission's release-beacon chain anchor (protocol/beacon.py)"
    )

    @model_validator(mode="after")
    def _no_actions_with_pause(self) -> PerformActions:
        if self.mode in ("pause", "resume") and self.actions:
            raise ValueError(f"mode {self.mode!r} carries no actions")
        return self


# --- type 5: synchronization signal ------------------------------------------------------------


class SyncSignal(_Body):
    """Type 5. Agent -> daemon: ``finished`` step k; daemon -> agent: ``release`` step k."""

    mission_id: MissionId
    step: int = Field(ge=0)
    kind: Literal["finished", "release"]


# --- type 6: close connection ------------------------------------------------------------------


class CloseReason(enum.StrEnum):
    NORMAL = "normal"
    REFUSED = "refused"
    PROTOCOL_ERROR = "protocol_error"
    REPLACED = "replaced"
    SHUTDOWN = "shutdown"


class Close(_Body):
    """Type 6. The sender closes the TCP connection after sending it."""

    reason: CloseReason
    message: str = Field(default="", max_length=512)
    code: Code | None = Field(default=None, description="v2: what the peer should do (docs/protocol.md)")


BODY_MODELS: dict[PacketType, type[_Body]] = {
    PacketType.REQUEST_CID: RequestCid,
    PacketType.RESPONSE_CID: ResponseCid,
    PacketType.STATUS: StatusReport,
    PacketType.SET_PARAMETERS: SetParameters,
    PacketType.PERFORM_ACTIONS: PerformActions,
    PacketType.SYNC: SyncSignal,
    PacketType.CLOSE: Close,
}

Body = RequestCid | ResponseCid | StatusReport | SetParameters | PerformActions | SyncSignal | Close


MUST_UNDERSTAND: dict[PacketType, tuple[str, ...]] = {
    PacketType.PERFORM_ACTIONS: ("actions",),
    PacketType.SET_PARAMETERS: ("geofence",),
}
"""Where an unknown field is an error, not ignored: ignoring part of a command or a fence is unsafe."""


def packet_type_of(body: Body) -> PacketType:
    """The packet type that carries ``body``."""
    for ptype, model in BODY_MODELS.items():
        if type(body) is model:
            return ptype
    raise TypeError(f"{type(body).__name__} is not a packet body")


__all__ = [
    "BODY_MODELS",
    "MUST_UNDERSTAND",
    "PROTOCOL_VERSION",
    "SUPPORTED_VERSIONS",
    "Action",
    "ActionFailure",
    "AgentParameters",
    "AltitudeRel",
    "Battery",
    "Body",
    "Camera",
    "Capabilities",
    "Close",
    "CloseReason",
    "Code",
    "CommandSource",
    "FenceCircle",
    "FenceVertex",
    "GeoPoint",
    "Geofence",
    "Gps",
    "PacketType",
    "PerformActions",
    "Position",
    "RequestCid",
    "ResponseCid",
    "Resume",
    "SetParameters",
    "StatusReport",
    "SyncSignal",
    "VelocityNed",
    "packet_type_of",
]
