"""Build a run from a config: every component and observer from its YAML.

:func:`build` is one straight line: shared checks, grid, densities, model, control,
plant, estimator, the components' own compatibility checks, the step bound, the
observers and the run's settings. It reads the whole config once; nothing reads the
config after it (:class:`Experiment` holds everything a run needs). Each component is
instantiated from its config node (``_target_`` plus the class's own parameters) by
:func:`component`, which hands it its run-time arguments (see
:mod:`harness.protocols` and :mod:`harness.observers`) and turns a refused parameter
into a :class:`~harness.runs.checks.ConfigError` that names the full key.
"""

from __future__ import annotations

import functools
import inspect
import re
from pathlib import Path
from typing import Any

import hydra.utils
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from harness.domains.base import Domain
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.loop import Experiment
from harness.observers.base import Observer, at_cadence, gives, needs
from harness.parameters import Incompatible, ParameterError
from harness.plants.limit import Limit
from harness.plants.link import whole_steps
from harness.protocols import (
    SHARED_QUANTITIES,
    Control,
    Estimator,
    Plant,
    check_parts,
    copies,
    follows_moving_target,
    period,
)
from harness.runs.checks import (
    SHARED_BLOCKS,
    ConfigError,
    check_built,
    check_resolvable,
    check_shared,
    check_unread,
    density_on_grid,
    init_on_free_space,
    target_on_grid,
)
from harness.runs.declared import as_declared
from harness.runs.domain import check_free_space, check_reachable, free_space
from harness.runs.identity import RunIdentity, choices, chosen_observers, resolved
from harness.runs.resources import check_memory
from harness.targets.densities import Density, Target
from harness.targets.moving import check_path, moves

_INTERPOLATION = re.compile(r"^\$\{([A-Za-z_][\w.]*)\}$")


_UNEXPECTED = re.compile(r"unexpected keyword argument '(\w+)'")


_MISSING = re.compile(r"missing \d+ required (?:keyword-only |positional )?arguments?: (.+)$")


OBSERVER_OPTIONS = (Path(__file__).parents[1] / "conf" / "observers").resolve()
"""The options of the config group ``observers`` (``observers/`` in
:data:`harness.api.CONFIG_DIR`), read for the observers an option lists in its defaults
(``default``)."""


PROTOCOLS: dict[str, type] = {
    "domain": Domain,
    "target": Density,
    "init": Density,
    "plant": Plant,
    "estimator": Estimator,
    "control": Control,
    "observers": Observer,
}
"""The protocol each config group's component implements (``observers``: each entry)."""


def public_key(cfg: DictConfig, group: str, name: str) -> str:
    """The key to name for parameter ``name`` of ``group``: the key it interpolates
    (``plant.n: ${agents.n}`` gives ``agents.n``), else ``group.name``.
    """
    node = OmegaConf.select(cfg, group, default=None)
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    value = raw.get(name) if isinstance(raw, dict) else None
    match = _INTERPOLATION.match(value) if isinstance(value, str) else None
    return match.group(1) if match else f"{group}.{name}"


def public_keys(cfg: DictConfig, group: str) -> dict[str, str]:
    """:func:`public_key` of every parameter of ``group`` (one pass over its node)."""
    node = OmegaConf.select(cfg, group, default=None)
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    out = {}
    for name, value in raw.items() if isinstance(raw, dict) else ():
        match = _INTERPOLATION.match(value) if isinstance(value, str) else None
        out[str(name)] = match.group(1) if match else f"{group}.{name!s}"
    return out


def _first_line(err: BaseException) -> str:
    """``Type: first line of the message`` of an exception."""
    text = str(err).strip()
    return f"{type(err).__name__}: {text.splitlines()[0]}" if text else type(err).__name__


def members(protocol: type) -> list[str]:
    """The attributes and methods a protocol asks for (``__call__`` included)."""
    names = list(getattr(protocol, "__annotations__", {}))
    for name, value in vars(protocol).items():
        if callable(value) and (not name.startswith("_") or name == "__call__"):
            names.append(name)
    return names


def _nested(value: Any) -> bool:
    """Whether a resolved value holds a config Hydra must instantiate itself (a nested
    ``_target_`` or another of its ``_``-keys).
    """
    if isinstance(value, dict):
        return any(str(k).startswith("_") or _nested(v) for k, v in value.items())
    if isinstance(value, list):
        return any(_nested(v) for v in value)
    return False


