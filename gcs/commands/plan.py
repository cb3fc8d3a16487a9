"""`gcs plan`: plan a multi-drone area search and write mission JSON, GeoJSON paths and a PNG.

The area may be GeoJSON, KML, a [[lat, lon], ...] list or a QGroundControl ``.plan``, whose
survey settings (planned home, altitude, line spacing, side overlap, grid angle) are kept unless
an option overrides them. ``--export plan,waypoints,kml`` also writes each drone's mission for
QGroundControl and Mission Planner and the whole plan as KML.

Area searches (zigzag/spiral/segmented/curved, path or region division) are planned here;
``--method psa|rsa`` (target and missed-map planning) is handed to ``gcs.commands.plan_targets``
when that module is installed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

from gcs.planning.areas import AreaFormatError
from gcs.planning.camera import Camera, CameraError, Spacing, spacing_from_camera, spacing_from_swath
from gcs.planning.division import DroneSpec, InsufficientCapabilityError
from gcs.planning.interchange import EXPORT_FORMATS, QgcSurvey, export_files, load_area_text
from gcs.planning.planner import PlanConfig, SearchPlan, plan_search
from gcs.planning.polygon import SelfIntersectionError
from protocol.geo import allow_negative_coordinates

_plan_targets: ModuleType | None
try:  # target/missed-map planning lives in its own module; the area planner works without it
    from gcs.commands import plan_targets as _plan_targets
except ImportError:
    _plan_targets = None


def _latlon(text: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LAT,LON, got {text!r}") from None
    return lat, lon


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _formats(text: str) -> list[str]:
    formats = [f.strip().lower().lstrip(".") for f in text.split(",") if f.strip()]
    bad = [f for f in formats if f not in EXPORT_FORMATS]
    if bad:
        raise argparse.ArgumentTypeError(f"export formats are {', '.join(EXPORT_FORMATS)}; got {bad}")
    return formats


def _camera(text: str) -> Camera:
    keys = {
        "res": "resolution_px",
        "fov": "fov_deg",
        "sensor": "sensor_width_mm",
        "focal": "focal_mm",
        "minpx": "min_pixels",
    }
    values: dict[str, Any] = {}
    for item in text.split(","):
        k, _, v = item.partition("=")
        if k.strip() not in keys or not v:
            raise argparse.ArgumentTypeError(
                f"camera fields are {', '.join(keys)} as key=value; got {item!r}"
            )
        values[keys[k.strip()]] = float(v)
    try:
        return Camera(**values)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_area_arguments(parser: argparse.ArgumentParser) -> None:
    """The area-search options (kept separate so they are easy to reuse and to test)."""
    allow_negative_coordinates(parser)  # --home -35.36,149.16
    parser.add_argument(
        "area", nargs="?", help="area file: GeoJSON Polygon/Feature, KML, QGC .plan, or [[lat,lon],...]"
    )
    parser.add_argument(
        "--drones", type=_at_least_one, help="number of drones (default 1; psa: the target file's)"
    )
    parser.add_argument(
        "--pattern",
        choices=["zigzag", "spiral", "segmented", "curved"],
        default="zigzag",
        help="survey pattern (docs/planning.md)",
    )
    parser.add_argument(
        "--division",
        choices=["path", "region", "partition"],
        default="path",
        help="how the area is shared among the drones (docs/planning.md)",
    )
    parser.add_argument("--swath", type=float, help="footprint width across track (m); needs --alt")
    parser.add_argument("--camera", type=_camera, help="res=PX,fov=DEG[,minpx=N] or res=,sensor=MM,focal=MM")
    parser.add_argument("--target-size", type=_floats, default=[0.5], help="pattern W[,H] in m (camera mode)")
    parser.add_argument("--overlap", type=float, default=0.0, help="side overlap fraction, 0..0.9")
    parser.add_argument("--alt", type=float, help="survey altitude above home (m); camera default: h_max")
    parser.add_argument("--speed", type=float, help="cruise speed m/s (default 5; psa: the target file's)")
    parser.add_argument("--home", type=_latlon, help="LAT,LON of the launch point (default: first vertex)")
    parser.add_argument("--out", type=Path, default=Path("plan-out"), help="output directory")
    parser.add_argument("--battery", type=_floats, help="battery fraction per drone, e.g. 1,0.8,0.5")
    parser.add_argument("--endurance", type=float, default=1200.0, help="full-charge endurance (s)")
    parser.add_argument("--reserve", type=float, default=0.2, help="battery reserve fraction")
    parser.add_argument("--segments", type=int, default=4, help="segmented: parts per leg")
    parser.add_argument("--shift", type=float, default=0.2, help="curved: midpoint shift x step (|s| <= 0.5)")
    parser.add_argument("--wind-from", type=float, dest="wind_from", help="curved: wind direction FROM (deg)")
    parser.add_argument("--angle", type=float, help="force the leg rotation (deg)")
    parser.add_argument(
        "--concave",
        choices=["decompose", "hull"],
        default="decompose",
        help="a concave area: decompose it into convex parts (default) or survey its convex hull",
    )
    parser.add_argument(
        "--return",
        dest="return_mode",
        choices=["rtl", "land_home"],
        default="rtl",
        help="after the survey: rtl (default) or land_home (each at its own launch point)",
    )
    parser.add_argument("--stagger", type=float, default=0.0, help="transit altitude step between drones (m)")
    parser.add_argument(
        "--allow-partial", action="store_true", help="plan even if the fleet cannot cover all"
    )
    parser.add_argument("--names", help="comma-separated agent names (default drone-1..N)")
    parser.add_argument(
        "--export",
        type=_formats,
        default=[],
        help="also write plan (QGroundControl, one per drone), waypoints (Mission Planner) and/or kml",
    )


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "plan",
        help="plan a multi-drone search (area coverage; psa/rsa with plan_targets)",
        conflict_handler="resolve",
    )
    add_area_arguments(parser)
    parser.add_argument(
        "--method",
        choices=["area", "psa", "rsa"],
        help="area search (default), psa (--targets FILE) or rsa (--missed-map FILE)",
    )
    if _plan_targets is not None:
        _plan_targets.add_arguments(parser)
    parser.set_defaults(run=run)


def _at_least_one(text: str) -> int:
    """``--drones``: a whole number of drones, at least 1 (0 used to plan for one, -2 to blame --battery)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{n}: a plan needs at least 1 drone")
    return n


