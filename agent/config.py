"""Agent settings: identity and links (fixed at start) and parameters the daemon may change (type 3)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from protocol.beacon import parse_beacon_address
from protocol.packets import AgentParameters, Capabilities

Reaction = Literal["report", "rtl", "land", "hold"]


class AgentSettings(BaseModel):
    """Parameters the daemon can push with a type-1 or type-3 packet; defaults apply until it does."""

    model_config = ConfigDict(validate_assignment=True)

    status_period_s: float = Field(default=0.5, ge=0.02, le=60.0)
    link_range_m: float | None = None
    battery_low_pct: float = Field(default=25.0, ge=0.0, le=100.0)
    battery_critical_pct: float = Field(default=12.0, ge=0.0, le=100.0)
    battery_low_action: Reaction = "rtl"
    battery_critical_action: Reaction = "land"
    lost_link_timeout_s: float = Field(default=15.0, gt=0.0)
    lost_link_action: Literal["continue", "hold", "rtl", "land"] = "continue"
    acceptance_radius_m: float = Field(default=2.0, gt=0.0)

    def apply(self, parameters: AgentParameters) -> list[str]:
        """Take every field the daemon set; returns the names changed."""
        changed = []
        for name, value in parameters.model_dump(exclude_none=True).items():
            if getattr(self, name) != value:
                setattr(self, name, value)
                changed.append(name)
        return changed


class SanityLimits(BaseModel):
    """What the agent refuses to fly whoever orders it (fixed at start; the daemon cannot change them).

    The distance and altitude limits bound where the orders take the vehicle, applied in
    sequence from its position (agent/limits.py): the orders before the first one that would
    cross a limit fly, that one and the rest of its batch are refused, and the daemon hears why
    (``command_refused`` exception at once, the status ``failure`` when the vehicle gets there).
    A batch that would overfill the queue is refused whole.
    """

    model_config = ConfigDict(extra="forbid")

    max_distance_from_home_m: float = Field(
        default=10_000.0,
        gt=0.0,
        le=1_000_000.0,
        description="horizontal distance from home of every place the queued orders lead to",
    )
    max_alt_m: float = Field(default=500.0, gt=0.0, le=10_000.0, description="metres above home")
    min_alt_m: float = Field(
        default=-500.0, ge=-1000.0, le=0.0, description="metres relative to home (below home: negative)"
    )
    check_geofence: bool = Field(
        default=True,
        description="refuse orders that lead outside the geofence the daemon installed (false: the "
        "fence is enforced in flight only, by its breach reaction)",
    )
    max_queue_actions: int = Field(default=20_000, ge=1, le=1_000_000)
    min_hold_s: float = Field(default=0.0, ge=0.0)
    max_hold_s: float = Field(default=3600.0, gt=0.0, le=86_400.0)


def _host_port(text: str, default_port: int) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    if not port.isdigit() or not 0 < int(port) < 65_536:
        raise ValueError(f"daemon address {text!r}: bad port")
    return host.strip("[]") or "127.0.0.1", int(port)


class AgentConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    identity: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]*$")
    gcs_host: str = "127.0.0.1"
    gcs_port: int = Field(default=4396, ge=1, le=65_535)
    key_hex: str
    daemons: list[str] = Field(
        default_factory=list,
        description="more daemons HOST:PORT of a cluster (docs/cluster.md): on failure the link "
        "moves to the next one, same identity and CID",
    )
    capabilities: Capabilities = Capabilities()
    settings: AgentSettings = AgentSettings()
    reconnect_min_s: float = Field(default=0.2, gt=0.0)
    reconnect_max_s: float = Field(default=5.0, gt=0.0)
    handshake_timeout_s: float = Field(default=5.0, gt=0.0)
    daemon_silence_s: float = Field(
        default=5.0,
        gt=0.0,
        description="drop and reconnect when nothing arrives for this long (keepalive 1 s)",
    )
    tls_ca: Path | None = Field(
        default=None, description="PEM CA bundle: connect over TLS, verify the daemon"
    )
    tls_cert: Path | None = Field(default=None, description="PEM client certificate (mutual TLS)")
    tls_key: Path | None = Field(default=None, description="PEM private key of tls_cert")
    tls_server_name: str | None = Field(default=None, description="name in the daemon's certificate")
    limits: SanityLimits = SanityLimits()
    status_buffer: int = Field(default=1200, ge=1, description="status reports kept while offline")
    replay_max_reports: int = Field(
        default=300,
        ge=2,
        le=400,
        description="buffered reports sent after an outage (thinned, state changes kept); the daemon "
        "takes a burst of 400",
    )
    arm_deadline_s: float = Field(default=60.0, gt=0.0)
    takeoff_tolerance: float = Field(default=0.95, gt=0.5, le=1.0, description="fraction of target altitude")
    resend_target_s: float = Field(default=3.0, gt=0.0, description="re-send a lost target")
    monitor_period_s: float = Field(default=0.25, gt=0.0)
    release_beacon: str | None = Field(
        default=None,
        description="IPV4:PORT to listen on for release beacons (UDP broadcast, protocol/beacon.py), "
        "e.g. 127.255.255.255:14650 on one host or 192.168.1.255:14650 on a LAN; None: TCP releases only",
    )

    @field_validator("release_beacon")
    @classmethod
    def _check_release_beacon(cls, value: str | None) -> str | None:
        if value is not None:
            parse_beacon_address(value)
        return value

    @field_validator("daemons")
    @classmethod
    def _check_daemons(cls, value: list[str]) -> list[str]:
        for text in value:
            _host_port(text, 4396)
        return value

    def daemon_addresses(self) -> list[tuple[str, int]]:
        """Every daemon to try, in order: ``gcs_host:gcs_port`` first, then ``daemons``."""
        return [(self.gcs_host, self.gcs_port)] + [_host_port(d, self.gcs_port) for d in self.daemons]