def _equal(a: Any, b: Any) -> bool:
    """Whether ``a == b`` (False for values that cannot be compared so)."""
    try:
        return bool(a == b)
    except Exception:
        return False


TUNABLE = "tunable"
"""A component's declaration of what a benchmark may tune (its gains with their ranges,
:mod:`harness.benchmark.space`): logged with the config, never passed to the class."""


def _factory(plain: dict[str, Any]) -> Any:
    """``_target_`` with its parameters bound, from resolved values: Hydra's
    ``instantiate(..., _partial_=True)``, done directly when no parameter holds a nested
    config (Hydra wraps the values in OmegaConf nodes again, about 5 ms a component,
    which a test suite building thousands of configs pays many times over).

    Raises:
        InstantiationException: for a ``_target_`` that cannot be loaded.
    """
    params = {k: v for k, v in plain.items() if k not in ("_target_", TUNABLE)}
    if _nested(params):
        kept = {k: v for k, v in plain.items() if k != TUNABLE}
        return hydra.utils.instantiate(kept, _partial_=True, _convert_="all")
    try:
        target = hydra.utils.get_object(str(plain["_target_"]))
    except Exception as err:
        raise InstantiationException(str(err)) from err
    return functools.partial(target, **as_declared(target, params))


def component(
    cfg: DictConfig, group: str, values: dict[str, Any] | None = None, **runtime: Any
) -> Any:
    """Instantiate the component of ``group`` (a dotted path for an observer,
    ``observers.log``) with its run-time arguments, from ``values`` (the config
    resolved once, :func:`harness.runs.identity.resolved`) when given.

    Raises:
        ConfigError: for a missing or unloadable ``_target_``, a parameter the class
            does not take or lacks, a refused parameter (:class:`ParameterError`), or
            an object that does not implement the group's protocol.
    """
    node = OmegaConf.select(cfg, group, default=None)
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(group, node, "a component config with _target_ (see docs/extending.md)")
    plain: Any = values if values is not None else OmegaConf.to_container(node, resolve=True)
    for part in group.split(".") if values is not None else ():
        plain = plain[part]
    try:
        factory = _factory(plain)
    except InstantiationException as err:
        cause = err.__cause__ or err
        first = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
        raise ConfigError(f"{group}._target_", node.get("_target_"), first) from None
    target = node.get("_target_")
    try:
        obj = factory(**runtime)
    except ParameterError as err:
        given = plain.get(err.name, err.value) if isinstance(plain, dict) else err.value
        value = given if _equal(given, err.value) else err.value  # as written: -1, not -1.0
        raise ConfigError(public_key(cfg, group, err.name), value, err.allowed) from None
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
    protocol = PROTOCOLS[group.split(".")[0]]
    if not isinstance(obj, protocol):
        lacks = ", ".join(m for m in members(protocol) if not hasattr(obj, m))
        allowed = f"must implement {protocol.__name__} (missing: {lacks})"
        raise ConfigError(f"{group}._target_", target, allowed)
    return obj


def _named(factory_target: Any, runtime: dict[str, Any]) -> dict[str, Any]:
    """The run-time arguments an observer's constructor names (all of them when it takes
    ``**kwargs``).
    """
    try:
        params = inspect.signature(factory_target).parameters
    except (TypeError, ValueError):
        return runtime
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return runtime
    return {k: v for k, v in runtime.items() if k in params}


def observers(
    cfg: DictConfig, values: dict[str, Any] | None = None, **runtime: Any
) -> dict[str, Observer]:
    """The observers of ``cfg.observers``, in config order, each given the run-time
    arguments its constructor names (:mod:`harness.observers`).

    Raises:
        ConfigError: as :func:`component`, naming ``observers.<name>...``.
    """
    node = cfg.get("observers")
    if node is None:
        return {}
    if not isinstance(node, DictConfig):
        raise ConfigError("observers", node, "a dict of observers (conf/observers/)")
    _check_unique(cfg)
    out = {}
    for key in node.keys():
        name = str(key)
        group = f"observers.{name}"
        entry = node.get(name)
        if not isinstance(entry, DictConfig) or "_target_" not in entry:
            raise ConfigError(group, entry, "an observer config with _target_")
        try:
            target = hydra.utils.get_object(str(entry._target_))
        except Exception:
            target = None  # component() names the unloadable target
        out[name] = component(cfg, group, values, **_named(target, runtime))
    _check_needs(cfg, out)
    return out


