"""Runs deconflicted RTL-all / land-all (the plan comes from :mod:`gcs.cooperation.returns`).

Each drone gets a small program through the vehicle authority, at the priority of whoever asked
(the operator, the daemon's emergency monitor, a mission abort):

* RTL: climb or descend in place to its layer, fly home in the layer, **wait** (a sync point of
  its own), land.
* land: **wait** where it is, land.
* A drone that returns alone gets the autopilot's own RTL (at its layer altitude) or LAND, which
  carries on even if the daemon link drops.

The wait is released per drone, on the status tick, as soon as it is cleared to descend. The
programs carry their own mission id (``return-...``), so they never count as mission progress.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

from gcs.control.authority import Owner, VehicleAuthority
from gcs.cooperation.returns import (
    RETURN_PREFIX,
    Airborne,
    Returner,
    ReturnPlan,
    assign_layers,
    cleared_to_descend,
    spread_landing_spots,
)
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action, Goto, Hold, Land, ReturnToLaunch
from protocol.packets import GeoPoint, Position, StatusReport

CLEARANCE = 1.5
"""A drone descends only when no lower drone is within this many horizontal margins of it."""
ReturnKind = Literal["rtl", "land"]
Publish = Callable[[str, str, str | None, dict[str, object]], None]


@dataclass(frozen=True)
class ReturnSettings:
    horizontal_margin_m: float = 4.0
    base_alt_m: float = 15.0
    layer_step_m: float = 3.0
    max_alt_m: float = 120.0


@dataclass
class _Return:
    mission_id: str
    kind: ReturnKind
    column: tuple[float, float]  # local east/north of where it descends
    alt: float
    released: bool = False
    seen: bool = False  # a status of the drone has shown this return's mission id


@dataclass
class VehicleView:
    """What the coordinator reads of one agent (only agents with a position are in the view)."""

    status: StatusReport
    position: Position
    home: GeoPoint | None


@dataclass
class ReturnCoordinator:
    authority: VehicleAuthority
    fleet: Callable[[], dict[str, VehicleView]]
    release: Callable[[str, str, int], None]  # ident, mission id, step
    publish: Publish
    settings: ReturnSettings = field(default_factory=ReturnSettings)
    active: dict[str, _Return] = field(default_factory=dict)

    def start(self, idents: list[str], kind: ReturnKind, owner: Owner, reason: str) -> list[str]:
        """Send each drone its return program; returns who got one (grounded ones included).

        A drone reported on the ground gets a stand-down (land: nothing to do if it is down, and
        it lands if the report was stale and its take-off had begun), so no queued take-off flies.
        """
        fleet = self.fleet()
        stamp = time.strftime("%H%M%S")
        mission_id = f"{RETURN_PREFIX}{kind}-{stamp}"
        views = {i: fleet[i] for i in idents if i in fleet}
        airborne = {i: v for i, v in views.items() if v.status.armed and not v.status.landed}
        grounded = []
        for ident in idents:
            if ident not in airborne:
                # Land, not an empty plan: its status may be stale and a take-off under way.
                why = f"{reason} (on the ground)"
                if self.authority.replace(ident, owner, mission_id, [Land(step=0)], why)[0]:
                    grounded.append(ident)
        if not airborne:
            return grounded
        first = next(iter(airborne.values())).position
        frame = LocalFrame(first.lat, first.lon)
        returners = []
        for ident, view in airborne.items():
            here = frame.local_point(view.position.lat, view.position.lon)
            home = frame.local_point(view.home.lat, view.home.lon) if kind == "rtl" and view.home else here
            returners.append(Returner(ident, here, view.position.alt_rel, home))
        cfg = self.settings
        # Layers start above the highest returner, so nobody descends into another's layer.
        base = max([cfg.base_alt_m] + [r.alt for r in returners]) if kind == "rtl" else 0.0
        plans = assign_layers(returners, cfg.horizontal_margin_m * 1.5, base, cfg.layer_step_m)
        if kind == "land":  # layers keep today's altitudes; only the spots and the order matter
            plans = [ReturnPlan(p.ident, p.layer, r.alt) for p, r in zip(plans, returners, strict=True)]
        # Spots two margins apart: a wait point is reached only to the agent's acceptance radius.
        spots: dict[str, tuple[float, float]] = {}
        if kind == "land" or any(airborne[r.ident].home is None for r in returners):  # who lands in place
            spots = spread_landing_spots(returners, plans, 2.0 * cfg.horizontal_margin_m)
        delivered = []
        for returner, plan in zip(returners, plans, strict=True):
            view = airborne[returner.ident]
            alt = min(cfg.max_alt_m, plan.alt)
            actions: list[Action]
            if len(returners) == 1:
                # Alone: the autopilot's own RTL / land, which goes on even if the link drops.
                actions = [ReturnToLaunch(step=0, alt=max(alt, 1.0)) if kind == "rtl" else Land(step=0)]
                column = returner.home
                alt_at_column = max(alt, 1.0)
            elif kind == "rtl" and view.home is not None:
                actions = [
                    Goto(step=0, lat=view.position.lat, lon=view.position.lon, alt=max(alt, 1.0)),
                    Goto(step=1, lat=view.home.lat, lon=view.home.lon, alt=max(alt, 1.0), sync=True),
                    Land(step=2),
                ]
                column = returner.home
                alt_at_column = max(alt, 1.0)
            else:
                spot = spots[returner.ident]
                lat, lon = frame.geodetic_point(*spot)
                moved = math.dist(spot, returner.position) > 0.5
                wait_point: Action = (
                    Goto(step=0, lat=lat, lon=lon, alt=max(view.position.alt_rel, 1.0), sync=True)
                    if moved
                    else Hold(step=0, seconds=0.0, sync=True)
                )
                actions = [wait_point, Land(step=1)]
                column = spot
                alt_at_column = view.position.alt_rel
            ok, why = self.authority.replace(returner.ident, owner, mission_id, actions, reason, order=kind)
            if ok:
                delivered.append(returner.ident)
                self.active[returner.ident] = _Return(
                    mission_id, kind, column, alt_at_column, released=len(returners) == 1
                )
            self.publish(
                "return_planned" if ok else "return_refused",
                f"{kind} layer {plan.layer} at {alt_at_column:.1f} m" if ok else f"{kind} refused: {why}",
                returner.ident,
                {"layer": plan.layer, "alt": round(alt_at_column, 1), "mission_id": mission_id},
            )
        self._frame = frame
        return delivered + grounded

    def tick(self) -> None:
        """Release the wait of every returning drone that is cleared to descend."""
        if not self.active:
            return
        fleet = self.fleet()
        frame = getattr(self, "_frame", None)
        if frame is None:
            return
        others = []
        for ident, view in fleet.items():
            s = view.status
            if not s.armed or s.landed:
                continue
            here = frame.local_point(view.position.lat, view.position.lon)
            job = self.active.get(ident)
            target = job.column if job is not None and not job.released else here
            others.append(Airborne(ident, here, view.position.alt_rel, target))
        for ident, job in list(self.active.items()):
            current = fleet.get(ident)
            if current is None:
                continue
            s = current.status
            if s.mission_id != job.mission_id:
                if (s.landed and not s.armed) or job.seen:
                    self.active.pop(ident, None)  # landed, or somebody gave it other orders since
                continue
            job.seen = True
            if job.released:
                if s.landed and not s.armed:
                    self.active.pop(ident, None)
                continue
            if s.waiting_sync is None:
                continue
            # It descends from where it actually is (a wait point is never exact).
            here = frame.local_point(current.position.lat, current.position.lon)
            if cleared_to_descend(
                ident, here, current.position.alt_rel, others, CLEARANCE * self.settings.horizontal_margin_m
            ):
                job.released = True
                self.release(ident, job.mission_id, s.waiting_sync)
                self.publish(
                    "return_cleared", f"cleared to {job.kind}", ident, {"mission_id": job.mission_id}
                )
