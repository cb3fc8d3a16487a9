"""Settings of the run-time cooperation services (collision, divergence, connectivity, emergency, energy).

Every option has a default chosen so that an unconfigured daemon behaves as before: the
collision margins fit the 3-drone demo (homes 5-6 m apart, transit altitudes 3 m apart), the
connectivity model is off until a link range is known, and energy checks use a conservative
fallback power model until a trained model is configured.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

EmergencyAction = Literal["event", "pause", "rtl", "land"]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class CollisionConfig(_Section):
    """Closest-point-of-approach conflict detection; the lower-priority drone is held (type-4 pause)."""

    enabled: bool = True
    horizontal_margin_m: float = Field(
        default=4.0, gt=0.0, description="predicted horizontal miss distance below which a pair conflicts"
    )
    vertical_margin_m: float = Field(
        default=2.0, gt=0.0, description="... and vertical separation below which it conflicts (both needed)"
    )
    horizon_s: float = Field(
        default=6.0, gt=0.0, description="look-ahead in vehicle seconds for the closest point of approach"
    )
    release_factor: float = Field(
        default=1.25, ge=1.0, description="margins are multiplied by this before a held pair counts as clear"
    )
    release_after_s: float = Field(
        default=0.6, ge=0.0, description="a pair must stay clear this long (wall s) before the release"
    )
    reassert_period_s: float = Field(
        default=2.0,
        gt=0.0,
        description="re-send pause to held drones this often (seed 000: sent periodically)",
    )
    min_check_interval_s: float = Field(
        default=0.05, ge=0.0, description="fleet-wide check at most this often (each status marks it due)"
    )
    escape: Literal["climb", "none"] = Field(
        default="climb",
        description="when holding the yielder is not enough (its hold point lies on the other's path), "
        "move it vertically out of the way; 'none' holds both and raises an event",
    )
    escape_buffer_m: float = Field(
        default=2.0, ge=0.0, description="vertical separation beyond the vertical margin an escape aims for"
    )
    min_escape_alt_m: float = Field(default=3.0, ge=0.0, description="an escape never descends below this")
    max_hold_s: float = Field(
        default=15.0,
        gt=0.0,
        description="a collision hold that has not resolved in this time (wall s) becomes an escape "
        "(or, with escape 'none', is released): holds never trap a drone",
    )
    default_speed_mps: float = Field(
        default=5.0, gt=0.0, description="assumed leg speed of a held drone whose plan gives none"
    )
    max_speed_mps: float = Field(
        default=20.0, gt=0.0, description="upper bound on speeds used to size the neighbour search radius"
    )


class DivergenceConfig(_Section):
    """Track versus planned leg: cross-track distance and along-track lag."""

    enabled: bool = True
    correct_m: float = Field(
        default=8.0, gt=0.0, description="cross-track error that triggers a correction (pause + resume)"
    )
    replan_m: float = Field(
        default=15.0,
        gt=0.0,
        description="cross-track error that triggers a replan: type-4 replace with a rejoin point on the "
        "planned leg followed by the remaining actions",
    )
    hover_drift_m: float = Field(
        default=6.0,
        gt=0.0,
        description="drift from the hover point while waiting at a sync step that is corrected",
    )
    lag_event_m: float = Field(
        default=40.0, gt=0.0, description="along-track lag behind the planned speed that raises an event"
    )
    persist_s: float = Field(
        default=0.5, ge=0.0, description="an error must last this long (wall s) before acting"
    )
    cooldown_s: float = Field(default=3.0, ge=0.0, description="no second action on a drone within this time")
    lookahead_m: float = Field(
        default=8.0, ge=0.0, description="the rejoin point lies this far ahead on the leg"
    )
    max_replans_per_step: int = Field(default=5, ge=0, description="then only events")
    acceptance_radius_m: float = Field(
        default=2.0,
        gt=0.0,
        description="waypoint arrival radius the daemon assumes when tracking progress, unless it pushed one "
        "to the agents (agent_parameters.acceptance_radius_m); the agent's own default is 2 m",
    )
    default_speed_mps: float = Field(default=5.0, gt=0.0, description="leg speed when the plan sets none")


class ConnectivityConfig(_Section):
    """Disk-model link graph: the daemon (base) and the drones are nodes, an edge within the range."""

    enabled: bool = True
    link_range_m: float | None = Field(
        default=None,
        gt=0.0,
        description="link range w; None = the daemon's agent parameter link_range_m; both None = off",
    )
    base: tuple[float, float] | None = Field(
        default=None, description="base station lat, lon; None = the home of the first drone that joins"
    )
    multihop: bool = Field(default=True, description="drones relay for each other (mesh, as OLSR); else star")
    policy: Literal["event", "hold", "return", "rtl"] = Field(
        default="hold",
        description="on a modelled disconnection: event only, hold (pause until reconnected), return toward "
        "the nearest connected node, or return to launch",
    )
    grace_s: float = Field(default=1.0, ge=0.0, description="disconnected this long (wall s) before acting")
    return_fraction: float = Field(
        default=0.7, gt=0.0, lt=1.0, description="'return' flies to this fraction of w from the nearest node"
    )
    preflight: bool = Field(default=True, description="warn at submission when a planned step disconnects")
    push_lost_link_action: bool = Field(
        default=False,
        description="send each joining agent link_range_m and a lost_link_action matching the policy, "
        "for real disconnections the daemon cannot act on",
    )


class EmergencyConfig(_Section):
    """Daemon-side duplicates of the agent's exception checks (defence in depth)."""

    enabled: bool = True
    fence_action: EmergencyAction | Literal["fence"] = Field(
        default="fence", description="'fence' = the breach_action of the fence the daemon sent"
    )
    battery_action: EmergencyAction = "rtl"
    battery_reserve_pct: float = Field(default=10.0, ge=0.0, le=100.0, description="kept after reaching home")
    battery_safety_factor: float = Field(
        default=1.3, ge=1.0, description="applied to the return-home estimate"
    )
    battery_window_s: float = Field(
        default=30.0, gt=0.0, description="wall seconds of history for the % drop rate (least squares)"
    )
    descent_mps: float = Field(default=1.5, gt=0.0, description="assumed landing descent speed (vehicle m/s)")
    gps_action: EmergencyAction = "land"
    gps_grace_s: float = Field(
        default=2.0, ge=0.0, description="fix below 3D this long (wall s) before acting"
    )
    stale_action: EmergencyAction = "event"
    stale_after_periods: float = Field(default=4.0, ge=1.0, description="status silence, in status periods")
    stale_min_s: float = Field(
        default=2.0, gt=0.0, description="... but never less than this (wall s): a busy host delays reports"
    )
    check_period_s: float = Field(default=0.5, gt=0.0, description="ticker for stale-status checks")


