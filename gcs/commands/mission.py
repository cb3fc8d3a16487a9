"""`gcs mission list | pause | resume | abort | retask | report [ID]`: mission control from the shell.

Without ID the command acts on the one running mission (and says so when there are several).
``retask [ID] [accept|reject]`` lists the re-task proposals of a survey whose drone left, or
answers the newest pending one (``--proposal rN`` another); ``report ID`` prints the coverage
report (``--json`` the API's document).
"""

from __future__ import annotations

import argparse
import json
from typing import Any, Literal

from gcs.commands._api import CommandError, api_arguments, call
from gcs.commands.run import render_progress
from gcs.http.client import FleetClient
from gcs.missions.model import MissionProgress


async def _running(client: FleetClient) -> list[str]:
    return [m.id for m in await client.missions(state="running")]


def pick_mission(args: argparse.Namespace) -> str:
    if args.mission_id:
        return str(args.mission_id)
    running = call(args, _running, token=False)
    if not running:
        raise CommandError("no mission is running", 1)
    if len(running) > 1:
        raise CommandError(f"{len(running)} missions are running; give one of: {', '.join(running)}")
    return running[0]


def _retask(args: argparse.Namespace, mission_id: str) -> int:
    answer = args.answer
    if answer is None:
        proposals = call(args, lambda client: client.retask_proposals(mission_id), token=False)
        if not proposals:
            print(f"mission {mission_id}: no re-task proposal")
        for p in proposals:
            print(_proposal_line(p))
        return 0

    async def decide(client: FleetClient) -> dict[str, Any]:
        return await client.retask(mission_id, answer, args.proposal)

    print(_proposal_line(call(args, decide)))
    return 0


def _proposal_line(p: dict[str, Any]) -> str:
    legs = "; ".join(
        f"{g['ident']} {g['survey_m']:.0f} m, {g['time_s']:.0f} s, "
        f"{g['energy_wh']:.1f} of {g['margin_wh']:.1f} Wh"
        for g in p["legs"]
    )
    return f"{p['id']} {p['state']:8} {p['dropped']}: {p['reason']}" + (f"\n    {legs}" if legs else "")


def _report(args: argparse.Namespace, mission_id: str) -> int:
    from gcs.missions.report import render_report

    report = call(args, lambda client: client.report(mission_id), token=False)
    if args.json:
        print(json.dumps(report.model_dump(mode="json"), indent=1))
    else:
        print("\n".join(render_report(report)))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.mission_command == "retask" and args.mission_id in ("accept", "reject") and args.answer is None:
        args.mission_id, args.answer = None, args.mission_id  # gcs mission retask accept
    if args.mission_command in ("retask", "report"):
        mission_id = pick_mission(args)
        return _retask(args, mission_id) if args.mission_command == "retask" else _report(args, mission_id)
    if args.mission_command == "list":
        missions = call(args, lambda client: client.missions(), token=False)
        for m in missions:
            print(f"{m.id:24} {m.state:9} {m.name}  {m.result or ''}")
        return 0
    mission_id = pick_mission(args)
    then: Literal["rtl", "hold"] = args.then

    async def command(client: FleetClient) -> MissionProgress:
        if args.mission_command == "pause":
            return await client.pause(mission_id)
        if args.mission_command == "resume":
            return await client.resume(mission_id)
        return await client.abort(mission_id, then)

    progress = call(args, command)
    print(f"mission {mission_id}: {render_progress(progress.model_dump(mode='json'))}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "mission",
        help="list missions; pause | resume | abort one; its re-task proposals; its coverage report",
    )
    parser.add_argument(
        "mission_command",
        choices=("list", "pause", "resume", "abort", "retask", "report"),
        help="what to do with the mission",
    )
    parser.add_argument("mission_id", nargs="?", metavar="ID", help="default: the one running mission")
    parser.add_argument(
        "answer", nargs="?", choices=("accept", "reject"), help="retask: answer the pending proposal"
    )
    parser.add_argument(
        "--proposal", default="latest", help="retask: which proposal (rN; default the newest)"
    )
    parser.add_argument("--json", action="store_true", help="report: the API's JSON document")
    parser.add_argument(
        "--then", choices=("rtl", "hold"), default="rtl", help="abort: fly home (default) or hold"
    )
    api_arguments(parser)
    parser.set_defaults(run=run)
