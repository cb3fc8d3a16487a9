"""The tests mirror the tree (issue 24): shared support lives in support modules, never in a test module,
and a test's folder tells its layer (unit, integration, end-to-end) by the map in docs/testing.md.

Read with ``ast``, nothing imported: a test module imported as a library runs its fixtures and
collection side effects twice and ties two tests' fates together, so it fails here by name.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

from tests.support.paths import ROOT

TESTS = ROOT / "tests"
LAYERS = ("unit", "integration", "end-to-end")
MAP_HEADING = "## Layers"
MAP_ROW = re.compile(r"^\| `(tests(?:/[a-z_0-9]+)+)` \| (unit|integration|end-to-end) \|")

UNIT_MAY_NOT_IMPORT = (
    "gcs.core.daemon",
    "agent.runtime",
    "sitl.fleet",
    "tests.backbone.helpers",
    "tests.cooperation.rig",
    "tests.support.rig",
    "tests.support.processes",
    "tests.api.fleet",
    "tests.faults",
    "tests.cluster",
    "playwright",
    "nats",
)
"""A unit test runs one module or algorithm in the test process: no daemon, agent runtime, simulator
fleet, rig, console-script process, browser or NATS (each of those makes it an integration test)."""

UNIT_MAY_NOT_CALL = ("open_connection", "start_server", "create_subprocess_exec", "open_client", "Popen")
"""Calls that open a socket or start a process: not in a unit test either."""


def _python_files() -> Iterator[Path]:
    yield from sorted(p for p in TESTS.rglob("*.py") if "__pycache__" not in p.parts)


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def _imports(path: Path) -> Iterator[tuple[int, str]]:
    """(line, dotted module) for every import in ``path`` (see :func:`_imports_in`)."""
    yield from _imports_in(path.read_text(), _module_name(path).rsplit(".", 1)[0])


def _imports_in(source: str, package: str) -> Iterator[tuple[int, str]]:
    """(line, dotted module) for every import in ``source`` of ``package``, relative ones resolved,
    ``from X import Y`` also giving ``X.Y`` (``Y`` may be a module)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")
                parent = parent[: len(parent) - (node.level - 1)]
                base = ".".join([*parent, base] if base else parent)
            yield node.lineno, base
            for alias in node.names:
                yield node.lineno, f"{base}.{alias.name}"


def _is_test_module(module: str) -> bool:
    parts = module.split(".")
    if parts[0] != "tests" or not parts[-1].startswith("test_"):
        return False
    return (ROOT.joinpath(*parts).with_suffix(".py")).is_file()


def layer_map() -> dict[str, str]:
    """Folder (``tests/...``) -> layer, from the table under ``## Layers`` in docs/testing.md."""
    text = (ROOT / "docs" / "testing.md").read_text()
    assert MAP_HEADING in text, f"docs/testing.md has no '{MAP_HEADING}' section: the layer map lives there"
    section = text.split(MAP_HEADING, 1)[1].split("\n## ", 1)[0]
    rows = [MAP_ROW.match(line) for line in section.splitlines()]
    mapping: dict[str, str] = {}
    for row in rows:
        if row is not None:
            assert row[1] not in mapping, f"{row[1]} is mapped twice in docs/testing.md"
            mapping[row[1]] = row[2]
    assert mapping, "the layer map in docs/testing.md has no rows"
    return mapping


def layer_of(path: Path, mapping: dict[str, str]) -> tuple[str, str] | None:
    """(folder, layer) of the deepest mapped folder holding ``path``, or None."""
    folder = path.relative_to(ROOT).parent
    for candidate in (folder, *folder.parents):
        key = candidate.as_posix()
        if key in mapping:
            return key, mapping[key]
    return None


def test_no_test_module_imports_another() -> None:
    offences = [
        f"{path.relative_to(ROOT)}:{line} imports {module}"
        for path in _python_files()
        for line, module in _imports(path)
        if _is_test_module(module) and module != _module_name(path)
    ]
    assert not offences, (
        "a test module is imported as a library; move what it shares to tests/support/<topic>.py or the "
        "package's rig/helper module:\n" + "\n".join(offences)
    )


def test_every_test_file_lives_in_a_folder_of_one_layer() -> None:
    mapping = layer_map()
    tests = [p for p in _python_files() if p.name.startswith("test_")]
    unmapped = [str(p.relative_to(ROOT)) for p in tests if layer_of(p, mapping) is None]
    assert not unmapped, (
        "test files in a folder the layer map of docs/testing.md does not name:\n" + "\n".join(unmapped)
    )
    used = {layer_of(p, mapping) for p in tests}
    stale = [folder for folder, layer in mapping.items() if (folder, layer) not in used]
    assert not stale, f"docs/testing.md maps folders that hold no test file of their own: {stale}"
    support = list((TESTS / "support").rglob("test_*.py"))
    assert not support, f"tests/support holds shared code, not tests: {support}"


def test_unit_folders_start_nothing() -> None:
    mapping = layer_map()
    offences: list[str] = []
    for path in _python_files():
        if not (path.name.startswith("test_") or path.name == "conftest.py"):
            continue
        found = layer_of(path, mapping)
        if found is None or found[1] != "unit":
            continue
        where = path.relative_to(ROOT)
        for line, module in _imports(path):
            if any(module == m or module.startswith(m + ".") for m in UNIT_MAY_NOT_IMPORT):
                offences.append(f"{where}:{line} imports {module}")
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call):
                name = (
                    node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
                )
                if name in UNIT_MAY_NOT_CALL:
                    offences.append(f"{where}:{node.lineno} calls {name}")
    assert not offences, (
        "a test in a unit folder starts a daemon, an agent, a simulator, a socket or a process; it "
        "belongs in an integration or end-to-end folder (docs/testing.md, Layers):\n" + "\n".join(offences)
    )


def test_the_checks_see_what_they_must_refuse() -> None:
    """The checks can fail: each way of importing a test module is found, and an unmapped folder."""
    sources = [
        "from tests.backbone.test_cli import main",
        "import tests.backbone.test_cli",
        "from tests.backbone import test_cli",
        "from .test_cli import main",
        "def f():\n    from ..backbone.test_cli import main",
    ]
    for source in sources:
        found = [m for _, m in _imports_in(source, "tests.backbone") if _is_test_module(m)]
        assert found, source
    assert not [
        m for _, m in _imports_in("from tests.backbone.helpers import wait", "tests.x") if _is_test_module(m)
    ]
    mapping = layer_map()
    assert layer_of(TESTS / "backbone" / "test_cli.py", mapping) == ("tests/backbone", "integration")
    assert layer_of(TESTS / "cooperation" / "units" / "test_authority.py", mapping) == (
        "tests/cooperation/units",
        "unit",
    )
    assert layer_of(ROOT / "elsewhere" / "test_x.py", mapping) is None