def _check_needs(cfg: DictConfig, watching: dict[str, Observer]) -> None:
    """Every metric an observer needs at every step (:func:`harness.observers.base.needs`:
    the guard's ``required``, the logger's always-numbers) is given at every step by an
    observer before it (:func:`~harness.observers.base.gives`, less what it gives only at
    a cadence, :func:`~harness.observers.base.at_cadence`: ``swarm_l2`` with
    ``log.positions_every`` above 1); not checked past an observer that computes without
    saying what it gives.

    A metric needed at every step must be given at every step, rather than checked only
    on the steps its giver is due: a guard that skipped the steps without it would not
    guard them, and a log would carry nulls where its contract promises numbers.

    Raises:
        ConfigError: naming the parameter that names a metric no observer before gives at
            every step (``observers`` itself for the logger, whose place in the list is
            what to change).
    """
    every: set[str] = set()
    sometimes: dict[str, tuple[str, str]] = {}  # metric -> (observer, cadence parameter)
    names = list(watching)
    for name, observer in watching.items():
        for param, metrics in needs(observer).items():
            missing = [m for m in metrics if m not in every]
            if missing:
                raise _not_given(cfg, names, name, param, metrics, missing, sometimes)
        more = gives(observer)
        if more is None:
            return  # what follows may need what this one gives: not known here
        slow = at_cadence(observer)
        for metric in more:
            if metric in slow:
                sometimes.setdefault(metric, (name, slow[metric]))
            else:
                every.add(metric)


def _not_given(
    cfg: DictConfig,
    names: list[str],
    name: str,
    param: str | None,
    metrics: tuple[str, ...],
    missing: list[str],
    sometimes: dict[str, tuple[str, str]],
) -> ConfigError:
    """The refusal of :func:`_check_needs`: observer ``name`` needs ``missing`` (of
    ``metrics``, named by its parameter ``param``) at every step.
    """
    before = ", ".join(names[: names.index(name)]) or "none"
    why = []
    for metric in missing:
        if metric in sometimes:
            giver, cadence = sometimes[metric]
            key = public_key(cfg, f"observers.{giver}", cadence)
            value = OmegaConf.select(cfg, f"observers.{giver}.{cadence}", default="?")
            why.append(f"{giver} gives {metric} only every {value} steps, {key}={value}")
    absent = [m for m in missing if m not in sometimes]
    if absent:
        why.append(f"none gives {', '.join(absent)}")
    if param is None:
        return ConfigError(
            "observers",
            names,
            f"observers in which those before {name} ({before}) give at every step the "
            f"metrics {name} needs ({'; '.join(why)}; observers=[default] does)",
        )
    return ConfigError(
        public_key(cfg, f"observers.{name}", param),
        list(metrics),
        f"metrics that the observers before {name} ({before}) give at every step "
        f"({'; '.join(why)})",
    )


def _check_unique(cfg: DictConfig) -> None:
    """Each observer is named once in the observer list chosen (``observers=[...]`` on
    the command line, :func:`harness.api.compose` or a sweep's job), counting those an
    option of ``conf/observers/`` lists in its own defaults (``default``): Hydra merges an
    observer named twice into one, so the run would not be the list written.

    Raises:
        ConfigError: naming ``observers``, with the list as written.
    """
    chosen = chosen_observers(cfg)
    if chosen is None:
        return
    seen: dict[str, str] = {}
    for option in chosen:
        for observer in _expanded(option):
            if observer in seen:
                holds = {o for o in (seen[observer], option) if o != observer}
                raise ConfigError(
                    "observers",
                    chosen,
                    f"a list that names each observer once ({observer} comes twice"
                    + "".join(f"; {o} holds it" for o in sorted(holds))
                    + ")",
                )
            seen[observer] = option


