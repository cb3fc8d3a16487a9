"""`gcs mission list | pause | resume | abort [ID]`: mission control from the shell.

Without ID the command acts on the one running mission (and says so when there are several).
"""

from __future__ import annotations

import argparse
from typing import Literal

from gcs.client import FleetClient
from gcs.commands._api import CommandError, api_arguments, call
from gcs.commands.run import render_progress
from gcs.missions import MissionProgress


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


def run(args: argparse.Namespace) -> int:
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
    parser = subparsers.add_parser("mission", help="list missions; pause | resume | abort one")
    parser.add_argument("mission_command", choices=("list", "pause", "resume", "abort"))
    parser.add_argument("mission_id", nargs="?", metavar="ID", help="default: the one running mission")
    parser.add_argument(
        "--then", choices=("rtl", "hold"), default="rtl", help="abort: fly home (default) or hold"
    )
    api_arguments(parser)
    parser.set_defaults(run=run)
