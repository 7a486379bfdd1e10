"""Config checks that no single component can make: the shared blocks and the
checks that span components.

Each component checks its own parameters when it is built (see
:mod:`harness.protocols`); :func:`harness.runs.build.build` calls :func:`check_shared`
before building and :func:`check_built` after. A refused value raises
:class:`ConfigError`, whose text is the one line the entry point prints (exit status 2).
"""

from __future__ import annotations

import math
import re
import shutil
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra.utils
import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from harness.control.field import sampled_data_dt_bound
from harness.estimators.kde import KDE
from harness.grid import Grid
from harness.loop import Experiment
from harness.parameters import ParameterError, flag, integer, number
from harness.protocols import Control, default_memory, memory_estimate, needs_robots, robot_count
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


GROUPS = ("plant", "estimator", "control", "target", "init", "observers")
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


LOGGED_BLOCKS = ("analysis",)
"""Optional blocks that nothing in a run reads and every run logs (in the ``config``
record): ``analysis``, a study preset's declaration of its analysis, which
:mod:`analysis.sweep` reads from the logs and checks. :func:`check_unread` accepts their
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


_REFERENCE = re.compile(r"\$\{\s*([A-Za-z_][\w.]*)\s*\}")


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
            referenced.update(_REFERENCE.findall(value))
        elif isinstance(value, list):
            referenced.update(_REFERENCE.findall(repr(value)))
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


UNLIMITED = 1 << 60
"""A memory limit at least this large (bytes) is no limit (cgroup v1 writes
``9223372036854771712`` for none)."""


def memory_available(root: Path = Path("/")) -> tuple[int, str] | None:
    """Bytes this process may still allocate, and where the figure comes from: the
    smallest of ``MemAvailable`` of ``/proc/meminfo``, the room left at every level of
    the process's cgroup (v2: ``memory.max - memory.current``; v1:
    ``memory.limit_in_bytes - memory.usage_in_bytes``; from its own group up to the
    root, so a limit set on a parent, as SLURM and systemd scopes do, counts) and the
    address space left under ``RLIMIT_AS``; None when none can be read.

    Args:
        root: The file system root to read ``/proc`` and ``/sys/fs/cgroup`` under
            (tests give a directory of their own).
    """
    found: list[tuple[int, str]] = []
    try:
        for line in (root / "proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append((int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"))
    except (OSError, ValueError, IndexError):
        pass
    found += _cgroup_room(root)
    if root == Path("/"):
        found += _rlimit_room(root)
    return min(found) if found else None


def _cgroup_room(root: Path) -> list[tuple[int, str]]:
    """``(bytes left, file)`` at every level of this process's cgroups that has a limit
    (v2 and v1 memory controllers).
    """
    try:
        lines = (root / "proc/self/cgroup").read_text().splitlines()
    except OSError:
        lines = []
    groups: list[tuple[Path, str, str]] = []  # (mount, limit file, usage file) per hierarchy
    paths: list[tuple[Path, str]] = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        if controllers == "":  # v2
            groups.append((root / "sys/fs/cgroup", "memory.max", "memory.current"))
            groups.append((root / "sys/fs/cgroup/unified", "memory.max", "memory.current"))
            paths += [(root / "sys/fs/cgroup", rel), (root / "sys/fs/cgroup/unified", rel)]
        elif "memory" in controllers.split(","):  # v1
            mount = root / "sys/fs/cgroup/memory"
            paths.append((mount, rel))
            groups.append((mount, "memory.limit_in_bytes", "memory.usage_in_bytes"))
    if not lines:  # no /proc/self/cgroup: the root groups only
        paths = [(root / "sys/fs/cgroup", "/"), (root / "sys/fs/cgroup/memory", "/")]
        groups = [
            (root / "sys/fs/cgroup", "memory.max", "memory.current"),
            (root / "sys/fs/cgroup/memory", "memory.limit_in_bytes", "memory.usage_in_bytes"),
        ]
    found: list[tuple[int, str]] = []
    seen: set[Path] = set()
    for mount, rel in paths:
        names = [(lim, use) for m, lim, use in groups if m == mount]
        level = mount / rel.strip("/")
        while True:
            for limit_name, usage_name in names:
                limit_file = level / limit_name
                if limit_file in seen:
                    continue
                seen.add(limit_file)
                try:
                    text = limit_file.read_text().strip()
                    if text == "max" or int(text) >= UNLIMITED:
                        continue
                    used = int((level / usage_name).read_text().strip())
                except (OSError, ValueError):
                    continue
                shown = "/" / limit_file.relative_to(root)
                found.append((int(text) - used, f"the cgroup limit {shown}"))
            if level == mount or mount not in level.parents:
                break
            level = level.parent
    return found


def _rlimit_room(root: Path) -> list[tuple[int, str]]:
    """The address space left under ``RLIMIT_AS`` (its soft limit minus ``VmSize``)."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, OSError, ValueError):
        return []
    if soft == resource.RLIM_INFINITY or soft >= UNLIMITED:
        return []
    used = 0
    try:
        for line in (root / "proc/self/status").read_text().splitlines():
            if line.startswith("VmSize:"):
                used = int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return [(soft - used, "RLIMIT_AS, the address space ulimit -v allows")]


