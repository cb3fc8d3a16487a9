"""Daemon settings (validated); the CLI and tests build one, later a TOML file will too."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gcs.cooperation.config import CooperationConfig
from protocol.auth import parse_key
from protocol.beacon import parse_beacon_address
from protocol.packets import AgentParameters
from protocol.wire import DEFAULT_MAX_BODY

CLUSTER_LOST_MARGIN_S = 2.0  # an agent's move to another daemon: reconnect, handshake, join, claim


def default_data_dir() -> Path:
    """Where the daemon keeps its database, fleet key and API token unless told otherwise."""
    return Path.home() / ".local" / "state" / "fleetgcs"


class TelemetryConfig(BaseModel):
    """How status reports are logged to the database (see gcs/observe/telemetry.py)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    period_s: float = Field(default=0.0, ge=0.0, description="keep one sample per agent per period; 0 = all")
    flush_s: float = Field(default=0.5, gt=0.0, le=60.0, description="batch write interval")
    retention_s: float = Field(default=7 * 86_400.0, gt=0.0, description="delete samples older than this")
    prune_every_s: float = Field(default=300.0, gt=0.0)


class DaemonConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    listen_host: str = "127.0.0.1"
    listen_port: int = Field(default=4396, ge=0, le=65_535)
    http_host: str | None = "127.0.0.1"
    http_port: int = Field(default=8080, ge=0, le=65_535)
    http_allowed_hosts: list[str] = Field(
        default_factory=list,
        description="DNS names the API may be addressed by besides loopback and http_host (Host, Origin)",
    )
    ws_max_message_bytes: int = Field(
        default=4096,
        ge=128,
        le=1 << 20,
        description="largest WebSocket message a client may send (the stream takes none; bigger closes it)",
    )
    stream_max_clients: int = Field(
        default=100, ge=1, le=10_000, description="WebSocket stream connections at once; more are refused"
    )
    stream_client_buffer_bytes: int = Field(
        default=1 << 20, ge=4096, description="messages queued for one stream client; the oldest are dropped"
    )
    stream_send_timeout_s: float = Field(
        default=10.0,
        gt=0.0,
        le=300.0,
        description="a stream client that does not read for this long is closed",
    )
    max_api_body_bytes: int = Field(
        default=16 << 20, ge=1024, description="largest HTTP request body, enforced while reading"
    )
    data_dir: Path = Field(default_factory=default_data_dir)
    database: Path | None = Field(default=None, description="default: DATA_DIR/fleetgcs.sqlite")
    new_database: bool = Field(
        default=False,
        description="begin a new fleet where the database went missing or is zero-length "
        "(gcs serve --new-fleet); a foreign file is never overwritten",
    )
    fleet_key_hex: str | None = Field(default=None, description="shared key; default: DATA_DIR/fleet.key")
    agent_keys_file: Path | None = Field(default=None, description="JSON {identity: hex key}")
    allow_unlisted_agents: bool = Field(
        default=True, description="with per-agent keys, also accept other identities that hold the fleet key"
    )
    api_token: str | None = Field(default=None, description="default: DATA_DIR/api.token")
    api_read_token: str | None = Field(
        default=None,
        min_length=16,
        description="optional read-only token: reads (GET, the stream) accept it as well as api_token",
    )
    http_reads_need_token: Literal["beyond_loopback", "always"] = Field(
        default="beyond_loopback",
        description="when reads need a token: only when http_host is not a loopback address (default), or "
        "always (e.g. behind a reverse proxy on loopback)",
    )
    handshake_timeout_s: float = Field(default=5.0, gt=0.0)
    tls_cert: Path | None = Field(default=None, description="PEM certificate: serve the agent link over TLS")
    tls_key: Path | None = Field(default=None, description="PEM private key of tls_cert")
    tls_client_ca: Path | None = Field(
        default=None, description="PEM CA bundle: require agents to present a certificate it signed (mTLS)"
    )
    max_body_bytes: int = Field(default=DEFAULT_MAX_BODY, ge=1024, le=64 << 20)
    max_agents: int = Field(default=1000, ge=1)
    max_handshakes: int = Field(
        default=64,
        ge=1,
        description="connections allowed to be in the handshake at once; more are refused busy",
    )
    max_handshakes_per_source: int = Field(
        default=16,
        ge=1,
        description="of those, held by one source address (IPv6: one /64); more are refused busy at once",
    )
    enroll_per_s: float = Field(
        default=10.0, gt=0.0, description="new identities one source address may enroll per second"
    )
    enroll_burst: int = Field(
        default=200, ge=1, description="new identities one source may enroll at once; more are refused busy"
    )
    enroll_new_agents: bool = Field(
        default=True,
        description="give a CID to identities the database has never seen; off = only known identities join",
    )
    banned_agents: list[str] = Field(default_factory=list, description="identities refused with code banned")
    replay_frames_per_s: float = Field(
        default=100.0, gt=0.0, description="buffered status reports/s an agent may replay after an outage"
    )
    replay_burst: int = Field(default=400, ge=1, description="buffered status reports it may send at once")
    max_exception_events: int = Field(
        default=30,
        ge=1,
        description="agent_exception events per agent per minute; more are counted, not logged",
    )
    max_frames_per_s: float = Field(
        default=200.0, gt=0.0, description="sustained frames/s one agent may send (status at 10 Hz is 10)"
    )
    frame_burst: int = Field(default=400, ge=1, description="frames an agent may send at once above the rate")
    max_pending_bytes: int = Field(
        default=4 << 20, ge=64 << 10, description="bytes queued towards one agent before it counts as stuck"
    )
    status_period_s: float = Field(default=0.5, ge=0.02, le=60.0)
    max_clock_skew_s: float = Field(
        default=3600.0,
        ge=1.0,
        le=1e9,
        description="a status report whose time is further than this from the daemon's clock is refused",
    )
    lost_after_periods: float = Field(default=6.0, ge=1.0)
    send_timeout_s: float = Field(default=5.0, gt=0.0)
    keepalive_s: float = Field(
        default=1.0,
        gt=0.0,
        le=60.0,
        description="send an empty type 3 to an agent we have not sent to for this long",
    )
    default_sync_timeout_s: float = Field(default=120.0, gt=0.0)
    release_beacon: str | None = Field(
        default=None,
        description="IPv4:PORT to broadcast barrier releases to ahead of the TCP release "
        "(protocol/beacon.py), e.g. 127.255.255.255:14650 on one host; default: TCP only",
    )
    lost_agent_policy: Literal["abort", "continue"] = "abort"
    agent_parameters: AgentParameters = AgentParameters()
    cooperation: CooperationConfig = Field(default_factory=CooperationConfig)
    telemetry: TelemetryConfig = Field(default_factory=TelemetryConfig)
    # operator interfaces (docs/configuration.md)
    tile_url: str | None = Field(
        default=None, max_length=500, description="dashboard background tiles, '{z}/{x}/{y}' template"
    )
    tile_mbtiles: Path | None = Field(
        default=None, description="dashboard background tiles from this MBTiles file (served by the daemon)"
    )
    extensions: list[str] = Field(
        default_factory=list, description="extension modules 'pkg.mod' or 'pkg.mod:factory' (docs/api.md)"
    )
    extension_options: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="options per extension, keyed by the module path as listed"
    )

    # cluster mode (docs/cluster.md): several daemons sharing the fleet through NATS JetStream
    cluster: list[str] = Field(
        default_factory=list,
        description="NATS servers nats://HOST:PORT of the cluster; empty = one daemon with its SQLite file",
    )
    cluster_replicas: int = Field(
        default=1, ge=1, le=5, description="JetStream replicas of the shared buckets (3 on a 3-node NATS)"
    )
    cluster_lease_ttl_s: float = Field(
        default=3.0, ge=0.5, le=60.0, description="a mission leader's lease; a standby takes over after it"
    )
    cluster_prune_after_s: float = Field(
        default=3600.0,
        ge=1.0,
        description="a finished mission's progress, barrier and lease keys go this long after it ends",
    )
    agent_daemon_silence_s: float = Field(
        default=5.0,
        gt=0.0,
        le=3600.0,
        description="the agents' daemon_silence_s: after that long without their daemon they move "
        "to the next one (the cluster's lost-agent timeout derives from it)",
    )
    cluster_lost_after_s: float | None = Field(
        default=None,
        gt=0.0,
        le=86_400.0,
        description="drop another daemon's agent after this long without its status; at least "
        f"agent_daemon_silence_s + {CLUSTER_LOST_MARGIN_S:g} s (default: that, or lost_after_s if longer)",
    )
    daemon_id: str | None = Field(
        default=None,
        pattern=r"^[A-Za-z0-9_-]{1,64}$",
        description="this daemon's name in the cluster; default: hostname-pid",
    )

    @field_validator("cluster", mode="before")
    @classmethod
    def _split_servers(cls, value: Any) -> Any:
        if isinstance(value, str):
            value = [part.strip() for part in value.split(",") if part.strip()]
        for url in value or []:
            if not isinstance(url, str) or not url.startswith(("nats://", "tls://")) or ":" not in url[7:]:
                raise ValueError(f"cluster server {url!r} is not nats://HOST:PORT")
        return value

    @field_validator("fleet_key_hex")
    @classmethod
    def _fleet_key(cls, value: str | None) -> str | None:
        if value is not None:
            parse_key(value)  # its ValueError says what is wrong (never the key itself)
        return value

    @field_validator("release_beacon")
    @classmethod
    def _beacon_address(cls, value: str | None) -> str | None:
        if value is not None:
            parse_beacon_address(value)  # its ValueError says what is wrong
        return value

    @model_validator(mode="after")
    def _liveness_agrees(self) -> DaemonConfig:
        """A stalled daemon's agents must move before the other daemons exclude them as lost."""
        floor = self.agent_daemon_silence_s + CLUSTER_LOST_MARGIN_S
        if self.cluster_lost_after_s is not None and self.cluster_lost_after_s < floor:
            raise ValueError(
                f"cluster_lost_after_s ({self.cluster_lost_after_s:g} s) must be at least "
                f"agent_daemon_silence_s ({self.agent_daemon_silence_s:g} s) + {CLUSTER_LOST_MARGIN_S:g} s: "
                "the agents of a stalled daemon must move to another daemon before the others "
                "count them as lost and exclude them from their missions"
            )
        return self

    @property
    def remote_lost_after_s(self) -> float:
        """How long another daemon's agent may be silent here before it counts as lost."""
        if self.cluster_lost_after_s is not None:
            return self.cluster_lost_after_s
        return max(self.lost_after_s, self.agent_daemon_silence_s + CLUSTER_LOST_MARGIN_S)

    @property
    def database_path(self) -> Path:
        return self.database or self.data_dir / "fleetgcs.sqlite"

    @property
    def lost_after_s(self) -> float:
        return self.status_period_s * self.lost_after_periods
