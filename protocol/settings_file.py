"""TOML configuration files with environment overrides, and logging setup, shared by gcs and agent.

It lives in ``protocol`` because both programs need it and neither may import the other. Pure
stdlib + pydantic: a file is read with :mod:`tomllib`, environment variables override single
fields, and the result is validated by the program's own pydantic models (docs/configuration.md).

Environment rule: for a section read with prefix ``P``, the field ``name`` is overridden by
``P + NAME`` (upper case) and a nested field ``outer.inner`` by ``P + OUTER__INNER``. Values are
parsed as JSON when they can be (``true``, ``5``, ``["a"]``), else taken as text.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError


class ConfigFileError(ValueError):
    """A configuration file (or override) that cannot be used; the message names the field."""


class LoggingConfig(BaseModel):
    """``[log]``: where and how the program logs."""

    model_config = ConfigDict(extra="forbid")

    level: str = Field(default="INFO", pattern=r"^(?i:debug|info|warning|error|critical)$")
    json_format: bool = Field(default=False, description="one JSON object per line (for journald/Loki)")
    file: Path | None = Field(default=None, description="log to this file (rotated) instead of stderr")
    max_bytes: int = Field(default=10 * 1024 * 1024, ge=1024, description="rotate the file at this size")
    backups: int = Field(default=5, ge=0, le=100, description="rotated files kept")


def package_version() -> str:
    """The installed fleetgcs version, for ``--version`` of gcs, agent and sitl."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fleetgcs")
    except PackageNotFoundError:
        return "unknown (not installed)"


def read_toml(path: Path) -> dict[str, Any]:
    import tomllib  # only when a file is read: an agent configured by flags never loads it (issue 29)

    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except OSError as exc:
        raise ConfigFileError(f"cannot read {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigFileError(f"{path} is not valid TOML: {exc}") from None


def _parse_env_value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def env_overrides(model: type[BaseModel], prefix: str, environ: Mapping[str, str]) -> dict[str, Any]:
    """The fields of ``model`` set by environment variables ``PREFIX + FIELD`` (nested: ``__``)."""
    out: dict[str, Any] = {}
    for name, info in model.model_fields.items():
        key = prefix + name.upper()
        if key in environ:
            out[name] = _parse_env_value(environ[key])
            continue
        sub = info.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            nested = env_overrides(sub, key + "__", environ)
            if nested:
                out[name] = nested
    return out


def merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merge key by key, anything else is replaced."""
    result = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(result.get(key), Mapping):
            result[key] = merge(dict(result[key]), value)
        else:
            result[key] = value
    return result


def first_error(exc: ValidationError, section: str) -> str:
    err = exc.errors()[0]
    where = ".".join([section, *(str(p) for p in err.get("loc", ()))])
    return f"{where}: {err.get('msg', 'invalid')}"


def load_section(
    model: type[BaseModel],
    table: Mapping[str, Any] | None,
    prefix: str,
    section: str,
    environ: Mapping[str, str] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Any:
    """Validate one ``[section]`` table of a file, with environment overrides, as ``model``."""
    values = merge(
        dict(table or {}), env_overrides(model, prefix, os.environ if environ is None else environ)
    )
    values = merge(values, extra or {})
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise ConfigFileError(first_error(exc, section)) from None


class JsonFormatter(logging.Formatter):
    """One JSON object per record: time, level, logger, message, and the exception if any."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False)


def configure_logging(config: LoggingConfig, verbose: bool = False) -> None:
    """Replace the root logger's handlers: stderr or a rotating file, plain text or JSON."""
    handler: logging.Handler
    if config.file is not None:
        from logging.handlers import RotatingFileHandler  # only for a file (pickle, queue...: issue 29)

        config.file.parent.mkdir(parents=True, exist_ok=True)
        handler = RotatingFileHandler(
            config.file, maxBytes=config.max_bytes, backupCount=config.backups, encoding="utf-8"
        )
    else:
        handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        JsonFormatter()
        if config.json_format
        else logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    )
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else config.level.upper())
