"""Collision avoidance: closest point of approach between drones, and who holds for whom.

Pure numpy/scipy, no I/O. A pair *conflicts* when, within the horizon, there is a moment at
which both its horizontal distance is under the horizontal margin and its vertical distance is
under the vertical margin (a cylinder around each drone, as TCAS-style separation standards
use: GPS altitude and horizontal errors differ, and drones stacked 3 m apart are safe).
Candidate pairs come from a cKDTree over horizontal positions with a radius that no pair
outside it can close within the horizon, so a check costs about O(N log N + pairs), not N^2.

Priority rule (who yields): a drone that cannot be paused (RTL, LAND, not flying a queue)
never yields. Among the others the **higher connection ID yields** to the lower one. CIDs are
unique and permanent, so "yields to" is a strict total order: there is no cycle of drones each
waiting for another, and the highest-priority drone of any group is never held for the group,
so it always makes progress and the group drains. The hold is only chosen when it actually
resolves the conflict (the other drone is moving and its path clears the held drone); when no
single hold does (head-on on one line, or a drone hovering on another's path), the
lower-priority drone *escapes* by climbing above the other's altitude plus the vertical margin
while the higher-priority one waits, after which an ordinary hold suffices. CIDs are a fixed
property rather than "remaining path" because remaining path changes as drones fly, so two
drones could swap priority mid-encounter and hold each other in turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from gcs.cooperation.config import CollisionConfig
from gcs.planning.geodesy import FloatArray

IntArray = NDArray[np.int64]
STATIONARY_MPS = 0.4
_EPS = 1e-9


def candidate_pairs(positions_en: FloatArray, radius: float) -> IntArray:
    """(M, 2) index pairs i < j whose horizontal distance is at most ``radius`` (cKDTree), in
    (i, j) order: the avoider handles conflicts in this order, so it must not depend on the tree's
    shape (which a subset of the fleet changes)."""
    if len(positions_en) < 2:
        return np.empty((0, 2), dtype=np.int64)
    tree = cKDTree(positions_en)
    pairs = np.asarray(tree.query_pairs(radius, output_type="ndarray"), dtype=np.int64).reshape(-1, 2)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


@dataclass(frozen=True)
class Approach:
    """Per pair: conflict flag, time of closest horizontal approach, miss distances there."""

    conflict: NDArray[np.bool_]
    t_cpa: FloatArray
    miss_h: FloatArray
    miss_v: FloatArray


def closest_approach(
    dp: FloatArray, dv: FloatArray, h_margin: FloatArray | float, v_margin: FloatArray | float, horizon: float
) -> Approach:
    """Vectorised CPA for relative positions ``dp`` and velocities ``dv`` (M, 3: east, north, up)."""
    dph, dvh = dp[:, :2], dv[:, :2]
    dz, dvz = dp[:, 2], dv[:, 2]
    h = np.broadcast_to(np.asarray(h_margin, dtype=float), dz.shape)
    vm = np.broadcast_to(np.asarray(v_margin, dtype=float), dz.shape)
    a = np.einsum("ij,ij->i", dvh, dvh)
    b = 2.0 * np.einsum("ij,ij->i", dph, dvh)
    c = np.einsum("ij,ij->i", dph, dph) - h * h
    moving = a > _EPS
    disc = b * b - 4.0 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    safe_a = np.where(moving, a, 1.0)
    h_lo = np.where(moving, (-b - sq) / (2.0 * safe_a), np.where(c < 0, -np.inf, np.inf))
    h_hi = np.where(moving, (-b + sq) / (2.0 * safe_a), np.where(c < 0, np.inf, -np.inf))
    h_lo = np.where(moving & (disc < 0), np.inf, h_lo)
    climbing = np.abs(dvz) > _EPS
    safe_vz = np.where(climbing, dvz, 1.0)
    ta, tb = (-vm - dz) / safe_vz, (vm - dz) / safe_vz
    inside_v = np.abs(dz) < vm
    v_lo = np.where(climbing, np.minimum(ta, tb), np.where(inside_v, -np.inf, np.inf))
    v_hi = np.where(climbing, np.maximum(ta, tb), np.where(inside_v, np.inf, -np.inf))
    lo = np.maximum(np.maximum(h_lo, v_lo), 0.0)
    hi = np.minimum(np.minimum(h_hi, v_hi), horizon)
    conflict = lo <= hi
    t_cpa = np.clip(np.where(moving, -b / (2.0 * safe_a), 0.0), 0.0, horizon)
    miss = dph + dvh * t_cpa[:, None]
    return Approach(
        conflict=conflict,
        t_cpa=t_cpa,
        miss_h=np.sqrt(np.einsum("ij,ij->i", miss, miss)),
        miss_v=np.abs(dz + dvz * t_cpa),
    )


def pair_conflicts(
    dp: list[float], dv: list[float], h_margin: float, v_margin: float, horizon: float
) -> bool:
    """:func:`closest_approach` for one pair in plain floats (numpy costs more than the maths here)."""
    a = dv[0] * dv[0] + dv[1] * dv[1]
    b = 2.0 * (dp[0] * dv[0] + dp[1] * dv[1])
    c = dp[0] * dp[0] + dp[1] * dp[1] - h_margin * h_margin
    if a > _EPS:
        disc = b * b - 4.0 * a * c
        if disc < 0:
            return False
        sq = math.sqrt(disc)
        h_lo, h_hi = (-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a)
    elif c < 0:
        h_lo, h_hi = -math.inf, math.inf
    else:
        return False
    if abs(dv[2]) > _EPS:
        ta, tb = (-v_margin - dp[2]) / dv[2], (v_margin - dp[2]) / dv[2]
        v_lo, v_hi = min(ta, tb), max(ta, tb)
    elif abs(dp[2]) < v_margin:
        v_lo, v_hi = -math.inf, math.inf
    else:
        return False
    return max(h_lo, v_lo, 0.0) <= min(h_hi, v_hi, horizon)


def find_conflicts(
    positions: FloatArray,
    velocities: FloatArray,
    config: CollisionConfig,
    margin_scale: FloatArray | None = None,
) -> tuple[IntArray, Approach]:
    """Conflicting pairs of a fleet: ``positions``/``velocities`` are (N, 3) east, north, up."""
    n = len(positions)
    if n < 2:
        return np.empty((0, 2), dtype=np.int64), closest_approach(
            np.empty((0, 3)), np.empty((0, 3)), config.horizontal_margin_m, config.vertical_margin_m, 1.0
        )
    scale = np.ones(n) if margin_scale is None else margin_scale
    speeds = np.linalg.norm(velocities[:, :2], axis=1)
    vmax = min(float(speeds.max(initial=0.0)), config.max_speed_mps)
    radius = config.horizontal_margin_m * float(scale.max()) + 2.0 * vmax * config.horizon_s
    pairs = candidate_pairs(positions[:, :2], radius)
    if len(pairs) == 0:
        return pairs, closest_approach(np.empty((0, 3)), np.empty((0, 3)), 1.0, 1.0, 1.0)
    i, j = pairs[:, 0], pairs[:, 1]
    pair_scale = np.maximum(scale[i], scale[j])
    approach = closest_approach(
        positions[j] - positions[i],
        velocities[j] - velocities[i],
        config.horizontal_margin_m * pair_scale,
        config.vertical_margin_m * pair_scale,
        config.horizon_s,
    )
    keep = approach.conflict
    return pairs[keep], Approach(
        keep[keep], approach.t_cpa[keep], approach.miss_h[keep], approach.miss_v[keep]
    )


# --- decisions ----------------------------------------------------------------------------------


@dataclass
class DroneState:
    """What the avoider needs of one airborne drone at this tick."""

    ident: str
    cid: int
    position: tuple[float, float, float]  # east, north, up (AMSL) metres (protocol.geo.LocalFrame)
    velocity: tuple[float, float, float]  # east, north, up m/s (vehicle time)
    desired: tuple[float, float, float] | None  # where it wants to go when not held
    yieldable: bool
    grounded: bool = False  # landed or disarmed: an obstacle, never a partner to wait for
    remaining_m: float | None = None  # to its leg target, where it stops (None: unknown / not stopping)


@dataclass(frozen=True)
class Escape:
    ident: str
    blockers: tuple[str, ...]  # the drones it climbs clear of (sorted)
    target_up: float  # AMSL metres to climb to
    reason: str

    @property
    def other(self) -> str:
        """The blockers as one name list, for messages."""
        return ", ".join(self.blockers)


@dataclass
class Decision:
    pause: dict[str, str] = field(default_factory=dict)  # ident -> reason
    resume: list[str] = field(default_factory=list)
    escapes: list[Escape] = field(default_factory=list)
    events: list[tuple[str, str, dict[str, object]]] = field(default_factory=list)  # kind, message, data


@dataclass
class _Escaping:
    escape: Escape
    started: float


class CollisionAvoider:
    """Turns conflicts into holds, releases and escapes; keeps the hold state between ticks."""

    def __init__(self, config: CollisionConfig, escape_timeout_s: float = 30.0) -> None:
        self.config = config
        self.escape_timeout_s = escape_timeout_s
        self.holds: dict[str, set[str]] = {}  # held drone -> drones it waits for
        self.escaping: dict[str, _Escaping] = {}
        self._last_conflict: dict[str, float] = {}
        self._held_since: dict[str, float] = {}
        self._reported: set[tuple[str, str]] = set()
        self._cannot_escape: set[str] = set()  # held because their escape could not be planned

    @property
    def held(self) -> set[str]:
        return set(self.holds)

    def forget(self, ident: str) -> None:
        """The drone left the airspace picture (landed, lost, handed to an emergency action)."""
        self.holds.pop(ident, None)
        self.escaping.pop(ident, None)
        self._last_conflict.pop(ident, None)
        self._held_since.pop(ident, None)
        self._cannot_escape.discard(ident)
        for blockers in self.holds.values():
            blockers.discard(ident)

    def escape_impossible(self, escape: Escape, now: float) -> None:
        """The escape could not be planned (e.g. the drone is still taking off): hold it instead.

        The hold is tracked like any other, so it is released once the pair is clear and expires
        after ``max_hold_s``; for that long the drone is not chosen to escape again (its partner
        climbs clear instead, if it can), and when the hold expires it is released, not re-escaped.
        """
        self.escaping.pop(escape.ident, None)
        self.holds[escape.ident] = set(escape.blockers)
        self._held_since[escape.ident] = now
        self._last_conflict[escape.ident] = now
        self._cannot_escape.add(escape.ident)

    def _may_escape(self, ident: str) -> bool:
        """False while a hold that replaced an impossible escape lasts (see escape_impossible)."""
        return ident not in self._cannot_escape

    def adopt(self, ident: str, now: float) -> None:
        """A hold another decider placed (cluster: the airspace changed hands): ours now, released
        like our own once no conflict needs it for ``release_after_s``."""
        self.holds.setdefault(ident, set())
        self._held_since.setdefault(ident, now)
        self._last_conflict[ident] = now

    def update(self, drones: list[DroneState], now: float) -> Decision:
        decision = Decision()
        index = {d.ident: k for k, d in enumerate(drones)}
        for ident in list(self.holds) + list(self.escaping):
            if ident not in index:
                if ident in self.holds:
                    decision.resume.append(ident)
                self.forget(ident)
        self._finish_escapes(drones, index, now, decision)
        if len(drones) < 2:
            self._release(set(), now, decision)
            return decision
        pos = np.array([d.position for d in drones], dtype=float)
        vel = self._effective_all(drones)
        held = np.array([d.ident in self.holds for d in drones], dtype=bool)
        scale = np.where(held, self.config.release_factor, 1.0)
        pairs, approach = find_conflicts(pos, vel, self.config, scale)
        wanted: dict[str, set[str]] = {}
        for (i, j), t_cpa, miss_h, miss_v in zip(
            pairs.tolist(), approach.t_cpa, approach.miss_h, approach.miss_v, strict=True
        ):
            a, b = drones[i], drones[j]
            detail = (
                f"{a.ident}/{b.ident} miss {miss_h:.1f} m horizontal, {miss_v:.1f} m vertical "
                f"in {t_cpa:.1f} s"
            )
            self._resolve(a, b, pos[i], pos[j], vel[i], vel[j], detail, wanted, decision, now)
        self._expire_long_holds(wanted, drones, index, now, decision)
        self._apply(wanted, now, decision)
        return decision

    def _expire_long_holds(
        self,
        wanted: dict[str, set[str]],
        drones: list[DroneState],
        index: dict[str, int],
        now: float,
        decision: Decision,
    ) -> None:
        """A hold never traps a drone: past ``max_hold_s`` the held drone climbs out of the way.

        A conflict that a hold has not resolved in that time is one with a partner that does not
        move away (hovering, waiting at a barrier, held itself), so waiting longer cannot help.
        """
        for ident in [i for i in wanted if i in self.holds and i not in self.escaping]:
            since = self._held_since.get(ident)
            if since is None or now - since < self.config.max_hold_s:
                continue
            me = drones[index[ident]]
            blockers = [drones[index[b]] for b in wanted[ident] if b in index]
            top = max([me.position[2]] + [b.position[2] for b in blockers])
            waited_for = tuple(sorted(wanted.pop(ident)))
            others = ", ".join(waited_for)
            self.holds.pop(ident, None)
            self._held_since.pop(ident, None)
            if self.config.escape == "none" or not me.yieldable or ident in self._cannot_escape:
                self._cannot_escape.discard(ident)
                decision.resume.append(ident)
                decision.events.append(
                    (
                        "collision_hold_expired",
                        f"{ident} held {self.config.max_hold_s:.0f} s for {others}; released",
                        {"agent": ident},
                    )
                )
                continue
            target = top + self.config.vertical_margin_m + self.config.escape_buffer_m
            escape = Escape(
                ident,
                waited_for,
                float(target),
                f"collision avoidance: held {self.config.max_hold_s:.0f} s for {others}; climbing clear",
            )
            self.escaping[ident] = _Escaping(escape, now)
            decision.escapes.append(escape)

    # --- internals ------------------------------------------------------------------------------

    def _effective_all(self, drones: list[DroneState]) -> FloatArray:
        """The velocity each drone is judged by (numpy; this runs every tick).

        A held drone, or one about to start a leg (nearly still, with a leg to fly), is judged by
        where it wants to go: its ~zero velocity would say "clear" the moment it stops, and it
        would be released straight back into the conflict. The others by their actual velocity.
        Nobody is predicted past its leg target: a drone that stops there within the horizon is
        slowed so that it just reaches it (formation flight ends legs a few metres apart).
        """
        actual = np.array([d.velocity for d in drones], dtype=float)
        zero = (0.0, 0.0, 0.0)
        desired = np.array([d.desired or zero for d in drones], dtype=float)
        has_desired = np.array([d.desired is not None for d in drones], dtype=bool)
        held = np.array([d.ident in self.holds for d in drones], dtype=bool)
        escaping = np.array([d.ident in self.escaping for d in drones], dtype=bool)
        slow = np.linalg.norm(actual, axis=1) < STATIONARY_MPS
        use_desired = ~escaping & (held | (slow & has_desired))
        vel = np.where(use_desired[:, None], desired, actual)
        remaining = np.array([np.inf if d.remaining_m is None else d.remaining_m for d in drones])
        reach = np.linalg.norm(vel, axis=1) * self.config.horizon_s
        factor = np.where(reach > remaining, remaining / np.maximum(reach, _EPS), 1.0)
        return np.asarray(vel * factor[:, None], dtype=float)

    def _pair_conflicts(self, pa: FloatArray, pb: FloatArray, va: FloatArray, vb: FloatArray) -> bool:
        dp, dv = (pb - pa).tolist(), (vb - va).tolist()
        cfg = self.config
        return pair_conflicts(dp, dv, cfg.horizontal_margin_m, cfg.vertical_margin_m, cfg.horizon_s)

    def _hold_resolves(self, y_pos: FloatArray, o_pos: FloatArray, o_vel: FloatArray) -> bool:
        """Holding the drone at ``y_pos`` helps only if the other moves and its path clears the hold point."""
        if float(np.linalg.norm(o_vel)) < STATIONARY_MPS:
            return False
        return not self._pair_conflicts(y_pos, o_pos, np.zeros(3), o_vel)

    def _resolve(
        self,
        a: DroneState,
        b: DroneState,
        pa: FloatArray,
        pb: FloatArray,
        va: FloatArray,
        vb: FloatArray,
        detail: str,
        wanted: dict[str, set[str]],
        decision: Decision,
        now: float,
    ) -> None:
        if a.grounded and b.grounded:
            return  # two parked drones
        if a.grounded or b.grounded:
            _parked, flying = (a, b) if a.grounded else (b, a)
            offset = (pb - pa) if flying is b else (pa - pb)
            v_flying = vb if flying is b else va
            apart = max(float(np.linalg.norm(offset[:2])), _EPS)
            if -float(np.dot(offset[:2], v_flying[:2])) / apart < STATIONARY_MPS:
                # Climbing, descending or moving away beside a parked drone: no conflict. A take-off
                # drifts a few dm/s; counted as closing in, it made an escape that cannot be planned
                # during a take-off (an error event) next to a landed, disarmed drone.
                return
        escaping = self.escaping.get(a.ident) or self.escaping.get(b.ident)
        if escaping is not None:  # the other waits until the escaping drone has climbed clear
            waiting = b if escaping.escape.ident == a.ident else a
            if waiting.yieldable:
                wanted.setdefault(waiting.ident, set()).add(escaping.escape.ident)
            return
        # Preferred yielder first: the higher CID; drones that cannot be paused never yield.
        order = sorted((a, b), key=lambda d: -d.cid)
        candidates = [d for d in order if d.yieldable]
        if not candidates:
            self._report(a, b, "collision_unresolved", f"neither drone can be held: {detail}", decision)
            return
        state = {a.ident: (pa, va), b.ident: (pb, vb)}
        for y in candidates:
            other = b if y is a else a
            if self._hold_resolves(state[y.ident][0], state[other.ident][0], state[other.ident][1]):
                wanted.setdefault(y.ident, set()).add(other.ident)
                return
        # No single hold resolves it: the drone that will not move by itself, else the preferred
        # yielder, climbs clear while the other waits.
        able = [d for d in candidates if self._may_escape(d.ident)]
        if not able:  # neither can climb out now: the preferred yielder waits (bounded by max_hold_s)
            wanted.setdefault(candidates[0].ident, set()).add((b if candidates[0] is a else a).ident)
            return
        still = [d for d in able if float(np.linalg.norm(state[d.ident][1])) < STATIONARY_MPS]
        escaper = still[0] if still else able[0]
        other = b if escaper is a else a
        if other.yieldable:
            wanted.setdefault(other.ident, set()).add(escaper.ident)
        if self.config.escape == "none":
            wanted.setdefault(escaper.ident, set()).add(other.ident)
            self._report(
                a, b, "collision_unresolved", f"no hold resolves it and escapes are off: {detail}", decision
            )
            return
        target = max(state[escaper.ident][0][2], state[other.ident][0][2]) + (
            self.config.vertical_margin_m + self.config.escape_buffer_m
        )
        escape = Escape(
            escaper.ident,
            (other.ident,),
            float(target),
            f"collision avoidance: climb clear of {other.ident}; {detail}",
        )
        self.escaping[escaper.ident] = _Escaping(escape, now)
        self.holds.pop(escaper.ident, None)  # the escape's replace overrides its pause
        self._held_since.pop(escaper.ident, None)
        decision.escapes.append(escape)

    def _finish_escapes(
        self, drones: list[DroneState], index: dict[str, int], now: float, decision: Decision
    ) -> None:
        for ident, state in list(self.escaping.items()):
            drone = drones[index[ident]]
            if abs(drone.position[2] - state.escape.target_up) < 1.0:
                del self.escaping[ident]
                decision.events.append(
                    ("collision_escaped", f"{ident} climbed clear of {state.escape.other}", {"agent": ident})
                )
            elif now - state.started > self.escape_timeout_s:
                del self.escaping[ident]
                decision.events.append(
                    (
                        "collision_escape_timeout",
                        f"{ident} did not reach its escape altitude",
                        {"agent": ident},
                    )
                )

    def _apply(self, wanted: dict[str, set[str]], now: float, decision: Decision) -> None:
        for ident, blockers in wanted.items():
            if ident in self.escaping:
                continue
            self._last_conflict[ident] = now  # the hold is still needed
            if ident not in self.holds:
                decision.pause[ident] = "collision avoidance: yield to " + ", ".join(sorted(blockers))
                self.holds[ident] = set(blockers)
                self._held_since[ident] = now
            else:
                self.holds[ident] |= blockers
        self._release(set(wanted), now, decision)

    def _release(self, still_wanted: set[str], now: float, decision: Decision) -> None:
        for ident in list(self.holds):
            if ident in still_wanted:
                continue
            if now - self._last_conflict.get(ident, -1e18) >= self.config.release_after_s:
                del self.holds[ident]
                self._held_since.pop(ident, None)
                self._cannot_escape.discard(ident)
                decision.resume.append(ident)

    def _report(self, a: DroneState, b: DroneState, kind: str, message: str, decision: Decision) -> None:
        key = (min(a.ident, b.ident), max(a.ident, b.ident))
        if key not in self._reported:
            self._reported.add(key)
            decision.events.append((kind, message, {"agents": list(key)}))
