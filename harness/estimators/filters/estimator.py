"""``estimator=filters``: the paper's two filters on the KDE (eqs. ``density filter`` to
``gradient Riccati``), run by the engine ``filter.engine``
(:mod:`harness.estimators.filters.engines`).
"""

from __future__ import annotations

import numpy as np

from harness.estimators.filters.common import FilterSettings, MeasurementModel
from harness.estimators.filters.engines import FilterEngine
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import ParameterError, integer, number
from harness.protocols import (
    Control,
    MemoryEstimate,
    default_memory,
    on_free_space,
    require_field,
)
from harness.records import Estimate, StepInput


class FilterEstimator:
    """The paper's two filters on the KDE (``estimator=filters``): eqs. ``density
    filter``, ``density Riccati``, ``gradient filter``, ``gradient Riccati``.

    The engine is chosen by name from :class:`harness.estimators.filters.engines.FilterEngine`'s
    registry: ``local`` (fast, default), ``reference`` (dense) or ``filterpy`` (dense,
    filterpy's ``KalmanFilter`` doing the algebra).

    Args:
        grid, model: Run-time arguments (the model gives ``sigma``).
        engine: Engine name (``filter.engine``).
        robots: Swarm size ``N`` of the KDE noise constants ``k``, ``k_g``.
        bandwidth: KDE bandwidth ``h`` (length).
        dt: Measurement period (s).
        process_noise, r_scale, r_floor, initial_variance, band_limit: As
            :class:`harness.estimators.filters.common.FilterSettings` (``filter.*``), checked by
            :meth:`~harness.estimators.filters.common.FilterSettings.checked`.
    """

    uses_kde = True
    carries = ("traces",)  # every estimate holds the filters' covariance traces
    free_space = True
    """On free space (``model.free``) with the ``local`` engine; the dense engines are
    refused there (one line, naming ``engine``)."""

    def resolution(self, measured: float | None) -> float | None:
        """The measurement's resolution: the filters estimate only the cosine modes of
        ``|k| <= band_limit / h`` that the KDE resolves
        (:class:`~harness.estimators.filters.common.BandLimit`), so their estimates carry no finer
        content than the measurement.
        """
        return measured

    def __init__(
        self,
        grid: Grid,
        model: FokkerPlanck,
        engine: str,
        robots: int,
        bandwidth: float,
        dt: float,
        process_noise: float = 0.1,
        r_scale: float = 1.0,
        r_floor: float = 0.05,
        initial_variance: float = 10.0,
        band_limit: float = 2.5,
    ) -> None:
        engines = sorted(FilterEngine.registry)
        if engine not in FilterEngine.registry:
            raise ParameterError("engine", engine, f"one of {', '.join(engines)}")
        settings = FilterSettings.checked(
            process_noise, r_scale, r_floor, initial_variance, band_limit
        )
        measurement = MeasurementModel(
            integer("robots", robots, 1), number("bandwidth", bandwidth, 0.0, strict=True), settings
        )
        dt = number("dt", dt, 0.0, strict=True)
        # the swarm's size and the loop's step, as the run's shared keys must give them
        self.copies = {"robots": ("robots", measurement.n_robots), "dt": ("dt", dt)}
        chosen = FilterEngine.named(engine)
        if model.free is None:
            self.engine = chosen(grid, model.sigma, dt, measurement)
            return
        on_free = sorted(name for name, e in FilterEngine.registry.items() if on_free_space(e))
        if not on_free_space(chosen):
            raise ParameterError(
                "engine", engine, f"{', '.join(on_free)} on a domain with obstacles"
            )
        self.engine = chosen(grid, model.sigma, dt, measurement, free=model.free)  # type: ignore[call-arg]

    @classmethod
    def memory_estimate(cls, grid: Grid, engine: str = "local", **params: object) -> MemoryEstimate:
        """The engine's (:meth:`FilterEngine.memory_bytes`; dense engines are ``O(M^2)``)
        plus the grid arrays; the default estimate for an unknown engine name.
        """
        chosen = FilterEngine.registry.get(engine) if isinstance(engine, str) else None
        extra = chosen.memory_bytes(grid) if chosen is not None else 0
        return MemoryEstimate(default_memory(grid).nbytes + extra, "engine")

    def check(self, control: Control, **parts: object) -> None:
        """The filters' transport model is ``A(v)`` of the law's field: refuse a law
        without one.
        """
        require_field(control, "for estimator=filters (their transport model is A(v) of it)")

    def _estimate(self, p_hat: np.ndarray, q_hat: np.ndarray) -> Estimate:
        return Estimate(p_hat, q_hat, *self.engine.traces)

    def initialize(self, inp: StepInput) -> Estimate:
        """Start both filters from the first KDE."""
        assert inp.p_kde is not None and inp.grad_kde is not None
        return self._estimate(*self.engine.initialize(inp.p_kde, inp.grad_kde))

    def step(self, inp: StepInput) -> Estimate:
        """Predict under the applied velocity, update with the KDE."""
        assert inp.v_applied is not None
        assert inp.p_kde is not None and inp.grad_kde is not None
        return self._estimate(*self.engine.step(inp.p_kde, inp.grad_kde, inp.v_applied, inp.a))
