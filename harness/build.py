"""Build a closed loop from a config: every component from its YAML.

:func:`build` is one straight line: shared checks, grid, densities, model, plant,
estimator, control, cross-component checks. Each component is instantiated from its
config group's node (``_target_`` plus the class's own parameters) by
:func:`component`, which hands it its run-time arguments (see
:mod:`harness.components`) and turns a refused parameter into a
:class:`~harness.checks.ConfigError` that names the full key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import hydra.utils
import numpy as np
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf

from harness import components
from harness.checks import (
    ConfigError,
    check_built,
    check_memory,
    check_resolvable,
    check_shared,
    check_unread,
    density_on_grid,
    target_on_grid,
)
from harness.components import Control, Density, Estimator, ParameterError, Plant
from harness.densities import Target
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid

_INTERPOLATION = re.compile(r"^\$\{([A-Za-z_][\w.]*)\}$")
_UNEXPECTED = re.compile(r"unexpected keyword argument '(\w+)'")
_MISSING = re.compile(r"missing \d+ required (?:keyword-only |positional )?arguments?: (.+)$")

PROTOCOLS: dict[str, type] = {
    "target": components.Density,
    "init": components.Density,
    "plant": components.Plant,
    "estimator": components.Estimator,
    "control": components.Control,
}
"""The protocol each config group's component implements."""


def public_key(cfg: DictConfig, group: str, name: str) -> str:
    """The key to name for parameter ``name`` of ``group``: the key it interpolates
    (``plant.n: ${agents.n}`` gives ``agents.n``), else ``group.name``.
    """
    node = cfg.get(group)
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    value = raw.get(name) if isinstance(raw, dict) else None
    match = _INTERPOLATION.match(value) if isinstance(value, str) else None
    return match.group(1) if match else f"{group}.{name}"


def _first_line(err: BaseException) -> str:
    """``Type: first line of the message`` of an exception."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0]}" if text else type(err).__name__


def component(cfg: DictConfig, group: str, **runtime: Any) -> Any:
    """Instantiate the component of ``group`` with its run-time arguments.

    Raises:
        ConfigError: for a missing or unloadable ``_target_``, a parameter the class
            does not take or lacks, a refused parameter (:class:`ParameterError`), or
            an object that does not implement the group's protocol.
    """
    node = cfg.get(group)
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(group, node, "a component config with _target_ (see docs/extending.md)")
    try:
        factory = hydra.utils.instantiate(node, _partial_=True, _convert_="all")
    except InstantiationException as err:
        cause = err.__cause__ or err
        first = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        raise ConfigError(f"{group}._target_", node.get("_target_"), first) from None
    target = node.get("_target_")
    try:
        obj = factory(**runtime)
    except ParameterError as err:
        raise ConfigError(public_key(cfg, group, err.name), err.value, err.allowed) from None
    except TypeError as err:
        text = str(err)
        unexpected, missing = _UNEXPECTED.search(text), _MISSING.search(text)
        if unexpected:
            name = unexpected.group(1)
            allowed = f"not a parameter of {target}"
            raise ConfigError(f"{group}.{name}", node.get(name), allowed) from None
        if missing:
            raise ConfigError(group, target, f"{target} needs {missing.group(1)}") from None
        raise ConfigError(group, target, _first_line(err)) from None
    except (ValueError, ArithmeticError, IndexError, KeyError, AttributeError) as err:
        # a constructor sees only config values and run-time objects: whatever it
        # raises (a list of the wrong length, an overflow) is a refused config
        raise ConfigError(group, target, _first_line(err)) from None
    protocol = PROTOCOLS[group]
    if not isinstance(obj, protocol):
        raise ConfigError(f"{group}._target_", target, f"must implement {protocol.__name__}")
    return obj


@dataclass(frozen=True)
class Experiment:
    """The built components of one run (see :func:`build`)."""

    grid: Grid
    target: Target
    init: Density
    p0: np.ndarray
    model: FokkerPlanck
    plant: Plant
    estimator: Estimator
    control: Control


def build(cfg: DictConfig) -> Experiment:
    """All components of a closed-loop config, checked.

    In order: every interpolation resolves, every key is read by something, the
    shared blocks, the memory the run will need (estimated from the components'
    parameters before any of them allocates), the components, the checks across them.
    Building draws no random numbers: robots are placed by ``plant.start(rng)``.

    Raises:
        ConfigError: for the first value that is not allowed.
    """
    check_resolvable(cfg)
    check_unread(cfg)
    check_shared(cfg)
    grid = Grid.square(cfg.grid.n, cfg.grid.length)
    check_memory(cfg, grid)
    target = target_on_grid(component(cfg, "target"), grid)
    init = component(cfg, "init")
    p0 = density_on_grid("init", init, grid)
    model = FokkerPlanck(grid, cfg.dynamics.sigma)
    control = component(cfg, "control", target=target)
    plant = component(cfg, "plant", grid=grid, model=model, init=init, control=control)
    estimator = component(cfg, "estimator", grid=grid, model=model)
    check_built(cfg, grid, target, control, plant, estimator)
    return Experiment(grid, target, init, p0, model, plant, estimator, control)