def run(args: argparse.Namespace) -> int:
    method = getattr(args, "method", None)
    if method is None and (getattr(args, "targets", None) or getattr(args, "missed_map", None)):
        method = "psa" if getattr(args, "targets", None) else "rsa"
    if method in ("psa", "rsa"):
        args.method = method
        if _plan_targets is None:
            print(
                f"error: --method {method} needs gcs.commands.plan_targets, which is not installed",
                file=sys.stderr,
            )
            return 2
        return int(_plan_targets.run(args))
    try:
        return _run_area(args)
    except SelfIntersectionError as exc:  # bad input: exit 2, as README says for every command
        print(f"gcs plan: {_crossings_in_latlon(args.area) or exc}", file=sys.stderr)
        return 2
    except (
        AreaFormatError,
        CameraError,
        InsufficientCapabilityError,
        ValueError,
    ) as exc:
        print(f"gcs plan: {exc}", file=sys.stderr)
        return 2


def _crossings_in_latlon(area_file: str) -> str | None:
    """The crossing edges of the area file's ring, located in the file's own lat/lon."""
    path = Path(area_file)
    found = load_area_text(path.read_text(), path.stem)[0].crossings()
    return found[0] if found is not None else None


def _spacing(args: argparse.Namespace, survey: QgcSurvey | None = None) -> Spacing:
    if args.camera is not None and args.swath is not None:
        raise ValueError("give either --swath or --camera, not both")
    if args.camera is None and args.swath is None and survey is not None and survey.step_m is not None:
        # the QGC survey's own spacing and altitude, as the operator set them there
        altitude = args.alt if args.alt is not None else survey.altitude_m
        if altitude is None:
            raise ValueError("the QGC survey has no altitude; give --alt")
        swath = survey.swath_m or survey.step_m
        return Spacing(altitude=altitude, swath=swath, step=survey.step_m, side_overlap=survey.side_overlap)
    if args.camera is not None:
        size = args.target_size
        return spacing_from_camera(
            args.camera, size[0], size[1] if len(size) > 1 else None, args.overlap, args.alt
        )
    if args.swath is None:
        raise ValueError("give --swath M (with --alt) or --camera ...")
    return spacing_from_swath(args.swath, args.alt if args.alt is not None else 30.0, args.overlap)


DEFAULT_SPEED_MPS = 5.0


def _speed(args: argparse.Namespace) -> float:
    return float(args.speed) if args.speed is not None else DEFAULT_SPEED_MPS


def _drones(args: argparse.Namespace) -> list[DroneSpec]:
    n = getattr(args, "drones", 1) or 1
    batteries = args.battery or [1.0] * n
    if len(batteries) != n:
        raise ValueError(f"--battery lists {len(batteries)} values for {n} drones")
    names = args.names.split(",") if args.names else [f"drone-{i + 1}" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"--names lists {len(names)} names for {n} drones")
    return [
        DroneSpec(
            name=nm, battery=b, endurance_s=args.endurance, speed_mps=_speed(args), reserve=args.reserve
        )
        for nm, b in zip(names, batteries, strict=True)
    ]


