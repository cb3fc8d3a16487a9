"""The daemon's TOML configuration file (``gcs serve --config gcs.toml``), see docs/configuration.md.

    [daemon]                      # any DaemonConfig field (gcs/core/config.py)
    listen_host = "0.0.0.0"
    http_port = 8080
    extensions = ["gcs.extensions.builtin.geofence_alarm"]
    [daemon.agent_parameters]     # nested models are tables
    battery_low_pct = 30
    [log]                         # protocol.settings_file.LoggingConfig
    json_format = true

Precedence, lowest first: built-in defaults < the file < environment (``FLEETGCS_<FIELD>``,
nested ``FLEETGCS_<TABLE>__<FIELD>``, logging ``FLEETGCS_LOG_<FIELD>``) < command-line flags
given explicitly. Everything is validated by the same pydantic models the code uses.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gcs.core.config import DaemonConfig
from protocol.settings_file import ConfigFileError, LoggingConfig, load_section, read_toml

DAEMON_PREFIX = "FLEETGCS_"
LOG_PREFIX = "FLEETGCS_LOG_"
SECTIONS = ("daemon", "log")

__all__ = ["ConfigFileError", "load_daemon_config"]


def load_daemon_config(
    path: Path | None,
    overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> tuple[DaemonConfig, LoggingConfig]:
    """Read ``path`` (optional), apply the environment, then ``overrides`` (explicit CLI flags)."""
    env = os.environ if environ is None else environ
    document = read_toml(path) if path is not None else {}
    unknown = sorted(set(document) - set(SECTIONS))
    if unknown:
        raise ConfigFileError(f"{path}: unknown table(s) {unknown}; expected {list(SECTIONS)}")
    daemon_env = {k: v for k, v in env.items() if not k.startswith(LOG_PREFIX)}
    daemon = load_section(
        DaemonConfig, document.get("daemon"), DAEMON_PREFIX, "daemon", daemon_env, overrides
    )
    log = load_section(LoggingConfig, document.get("log"), LOG_PREFIX, "log", env)
    return daemon, log
