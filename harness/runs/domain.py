"""The run's domain: free space resolved on the grid, and the parts that must honour it
(:mod:`harness.domains`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from harness.domains.base import FreeSpace
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.protocols import on_free_space
from harness.runs.checks import ConfigError
from harness.runs.identity import choices
from harness.targets.densities import Target
from harness.targets.moving import moves


def free_space(
    cfg: DictConfig, data: dict[str, Any], grid: Grid, component: Callable[..., Any]
) -> FreeSpace | None:
    """Free space of ``cfg.domain`` on ``grid`` (:class:`harness.domains.base.FreeSpace`),
    or None for a domain without obstacles (the square: every part runs as on the
    plain rectangle, bit for bit). A config without a ``domain`` node is the square.
    ``component`` builds the domain (:func:`harness.runs.build.component`).

    Raises:
        ConfigError: naming ``domain`` when its obstacles cover every cell, or a
            parameter of the domain that is not allowed.
    """
    if OmegaConf.select(cfg, "domain", default=None) is None:
        return None
    domain = component(cfg, "domain", data)
    try:
        free = domain.resolve(grid)
    except ParameterError as err:
        if err.name == "domain":
            raise ConfigError(
                "domain", choices(cfg).get("domain", domain.name), err.allowed
            ) from None
        raise ConfigError(f"domain.{err.name}", err.value, err.allowed) from None
    return None if free.everywhere else free


def check_reachable(free: FreeSpace | None, target: Target, init_cells: np.ndarray) -> None:
    """Every component of free space where the target puts mass holds some of the initial
    density: no law moves robots or mass between components (closed faces carry no
    flux, and the robots reflect at obstacles).

    Args:
        free: The run's free space (None: the square, one component).
        target: The target on the grid (``p_*``, 0 on blocked cells).
        init_cells: The initial density's cell values ``(ny, nx)``.

    Raises:
        ConfigError: naming ``target`` and the mass no robot can reach.
    """
    if free is None or free.n_components < 2:
        return
    g = free.grid
    for k in range(free.n_components):
        inside = free.labels == k
        wanted = g.integrate(np.where(inside, target.p, 0.0))
        start = g.integrate(np.where(inside, init_cells, 0.0))
        if wanted > 0 and not start > 0:
            raise ConfigError(
                "target",
                target.density,
                f"a target reachable from the start: it puts mass {wanted:.3g} in component {k} "
                "of free space, where no robot starts and none can enter",
            )


def check_free_space(
    cfg: DictConfig, free: FreeSpace | None, target: Target, parts: dict[str, Any]
) -> None:
    """On a domain with obstacles, every part must honour them
    (:func:`harness.protocols.on_free_space`), and the target must not move.

    Raises:
        ConfigError: naming ``domain`` and the part that runs only on the square.
    """
    if free is None:
        return
    chosen = choices(cfg)
    domain = chosen.get("domain", "domain")
    for group, part in parts.items():
        if not on_free_space(part):
            name = chosen.get(group, type(part).__name__)
            raise ConfigError(
                "domain", domain, f"square, the only domain {group}={name} runs on (no obstacles)"
            )
    if moves(target):
        raise ConfigError("domain", domain, "square, the only domain a moving target runs on")
