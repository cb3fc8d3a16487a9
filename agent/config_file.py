"""The agent's TOML configuration file (``agent run --config agent.toml``), see docs/configuration.md.

    [agent]                      # any AgentConfig field (agent/config.py), plus key_file
    identity = "drone-1"
    gcs_host = "192.168.10.1"
    key_file = "/etc/fleetgcs/fleet.key"
    [agent.capabilities]
    max_speed_mps = 12
    [autopilot]
    backend = "mavlink"
    connection = "/dev/serial0:921600"
    mavlink_out = ["udp:192.168.1.20:14550"]   # the pilot's QGroundControl (MAVLink router)
    [log]
    json_format = true

Environment overrides: ``FLEETGCS_AGENT_<FIELD>`` for [agent] (nested ``__``),
``FLEETGCS_AUTOPILOT_<FIELD>``, ``FLEETGCS_AGENT_LOG_<FIELD>``; ``FLEETGCS_KEY`` gives the key.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from agent.autopilot.mavlink_router import parse_endpoint
from agent.config import AgentConfig
from protocol.settings_file import (
    ConfigFileError,
    LoggingConfig,
    env_overrides,
    load_section,
    merge,
    read_toml,
)

AGENT_PREFIX = "FLEETGCS_AGENT_"
AUTOPILOT_PREFIX = "FLEETGCS_AUTOPILOT_"
LOG_PREFIX = "FLEETGCS_AGENT_LOG_"
SECTIONS = ("agent", "autopilot", "log")


class AutopilotSection(BaseModel):
    """``[autopilot]``: which backend and how to reach the flight controller."""

    model_config = ConfigDict(extra="forbid")

    backend: Literal["mavlink", "mavsdk", "memory"] = "mavlink"
    connection: str = Field(
        default="tcp:127.0.0.1:5760", description="e.g. /dev/serial0:921600, udpin:0.0.0.0:14550"
    )
    speedup: float = Field(default=1.0, gt=0.0, description="memory backend only")
    tlog: Path | None = Field(default=None, description="append MAVLink traffic to this .tlog")
    mavlink_signing_key_file: Path | None = None
    mavlink_out: list[str] = Field(
        default_factory=list,
        description="mavlink backend: extra ground stations sharing the autopilot link (the agent's "
        "MAVLink router), e.g. udp:192.168.1.20:14550 for QGroundControl; udpin:HOST:PORT and "
        "tcpin:HOST:PORT listen; what they command counts as the pilot's (docs/raspberry-pi.md)",
    )

    @field_validator("mavlink_out", mode="before")
    @classmethod
    def _split_endpoints(cls, value: object) -> object:
        if isinstance(value, str):  # FLEETGCS_AUTOPILOT_MAVLINK_OUT=udp:...,tcpin:...
            value = [part for part in value.split(",") if part.strip()]
        if isinstance(value, list):
            for text in value:
                if isinstance(text, str):
                    parse_endpoint(text)  # RouterConfigError (a ValueError) names it and why
        return value


class AgentFile(BaseModel):
    agent: AgentConfig
    autopilot: AutopilotSection = AutopilotSection()
    log: LoggingConfig = LoggingConfig()


def load_agent_config(
    path: Path | None,
    agent_overrides: Mapping[str, Any] | None = None,
    autopilot_overrides: Mapping[str, Any] | None = None,
    environ: Mapping[str, str] | None = None,
) -> AgentFile:
    """File < environment < overrides (explicit command-line flags); the key from key_file if given."""
    env = os.environ if environ is None else environ
    document = read_toml(path) if path is not None else {}
    unknown = sorted(set(document) - set(SECTIONS))
    if unknown:
        raise ConfigFileError(f"{path}: unknown table(s) {unknown}; expected {list(SECTIONS)}")
    table = merge(dict(document.get("agent") or {}), env_overrides(AgentConfig, AGENT_PREFIX, env))
    key_file = table.pop("key_file", None) or env.get(AGENT_PREFIX + "KEY_FILE")
    table = merge(table, agent_overrides or {})
    if "key_hex" not in table:
        if env.get("FLEETGCS_KEY"):
            table["key_hex"] = env["FLEETGCS_KEY"].strip()
        elif key_file:
            try:
                table["key_hex"] = Path(key_file).read_text().strip()
            except OSError as exc:
                raise ConfigFileError(f"agent.key_file: cannot read {key_file}: {exc.strerror}") from None
    agent = load_section(AgentConfig, table, AGENT_PREFIX, "agent", {})  # environment merged above
    autopilot = load_section(
        AutopilotSection, document.get("autopilot"), AUTOPILOT_PREFIX, "autopilot", env, autopilot_overrides
    )
    log = load_section(LoggingConfig, document.get("log"), LOG_PREFIX, "log", env)
    return AgentFile(agent=agent, autopilot=autopilot, log=log)
