"""The simulator's shape: small units, and a PX4 personality whose hooks still exist on the engine.

A hook renamed in sitl/vehicle/ would leave Px4Vehicle's override silently unused; this catches it.
"""

from __future__ import annotations

import ast
from pathlib import Path

from sitl.px4 import Px4Vehicle
from sitl.vehicle import SimVehicle

SITL = Path(__file__).resolve().parents[2] / "sitl"
PX4_OWN = {"set_px4_mode"}  # public methods only the personality has


def test_no_class_over_500_and_no_function_over_120_lines() -> None:
    too_long = []
    for path in sorted(SITL.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                limit = 500 if isinstance(node, ast.ClassDef) else 120
                size = (node.end_lineno or node.lineno) - node.lineno + 1
                if size > limit:
                    too_long.append(f"{path.relative_to(SITL.parent)}:{node.lineno} {node.name} {size} lines")
    assert not too_long


def test_every_public_px4_override_is_an_engine_hook() -> None:
    own = {name for name in vars(Px4Vehicle) if not name.startswith("_") and callable(vars(Px4Vehicle)[name])}
    orphans = sorted(own - PX4_OWN - set(dir(SimVehicle)))
    assert not orphans, f"Px4Vehicle overrides methods SimVehicle no longer has: {orphans}"