def _expanded(option: str, depth: int = 0) -> list[str]:
    """The observers of ``option``: itself, or for an option of ``conf/observers/`` that
    lists others in its defaults (``default``), theirs.
    """
    path = OBSERVER_OPTIONS / f"{option}.yaml"
    try:
        node = OmegaConf.load(path) if path.is_file() else None
    except Exception:  # Hydra reports a file it cannot read
        node = None
    listed = node.get("defaults") if isinstance(node, DictConfig) else None
    inner = [d for d in listed or () if isinstance(d, str) and d != "_self_"]
    if not inner or depth >= 8:
        return [option]
    return [name for d in inner for name in _expanded(d, depth + 1)]


def resolve(cfg: DictConfig) -> dict[str, Any]:
    """The config resolved once (:func:`harness.runs.identity.resolved`), or the
    :class:`ConfigError` of :func:`harness.runs.checks.check_resolvable` naming the key that
    does not resolve (or the missing shared block).
    """
    if all(block in cfg for block in SHARED_BLOCKS):
        try:
            return resolved(cfg)
        except OmegaConfBaseException:
            pass
    check_resolvable(cfg)  # raises, naming the key
    return resolved(cfg)


def _refused(cfg: DictConfig, err: Incompatible) -> ConfigError:
    """``err`` as the config error a user reads: a config group's value is the option
    chosen in it (``control=svgd``), not the class it built; a key keeps its value.
    """
    return ConfigError(err.name, choices(cfg).get(err.name, err.value), err.allowed)


def _check_parts(cfg: DictConfig, plant: Plant, estimator: Estimator, control: Control) -> None:
    """Each component's own ``check`` of the others (:func:`harness.protocols.check_parts`),
    refused naming the config group and its option.
    """
    try:
        check_parts(plant, estimator, control)
    except Incompatible as err:
        raise _refused(cfg, err) from None


def _limit(
    cfg: DictConfig, plant: Plant, control: Control, grid: Grid, model: FokkerPlanck, init: Density
) -> Limit | None:
    """The loop's ``N -> infinity`` limit (:meth:`harness.plants.limit.Limit.of`), refused
    naming ``control`` and its option for a law it cannot follow.
    """
    try:
        return Limit.of(plant, control, grid, model, init)
    except Incompatible as err:
        raise _refused(cfg, err) from None


def _on_path(cfg: DictConfig, density: Density, grid: Grid) -> Density:
    """``density``, after its own check of its path on ``grid`` (a moving target's
    ``check(grid)``, :class:`harness.targets.moving.RotatingMixture`), refused naming the key.
    """
    try:
        check_path(density, grid)
    except ParameterError as err:
        raise ConfigError(public_key(cfg, "target", err.name), err.value, err.allowed) from None
    return density


COPY_TOLERANCE = 1e-9
"""Relative difference below which a component's copy of a shared quantity is that
quantity (the rounding of a decimal value written twice)."""


def _check_copies(cfg: DictConfig, parts: dict[str, Any]) -> None:
    """Each component's copy of a shared quantity (:func:`harness.protocols.copies`: the
    filters' ``robots``, a plant's ``dt``) equals the run's own (``agents.n``, ``sim.dt``).

    A copy is an interpolation (``robots: ${agents.n}``) in the component's YAML; an
    override of the copy alone would make the component compute with a number the rest of
    the run, and the log's shared keys, do not have (the filters' noise constants of 5
    robots for a swarm of 200, a link counting its period in steps of 0.04 s while the
    loop steps 0.02 s).

    Raises:
        ConfigError: naming the copy's key, for one that differs.
    """
    for group, part in parts.items():
        for param, (quantity, value) in copies(part).items():
            shared, unit, what = SHARED_QUANTITIES[quantity]
            truth = float(OmegaConf.select(cfg, shared))
            if abs(float(value) - truth) > COPY_TOLERANCE * max(abs(truth), 1.0):
                raise ConfigError(
                    public_key(cfg, group, param),
                    value,
                    f"{shared} = {truth:g}{unit}, {what}, of which {group}.{param} is a copy "
                    f"(set {shared} instead)",
                )


