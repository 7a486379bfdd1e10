"""Config checks that no single component can make: the shared blocks and the
checks that span components.

Each component checks its own parameters when it is built (see
:mod:`harness.components`); :func:`harness.build.build` calls :func:`check_shared`
before building and :func:`check_built` after. A refused value raises
:class:`ConfigError`, whose text is the one line the entry point prints (exit status 2).
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
from omegaconf import DictConfig

from harness.components import Control, Density, ParameterError, flag, integer, number
from harness.control import sampled_data_dt_bound
from harness.densities import Box, Target
from harness.grid import Grid
from harness.kde import KDE

MAX_STEPS = 10_000_000
"""Largest number of steps ``sim.t_final / sim.dt`` of one run."""

PROGRESS = ("auto", "on", "off")
"""Values of ``log.progress``."""


class ConfigError(ValueError):
    """A config value that is not allowed; ``str()`` is the one-line message."""

    def __init__(self, key: str, value: Any, allowed: str) -> None:
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"invalid config: {key}={value!r}: {allowed}")


class ConfigWarning(UserWarning):
    """A config that runs, but a check could not be made."""


def _block(cfg: DictConfig, name: str) -> Any:
    """``cfg[name]``, or a :class:`ConfigError` when the block is missing."""
    node = cfg.get(name) if isinstance(cfg, DictConfig) else None
    if node is None:
        raise ConfigError(name, None, "a required config block")
    return node


def _shared(key: str, check: Any, *args: Any) -> Any:
    """Run a parameter check on a shared key, naming the key in the error."""
    name = key.rsplit(".", 1)[-1]
    try:
        return check(name, *args)
    except ParameterError as err:
        raise ConfigError(key, err.value, err.allowed) from None


def check_shared(cfg: DictConfig) -> None:
    """The shared blocks: ``seed``, ``grid``, ``agents``, ``dynamics``, ``sim``, ``kde``,
    ``log`` (types and ranges), and the time step against the horizon and the domain.
    """
    _shared("seed", integer, cfg.get("seed"), 0)
    grid, sim, kde, log = (_block(cfg, b) for b in ("grid", "sim", "kde", "log"))
    n = _shared("grid.n", integer, grid.get("n"), 4)
    if n > 512:
        raise ConfigError("grid.n", n, "at most 512 (memory)")
    length = _shared("grid.length", number, grid.get("length"), 0.0, True)
    _shared("agents.n", integer, _block(cfg, "agents").get("n"), 1)
    sigma = _shared("dynamics.sigma", number, _block(cfg, "dynamics").get("sigma"), 0.0)
    dt = _shared("sim.dt", number, sim.get("dt"), 0.0, True)
    t_final = _shared("sim.t_final", number, sim.get("t_final"), 0.0, True)
    h = _shared("kde.bandwidth", number, kde.get("bandwidth"), 0.0, True)
    if h > length:
        raise ConfigError("kde.bandwidth", h, f"at most the domain side {length}")
    _shared("kde.mirror", flag, kde.get("mirror"))
    _shared("kde.debias", flag, kde.get("debias"))
    if kde.get("method") not in KDE.METHODS:
        raise ConfigError("kde.method", kde.get("method"), f"one of {', '.join(KDE.METHODS)}")
    _shared("log.field_every", integer, log.get("field_every"), 1)
    _shared("log.positions_every", integer, log.get("positions_every"), 1)
    _shared("log.w2_every", integer, log.get("w2_every"), 1)
    _shared("log.floor_draws", integer, log.get("floor_draws"), 2)
    _shared("log.live", flag, log.get("live"))
    port = _shared("log.live_port", integer, log.get("live_port"), 0)
    if port > 65535:
        raise ConfigError("log.live_port", port, "a TCP port, 0 to 65535 (0: any free port)")
    if not isinstance(log.get("live_host"), str) or not log.get("live_host"):
        raise ConfigError("log.live_host", log.get("live_host"), "an address such as 127.0.0.1")
    if log.get("progress") not in PROGRESS:
        raise ConfigError("log.progress", log.get("progress"), f"one of {', '.join(PROGRESS)}")
    if dt > t_final:
        raise ConfigError("sim.dt", dt, f"at most sim.t_final = {t_final}")
    if round(t_final / dt) > MAX_STEPS:
        raise ConfigError("sim.t_final", t_final, f"at most {MAX_STEPS:.0e} steps of sim.dt")
    # Euler-Maruyama with reflection: a noise step must be well inside the domain
    if math.sqrt(2 * sigma * dt) > length / 10:
        raise ConfigError(
            "sim.dt", dt, f"small enough that sqrt(2 sigma dt) <= {length / 10} (domain / 10)"
        )


def density_on_grid(key: str, density: Density, grid: Grid) -> np.ndarray:
    """``density`` on ``grid``, refused unless finite, of unit mass and inside the domain."""
    try:
        p = density.on_grid(grid)
    except (ValueError, TypeError) as err:
        raise ConfigError(key, density, str(err)) from None
    require_density = bool(np.isfinite(p).all()) and abs(grid.integrate(p) - 1.0) < 1e-9
    if not require_density:
        raise ConfigError(key, density, "a density that is finite and normalisable on the grid")
    if isinstance(density, Box):
        inside = density.x1 <= grid.x1 and density.y1 <= grid.y1
        if not inside:
            raise ConfigError(f"{key}.x1", density.x1, f"a box inside [0, {grid.x1}]^2")
    return p


def target_on_grid(density: Density, grid: Grid) -> Target:
    """The target on the grid; refused unless strictly positive there."""
    density_on_grid("target", density, grid)
    try:
        return Target.from_density(grid, density)
    except ValueError as err:
        raise ConfigError("target", density, str(err)) from None


def resolution(plant: Any, estimator: Any) -> float | None:
    """The smallest scale (length) the estimates resolve: the estimator's
    ``resolution(measured)`` of the plant's measurement ``resolution`` (None: grid
    resolution, also for components that do not say).
    """
    measured = getattr(plant, "resolution", None)
    of = getattr(estimator, "resolution", None)
    return of(measured) if callable(of) else None


def check_built(
    cfg: DictConfig, grid: Grid, target: Target, control: Control, plant: Any, estimator: Any
) -> None:
    """Checks across components: the sampled-data step bound
    (:func:`harness.control.sampled_data_dt_bound`) of the control law near the target,
    for the resolution of the estimates the plant and estimator give (:func:`resolution`).

    Near ``p_*`` the feedback diffusivity is the law's at ``p = p_*`` (``alpha`` for the
    paper's law); a ``dt`` above the bound there makes the loop unstable on some grid
    mode and is refused. (Far from the target, at the start, the diffusivity can be
    larger, ``alpha max(p_0 / p_*)``; an overshoot there is transient and not refused.)
    A law without :meth:`~harness.components.Control.feedback_diffusivity` (or returning
    None) is not refused; a :class:`ConfigWarning` says the bound was not checked.
    """
    rate = getattr(control, "feedback_diffusivity", None)
    diffusivity = rate(target.p) if rate is not None else None
    if diffusivity is None:
        warnings.warn(
            f"{type(control).__name__} gives no feedback diffusivity: the sampled-data "
            "step bound of sim.dt is not checked",
            ConfigWarning,
            stacklevel=2,
        )
        return
    h = resolution(plant, estimator)
    bound = sampled_data_dt_bound(grid, diffusivity, h, cfg.dynamics.sigma)
    if cfg.sim.dt > bound:
        scale = "grid resolution" if h is None else f"resolution {h:g}"
        raise ConfigError(
            "sim.dt",
            cfg.sim.dt,
            f"at most the sampled-data bound {bound:.3g} s for this control near the "
            f"target, grid and estimates of {scale} (harness.control.sampled_data_dt_bound)",
        )


def describe(err: BaseException, argv: list[str]) -> str:
    """One line for a config that does not compose (a Hydra or OmegaConf error), naming
    the key when the error carries one and the value given for it on the command line.
    """
    cause = err.__cause__ or err.__context__ or err
    key = getattr(cause, "full_key", None) or getattr(err, "full_key", None)
    text = str(cause).strip() or str(err).strip()
    first = text.splitlines()[0] if text else type(cause).__name__
    if key:
        given = [a.split("=", 1) for a in argv if "=" in a]
        value = next((v for k, v in given if k.lstrip("+~") == key), None)
        return f"invalid config: {key}={value!r}: {first}"
    return f"invalid config: {first}"


__all__ = [
    "ConfigError",
    "ConfigWarning",
    "check_built",
    "check_shared",
    "density_on_grid",
    "describe",
    "target_on_grid",
]
