"""Pre-flight checks of a submitted mission: planned link coverage and predicted energy."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from gcs.cooperation.config import CooperationConfig
from gcs.cooperation.connectivity import preflight_disconnections
from gcs.cooperation.energy import EnergyModel, capability_power_w, predict_plan_energy
from gcs.missions.runner import MissionRejected
from gcs.observe.events import EventBus
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action
from protocol.taskfile import TaskFile

if TYPE_CHECKING:
    from gcs.core.context import AgentRecord

StartPoints = dict[str, tuple[float, float, float]]


def start_points(
    plans: dict[str, list[Action]], session_of: Callable[[str], AgentRecord | None]
) -> StartPoints:
    """Where each drone of ``plans`` starts: its reported position, else its home."""
    homes: StartPoints = {}
    for ident in plans:
        session = session_of(ident)
        status = session.status if session else None
        if status is not None and status.position is not None:
            p = status.position
            homes[ident] = (p.lat, p.lon, max(p.alt_rel, 0.0))
        elif session is not None and session.home is not None:
            homes[ident] = (session.home.lat, session.home.lon, 0.0)
    return homes


class PreflightChecks:
    def __init__(
        self,
        config: CooperationConfig,
        session_of: Callable[[str], AgentRecord | None],
        events: EventBus,
        link_range: Callable[[], float | None],
        base: Callable[[], tuple[float, float] | None],
        model: Callable[[], EnergyModel],
    ) -> None:
        self.config = config
        self._session_of = session_of
        self._events = events
        self._link_range = link_range
        self._base = base
        self._model = model

    async def __call__(self, task: TaskFile, plans: dict[str, list[Action]]) -> None:
        homes = start_points(plans, self._session_of)
        if set(homes) != set(plans):
            return  # positions unknown yet; the mission runner checks connections itself
        if self.config.connectivity.enabled and self.config.connectivity.preflight:
            self._links(plans, homes)
        if self.config.energy.enabled:
            self._energy(task, plans, homes)

    def _links(self, plans: dict[str, list[Action]], homes: StartPoints) -> None:
        w = self._link_range()
        if w is None:
            return
        first = next(iter(homes.values()))
        base = self._base() or (first[0], first[1])
        frame = LocalFrame(base[0], base[1])
        problems = preflight_disconnections(
            plans, homes, frame, frame.local_point(*base), w, self.config.connectivity.multihop
        )
        for step, ident in problems:
            self._events.publish(
                "connectivity_warning",
                f"planned step {step} leaves {ident} out of link range ({w:.0f} m) of the base and the fleet",
                severity="warning",
                agent=ident,
                data={"step": step, "preflight": True},
            )

    def predict_energy(
        self, plans: dict[str, list[Action]], homes: StartPoints
    ) -> dict[str, tuple[float, float, float]]:
        """Per agent: (plan time s, plan distance m, predicted Wh), by the one shared estimator."""
        cfg = self.config.energy
        power = {
            a: capability_power_w(s.capabilities.battery_wh, s.capabilities.endurance_s, cfg)
            for a in plans
            if (s := self._session_of(a)) is not None
        }
        model = self._model()
        predictions = predict_plan_energy(plans, homes, cfg, model if model.trained_on else None, power)
        return {a: (e.time_s, e.distance_m, e.energy_wh) for a, e in predictions.items()}

    def _energy(self, task: TaskFile, plans: dict[str, list[Action]], homes: StartPoints) -> None:
        cfg = self.config.energy
        refusals = []
        report: dict[str, dict[str, float]] = {}
        for ident, (t, d, need) in self.predict_energy(plans, homes).items():
            session = self._session_of(ident)
            capacity = (session.capabilities.battery_wh if session else None) or cfg.default_battery_wh
            status = session.status if session else None
            pct = status.battery.pct if status is not None and status.battery.pct is not None else 100.0
            available = capacity * pct / 100.0
            reserve = capacity * cfg.reserve_pct / 100.0
            report[ident] = {
                "plan_time_s": round(t, 1),
                "plan_distance_m": round(d, 1),
                "predicted_wh": round(need, 2),
                "available_wh": round(available, 2),
                "reserve_wh": round(reserve, 2),
            }
            if need + reserve > available:
                refusals.append(
                    f"{ident} needs {need:.1f} Wh (plan {t:.0f} s, {d:.0f} m) + reserve {reserve:.1f} Wh "
                    f"but has {available:.1f} Wh ({pct:.0f}% of {capacity:.0f} Wh)"
                )
        self._events.publish(
            "energy_prediction",
            f"{task.name}: "
            + "; ".join(
                f"{a} {r['predicted_wh']:.1f} of {r['available_wh']:.1f} Wh" for a, r in report.items()
            ),
            severity="warning" if refusals else "info",
            data={"agents": report, "model_trained_on": self._model().trained_on},
        )
        if refusals:
            raise MissionRejected("energy check: " + "; ".join(refusals))