def _check_period(cfg: DictConfig, control: Control) -> None:
    """The period of a law that decides once per period (:func:`harness.protocols.period`)
    is a whole number of steps of ``sim.dt``, as ``link.period`` must be
    (:func:`harness.plants.link.whole_steps`); a law never rounds it.

    Raises:
        ConfigError: naming the law's ``period`` key.
    """
    every = period(control)
    if every is None:
        return
    try:
        whole_steps("period", every, float(cfg.sim.dt), 1)
    except ParameterError as err:
        raise ConfigError(public_key(cfg, "control", "period"), err.value, err.allowed) from None


def _check_follows(cfg: DictConfig, target: Target, control: Control) -> None:
    """Refuse a law that cannot follow a moving target
    (:func:`harness.protocols.follows_moving_target`) when the target moves.
    """
    if moves(target) and not follows_moving_target(control):
        raise ConfigError(
            "control",
            choices(cfg).get("control", type(control).__name__),
            "a law that follows a moving target p_*(t) (paper, heat, langevin) with target=moving",
        )


def build(cfg: DictConfig) -> Experiment:
    """Everything a run of ``cfg`` needs, checked; the only reader of the config
    (:func:`_build`). A refusal that names a config group by the object built from it
    (``target=GaussianMixture(...)``) names the option chosen instead (``target=three_bumps``).

    Raises:
        ConfigError: for the first value that is not allowed.
    """
    try:
        return _build(cfg)
    except ConfigError as err:
        option = choices(cfg).get(err.key)
        if option is not None and not isinstance(err.value, (str, int, float, list, tuple)):
            err.value = option
            err.args = (f"invalid config: {err.key}={option!r}: {err.allowed}",)
        raise


def _build(cfg: DictConfig) -> Experiment:
    """Everything a run of ``cfg`` needs, checked.

    In order: every interpolation resolves, every key is read by something, the
    shared blocks, the memory the run will need (estimated from the components'
    parameters before any of them allocates), the components, each component's own
    check of the others, the loop's ``N -> infinity`` limit, the step bound, each
    component's copies of the shared quantities (``agents.n``, ``sim.dt``), a periodic
    law's period in whole steps, the observers (each metric one needs given by one
    before it) and the run's identity.
    Building draws no random numbers (robots are placed by ``plant.start(rng)``),
    writes nothing and opens nothing (observers open files and ports when the run
    starts).

    Raises:
        ConfigError: for the first value that is not allowed.
    """
    data = resolve(cfg)
    check_unread(cfg)
    check_shared(cfg)
    grid = Grid.square(cfg.grid.n, cfg.grid.length)
    check_memory(cfg, grid)
    free = free_space(cfg, data, grid, component)
    target = target_on_grid(_on_path(cfg, component(cfg, "target", data), grid), grid, free)
    init = component(cfg, "init", data)
    init_cells = density_on_grid("init", init, grid)
    if free is not None:
        init_on_free_space(init, grid, free)
        check_reachable(free, target, init_cells)
    model = FokkerPlanck(grid, float(cfg.dynamics.sigma), free=free)
    control = component(cfg, "control", data, target=target)
    _check_follows(cfg, target, control)
    plant = component(cfg, "plant", data, grid=grid, model=model, init=init)
    estimator = component(cfg, "estimator", data, grid=grid, model=model)
    parts = {"plant": plant, "estimator": estimator, "control": control}
    check_free_space(cfg, free, target, parts)
    _check_parts(cfg, plant, estimator, control)
    limit = _limit(cfg, plant, control, grid, model, init)
    check_built(cfg, grid, target, control, plant, estimator)
    _check_copies(cfg, {"plant": plant, "estimator": estimator, "control": control})
    _check_period(cfg, control)
    steps = round(cfg.sim.t_final / cfg.sim.dt)
    identity = RunIdentity(data, int(cfg.seed), choices(cfg))
    watching = observers(
        cfg, data, grid=grid, target=target, control=control, plant=plant, limit=limit,
        estimator=estimator, steps=steps, identity=identity, init=init,
    )  # fmt: skip
    keys = {
        f"observers.{name}.{param}": key
        for name in watching
        for param, key in public_keys(cfg, f"observers.{name}").items()
    }
    return Experiment(
        grid, target, init, model, plant, limit, estimator, control,
        observers=watching,
        seed=int(cfg.seed),
        dt=float(cfg.sim.dt),
        steps=steps,
        identity=identity,
        keys=keys,
    )  # fmt: skip
