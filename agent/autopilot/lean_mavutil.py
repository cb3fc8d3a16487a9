"""pymavlink's ``mavutil`` without the imports a link never uses (issue 29: the agent's memory).

``mavutil`` imports at module level the v1 ``all`` dialect (only so that pyinstaller bundles it;
the agent speaks MAVLink 2 with ``ardupilotmega``) and ``mavexpression``, the log-expression
evaluator, which loads NumPy through ``mavextra``. On a companion computer that was ~9 MiB of
the agent's RSS (61 -> 45 MiB measured at import). :func:`kept_out` keeps both out while
``mavutil`` loads: the dialect import fails as ``mavutil`` allows it to, and ``mavexpression``
is a placeholder that imports the real module the first time anything uses it (only log
filtering does), so nothing of pymavlink stops working.

Two more, ~1.2 MiB together: ``curses`` (``mavutil`` takes ``curses.ascii.isprint`` for
``is_printable`` if it can, which loads ncurses; without it, its own fallback answers the
same for ASCII) and the XML parser ``generator.mavparse`` with expat, which ``set_dialect``
imports only for two protocol-name constants (the generator is needed only when a dialect
module is missing). While ``mavutil`` loads, ``curses`` is "not importable" and ``mavparse``
a placeholder holding those two constants; afterwards both import as usual.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import types
from collections.abc import Iterator

SKIPPED = ("pymavlink.dialects.v10.all", "curses")
ON_FIRST_USE = "pymavlink.mavexpression"
PARSER = "pymavlink.generator.mavparse"
PARSER_CONSTANTS = {"PROTOCOL_1_0": "1.0", "PROTOCOL_2_0": "2.0"}  # as pymavlink's mavparse has them


class _OnFirstUse(types.ModuleType):
    """Stands for a module until an attribute of it is read: then the real one is imported."""

    def __getattr__(self, name: str) -> object:
        if sys.modules.get(self.__name__) is self:  # still loading mavutil: nothing may use it yet
            raise AttributeError(name)
        return getattr(importlib.import_module(self.__name__), name)


@contextlib.contextmanager
def kept_out() -> Iterator[None]:
    """Import ``pymavlink.mavutil`` in this block: without the v1 ``all`` dialect, NumPy, curses, expat."""
    placed: dict[str, types.ModuleType | None] = {}
    parser = _OnFirstUse(PARSER)
    parser.__dict__.update(PARSER_CONSTANTS)
    stand_ins: list[tuple[str, types.ModuleType | None]] = [
        *((name, None) for name in SKIPPED),
        (ON_FIRST_USE, _OnFirstUse(ON_FIRST_USE)),
        (PARSER, parser),
    ]
    for name, stand_in in stand_ins:
        if name not in sys.modules:
            sys.modules[name] = stand_in  # type: ignore[assignment]  # None: "not importable"
            placed[name] = stand_in
    try:
        yield
    finally:
        for name, stand_in in placed.items():
            if name in sys.modules and sys.modules[name] is stand_in:
                del sys.modules[name]  # a later import gets the real module


__all__ = ["kept_out"]
