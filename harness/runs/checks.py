"""Config checks that no single component can make: the shared blocks and the
checks that span components.

Each component checks its own parameters when it is built (see
:mod:`harness.protocols`); :func:`harness.runs.build.build` calls :func:`check_shared`
before building and :func:`check_built` after; the memory and disk a run needs are
checked in :mod:`harness.runs.resources`. A refused value raises :class:`ConfigError`,
whose text is the one line the entry point prints (exit status 2).
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from harness.control.field import sampled_data_dt_bound
from harness.domains.base import FreeSpace
from harness.estimators.kde import KDE
from harness.grid import Grid
from harness.parameters import ParameterError, flag, integer, number
from harness.protocols import Control, needs_robots
from harness.targets.densities import Density, Target

MAX_STEPS = 10_000_000
"""Largest number of steps ``sim.t_final / sim.dt`` of one run."""


MIN_BANDWIDTH_CELLS = 0.1
"""``kde.bandwidth`` is at least this fraction of the cell size: a kernel much narrower
than a cell is sampled only at cell centres, so its grid integral is no longer 1 and
its noise constants ``k ~ 1 / h^2``, ``k_g ~ 1 / h^4`` overflow for tiny ``h``."""


STEP_TOLERANCE = 1e-6
"""``sim.t_final / sim.dt`` may differ from a whole number by this much (in steps: the
rounding of decimal fractions such as 0.06 / 0.02, never a part of a step)."""


SHARED_BLOCKS = ("grid", "agents", "dynamics", "sim", "kde", "log")
"""Config blocks every run needs."""


GROUPS = ("plant", "estimator", "control", "target", "init", "observers", "domain")
"""Config groups whose node is one component (``_target_`` and its parameters), or a
dict of them (``observers``)."""


SHARED_KEYS = frozenset(
    {
        "seed",
        "grid.n",
        "grid.length",
        "agents.n",
        "dynamics.sigma",
        "sim.dt",
        "sim.t_final",
        "kde.bandwidth",
        "kde.mirror",
        "kde.method",
        "kde.debias",
        "log.field_every",
        "log.positions_every",
        "log.w2_every",
        "log.floor_draws",
        "log.floor_cache",
        "log.progress",
        "log.live",
        "log.live_host",
        "log.live_port",
    }
)
"""Keys of the shared blocks that the harness reads itself, and the ``log`` block the
observers read (allowed also when a config leaves an observer out); any other key
outside the component nodes must be read by a component through interpolation
(:func:`check_unread`)."""


DEFAULT_UNREAD = {
    "agents.localisation_noise": 0.0,
    "link.period": None,
    "link.latency": 0.0,
    "link.loss": 0.0,
}
"""Keys of the shared blocks that a component may leave unread at these values (a
feature left off, such as a plant of one's own without localisation error); set to
anything else, nothing reading them is refused like any unread key."""


LOGGED_BLOCKS = ("analysis", "scenario", "point")
"""Optional blocks that nothing in a run reads and every run logs (in the ``config``
record): ``analysis``, a study preset's declaration of its analysis, which
:mod:`analysis.sweep` reads from the logs and checks; ``scenario``, a benchmark
scenario's description (``conf/scenario/``); ``point``, what a benchmark's run is
for (its role and trial, :mod:`harness.benchmark`). :func:`check_unread` accepts their
keys; they are part of the config hash (:func:`harness.runs.identity.config_hash`), since
they are logged."""


PRESENTATION_KEYS = (
    "log.progress",
    "log.live",
    "log.live_host",
    "log.live_port",
    "log.floor_cache",
    "observers.progress",
    "observers.live",
    "observers.swarm.floor_cache",
)
"""Keys (and observers) that change how a run is shown, or where it keeps the finite-N
floors it reuses (:mod:`harness.observers.floor_cache`; only the ``theory`` record's
``swarm_floor_source`` says whether they were computed or read), not what it computes
or logs (left out of the config hash, :func:`harness.runs.identity.config_hash`)."""


REFERENCE = re.compile(r"\$\{\s*([A-Za-z_][\w.]*)\s*\}")
"""An interpolation of one key, ``${a.b}`` (group 1: the key ``a.b``)."""


class ConfigError(ValueError):
    """A config value that is not allowed; ``str()`` is the one-line message."""

    def __init__(self, key: str, value: Any, allowed: str) -> None:
        self.key, self.value, self.allowed = key, value, allowed
        super().__init__(f"invalid config: {key}={value!r}: {allowed}")


def config_line(err: ConfigError) -> str:
    """The one line to print for ``err``: its text, completed by the reason of the error
    it was made from when its text stops at a colon (``Error loading 'pkg.Law':``, whose
    reason, such as the missing module, is on the cause's next lines).
    """
    text = str(err)
    cause = err.__context__
    while text.endswith(":") and cause is not None:
        lines = [ln.strip() for ln in str(cause).strip().splitlines() if ln.strip()]
        if len(lines) > 1:
            return f"{text} {lines[1]}"
        cause = cause.__cause__ or cause.__context__
    return text


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
    """The shared blocks: ``seed``, ``grid``, ``agents``, ``dynamics``, ``sim``, ``kde``
    (types and ranges), and the time step against the horizon and the domain. (The
    ``log`` block's values are the observers' parameters, checked when they are built.)
    """
    _shared("seed", integer, cfg.get("seed"), 0)
    grid, sim, kde = (_block(cfg, b) for b in ("grid", "sim", "kde"))
    _block(cfg, "log")  # read by the observers, which check their own values
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
    cell = length / n
    if h < cell * MIN_BANDWIDTH_CELLS:
        raise ConfigError(
            "kde.bandwidth",
            h,
            f"at least {MIN_BANDWIDTH_CELLS:g} x the cell size {cell:.3g} = "
            f"{cell * MIN_BANDWIDTH_CELLS:.3g} (a narrower kernel falls between cell centres)",
        )
    _shared("kde.mirror", flag, kde.get("mirror"))
    _shared("kde.debias", flag, kde.get("debias"))
    if kde.get("method") not in KDE.METHODS:
        raise ConfigError("kde.method", kde.get("method"), f"one of {', '.join(KDE.METHODS)}")
    if dt > t_final:
        raise ConfigError("sim.dt", dt, f"at most sim.t_final = {t_final}")
    if t_final / dt > MAX_STEPS:
        raise ConfigError("sim.t_final", t_final, f"at most {MAX_STEPS:.0e} steps of sim.dt")
    steps = t_final / dt
    if abs(steps - round(steps)) > STEP_TOLERANCE:
        below, above = math.floor(steps) * dt, math.ceil(steps) * dt
        raise ConfigError(
            "sim.t_final",
            t_final,
            f"a whole number of steps of sim.dt = {dt:g} s (it is {steps:.6g} steps; "
            f"{below:.6g} or {above:.6g} s would end exactly there)",
        )
    # Euler-Maruyama with reflection: a noise step must be well inside the domain
    if math.sqrt(2 * sigma * dt) > length / 10:
        raise ConfigError(
            "sim.dt", dt, f"small enough that sqrt(2 sigma dt) <= {length / 10} (domain / 10)"
        )


def _leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``(dotted key, raw value)`` of every leaf below ``node`` (lists are leaves)."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, f"{prefix}{key}.")
    else:
        yield prefix.rstrip("."), node


def check_resolvable(cfg: DictConfig) -> None:
    """Every interpolation of the config (outside ``hydra``) resolves.

    Raises:
        ConfigError: naming the first key whose value does not resolve, its raw value
            and OmegaConf's reason (a missing key, a deleted block, a bad resolver); a
            deleted shared block (``~sim``) is named itself.
    """
    for block in SHARED_BLOCKS:
        if block not in cfg:
            raise ConfigError(block, None, "a required config block")
    for name in cfg:
        if name == "hydra":
            continue
        try:
            node = cfg._get_node(name)
            if isinstance(node, (DictConfig, ListConfig)):
                OmegaConf.to_container(node, resolve=True, throw_on_missing=True)
            else:
                cfg[name]
        except OmegaConfBaseException as err:
            key = str(getattr(err, "full_key", "") or name)
            raw: Any = OmegaConf.to_container(cfg, resolve=False)
            try:
                for part in key.split("."):
                    raw = raw[part] if isinstance(raw, dict) else raw[int(part)]
            except (KeyError, ValueError, IndexError, TypeError):
                raw = None
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise ConfigError(key, raw, f"must resolve ({first})") from None


def check_unread(cfg: DictConfig) -> None:
    """Every key outside the component nodes is read: by the harness itself
    (:data:`SHARED_KEYS`), by a component through an interpolation such as
    ``${filter.process_noise}``, or by the analysis from the log (the keys of
    :data:`LOGGED_BLOCKS`). (A key inside a component node that its class does not take
    is refused when the component is built.)

    Raises:
        ConfigError: for a key nothing reads (``+grid.foo=1``, ``+foo=1``).
    """
    raw = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(raw, dict)
    raw.pop("hydra", None)
    referenced = set()
    for _, value in _leaves(raw):
        if isinstance(value, str):
            referenced.update(REFERENCE.findall(value))
        elif isinstance(value, list):
            referenced.update(REFERENCE.findall(repr(value)))
    outside = {k: v for k, v in raw.items() if k not in GROUPS and k not in LOGGED_BLOCKS}
    for key, value in _leaves(outside):
        if key in SHARED_KEYS or key in referenced:
            continue
        if key in DEFAULT_UNREAD and value == DEFAULT_UNREAD[key]:
            continue  # a plant of one's own need not read a feature left off
        if any(key.startswith(r + ".") for r in referenced):
            continue
        raise ConfigError(
            key, value, "a key nothing reads (no component or shared block has this parameter)"
        )


def density_on_grid(key: str, density: Density, grid: Grid) -> np.ndarray:
    """``density`` on ``grid``, refused unless finite and of unit mass, and when its
    ``on_grid`` refuses the grid (a ``ValueError``: a box outside the domain, say).
    """
    try:
        p = density.on_grid(grid)
    except (ValueError, TypeError) as err:
        name, _, why = str(err).partition(": ")
        if why and name.isidentifier() and hasattr(density, name):  # a parameter's refusal
            raise ConfigError(f"{key}.{name}", getattr(density, name), why) from None
        raise ConfigError(key, density, str(err)) from None
    require_density = bool(np.isfinite(p).all()) and abs(grid.integrate(p) - 1.0) < 1e-9
    if not require_density:
        raise ConfigError(key, density, "a density that is finite and normalisable on the grid")
    return p


MIN_FREE_SHARE = 1e-3
"""Least share of a target's or an initial density's mass that must lie in free space
(dimensionless). Below it the density is, in all but round-off, inside obstacles:
restricting it to free space would renormalise its tails into another density, and the
robots' rejection sampler would need ``N / share`` draws."""


def _free_share(p: np.ndarray, grid: Grid, free: np.ndarray) -> float:
    """The share of the mass of ``p`` (on ``grid``) on the cells where ``free`` holds."""
    total = grid.integrate(p)
    return float(grid.integrate(np.where(free, p, 0.0)) / total) if total > 0 else 0.0


def target_on_grid(density: Density, grid: Grid, free: FreeSpace | None = None) -> Target:
    """The target on the grid, restricted to ``free`` when given; refused unless
    strictly positive there (on free space: at least :data:`MIN_FREE_SHARE` of its
    mass there).
    """
    p = density_on_grid("target", density, grid)
    if free is not None and not (share := _free_share(p, grid, free.cells)) >= MIN_FREE_SHARE:
        raise ConfigError(
            "target",
            density,
            f"a target with at least {MIN_FREE_SHARE:g} of its mass in free space "
            f"(it puts {share:.3g} there)",
        )
    try:
        return Target.from_density(grid, density, free)
    except ValueError as err:
        raise ConfigError("target", density, str(err)) from None


def init_on_free_space(density: Density, grid: Grid, free: FreeSpace) -> None:
    """Refuse an initial density with less than :data:`MIN_FREE_SHARE` of its mass on
    the free cells of ``free`` (where the mean field starts) or on the free squares of
    its raster (where the robots start: the density at the squares' centres).
    """
    p = density_on_grid("init", density, grid)
    share = _free_share(p, grid, free.cells)
    if share >= MIN_FREE_SHARE:
        r = free.raster.shape[0]
        squares = Grid(r, r, grid.x0, grid.x1, grid.y0, grid.y1)
        share = _free_share(density.on_grid(squares), squares, free.raster == 0)
    if not share >= MIN_FREE_SHARE:
        raise ConfigError(
            "init",
            density,
            f"an initial density with at least {MIN_FREE_SHARE:g} of its mass in free space "
            f"(it puts {share:.3g} there)",
        )


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
    """The check across components that none can make alone: the sampled-data step bound
    (:func:`harness.control.field.sampled_data_dt_bound`) of the control law near the target,
    for the resolution of the estimates the plant and estimator give (:func:`resolution`).

    Near ``p_*`` the feedback diffusivity is the law's at ``p = p_*`` (``alpha`` for the
    paper's law); a ``dt`` above the bound there makes the loop unstable on some grid
    mode and is refused. (Far from the target, at the start, the diffusivity can be
    larger, ``alpha max(p_0 / p_*)``; an overshoot there is transient and not refused.)
    A law that smooths at a scale of its own (a ``resolution`` attribute, length: the
    kernel laws of :mod:`harness.control.kernels`, which read positions, not estimates) is
    bounded at that scale. A law without :meth:`~harness.protocols.Control.feedback_diffusivity`
    (or returning None) is not refused; a :class:`ConfigWarning` says the bound was not
    checked, except for a law without a mean-field form (``needs_robots``), whose robots
    steer to waypoints rather than follow a feedback field, and have no such bound.
    """
    if needs_robots(control):
        return
    rate = getattr(control, "feedback_diffusivity", None)
    diffusivity = rate(target.p) if rate is not None else None
    if diffusivity is not None and not (
        isinstance(diffusivity, (int, float, np.floating, np.integer))
        and math.isfinite(float(diffusivity))
        and float(diffusivity) >= 0
    ):
        raise ConfigError(
            "control",
            type(control).__name__,
            f"a law whose feedback_diffusivity near the target is a finite number >= 0 "
            f"(it gives {diffusivity!r}: the sampled-data step bound cannot be checked)",
        )
    if diffusivity is None:
        warnings.warn(
            f"{type(control).__name__} gives no feedback diffusivity: the sampled-data "
            "step bound of sim.dt is not checked",
            ConfigWarning,
            stacklevel=2,
        )
        return
    own = getattr(control, "resolution", None)
    h = own if isinstance(own, float) else resolution(plant, estimator)
    bound = sampled_data_dt_bound(grid, float(diffusivity), h, cfg.dynamics.sigma, target.free)
    if cfg.sim.dt > bound:
        scale = "grid resolution" if h is None else f"resolution {h:g}"
        raise ConfigError(
            "sim.dt",
            cfg.sim.dt,
            f"at most the sampled-data bound {bound:.3g} s for this control near the "
            f"target, grid and estimates of {scale} (harness.control.field.sampled_data_dt_bound)",
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
