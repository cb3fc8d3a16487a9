"""ArduCopter-style parameter table (names, units and defaults as in ArduCopter 4.x).

Parameters live in memory only: unlike a real SITL instance (which keeps an eeprom file), every process
start gives the defaults below plus any overrides passed in the configuration.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Mapping

# MAV_PARAM_TYPE values
INT8 = 2
INT16 = 4
INT32 = 6
REAL32 = 9

# name -> (default, MAV_PARAM_TYPE). Units follow ArduCopter (cm, cm/s, V, s, ms).
DEFAULTS: dict[str, tuple[float, int]] = {
    "SYSID_THISMAV": (1, INT16),
    "SYSID_MYGCS": (255, INT16),
    "ARMING_CHECK": (1, INT32),
    "DISARM_DELAY": (10, INT8),
    "WPNAV_SPEED": (500.0, REAL32),
    "WPNAV_ACCEL": (250.0, REAL32),
    "WPNAV_SPEED_UP": (250.0, REAL32),
    "WPNAV_SPEED_DN": (150.0, REAL32),
    "WPNAV_ACCEL_Z": (100.0, REAL32),
    "WPNAV_RADIUS": (200.0, REAL32),
    "LOIT_SPEED": (1250.0, REAL32),
    "LAND_SPEED": (50, INT16),
    "LAND_SPEED_HIGH": (0, INT16),
    "LAND_ALT_LOW": (1000, INT16),
    "RTL_ALT": (1500, INT32),
    "RTL_ALT_FINAL": (0, INT16),
    "RTL_CLIMB_MIN": (0, INT16),
    "RTL_SPEED": (0, INT16),
    "RTL_LOIT_TIME": (5000, INT32),
    "FENCE_ENABLE": (0, INT8),
    "FENCE_TYPE": (7, INT8),
    "FENCE_ACTION": (1, INT8),
    "FENCE_ALT_MAX": (100.0, REAL32),
    "FENCE_RADIUS": (300.0, REAL32),
    "FENCE_MARGIN": (2.0, REAL32),
    "FENCE_TOTAL": (0, INT8),
    "BATT_MONITOR": (4, INT8),
    "BATT_CAPACITY": (5000, INT32),
    "BATT_LOW_VOLT": (10.5, REAL32),
    "BATT_CRT_VOLT": (0.0, REAL32),
    "BATT_ARM_VOLT": (0.0, REAL32),
    "BATT_LOW_TIMER": (10, INT8),
    "BATT_FS_LOW_ACT": (0, INT8),
    "BATT_FS_CRT_ACT": (0, INT8),
    "FS_EKF_ACTION": (1, INT8),
    "FS_EKF_THRESH": (0.8, REAL32),
    "FS_GCS_ENABLE": (0, INT8),
    "SIM_WIND_SPD": (0.0, REAL32),
    "SIM_WIND_DIR": (180.0, REAL32),
    "SIM_WIND_TURB": (0.0, REAL32),
    "SIM_GPS_DISABLE": (0, INT8),  # older ArduPilot SITL
    "SIM_GPS1_ENABLE": (1, INT8),  # ArduPilot 4.7 SITL: 0 = no GPS
    "SIM_SPEEDUP": (1.0, REAL32),
}


class ParamStore:
    """Ordered parameter table with change callbacks (so e.g. SIM_WIND_* take effect immediately)."""

    def __init__(
        self,
        overrides: Mapping[str, float] | None = None,
        defaults: Mapping[str, tuple[float, int]] | None = None,
    ) -> None:
        table = DEFAULTS if defaults is None else defaults  # another autopilot's table (sitl/px4_params.py)
        self._names: list[str] = list(table)
        self._values: dict[str, float] = {k: float(v) for k, (v, _t) in table.items()}
        self._types: dict[str, int] = {k: t for k, (_v, t) in table.items()}
        self.on_change: Callable[[str, float], None] | None = None
        for k, v in (overrides or {}).items():
            self.define(k, float(v))

    def define(self, name: str, value: float, ptype: int = REAL32) -> None:
        """Add (or overwrite) a parameter without firing the change callback."""
        name = name.upper()
        if name not in self._values:
            self._names.append(name)
            self._types[name] = ptype
        self._values[name] = float(value)

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __len__(self) -> int:
        return len(self._names)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def get(self, name: str, default: float = 0.0) -> float:
        """Value of ``name`` or ``default``."""
        return self._values.get(name, default)

    def index(self, name: str) -> int:
        """Position of ``name`` in PARAM_VALUE numbering."""
        return self._names.index(name)

    def name_at(self, index: int) -> str | None:
        """Name at PARAM_VALUE index ``index`` or None."""
        return self._names[index] if 0 <= index < len(self._names) else None

    def ptype(self, name: str) -> int:
        """MAV_PARAM_TYPE of ``name``."""
        return self._types[name]

    def set(self, name: str, value: float) -> bool:
        """Set an existing parameter (integers are rounded like ArduPilot); False if unknown or NaN."""
        if name not in self._values or math.isnan(value) or math.isinf(value):
            return False
        if self._types[name] != REAL32:
            value = float(round(value))
        self._values[name] = float(value)
        if self.on_change is not None:
            self.on_change(name, float(value))
        return True
