"""pymavlink's ``mavutil`` without two imports a link never uses (issue 29: the agent's memory).

``mavutil`` imports at module level the v1 ``all`` dialect (only so that pyinstaller bundles it;
the agent speaks MAVLink 2 with ``ardupilotmega``) and ``mavexpression``, the log-expression
evaluator, which loads NumPy through ``mavextra``. On a companion computer that was ~9 MiB of
the agent's RSS (61 -> 45 MiB measured at import). :func:`kept_out` keeps both out while
``mavutil`` loads: the dialect import fails as ``mavutil`` allows it to, and ``mavexpression``
is a placeholder that imports the real module the first time anything uses it (only log
filtering does), so nothing of pymavlink stops working.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import types
from collections.abc import Iterator

SKIPPED = "pymavlink.dialects.v10.all"
ON_FIRST_USE = "pymavlink.mavexpression"


class _OnFirstUse(types.ModuleType):
    """Stands for a module until an attribute of it is read: then the real one is imported."""

    def __getattr__(self, name: str) -> object:
        if sys.modules.get(self.__name__) is self:  # still loading mavutil: nothing may use it yet
            raise AttributeError(name)
        return getattr(importlib.import_module(self.__name__), name)


@contextlib.contextmanager
def kept_out() -> Iterator[None]:
    """Import ``pymavlink.mavutil`` inside this block: without the v1 ``all`` dialect and NumPy."""
    placed: dict[str, types.ModuleType | None] = {}
    stand_ins: list[tuple[str, types.ModuleType | None]] = [
        (SKIPPED, None),
        (ON_FIRST_USE, _OnFirstUse(ON_FIRST_USE)),
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
