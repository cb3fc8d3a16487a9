"""Pick an autopilot backend by name (the agent CLI's ``--autopilot-backend``)."""

from __future__ import annotations

from typing import Any

from agent.autopilot.base import Autopilot

BACKENDS = ("mavlink", "mavsdk", "memory")


def create_autopilot(backend: str, connection: str, **options: Any) -> Autopilot:
    """Build an :class:`Autopilot`.

    * ``"mavlink"`` (default for ArduPilot and generic MAVLink autopilots):
      :class:`agent.autopilot.mavlink_backend.MavlinkAutopilot` (``connection`` like
      ``/dev/ttyAMA0:921600``, ``udpin:0.0.0.0:14550``, ``tcp:127.0.0.1:5760``);
    * ``"mavsdk"`` (PX4): :class:`agent.autopilot.mavsdk_backend.MavsdkAutopilot` (``connection``
      like ``udpin://0.0.0.0:14540``, ``tcpout://127.0.0.1:5760``, ``serial:///dev/ttyAMA0:921600``);
    * ``"memory"``: :class:`agent.autopilot.memory.MemoryAutopilot`, a simulated vehicle in process
      (``connection`` may be ``"lat,lon,alt_amsl"`` for its home, or ``""``/``"memory"``).

    Backends are imported lazily so that, e.g., the memory backend works without pymavlink/mavsdk.
    ``options`` are the backend's keyword arguments.
    """
    name = (backend or "mavlink").strip().lower()
    if name == "mavlink":
        from agent.autopilot.mavlink_backend import MavlinkAutopilot

        return MavlinkAutopilot(connection, **options)
    if name == "mavsdk":
        from agent.autopilot.mavsdk_backend import MavsdkAutopilot

        return MavsdkAutopilot(connection, **options)
    if name == "memory":
        from agent.autopilot.memory import MemoryAutopilot

        home = _parse_home(connection)
        if home is not None and "home" not in options:
            options["home"] = home
        return MemoryAutopilot(**options)
    raise ValueError(f"unknown autopilot backend {backend!r}; choose one of {', '.join(BACKENDS)}")


def _parse_home(connection: str) -> tuple[float, float, float] | None:
    parts = [p for p in connection.replace("memory:", "").split(",") if p.strip()]
    if len(parts) != 3:
        return None
    try:
        lat, lon, alt = (float(p) for p in parts)
    except ValueError:
        return None
    return lat, lon, alt
