"""`gcs energy train|predict`: the two-step energy model (seed 004 2.2.6) from recorded flight logs."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import (
    EnergyModel,
    accuracy,
    fit_energy_model,
    load_training_set,
    predict_plan_energy,
)
from gcs.cooperation.flightlog import FlightLogError
from protocol.actions import Action, Goto, Land, Waypoints
from protocol.taskfile import TaskFileError, load_task_text


def train(args: argparse.Namespace) -> int:
    logs = [Path(p) for p in args.logs]
    try:
        flights, pairs = load_training_set(logs, EnergyConfig())
    except (FlightLogError, OSError, ValueError) as exc:
        print(f"gcs energy train: {exc}", file=sys.stderr)
        return 2
    model = fit_energy_model(flights, pairs, pure_krr=args.pure_krr, select=True, folds=args.folds)
    measured = np.array([f.energy_wh for f in flights])
    Path(args.out).write_text(model.to_json() + "\n")
    print(f"trained on {len(flights)} flights ({len(pairs)} with plans for the sim->real step)")
    if model.selection:
        print(
            f"{args.folds}-fold accuracy from the plan: two-step {100 * model.selection['two_step']:.2f}%, "
            f"baseline (least squares on planned time) {100 * model.selection['baseline']:.2f}%; "
            f"kept the {model.kind} model"
        )
    else:
        fitted = model.energy_from_real(
            np.array([f.time_s for f in flights]), np.array([f.distance_m for f in flights])
        )
        print(
            f"training accuracy {100 * accuracy(fitted, measured):.2f}% (in-sample: give every log its "
            "plan sidecar, and at least 4 flights, for the k-fold comparison with the baseline)"
        )
    print(f"model written to {args.out}")
    return 0


def first_place(actions: list[Action]) -> tuple[float, float]:
    """The first lat/lon a plan flies to (a goto, a waypoint or a landing point)."""
    for action in actions:
        if isinstance(action, Waypoints):
            return action.points[0].lat, action.points[0].lon
        if isinstance(action, (Goto, Land)) and action.lat is not None and action.lon is not None:
            return action.lat, action.lon
    raise ValueError("the plan flies to no absolute position; give --home LAT,LON")


def predict(args: argparse.Namespace) -> int:
    try:
        task = load_task_text(Path(args.mission).read_text())
        model = EnergyModel.load(Path(args.model))
        plans = {plan.label: list(plan.actions) for plan in task.plans}
        homes = {}
        for label, actions in plans.items():
            if args.home:
                lat, lon = (float(v) for v in args.home.split(","))
            else:  # without a home: take off under the first place the plan flies to
                lat, lon = first_place(actions)
            homes[label] = (lat, lon, 0.0)
    except (OSError, TaskFileError, ValueError) as exc:
        print(f"gcs energy predict: {exc}", file=sys.stderr)
        return 2
    estimates = predict_plan_energy(plans, homes, EnergyConfig(speed_mps=args.speed), model)
    rows = {
        label: {
            "plan_time_s": round(e.time_s, 1),
            "plan_distance_m": round(e.distance_m, 1),
            "energy_wh": round(e.energy_wh, 2),
        }
        for label, e in estimates.items()
    }
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'agent':16} {'time s':>8} {'dist m':>9} {'energy Wh':>10}")
    for label, row in rows.items():
        print(f"{label:16} {row['plan_time_s']:8.0f} {row['plan_distance_m']:9.0f} {row['energy_wh']:10.2f}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("energy", help="train or apply the energy prediction model")
    sub = parser.add_subparsers(dest="energy_command", required=True)
    p = sub.add_parser("train", help="fit the two-step model on flight-log CSVs (plan sidecars optional)")
    p.add_argument("logs", nargs="+", help="flight logs (one CSV per drone-flight)")
    p.add_argument("--out", required=True, help="model JSON to write")
    p.add_argument("--pure-krr", action="store_true", help="the paper's KRR alone, without the linear trend")
    p.add_argument("--folds", type=int, default=5, help="k of the k-fold comparison with the baseline")
    p.set_defaults(run=train)
    q = sub.add_parser("predict", help="predict each drone's energy for a task file")
    q.add_argument("mission", help="task file (fleetgcs JSON or CoUAS)")
    q.add_argument("--model", required=True, help="model JSON from `gcs energy train`")
    q.add_argument("--home", help="LAT,LON take-off point for every plan (default: under its first target)")
    q.add_argument("--speed", type=float, default=5.0, help="cruise speed of legs that set none (m/s)")
    q.add_argument("--json", action="store_true", help="print JSON")
    q.set_defaults(run=predict)
