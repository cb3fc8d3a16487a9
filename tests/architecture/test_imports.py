"""Which package may import which (docs/architecture.md, "Packages and their rules"), checked two ways.

* **In isolation:** every ``gcs`` module is imported first thing in a fresh interpreter, so a
  module-level import circle (which only bites when a module other than the usual entry is
  imported first) fails here by name.
* **By the table:** the ``import`` statements of ``protocol``, ``agent``, ``sitl`` and ``gcs`` are
  read with ``ast`` (``TYPE_CHECKING`` imports included: a contract is a dependency too) and
  checked against :data:`MAY_IMPORT` and the rules below it.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.paths import ROOT

OURS = ("protocol", "agent", "sitl", "gcs")
IMPORT_TIMEOUT_S = 30

MAY_IMPORT: dict[str, tuple[str, ...]] = {
    "protocol": ("protocol",),  # pure: nothing of ours
    "agent": ("agent", "protocol"),  # never gcs
    "sitl": ("sitl", "protocol"),  # runs from the agent install: never gcs or agent
    "gcs.planning": ("gcs.planning", "protocol"),  # pure algorithms
    "gcs": ("gcs", "protocol"),  # never agent, never sitl
}
"""Package (longest prefix wins) -> the packages of ours its modules may import."""

ENTRY_POINTS = ("gcs.__main__", "gcs.cli", "gcs.commands", "gcs.commands.demo_mission")
"""The only modules that may import the composition root, ``gcs.core.daemon``."""

MANAGER_USERS = ("gcs.core.daemon", "gcs.core.context")
"""The only modules that may name ``AgentManager`` (its send side goes to the command port only)."""

CLUSTER_USERS = ("gcs.core.daemon", "gcs.http.app", "gcs.core.context", "gcs.commands.cluster")
"""Outside ``gcs.cluster``: who may import it (lazily, cluster mode only; the context for types)."""

SENDERS = (
    "gcs.link.agents",
    "gcs.link.sender",
    "gcs.link.session",
    "gcs.link.outbox",
    "gcs.control.command_port",
    "gcs.control.authority",
    "gcs.cluster.node",
)
"""The only ``gcs`` modules that call ``post``/``burst``/``write_now`` on an agent link (the
cluster node's remote session forwards its own)."""

NOT_LINKS = ("router", "app", "api", "client", "self._client", "http")
"""Receivers of a ``.post(...)`` that are HTTP routers or clients, not agent links."""


def _modules(package: str) -> Iterator[tuple[str, Path]]:
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _imports(path: Path) -> Iterator[tuple[int, str, list[str]]]:
    """(line, imported module, names) for every absolute import of ours in ``path``."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if node.module.split(".")[0] in OURS:
                yield node.lineno, node.module, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in OURS:
                    yield node.lineno, alias.name, []


def _rule(module: str) -> tuple[str, tuple[str, ...]]:
    package = max((p for p in MAY_IMPORT if _within(module, (p,))), key=len)
    return package, MAY_IMPORT[package]


ALL = [(m, p) for package in OURS for m, p in _modules(package)]
GCS = [m for m, _ in _modules("gcs") if m != "gcs.__main__"]  # __main__ runs the CLI


ISOLATE = """
import contextlib, importlib, json, os, signal, sys
for name in sys.argv[2].split(","):  # third-party dependencies only: none of ours is loaded here
    with contextlib.suppress(Exception):
        importlib.import_module(name)
failed = {}
for module in sys.argv[1].split(","):
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child imports one module of ours first thing, then exits
        os.close(read)
        signal.alarm(int(sys.argv[3]))
        try:
            importlib.import_module(module)
            os._exit(0)
        except BaseException as exc:
            os.write(write, f"{type(exc).__name__}: {exc}"[:500].encode())
            os._exit(1)
    os.close(write)
    with os.fdopen(read) as pipe:
        why = pipe.read()
    _, code = os.waitpid(pid, 0)
    if code:
        failed[module] = why or f"exit status {code} (killed after {sys.argv[3]} s?)"
print(json.dumps(failed))
"""


def _third_party() -> list[str]:
    """The top-level packages ``gcs`` imports that are not ours and not the standard library."""
    names = set()
    for _, path in _modules("gcs"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
            elif isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
    return sorted(n for n in names if n not in OURS and n not in sys.stdlib_module_names)


@pytest.mark.timeout(600)  # ~30 s of CPU; on a loaded machine its wall time is many times that
def test_every_gcs_module_imports_in_isolation() -> None:
    """Each ``gcs`` module imported first, in its own forked process: a module-level circle fails
    here by name. The parent preloads only third-party packages (numpy, FastAPI... are not under
    test and cost seconds per interpreter); each child is bounded by an alarm, the whole by a timeout.
    """
    done = subprocess.run(
        [sys.executable, "-c", ISOLATE, ",".join(GCS), ",".join(_third_party()), str(IMPORT_TIMEOUT_S)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=540,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    failed = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(GCS) > 50
    assert not failed, failed


def test_the_allowed_imports_table_holds() -> None:
    broken = []
    for module, path in ALL:
        package, allowed = _rule(module)
        for line, target, _ in _imports(path):
            if not _within(target, allowed):
                broken.append(f"{path.relative_to(ROOT)}:{line} {package} imports {target}")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize(
    ("target", "users", "why"),
    [
        (
            "gcs.core.daemon",
            (*ENTRY_POINTS, "gcs.core.daemon"),
            "only entry points import the composition root",
        ),
        ("gcs.cluster", CLUSTER_USERS, "cluster mode is plugged in by the composition root"),
    ],
)
def test_who_may_import_a_package(target: str, users: tuple[str, ...], why: str) -> None:
    broken = [
        f"{path.relative_to(ROOT)}:{line} imports {imported}"
        for module, path in ALL
        if not _within(module, users) and not _within(module, (target,))
        for line, imported, _ in _imports(path)
        if _within(imported, (target,))
    ]
    assert not broken, f"{why}:\n" + "\n".join(broken)


def test_only_the_composition_root_names_the_agent_manager() -> None:
    broken = [
        f"{path.relative_to(ROOT)}:{line}"
        for module, path in ALL
        if not _within(module, (*MANAGER_USERS, "gcs.link.agents"))
        for line, imported, names in _imports(path)
        if imported == "gcs.link.agents" and "AgentManager" in names
    ]
    # The manager's send side is a part of its own (gcs/link/sender.py): only the manager holds it.
    broken += [
        f"{path.relative_to(ROOT)}:{line}"
        for module, path in ALL
        if not _within(module, ("gcs.link.agents", "gcs.link.sender"))
        for line, imported, _ in _imports(path)
        if imported == "gcs.link.sender"
    ]
    assert not broken, "services, missions and the cluster get a view, not the manager:\n" + "\n".join(broken)


def test_only_the_command_port_puts_frames_on_an_agent_link() -> None:
    """No ``x.post(...)`` / ``x.burst(...)`` / ``x.write_now(...)`` outside :data:`SENDERS`."""
    broken = []
    for module, path in _modules("gcs"):
        if _within(module, SENDERS):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            if node.func.attr in ("post", "burst", "write_now"):
                receiver = ast.unparse(node.func.value)
                if receiver.split(".")[-1] not in NOT_LINKS and receiver not in NOT_LINKS:
                    broken.append(f"{path.relative_to(ROOT)}:{node.lineno} {receiver}.{node.func.attr}(...)")
    assert not broken, "\n".join(broken)


def test_gcs_has_no_top_level_module_besides_its_entry_points() -> None:
    """The tree shows the architecture: every job is a subpackage (docs/architecture.md)."""
    top = sorted(p.stem for p in (ROOT / "gcs").glob("*.py"))
    assert top == ["__init__", "__main__", "cli"], top