class EnergyConfig(_Section):
    """Two-step energy prediction (seed 004 2.2.6) and the pre-flight energy check."""

    enabled: bool = True
    model_path: Path | None = Field(default=None, description="JSON from `gcs energy train`; None = fallback")
    fallback_power_w: float = Field(
        default=250.0, gt=0.0, description="without a model: energy = this power x predicted flight time"
    )
    default_battery_wh: float = Field(
        default=55.0, gt=0.0, description="capacity when the agent's capabilities give no battery_wh"
    )
    reserve_pct: float = Field(
        default=20.0, ge=0.0, lt=100.0, description="of capacity, kept after the mission"
    )
    speed_mps: float = Field(default=5.0, gt=0.0, description="cruise speed of legs that set none")
    climb_mps: float = Field(default=2.5, gt=0.0)
    descent_mps: float = Field(default=1.5, gt=0.0)
    accel_mps2: float = Field(default=2.5, gt=0.0)
    land_final_mps: float = Field(default=0.5, gt=0.0, description="landing speed below land_slow_below_m")
    land_slow_below_m: float = Field(default=10.0, ge=0.0, description="ArduCopter LAND_ALT_LOW")
    rtl_alt_m: float = Field(default=15.0, ge=0.0, description="RTL climbs to at least this altitude")
    rtl_speed_mps: float = Field(default=5.0, gt=0.0, description="RTL flies home at this speed")
    record_dir: Path | None = Field(
        default=None, description="record every drone-flight as a flight-log CSV here (training data)"
    )
    record_time_scale: float = Field(
        default=1.0,
        gt=0.0,
        description="vehicle seconds per wall second in recorded logs (simulator speed-up)",
    )


class CooperationConfig(_Section):
    """All cooperation services; each section can be switched off on its own."""

    collision: CollisionConfig = Field(default_factory=CollisionConfig)
    divergence: DivergenceConfig = Field(default_factory=DivergenceConfig)
    connectivity: ConnectivityConfig = Field(default_factory=ConnectivityConfig)
    emergency: EmergencyConfig = Field(default_factory=EmergencyConfig)
    energy: EnergyConfig = Field(default_factory=EnergyConfig)
    vehicle_time_scale: float = Field(
        default=1.0,
        gt=0.0,
        description="vehicle seconds per wall second (a simulator's speed-up); scales planned-speed timing",
    )
