"""Where the real ArduCopter SITL binary is: $ARDUPILOT_SITL, else ../shared/ardupilot/arducopter
beside the repository (how CI lays it out). Tests that need it skip with this module's reason."""

from __future__ import annotations

import os
from pathlib import Path

from tests.support.paths import ROOT

DEFAULT = ROOT.parent / "shared" / "ardupilot" / "arducopter"


def ardupilot_binary() -> str | None:
    """The binary to run, or None when neither ARDUPILOT_SITL nor the default path is executable."""
    env = os.environ.get("ARDUPILOT_SITL")
    for cand in (Path(env).expanduser() if env else None, DEFAULT):
        if cand is not None and cand.is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


SKIP_REASON = (
    f"real ArduCopter SITL not available: set ARDUPILOT_SITL to an arducopter binary or put one at {DEFAULT}"
)
