"""``gcs plan --targets FILE --method psa`` and ``gcs plan --missed-map FILE --method rsa``.

The ``plan`` command (gcs/commands/plan.py) owns ``--method``, ``--out``, ``--drones``,
``--speed`` and ``--alt`` and calls :func:`add_arguments` / :func:`run` here. Writes
``mission.json`` (task file), ``plan.geojson``, ``plan.png`` and ``report.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gcs.cooperation.config import CollisionConfig
from gcs.planning._fleet_io import FleetFileError, geojson_lines, load_missed_map, load_targets
from gcs.planning._psa_mission import psa_mission
from gcs.planning.geodesy import LocalFrame
from gcs.planning.mission import mission_from_paths
from gcs.planning.psa import plan_psa
from gcs.planning.rsa import RsaError, plan_rsa


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the PSA / RSA planners (names chosen not to clash with the plan command's)."""
    g = parser.add_argument_group("fleet planners (psa, rsa)")
    g.add_argument(
        "--targets", type=Path, metavar="FILE", help="PSA target file (JSON, docs/fleet-planners.md)"
    )
    g.add_argument("--missed-map", type=Path, metavar="FILE", help="RSA missed-area grid map (JSON)")
    g.add_argument(
        "--link-range", type=float, metavar="M", help="PSA: drone link range w (overrides the file)"
    )
    g.add_argument(
        "--min-separation",
        type=float,
        metavar="M",
        help="PSA: closest two drones may come at any time, turns included (default: the collision "
        "service's horizontal margin x release factor, 5 m)",
    )
    g.add_argument(
        "--track-margin",
        type=float,
        metavar="M",
        help="PSA: how far a flown track may stray from the plan; the plan keeps w and the separation "
        "with this much to spare on each drone (default 2 m: the agent's acceptance radius, since "
        "each leg starts up to that far from its planned start)",
    )
    g.add_argument("--channel-spacing", type=float, metavar="M", help="RSA: channel spacing d_nbh")
    g.add_argument("--flight-distance", type=float, metavar="M", help="RSA: allowed flight distance d_flt")
    g.add_argument("--access-side", choices=["west", "east", "south", "north"], help="RSA: accessible side")
    g.add_argument(
        "--safety-distance", type=float, metavar="M", help="RSA: entry/exit lane separation d_sfty"
    )


def _opt(args: argparse.Namespace, name: str, default: object) -> object:
    """The command-line value when given, else the file's (or the planner's) default."""
    value = getattr(args, name, None)
    return default if value is None else value