def _run_area(args: argparse.Namespace) -> int:
    if not args.area:
        print("error: give an AREA file (or --method psa/rsa)", file=sys.stderr)
        return 2
    path = Path(args.area)
    text = path.read_text()  # a missing file or a directory: the CLI's one-line OSError message
    try:
        area, survey = load_area_text(text, path.stem)
    except AreaFormatError as exc:
        raise AreaFormatError(f"{path}: {exc}") from None
    drones = _drones(args)
    angle = args.angle if args.angle is not None else (survey.angle_deg if survey else None)
    home = args.home if args.home is not None else (survey.home if survey else None)
    config = PlanConfig(
        pattern=args.pattern,
        division=args.division,
        concave=args.concave,
        segments=args.segments,
        shift=args.shift,
        wind_from_deg=args.wind_from,
        angle_deg=angle,
        allow_partial=args.allow_partial,
        return_mode=args.return_mode,
        transit_alt_step=args.stagger,
        name=area.name,
    )
    plan = plan_search(
        area, drones, _spacing(args, survey), config, home, _speed(args), [d.name for d in drones]
    )
    write_outputs(plan, args.out)
    write_exports(plan, args.out, args.export, _speed(args), home_given=home is not None)
    if args.export and home is None:
        print(
            "gcs plan: note: the exports' homes are the area's first corner (give --home LAT,LON, "
            "or plan through the daemon for each drone's real home); the files say so",
            file=sys.stderr,
        )
    print(json.dumps(plan.summary, indent=2))
    return 0


def write_outputs(plan: SearchPlan, out: Path) -> dict[str, Path]:
    """mission.json (TaskFile), paths.geojson (area + one LineString per drone), plan.png."""
    out.mkdir(parents=True, exist_ok=True)
    files = {"mission": out / "mission.json", "geojson": out / "paths.geojson", "png": out / "plan.png"}
    files["mission"].write_text(plan.taskfile.model_dump_json(indent=2, exclude_none=True))
    ring = [[lon, lat] for lat, lon in plan.frame.points_to_geodetic(plan.area_local)]
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"role": "area"},
            "geometry": {"type": "Polygon", "coordinates": [[*ring, ring[0]]]},
        }
    ]
    for drone, pts in zip(plan.drones, plan.paths_latlon, strict=True):
        if len(pts) < 2:
            continue
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "path", "drone": drone.name},
                "geometry": {"type": "LineString", "coordinates": [[lon, lat] for lat, lon in pts]},
            }
        )
    files["geojson"].write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    plot_plan(plan, files["png"])
    return files


def write_exports(
    plan: SearchPlan, out: Path, formats: list[str], speed: float, *, home_given: bool = False
) -> dict[str, Path]:
    """Each drone's mission as QGC ``.plan`` / Mission Planner ``.waypoints``, the plan as KML.

    Without ``home_given`` (``--home`` or a QGC survey's planned home) the homes are the area's
    first corner, a stand-in the files name as such; home altitudes are never known here.
    """
    homes_local = [d.home if d.home is not None else tuple(plan.home_local) for d in plan.drones]
    homes = {
        p.label: (float(lat), float(lon))
        for p, (lat, lon) in zip(plan.taskfile.plans, plan.frame.points_to_geodetic(homes_local), strict=True)
    }
    area = [(float(a), float(b)) for a, b in plan.frame.points_to_geodetic(plan.area_local)]
    texts = export_files(
        plan.taskfile,
        homes,
        formats,
        area=area,
        altitude_m=plan.spacing.altitude,
        cruise_speed=speed,
        assumed_homes=() if home_given else list(homes),
    )
    files: dict[str, Path] = {}
    for name, text in texts.items():
        files[name] = out / ("plan.kml" if name.endswith(".kml") else name)
        files[name].write_text(text)
    return files


def plot_plan(plan: SearchPlan, path: Path) -> None:
    """Area, per-drone paths in distinct colours, home, and coverage gaps (local metres)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8))
    a = plan.area_local
    ax.fill(a[:, 0], a[:, 1], color="0.92", edgecolor="0.4", label="area")
    cmap = plt.get_cmap("tab10")
    for i, (drone, pts) in enumerate(zip(plan.drones, plan.paths_local, strict=True)):
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], "-", color=cmap(i % 10), lw=1.2, label=drone.name)
            ax.plot(*pts[0], "o", color=cmap(i % 10), ms=4)
    for g in plan.coverage.gaps:
        x, y = g.exterior.xy
        ax.fill(x, y, color="red", alpha=0.5)
    ax.plot(*plan.home_local, "k^", ms=9, label="home")
    s = plan.summary
    ax.set_title(
        f"{s['pattern']} / {s['division']} - covered {s['coverage']['covered_pct']:.1f}% "
        f"- {s['total_length_m']:.0f} m"
    )
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)
