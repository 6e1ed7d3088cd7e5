"""The fusion engine as the backend sees it: a small protocol, and the factory of the real one.

The server, the replay and the overlay are written against ``FusionEngine`` only, so any
object with these methods (the real ``estimator.pipeline.Fusion``, a test double) can be
replayed. ``create_engine`` is the one place that builds the real estimator.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from estimator.records import Calibration, GnssEpoch, NavigationData


@runtime_checkable
class FusionEngine(Protocol):
    """What the backend needs from a fusion engine (``estimator.pipeline.Fusion``).

    The returned states are duck-typed ``FusedState`` objects: ``time``, ``position_ned``,
    ``llh_deg``, ``velocity_ned``, ``euler``, ``C_body_to_level``, ``rate_of_turn``,
    ``omega_body``, ``position_cov``, ``attitude_cov`` and ``status`` (``phase``,
    ``compass_fixed``, ``satellites``, ``vo_status``, ``scale``, ``scale_converged``,
    ``message``).
    """

    def process_imu(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None: ...

    def process_gnss(self, t: float, epochs: Sequence[GnssEpoch | None]) -> None: ...

    def process_frame(self, t: float, image: np.ndarray) -> Any | None: ...

    def state(self) -> Any | None: ...

    def structure(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    # The structure window's views with their solved attitudes
    # (``estimator.landmarks.SolvedViews``), None without them: the designated targets are
    # triangulated in them.
    def solved_views(self) -> Any | None: ...

    def timing(self) -> dict: ...


# (calibration, nav, options as a dict of FusionOptions fields) -> engine
EngineFactory = Callable[[Calibration, NavigationData, dict[str, Any]], FusionEngine]


def create_engine(calibration: Calibration, nav: NavigationData,
                  options: dict[str, Any]) -> FusionEngine:
    """The real estimator (``estimator.pipeline.Fusion``) with ``FusionOptions(**options)``.

    Imported here, not at module level, so the web stack starts (and reports a clear error)
    while the estimator is missing or broken.
    """
    try:
        from estimator.pipeline import Fusion, FusionOptions
    except ImportError as exc:  # only while the estimator is not installed/complete
        raise RuntimeError(f"the fusion engine (estimator.pipeline) cannot be imported: "
                           f"{exc}") from exc
    return Fusion(calibration, nav, FusionOptions(**options))