def _plot(out: Path, title: str, paths: list[np.ndarray], extra: list[tuple[np.ndarray, str]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    for poly, style in extra:
        ax.plot(poly[:, 0], poly[:, 1], style, lw=0.8, ms=3)
    for j, p in enumerate(paths):
        ax.plot(p[:, 0], p[:, 1], lw=1.0, label=f"drone {j + 1}")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title)
    ax.legend(fontsize=7, loc="best")
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _write(out: Path, mission: object, geojson: dict[str, object], report: dict[str, object]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "mission.json").write_text(mission.model_dump_json(indent=1))  # type: ignore[attr-defined]
    (out / "plan.geojson").write_text(json.dumps(geojson))
    (out / "report.json").write_text(json.dumps(report, indent=1))


def _run_psa(args: argparse.Namespace, out: Path) -> int:
    doc, frame, pts = load_targets(args.targets)
    drones = int(_opt(args, "drones", doc.config.drones))  # type: ignore[call-overload]
    link = float(_opt(args, "link_range", doc.config.link_range_m))  # type: ignore[arg-type]
    speed = float(_opt(args, "speed", doc.config.speed_mps))  # type: ignore[arg-type]
    alt = float(_opt(args, "alt", doc.config.alt_m))  # type: ignore[arg-type]
    collision = CollisionConfig()
    default_sep = collision.horizontal_margin_m * collision.release_factor
    separation = float(_opt(args, "min_separation", doc.config.min_separation_m or default_sep))  # type: ignore[arg-type]
    margin = float(_opt(args, "track_margin", doc.config.track_margin_m))  # type: ignore[arg-type]
    if drones < 1 or link <= 0 or speed <= 0 or alt <= 0:
        raise FleetFileError("drones, link range, speed and altitude must be positive")
    if separation < 0 or margin < 0:
        raise FleetFileError("--min-separation and --track-margin must not be negative")
    plan = plan_psa(pts, drones, link, speed, min_separation=separation, track_margin=margin)
    if doc.homes is not None:
        if len(doc.homes) != drones:
            raise FleetFileError(f"the target file lists {len(doc.homes)} homes for {drones} drones")
        plan = plan.from_homes(frame.points_to_local([(h.lat, h.lon) for h in doc.homes]))
    check = plan.check()
    traj = plan.trajectory
    names = [f"drone-{j + 1}" for j in range(drones)]
    paths_ll = []
    for j in range(drones):
        lat, lon = frame.to_geodetic(traj.positions[j, :, 0], traj.positions[j, :, 1])
        paths_ll.append(list(zip(lat.tolist(), lon.tolist(), strict=True)))
    c = plan.costs
    report = {
        "method": "psa",
        "targets": len(pts),
        "rounds": len(plan.rounds),
        "L_fleet_m": c.fleet_length,
        "sum_L_k_m": sum(c.round_lengths),
        "L_trans_m": c.transfer,
        "L_adjust_scan_m": c.scan_adjust,
        "L_adjust_turns_m": c.turn_adjust,
        "theorem1_bound_m": c.lower_bound,
        "duration_s": float(plan.flown.times[-1]),
        "link_range_m": link,
        "min_separation_m": separation,
        "track_margin_m": margin,
        "planned_max_neighbour_m": check.max_neighbour_distance,
        "planned_min_separation_m": check.min_separation,
        "barriers": int(traj.sync.sum()),
        "check_ok": check.ok,
        "violations": [v.detail for v in check.violations[:20]],
    }
    _write(
        out,
        psa_mission(
            traj,
            frame,
            alt,
            speed,
            names,
            assembly=None if plan.assembly is None else plan.assembly.trajectory,
            assembly_speeds=None if plan.assembly is None else plan.assembly.speeds.tolist(),
        ),
        geojson_lines(paths_ll, names, method="psa"),
        report,
    )
    hulls = [np.vstack([r.hull, r.hull[:1]]) for r in plan.rounds if len(r.hull) > 1]
    _plot(
        out / "plan.png",
        f"PSA: {len(pts)} targets, {drones} drones, L_fleet {c.fleet_length:.0f} m",
        [traj.positions[j] for j in range(drones)],
        [(h, "k--") for h in hulls] + [(pts, "r*")],
    )
    print(
        f"psa: {len(pts)} targets, {len(plan.rounds)} rounds, L_fleet {c.fleet_length:.1f} m "
        f"(bound {c.lower_bound:.1f} m), neighbours <= {check.max_neighbour_distance:.1f} m "
        f"(w {link:g} m), pairs >= {min(check.min_separation, 1e9):.1f} m, "
        f"check {'ok' if check.ok else 'FAILED'} -> {out}"
    )
    return 0 if check.ok else 1


def _run_rsa(args: argparse.Namespace, out: Path) -> int:
    doc, missed = load_missed_map(args.missed_map)
    plan = plan_rsa(
        missed,
        d_nbh=float(_opt(args, "channel_spacing", doc.channel_spacing_m)),  # type: ignore[arg-type]
        d_flt=float(_opt(args, "flight_distance", doc.flight_distance_m)),  # type: ignore[arg-type]
        side=_opt(args, "access_side", doc.side),  # type: ignore[arg-type]
        d_sfty=float(_opt(args, "safety_distance", doc.safety_m)),  # type: ignore[arg-type]
        standoff=doc.standoff_m,
    )
    alt = float(_opt(args, "alt", 20.0))  # type: ignore[arg-type]
    speed = _opt(args, "speed", None)
    frame = LocalFrame(missed.origin_lat, missed.origin_lon)
    names = [f"drone-{j + 1}" for j in range(len(plan.drones))]
    paths_ll, en_paths = [], []
    for d in plan.drones:
        en = missed.to_east_north(d.path)
        en_paths.append(en)
        lat, lon = frame.to_geodetic(en[:, 0], en[:, 1])
        paths_ll.append(list(zip(lat.tolist(), lon.tolist(), strict=True)))
    report = {
        "method": "rsa",
        "zones": len(plan.zones),
        "labelled_zones": plan.zone_count_before_merge,
        "drones_needed": len(plan.drones),
        "lengths_m": [d.length for d in plan.drones],
    }
    if not plan.drones:
        print("rsa: no missed cells, nothing to fly")
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps(report, indent=1))
        return 0
    mission = mission_from_paths(
        paths_ll,
        alt,
        None if speed is None else float(speed),  # type: ignore[arg-type]
        names,
        homes_latlon=[p[-1] for p in paths_ll],
        return_mode="land_home",
        name="rsa",
    )
    _write(out, mission, geojson_lines(paths_ll, names, method="rsa"), report)
    rects = [missed.to_east_north(np.vstack([z.rectangle, z.rectangle[:1]])) for z in plan.zones]
    cells = missed.to_east_north(missed.cell_centres(missed.grid == 0))
    _plot(
        out / "plan.png",
        f"RSA: {len(plan.zones)} zones, {len(plan.drones)} drones",
        en_paths,
        [(cells, "r,")] + [(r, "k--") for r in rects],
    )
    print(f"rsa: {len(plan.zones)} zones, {len(plan.drones)} drones needed -> {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """Plan with PSA (``--targets``) or RSA (``--missed-map``); exit 2 with a message on bad input."""
    method = getattr(args, "method", None) or ("psa" if getattr(args, "targets", None) else "rsa")
    out = Path(_opt(args, "out", "plan-out"))  # type: ignore[arg-type]
    try:
        if method == "psa":
            if getattr(args, "targets", None) is None:
                raise FleetFileError("--method psa needs --targets FILE")
            return _run_psa(args, out)
        if method == "rsa":
            if getattr(args, "missed_map", None) is None:
                raise FleetFileError("--method rsa needs --missed-map FILE")
            return _run_rsa(args, out)
        raise FleetFileError(f"plan_targets handles psa and rsa, not {method!r}")
    except (FleetFileError, RsaError, ValueError) as exc:
        print(f"gcs plan: error: {exc}", file=sys.stderr)
        return 2
