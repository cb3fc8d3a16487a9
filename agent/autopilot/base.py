"""The contract between the agent's command queue and an autopilot backend.

A backend only *commands* the vehicle and *reports* its telemetry. Waiting for an action to
complete (arrival within an acceptance radius, takeoff altitude reached, landed and disarmed)
is the queue's job, done by watching :meth:`Autopilot.telemetry`, so every backend (in-memory,
pymavlink/ArduPilot, MAVSDK/PX4) behaves the same way to the rest of the agent.

Every command method either returns once the autopilot accepted the command, or raises
:class:`CommandRefused` (the autopilot said no; ``reason`` carries its words, e.g. the last
``PreArm:`` STATUSTEXT) or :class:`CommandTimeout` (no answer after the backend's retries).
"""

from __future__ import annotations

import abc
import asyncio
import time
from dataclasses import dataclass, field

from protocol.geo import distance_m, offset_latlon

ARM_RETRY_INTERVAL_S = 0.5  # how often backends retry arming through pre-arm refusals
LAND_ARRIVAL_RADIUS_M = 2.0  # how close to a requested landing point before descending
HEARTBEAT_TIMEOUT_S = 3.0  # default link-loss threshold; backends may configure their own


class AutopilotError(Exception):
    """Base class of every error an autopilot backend raises."""


class CommandRefused(AutopilotError):
    """The autopilot answered and refused the command."""

    def __init__(self, command: str, reason: str) -> None:
        super().__init__(f"{command} refused: {reason}")
        self.command = command
        self.reason = reason


class CommandTimeout(AutopilotError):
    """The autopilot did not answer the command in time, retries included."""

    def __init__(self, command: str, seconds: float) -> None:
        super().__init__(f"{command}: no answer from the autopilot within {seconds:.1f} s")
        self.command = command
        self.seconds = seconds


class PilotInControl(AutopilotError):
    """A pilot put the vehicle in a mode the agent did not ask for: nothing that moves it is sent."""


class LinkLost(AutopilotError):
    """No heartbeat from the autopilot for longer than the backend's link timeout."""


@dataclass(slots=True)
class Telemetry:
    """The latest known state of the vehicle, in the units the protocol's status report uses.

    Angles in degrees, distances in metres, speeds in m/s, ``alt_rel`` above home,
    ``alt_amsl`` above mean sea level; velocity is NED. ``battery_pct`` is 0..100 or ``None``
    when unknown. ``mode`` is the autopilot's mode name in upper case (``GUIDED``, ``AUTO``,
    ``LOITER``, ``RTL``, ``LAND``, ``BRAKE``, ...). ``landed`` is true on the ground.
    """

    lat: float = 0.0
    lon: float = 0.0
    alt_rel: float = 0.0
    alt_amsl: float = 0.0
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    heading_deg: float = 0.0
    battery_pct: float | None = None
    voltage_v: float | None = None
    current_a: float | None = None
    mode: str = "UNKNOWN"
    armed: bool = False
    landed: bool = True
    gps_fix: int = 0
    satellites: int = 0
    home_lat: float | None = None
    home_lon: float | None = None
    home_alt_amsl: float | None = None
    mission_current: int = -1  # MISSION_CURRENT seq while flying an uploaded mission, else -1
    # Latched once the vehicle has reported a 3-D fix and a non-zero position: before that
    # (ArduCopter: the first 11-13 s after boot) lat/lon are 0,0 and mean nothing.
    position_known: bool = False
    vehicle_time_s: float | None = None  # autopilot clock (time_boot_ms) of the position, if reported
    last_heartbeat_monotonic: float = 0.0
    # A mode the vehicle was put in by someone else (a pilot's RC switch, another ground station),
    # until it is back in the agent's mode; always None when the backend does not track it.
    pilot_mode: str | None = None
    status_texts: list[str] = field(default_factory=list)
    # The autopilot's heartbeat says MAV_STATE_CRITICAL or EMERGENCY: a failsafe of its own is active
    # (PX4's failsafe framework, ArduCopter's failsafes). PX4 sends no STATUSTEXT on its onboard
    # (API) link, so this is the only word of its failsafe an agent there gets.
    autopilot_failsafe: bool = False

    def latch_position(self) -> None:
        """Set :attr:`position_known` when the current fix and position allow it (never clears)."""
        if not self.position_known and self.gps_fix >= 3 and (self.lat, self.lon) != (0.0, 0.0):
            self.position_known = True

    @property
    def has_position(self) -> bool:
        """True while the vehicle reports a 3D fix, and it has reported a position and a home."""
        return self.gps_fix >= 3 and self.position_known and self.home_lat is not None


@dataclass(slots=True, frozen=True)
class MissionPoint:
    """One waypoint of an uploaded autopilot mission (altitude relative to home)."""

    lat: float
    lon: float
    alt_rel_m: float


@dataclass(slots=True, frozen=True)
class FenceCircle:
    """An inclusion circle (centre lat/lon in degrees, radius in metres)."""

    lat: float
    lon: float
    radius_m: float


