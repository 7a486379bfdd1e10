"""Resource checks of a run before it starts: the memory it will need against what the
machine has, and the disk its log will need against the free space.

:func:`check_memory` runs in :func:`harness.runs.build.build`, before any array is
allocated; :func:`disk_need` is what the built observers say they will write, and
:func:`check_disk` compares it with the file system that will hold the log (when the
run starts, and before Hydra writes anything, in
:class:`harness.runs.app.CheckCallback`). A run that does not fit raises
:class:`~harness.runs.checks.ConfigError` naming the key that sizes it most.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra.utils
from omegaconf import DictConfig, OmegaConf

from harness.grid import Grid
from harness.loop import Experiment
from harness.observers.base import disk_bytes
from harness.protocols import default_memory, memory_estimate, robot_count
from harness.runs.checks import GROUPS, REFERENCE, ConfigError

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
    its YAML parameters, and ``free_space=True`` on a domain other than the square; a
    conservative default otherwise), the shared model (the
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
    obstacles = _has_obstacles(cfg)
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
        if obstacles:
            params["free_space"] = True
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


def _has_obstacles(cfg: DictConfig) -> bool:
    """Whether the run's domain may have obstacles: any domain but the plain square
    (:class:`harness.domains.square.Square`, also when ``domain`` is absent).
    """
    from harness.domains.square import Square

    target = OmegaConf.select(cfg, "domain._target_", default=None)
    if target is None:
        return False
    try:
        cls = hydra.utils.get_class(str(target))
    except Exception:  # not importable: the build refuses it
        return False
    return not (isinstance(cls, type) and issubclass(cls, Square))


def _public_key(cfg: DictConfig, group: str, name: str) -> str:
    node = cfg.get(group)
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else {}
    value = raw.get(name) if isinstance(raw, dict) else None
    match = REFERENCE.fullmatch(value.strip()) if isinstance(value, str) else None
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
    their ``disk_bytes(robots) -> (bytes, parameter)`` (:func:`harness.observers.base.disk_bytes`),
    naming the public key of the parameter of the largest (``log.positions_every`` when
    the robots' positions are most of the log).
    """
    robots = robot_count(exp.plant)
    parts = []
    for name, observer in exp.observers.items():
        estimate = disk_bytes(observer, robots)
        if estimate is not None:
            nbytes, param = estimate
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
