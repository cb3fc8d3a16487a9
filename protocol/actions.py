"""Actions a type-4 packet asks an agent to perform, and that a task file lists per agent.

Every action carries ``step`` (its index in the mission, shared across agents so that sync
points line up) and ``sync``: when true, the agent reports "finished step k" after completing
the action and waits for the daemon's "release step k" before starting the next one.
Units: degrees for lat/lon, metres for altitudes (relative to home) and offsets, m/s, seconds.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

Latitude = Annotated[float, Field(ge=-90.0, le=90.0, allow_inf_nan=False)]
Longitude = Annotated[float, Field(ge=-180.0, le=180.0, allow_inf_nan=False)]
AltitudeRel = Annotated[float, Field(ge=-1000.0, le=10_000.0, allow_inf_nan=False)]
Metres = Annotated[float, Field(ge=-100_000.0, le=100_000.0, allow_inf_nan=False)]
Speed = Annotated[float, Field(gt=0.0, le=100.0, allow_inf_nan=False)]

MAX_WAYPOINTS_PER_ACTION = 2000


class _Action(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    step: int = Field(ge=0, le=1_000_000, description="mission step index (shared across agents)")
    sync: bool = Field(default=False, description="wait for the daemon's release after this action")
    timeout_s: float | None = Field(
        default=None, gt=0.0, le=86_400.0, description="per-action timeout; None = agent default"
    )


class Takeoff(_Action):
    """Arm in GUIDED and climb to ``alt`` metres above home."""

    kind: Literal["takeoff"] = "takeoff"
    alt: Annotated[float, Field(gt=0.0, le=10_000.0, allow_inf_nan=False)]


class Goto(_Action):
    """Fly to a global position; complete on arrival within the acceptance radius."""

    kind: Literal["goto"] = "goto"
    lat: Latitude
    lon: Longitude
    alt: AltitudeRel
    speed: Speed | None = None


class GoBy(_Action):
    """Fly by a local offset (north, east, up metres) from where the action starts."""

    kind: Literal["go_by"] = "go_by"
    north: Metres
    east: Metres
    up: Metres = 0.0
    speed: Speed | None = None

    def as_goto(self, lat: float, lon: float, alt: float) -> Goto:
        """This offset resolved to its fixed target: what is left of it once it has started."""
        return Goto(
            step=self.step,
            sync=self.sync,
            timeout_s=self.timeout_s,
            lat=lat,
            lon=lon,
            alt=alt,
            speed=self.speed,
        )


class Land(_Action):
    """Land here, or at ``lat``/``lon`` when both are given; complete when disarmed."""

    kind: Literal["land"] = "land"
    lat: Latitude | None = None
    lon: Longitude | None = None


class ReturnToLaunch(_Action):
    """Return to the launch point and land; complete when disarmed.

    ``alt`` (metres above home) is the altitude of the return leg: the autopilot climbs to it
    (or stays higher if it already is) and flies home at it. Distinct altitudes keep drones
    whose homes are a few metres apart from meeting on the way back. None = the autopilot's
    own setting (ArduCopter RTL_ALT, 15 m by default).
    """

    kind: Literal["rtl"] = "rtl"
    alt: Annotated[float, Field(ge=2.0, le=3000.0, allow_inf_nan=False)] | None = None


class Hold(_Action):
    """Hold position for ``seconds``."""

    kind: Literal["hold"] = "hold"
    seconds: Annotated[float, Field(ge=0.0, le=86_400.0, allow_inf_nan=False)]


class SetSpeed(_Action):
    """Change the cruise speed for the following legs."""

    kind: Literal["set_speed"] = "set_speed"
    speed: Speed


class Waypoint(BaseModel):
    """One point of a survey leg."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lat: Latitude
    lon: Longitude
    alt: AltitudeRel


class Waypoints(_Action):
    """Fly a list of waypoints in order (a survey leg); complete at the last one."""

    kind: Literal["waypoints"] = "waypoints"
    points: list[Waypoint] = Field(min_length=1, max_length=MAX_WAYPOINTS_PER_ACTION)
    speed: Speed | None = None


Action = Annotated[
    Takeoff | Goto | GoBy | Land | ReturnToLaunch | Hold | SetSpeed | Waypoints,
    Field(discriminator="kind"),
]
"""Any action; the ``kind`` field selects the model."""
