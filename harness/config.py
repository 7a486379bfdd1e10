"""Structured configs (Hydra / OmegaConf schemas) and builders from them.

Each dataclass is one config group or block; Hydra checks types at composition,
so ``grid.n=abc`` fails before anything runs. Units are listed per field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore


@dataclass
class GridConf:
    """``n``: cells per side of the square domain ``[0, length]^2``; ``length`` in
    length units (the paper: 30 cells on the unit square).
    """

    n: int = 30
    length: float = 1.0


@dataclass
class DynamicsConf:
    """``sigma``: noise intensity in ``dX = v dt + sqrt(2 sigma) dB`` (length^2 / s);
    the paper's ``sqrt(2 sigma) = 0.01`` gives ``5e-5``.
    """

    sigma: float = 5e-5


@dataclass
class ControlConf:
    """``law``: ``paper`` (eq. ``modified density feedback law using estimates``) or
    ``heat`` (prior law, estimate in the denominator); ``alpha``: feedback gain
    (length^4 / s); ``density_floor``: the heat law's floor on ``p_hat`` (1 /
    length^2); ``noise_compensation``: the heat law's ``-sigma q_hat / p_hat`` term.
    """

    law: str = "paper"
    alpha: float = 0.003
    density_floor: float = 0.1
    noise_compensation: bool = True


@dataclass
class SimConf:
    """``dt``: control and measurement period (s); ``t_final``: horizon (s)."""

    dt: float = 0.01
    t_final: float = 100.0


@dataclass
class DensityConf:
    """A density family (see :func:`harness.densities.make_density`).

    ``kind``: ``uniform`` | ``box`` | ``gaussian_mixture`` | ``default_target``.
    Box corners ``x0, x1, y0, y1`` and mixture ``means`` (pairs), ``stds``,
    ``weights`` in length units; ``floor`` is the uniform fraction of the mass.
    """

    kind: str = "default_target"
    x0: float = 0.15
    x1: float = 0.85
    y0: float = 0.15
    y1: float = 0.85
    means: list[Any] = field(default_factory=list)
    stds: list[float] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    floor: float = 0.2


@dataclass
class PlantConf:
    """``name``: ``agents`` (robots, KDE measurements) or ``meanfield`` (no robots;
    measurements are the truth plus seeded Gaussian noise of the KDE's variance).
    """

    name: str = "agents"


@dataclass
class AgentsConf:
    """``n``: number of robots ``N``."""

    n: int = 1024


@dataclass
class KDEConf:
    """``bandwidth``: kernel standard deviation ``h`` (length); ``mirror``: wall images;
    ``method``: ``auto`` | ``exact`` | ``binned``.
    """

    bandwidth: float = 0.04
    mirror: bool = True
    method: str = "auto"


@dataclass
class FilterConf:
    """``method``: ``local`` (fast) | ``reference`` (dense) | ``filterpy`` (dense,
    filterpy engine); the rest as :class:`harness.filters.common.FilterSettings`
    (``process_noise`` in 1 / s, ``r_floor`` in 1 / length^2).
    """

    method: str = "local"
    process_noise: float = 0.1
    r_scale: float = 1.0
    r_floor: float = 0.05
    initial_variance: float = 10.0


@dataclass
class EstimatorConf:
    """``name``: ``filters`` | ``kde`` | ``exact`` | ``injected``; ``delta``: size of
    the injected error (1 / length); ``omega``: its rotation rate (rad / s);
    ``modes``: its highest cosine mode per axis.
    """

    name: str = "filters"
    delta: float = 0.0
    omega: float = 0.1
    modes: int = 4


@dataclass
class LogConf:
    """``field_every``/``positions_every``: steps between field / position messages;
    ``progress``: ``auto`` (a bar when stderr is a terminal) | ``on`` | ``off``.
    """

    field_every: int = 10
    positions_every: int = 10
    progress: str = "auto"


@dataclass
class ClosedLoopConf:
    """The closed-loop experiment (``python -m experiments.closed_loop``)."""

    seed: int = 0
    grid: GridConf = field(default_factory=GridConf)
    plant: PlantConf = field(default_factory=PlantConf)
    agents: AgentsConf = field(default_factory=AgentsConf)
    dynamics: DynamicsConf = field(default_factory=DynamicsConf)
    control: ControlConf = field(default_factory=ControlConf)
    sim: SimConf = field(default_factory=SimConf)
    kde: KDEConf = field(default_factory=KDEConf)
    filter: FilterConf = field(default_factory=FilterConf)
    estimator: EstimatorConf = field(default_factory=EstimatorConf)
    target: DensityConf = field(default_factory=DensityConf)
    init: DensityConf = field(default_factory=lambda: DensityConf(kind="box"))
    log: LogConf = field(default_factory=LogConf)


def density_spec(conf: Any) -> dict:
    """The plain mapping :func:`harness.densities.make_density` takes, from a
    :class:`DensityConf` (only the keys its ``kind`` uses).
    """
    kind = conf.kind
    if kind == "box":
        return {"kind": kind, "x0": conf.x0, "x1": conf.x1, "y0": conf.y0, "y1": conf.y1}
    if kind == "gaussian_mixture":
        return {
            "kind": kind,
            "means": [list(m) for m in conf.means],
            "stds": list(conf.stds),
            "weights": list(conf.weights),
            "floor": conf.floor,
        }
    return {"kind": kind}


def register_configs() -> None:
    """Register the schemas with Hydra's ConfigStore."""
    cs = ConfigStore.instance()
    cs.store(name="closed_loop_schema", node=ClosedLoopConf)
    cs.store(group="target", name="density_schema", node=DensityConf)
    cs.store(group="init", name="density_schema", node=DensityConf)