@dataclass(slots=True, frozen=True)
class FenceSpec:
    """The parts of a geofence an autopilot can enforce by itself."""

    polygon: tuple[tuple[float, float], ...] = ()  # inclusion polygon, (lat, lon) vertices
    circle: FenceCircle | None = None
    max_alt_m: float | None = None  # ceiling above home
    breach_action: str = "rtl"  # "rtl" | "land" | "hold" | "report"


class Autopilot(abc.ABC):
    """What the agent's queue and exception monitor need from a flight controller."""

    def pilot_modes(self) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
        """(the vehicle's own failsafe modes, the modes an operator may release a pilot's control
        from) when this backend tells a pilot's mode change from the agent's (``Telemetry.pilot_mode``);
        None when it does not."""
        return None

    def adopt_mode(self) -> None:
        """The operator released the pilot's control: the present mode is the agent's from now on."""
        return None  # nothing to adopt where pilot_modes() is None

    @abc.abstractmethod
    async def connect(self, timeout: float = 30.0) -> None:
        """Open the link, wait for the vehicle heartbeat, request telemetry streams."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Release the link. Idempotent."""

    @abc.abstractmethod
    def telemetry(self) -> Telemetry:
        """The latest telemetry snapshot (never blocks)."""

    @abc.abstractmethod
    async def arm(self, deadline_s: float = 60.0) -> None:
        """Switch to GUIDED and arm, retrying pre-arm refusals until ``deadline_s``."""

    @abc.abstractmethod
    async def takeoff(self, alt_rel_m: float) -> None:
        """Command a takeoff to ``alt_rel_m`` above home (vehicle armed, landed, GUIDED)."""

    @abc.abstractmethod
    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        """Set a global position target (GUIDED). Returns once sent/accepted, not on arrival."""

    @abc.abstractmethod
    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        """Land here, or at lat/lon when given."""

    @abc.abstractmethod
    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        """Switch to return-to-launch; ``alt_rel_m`` (above home) sets the return altitude first."""

    @abc.abstractmethod
    async def hold(self) -> None:
        """Stop and hold position (BRAKE or LOITER, or a position target at the current point)."""

    @abc.abstractmethod
    async def set_speed(self, speed_mps: float) -> None:
        """Change the horizontal cruise speed."""

    @abc.abstractmethod
    async def upload_fence(self, fence: FenceSpec) -> bool:
        """Install the fence on the autopilot; False when the autopilot cannot enforce it."""

    async def go_by(self, north_m: float, east_m: float, up_m: float, speed_mps: float | None = None) -> None:
        """Move by a local NED offset from the current position.

        The default turns the offset into a global target; backends with a native local-offset
        command (MAVLink ``MAV_FRAME_LOCAL_OFFSET_NED``) may override it.
        """
        now = self.telemetry()
        lat, lon = offset_latlon(now.lat, now.lon, north_m, east_m)
        await self.goto(lat, lon, now.alt_rel + up_m, speed_mps)

    def ensure_link(self, what: str) -> None:
        """Raise :class:`LinkLost` (naming ``what``) when no heartbeat came for ``HEARTBEAT_TIMEOUT_S``."""
        age = time.monotonic() - self.telemetry().last_heartbeat_monotonic
        if age > HEARTBEAT_TIMEOUT_S:
            raise LinkLost(f"{what}: no heartbeat from the vehicle for {age:.1f} s")

    async def approach_landing_point(self, lat: float, lon: float) -> None:
        """Fly to ``lat``/``lon`` at the current altitude and wait for arrival.

        For autopilots whose land command ignores a position (ArduCopter's NAV_LAND, MAVSDK's
        land): backends call it from :meth:`land` before descending. Raises
        :class:`CommandTimeout` after 30 s + 1.5 s per metre, :class:`CommandRefused` if the
        vehicle disarms on the way, :class:`LinkLost` if the link drops.
        """
        now = self.telemetry()
        dist = distance_m(now.lat, now.lon, lat, lon)
        if dist <= LAND_ARRIVAL_RADIUS_M or now.landed:
            return
        await self.goto(lat, lon, max(now.alt_rel, 2.0))
        limit = 30.0 + 1.5 * dist
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline:
            self.ensure_link("land")
            now = self.telemetry()
            if distance_m(now.lat, now.lon, lat, lon) <= LAND_ARRIVAL_RADIUS_M:
                return
            if not now.armed:
                raise CommandRefused("land", "vehicle disarmed on the way to the landing point")
            await asyncio.sleep(0.1)
        raise CommandTimeout("land (reposition)", limit)

    async def disarm(self) -> None:
        """Disarm (only on the ground). Backends override when they support it."""
        raise CommandRefused("disarm", "not supported by this backend")

    async def upload_mission(self, points: list[MissionPoint]) -> None:
        """Upload a waypoint mission (the autopilot flies it in AUTO after :meth:`start_mission`)."""
        raise CommandRefused("mission upload", "not supported by this backend")

    async def start_mission(self) -> None:
        """Start the uploaded mission (AUTO)."""
        raise CommandRefused("mission start", "not supported by this backend")
