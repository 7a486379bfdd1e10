"""Meaning checks of a closed-loop config, before anything is written.

Hydra's structured configs reject wrong *types* at composition; :func:`validate`
rejects wrong *values*, each with one line naming the key, the value and what is
allowed (:class:`ConfigError`). The entry point turns it into exit status 2.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from harness.config import density_spec
from harness.control import sampled_data_dt_bound
from harness.densities import Box, Target, make_density
from harness.grid import Grid

SAMPLED_DATA_FACTOR = 10.0
"""``sim.dt`` may exceed the worst-case sampled-data bound
(:func:`harness.control.sampled_data_dt_bound`, which the paper's own setting meets
only to within 7 %) by at most this factor; beyond it the held feedback overshoots."""


class ConfigError(ValueError):
    """A config value that is not allowed; ``str()`` is the one-line message."""

    def __init__(self, key: str, value: Any, allowed: str) -> None:
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"invalid config: {key}={value!r}: {allowed}")


def _lookup(cfg: Any, key: str) -> Any:
    """The value at a dotted key."""
    node: Any = cfg
    for part in key.split("."):
        node = node[part]
    return node


def _check(ok: bool, key: str, value: Any, allowed: str) -> None:
    if not ok:
        raise ConfigError(key, value, allowed)


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def validate(cfg: Any) -> None:
    """Raise :class:`ConfigError` for the first value that is not allowed."""
    choices = {
        "plant.name": ("agents", "meanfield"),
        "estimator.name": ("filters", "kde", "exact", "injected"),
        "control.law": ("paper", "heat"),
        "filter.method": ("local", "reference", "filterpy"),
        "kde.method": ("auto", "exact", "binned"),
        "log.progress": ("auto", "on", "off"),
        "target.kind": ("uniform", "box", "gaussian_mixture", "default_target"),
        "init.kind": ("uniform", "box", "gaussian_mixture", "default_target"),
    }
    for key, allowed in choices.items():
        value = _lookup(cfg, key)
        _check(value in allowed, key, value, f"one of {', '.join(allowed)}")
    ints = {
        "seed": (0, "an integer >= 0"),
        "grid.n": (4, "an integer >= 4"),
        "agents.n": (1, "an integer >= 1"),
        "log.field_every": (1, "an integer >= 1"),
        "log.positions_every": (1, "an integer >= 1"),
        "estimator.modes": (1, "an integer >= 1"),
    }
    for key, (low, allowed) in ints.items():
        value = _lookup(cfg, key)
        _check(isinstance(value, int) and value >= low, key, value, allowed)
    _check(cfg.grid.n <= 512, "grid.n", cfg.grid.n, "at most 512 (memory)")
    positive = (
        "grid.length",
        "kde.bandwidth",
        "sim.dt",
        "sim.t_final",
        "filter.r_scale",
        "filter.r_floor",
        "filter.initial_variance",
        "control.density_floor",
    )
    for key in positive:
        value = _lookup(cfg, key)
        _check(_finite(value) and value > 0, key, value, "a finite number > 0")
    non_negative = ("control.alpha", "dynamics.sigma", "filter.process_noise", "estimator.delta")
    for key in non_negative:
        value = _lookup(cfg, key)
        _check(_finite(value) and value >= 0, key, value, "a finite number >= 0")
    _check(_finite(cfg.estimator.omega), "estimator.omega", cfg.estimator.omega, "a finite number")
    length = cfg.grid.length
    _check(
        cfg.kde.bandwidth <= length,
        "kde.bandwidth",
        cfg.kde.bandwidth,
        f"at most the domain side {length}",
    )
    _check(
        cfg.sim.dt <= cfg.sim.t_final,
        "sim.dt",
        cfg.sim.dt,
        f"at most sim.t_final = {cfg.sim.t_final}",
    )
    steps = round(cfg.sim.t_final / cfg.sim.dt)
    _check(steps <= 10_000_000, "sim.t_final", cfg.sim.t_final, "at most 1e7 steps of sim.dt")
    # Euler-Maruyama with reflection: a noise step must be well inside the domain
    noise_step = math.sqrt(2 * cfg.dynamics.sigma * cfg.sim.dt)
    _check(
        noise_step <= length / 10,
        "sim.dt",
        cfg.sim.dt,
        f"small enough that sqrt(2 sigma dt) <= {length / 10} (domain / 10)",
    )
    grid = Grid.square(cfg.grid.n, length)
    for key in ("target", "init"):
        node = cfg[key]
        try:
            density = make_density(density_spec(node))
            p = density.on_grid(grid)
        except (ValueError, KeyError, TypeError) as err:
            raise ConfigError(key, dict(density_spec(node)), str(err)) from None
        _check(
            bool(np.isfinite(p).all()) and abs(grid.integrate(p) - 1.0) < 1e-9,
            key,
            density_spec(node),
            "a density that is finite and normalisable on the grid",
        )
        if isinstance(density, Box):
            _check(
                density.x1 <= length and density.y1 <= length,
                f"{key}.x1",
                density.x1,
                f"a box inside [0, {length}]^2",
            )
    target = make_density(density_spec(cfg.target))
    try:
        tgt = Target.from_density(grid, target)
    except ValueError as err:
        raise ConfigError("target", density_spec(cfg.target), str(err)) from None
    p0 = make_density(density_spec(cfg.init)).on_grid(grid)
    if cfg.control.law == "paper":
        bound = sampled_data_dt_bound(grid, cfg.control.alpha, float(np.max(p0 / tgt.p)))
        _check(
            cfg.sim.dt <= SAMPLED_DATA_FACTOR * bound,
            "sim.dt",
            cfg.sim.dt,
            f"at most {SAMPLED_DATA_FACTOR:g} x the sampled-data bound {bound:.3g} s "
            "for this alpha, grid and start (harness.control.sampled_data_dt_bound)",
        )


def check_overrides(argv: list[str], config_name: str) -> str | None:
    """Compose ``config_name`` with the command line's overrides and validate it.

    Returns the one-line error, or None when the config is allowed. Multirun
    command lines (``-m``) are left to each job, which validates its own config.
    """
    from pathlib import Path

    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from harness.config import register_configs

    if "-m" in argv or "--multirun" in argv:
        return None
    overrides = [a for a in argv if not a.startswith("-") and not a.startswith("hydra")]
    register_configs()
    conf_dir = Path(__file__).resolve().parents[1] / "conf"
    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            cfg = compose(config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        cause = err.__cause__ or err.__context__ or err
        key = getattr(cause, "full_key", None) or getattr(err, "full_key", None)
        first = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        value = next(
            (
                a.split("=", 1)[1]
                for a in overrides
                if key and a.split("=", 1)[0].lstrip("+~") == key
            ),
            None,
        )
        if key:
            return f"invalid config: {key}={value!r}: {first}"
        return f"invalid config: {first}"
    try:
        validate(cfg)
    except ConfigError as err:
        return str(err)
    return None
