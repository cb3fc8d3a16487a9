"""Run-time cooperation services of the daemon (seed 004 section 2.2.1, seed 000 section IV).

Pure algorithms (``collision``, ``divergence``, ``connectivity``, ``emergency``, ``energy``,
``legs``) are separate from the glue that listens to status reports and sends packets
(``service``). ``cooperation_services(config)`` builds what the daemon runs.
"""

from __future__ import annotations

from typing import Any

from gcs.cooperation.config import CooperationConfig

__all__ = ["CooperationConfig", "cooperation_services"]


def cooperation_services(config: CooperationConfig) -> list[Any]:
    """The services for :class:`gcs.daemon.Daemon` (imported lazily: the daemon imports this module)."""
    from gcs.cooperation.service import CooperationService

    return [CooperationService(config)]
