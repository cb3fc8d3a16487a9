"""Missions from the tools operators already use: a QGroundControl ``.plan`` or Mission Planner
``.waypoints`` (``QGC WPL 110``) file is one drone's mission; a set of them (one file per drone,
or a folder of them) is a fleetgcs task. The drone is named by the file name (``drone-1.plan``
flies on ``drone-1``), as ``gcs plan --export`` names its files, so an export re-imports as is.

Used by ``gcs run``, ``POST /api/v1/missions/import`` and the dashboard's mission upload.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path, PurePath
from typing import Literal

from pydantic import ValidationError

from gcs.planning.interchange import (
    MAX_TEXT_CHARS,
    InterchangeError,
    items_to_actions,
    read_qgc_mission,
    read_waypoints,
)
from protocol.taskfile import AgentPlan, TaskFile, TaskFileError, first_error, require_landing

MISSION_SUFFIXES = (".plan", ".waypoints")
MAX_FILES = 1000

MissionFormat = Literal["qgc-plan", "waypoints"]


def mission_format(text: str) -> MissionFormat | None:
    """Which one-drone mission format ``text`` is in, or None for any other document."""
    body = text.lstrip("\ufeff").lstrip()
    if body.startswith("QGC WPL"):
        return "waypoints"
    if body.startswith("{"):
        try:
            obj = json.loads(body)
        except json.JSONDecodeError:
            return None
        if isinstance(obj, dict) and obj.get("fileType") == "Plan":
            return "qgc-plan"
    return None


def agent_plan_from_text(text: str, agent: str) -> AgentPlan:
    """One drone's mission from the text of a ``.plan`` or ``.waypoints`` file."""
    if len(text) > MAX_TEXT_CHARS:
        raise InterchangeError(f"larger than {MAX_TEXT_CHARS} characters")
    kind = mission_format(text)
    if kind is None:
        raise InterchangeError(
            'not a QGroundControl .plan (JSON with "fileType": "Plan") nor a Mission Planner '
            ".waypoints file (first line 'QGC WPL 110')"
        )
    body = text.lstrip("\ufeff")
    if kind == "waypoints":
        _, items = read_waypoints(body)
    else:
        _, items = read_qgc_mission(json.loads(body))
    if not items:
        raise InterchangeError("the mission has no items")
    actions = items_to_actions(items)
    try:
        return AgentPlan(agent=agent, actions=actions)
    except ValidationError as exc:
        raise InterchangeError(first_error(exc)) from None


def agent_name(filename: str) -> str:
    """The drone a mission file is for: its name without the suffix (``drone-1.plan``)."""
    return PurePath(filename).stem


def task_from_mission_files(
    files: Mapping[str, str],
    name: str = "imported-mission",
    *,
    allow_airborne_end: bool = False,
    agent: str | None = None,
) -> TaskFile:
    """A task from one mission file per drone (file name -> text); errors name the file and item.

    ``agent`` names the drone of a single file instead of its file name.

    Raises :class:`TaskFileError`: a format that is not a mission, an item without a fleetgcs
    action, two files for one drone, or a drone that would not land (unless allowed).
    """
    if not files:
        raise TaskFileError("no mission files (.plan or .waypoints)")
    if len(files) > MAX_FILES:
        raise TaskFileError(f"{len(files)} mission files; at most {MAX_FILES}")
    if agent is not None and len(files) != 1:
        raise TaskFileError(f"an agent name is for one mission file, not {len(files)}")
    plans: list[AgentPlan] = []
    drones: dict[str, str] = {}
    for filename, text in sorted(files.items()):
        drone = agent or agent_name(filename)
        if drone in drones:
            raise TaskFileError(f"{drones[drone]} and {filename} are both missions for {drone}")
        drones[drone] = filename
        try:
            plans.append(agent_plan_from_text(text, drone))
        except InterchangeError as exc:
            raise TaskFileError(f"{filename}: {exc}") from None
    try:
        task = TaskFile(
            name=name[:128] or "imported-mission", allow_airborne_end=allow_airborne_end, plans=plans
        )
    except ValidationError as exc:
        raise TaskFileError(f"invalid mission: {first_error(exc)}") from None
    require_landing(task)
    return task


def mission_paths(path: Path) -> list[Path]:
    """The mission files of ``path``: the file itself, or the .plan/.waypoints files of a folder."""
    if not path.is_dir():
        return [path]
    found = sorted(p for p in path.iterdir() if p.suffix.lower() in MISSION_SUFFIXES and p.is_file())
    if not found:
        raise TaskFileError(f"{path} holds no mission files (.plan or .waypoints)")
    return found


def is_mission_path(path: Path) -> bool:
    """Whether ``gcs run`` should read ``path`` as mission files rather than a task file."""
    if path.is_dir() or path.suffix.lower() in MISSION_SUFFIXES:
        return True
    try:
        with path.open(encoding="utf-8", errors="replace") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.lstrip("\ufeff").lstrip().startswith("QGC WPL") or '"fileType": "Plan"' in head


def load_mission_files(path: Path, *, agent: str | None = None, allow_airborne_end: bool = False) -> TaskFile:
    """A task from a mission file or a folder of them; ``agent`` renames a single file's drone."""
    paths = mission_paths(path)
    if agent is not None and len(paths) != 1:
        raise TaskFileError(f"--agent names the drone of one mission file; {path} holds {len(paths)}")
    files: dict[str, str] = {}
    for p in paths:
        try:
            text = p.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise TaskFileError(f"cannot read {p}: {exc}") from None
        files[p.name] = text
    name = path.stem if path.is_file() else path.resolve().name
    return task_from_mission_files(files, name, allow_airborne_end=allow_airborne_end, agent=agent)