def _size(nbytes: float) -> str:
    """``nbytes`` in human units (decimal: kB, MB, GB, TB)."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if nbytes >= scale:
            return f"{nbytes / scale:.3g} {unit}"
    return f"{nbytes:.0f} B"


PROCESS_BYTES = 256 << 20
"""The process before its arrays: the interpreter, its libraries and the compiled kernels
(about 180 MiB of peak resident memory after building a small loop, measured)."""


def check_memory(cfg: DictConfig, grid: Grid, available: tuple[int, str] | None = None) -> int:
    """Estimate the memory of the run before building it, and refuse it above what the
    machine has (:func:`memory_available`, or ``available`` when given).

    The estimate is the sum of the components' own
    (:func:`harness.protocols.memory_estimate`: ``memory_estimate`` on the class, from
    its YAML parameters; a conservative default otherwise), the shared model (the
    Fokker-Planck operator and its LU factorisation, the logger's buffers) and
    :data:`PROCESS_BYTES`, the process itself.

    Returns:
        The estimate (bytes).

    Raises:
        ConfigError: naming the parameter of the largest component, with the estimate
            and what is available in the message.
    """
    parts: list[tuple[int, str]] = [
        (default_memory(grid).nbytes + (8 << 20) + PROCESS_BYTES, "grid.n")
    ]
    for group in GROUPS:
        node = cfg.get(group)
        if not isinstance(node, DictConfig) or "_target_" not in node:
            continue
        try:
            cls = hydra.utils.get_class(str(node._target_))
        except Exception:  # not a class (a factory function) or not importable: built later
            cls = object
        resolved = OmegaConf.to_container(node, resolve=True)
        params = {str(k): v for k, v in resolved.items()} if isinstance(resolved, dict) else {}
        params.pop("_target_", None)
        try:
            estimate = memory_estimate(cls, grid, params)
        except Exception:  # a bad parameter is refused when the component is built
            estimate = default_memory(grid)
        key = _public_key(cfg, group, estimate.parameter) if estimate.parameter else "grid.n"
        parts.append((estimate.nbytes, key))
    total = sum(b for b, _ in parts)
    have = memory_available() if available is None else available
    if have is not None and total > have[0]:
        nbytes, key = max(parts)
        value = OmegaConf.select(cfg, key, default=None)
        raise ConfigError(
            key,
            value,
            f"the run needs about {_size(total)} of memory ({_size(nbytes)} for this), "
            f"more than the {_size(have[0])} available ({have[1]})",
        )
    return total


def _public_key(cfg: DictConfig, group: str, name: str) -> str:
    node = cfg.get(group)
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    value = raw.get(name) if isinstance(raw, dict) else None
    match = _REFERENCE.fullmatch(value.strip()) if isinstance(value, str) else None
    return match.group(1) if match else f"{group}.{name}"


@dataclass(frozen=True)
class DiskNeed:
    """The size (bytes) the run's files will need, the run's steps, and the key to name
    when they do not fit (``key=value``).
    """

    nbytes: int
    key: str
    value: Any
    steps: int


def disk_need(exp: Experiment) -> DiskNeed:
    """What the observers of ``exp`` that write files say they will write: the sum of
    their ``disk_bytes(robots) -> (bytes, parameter)``, naming the public key of the
    parameter of the largest (``log.positions_every`` when the robots' positions are
    most of the log).
    """
    robots = robot_count(exp.plant)
    parts = []
    for name, observer in exp.observers.items():
        estimate = getattr(observer, "disk_bytes", None)
        if estimate is not None:
            nbytes, param = estimate(robots)
            parts.append((nbytes, name, param, getattr(observer, param, None)))
    if not parts:
        return DiskNeed(0, "observers", None, exp.steps)
    _, name, param, value = max(parts)
    key = exp.keys.get(f"observers.{name}.{param}", f"observers.{name}.{param}")
    return DiskNeed(sum(p[0] for p in parts), key, value, exp.steps)


def check_disk(need: DiskNeed, out_dir: Path) -> int:
    """Refuse a run whose log (:func:`disk_need`) is larger than the free space of the
    file system that will hold ``out_dir``.

    Returns:
        The estimate (bytes).

    Raises:
        ConfigError: naming the key of ``need``, with the estimate and the free space.
    """
    existing = Path(out_dir).absolute()
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    try:
        free = shutil.disk_usage(existing).free
    except OSError:
        return need.nbytes
    if need.nbytes > free:
        raise ConfigError(
            need.key,
            need.value,
            f"the log would need about {_size(need.nbytes)} ({need.steps} steps, "
            f"uncompressed) and {existing} has {_size(free)} free; log less often or "
            "shorten sim.t_final",
        )
    return need.nbytes


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
    bound = sampled_data_dt_bound(grid, float(diffusivity), h, cfg.dynamics.sigma)
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
