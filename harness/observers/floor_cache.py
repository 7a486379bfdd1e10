"""A content-keyed store of the finite-N floors, so each is computed once per content.

The floors of ``swarm_l2`` and ``swarm_w2`` (:meth:`harness.observers.swarm.SwarmTruth.floors`,
:func:`harness.observers.swarm_metrics.floors`) are ``D`` Monte-Carlo draws of ``N`` robots from
``p_*``, each evaluated with the run's KDE and an optimal transport: about 9 s at
``N = 4096`` on the 30 x 30 grid, 50 s at 64 x 64. They depend only on

* the target: its continuous density, which the draws sample (:func:`describe_density`),
  and its cell values ``p_*``;
* the grid (cells and bounds), ``N``, the KDE's settings (``h``, wall images, method,
  ``bin_factor``, ``exact_max_robots`` and the binning nodes they give) and ``K_h p_*``;
* the target measure of the transport (method, refinement, its grid, its atoms and
  masses), the EMD threshold and the sliced distance's directions;
* on a domain with obstacles, free space: its cells, faces and the robots' raster
  (:func:`free_inputs`; absent on the square, whose keys do not change);
* the draws ``D`` and the seed stream (``numpy.random.default_rng([seed, 2])``, PCG64);
* the code: :data:`FLOOR_VERSION` and the versions of numpy, scipy, POT and numba.

:func:`floor_inputs` writes these down as plain JSON values (arrays as SHA-256 digests of
their bytes); the key is ``SHA-256(canonical JSON of the inputs)`` (:func:`floor_key`:
sorted keys, no spaces, floats as their shortest round-trip ``repr``). A target whose
density has no faithful description (any class other than the project's own
:class:`~harness.targets.densities.Uniform`, :class:`~harness.targets.densities.Box` and
:class:`~harness.targets.densities.GaussianMixture`, whose sampling code :data:`FLOOR_VERSION`
covers) gets no key and is never cached.

:class:`FloorCache` keeps one file ``<key>.json`` per key in a directory::

    {"key": KEY, "inputs": {...}, "floors": {"swarm_l2_floor_mean": "0.0712...", ...},
     "checksum": SHA-256(canonical JSON of "floors")}

with the floors as the ``theory`` record's strings (``repr`` of each float), so a floor
read back is bit-identical to the one computed. A file is written whole or not at all
(a temporary file in the same directory, ``fsync``, ``os.replace``), so jobs that
compute the same floor at once both succeed and leave one whole file; it replaces
only a regular file (a FIFO, a device, a directory or a symbolic link at its name is
left alone and never written into). A file is read through :mod:`harness.files`: only
a regular file, opened without blocking, at most :data:`RECORD_BYTES`. It is used only
when it parses, its inputs equal the requested ones, its key is theirs, the checksum
matches its floors and the floors are what the computation gives (:func:`floor_problem`:
the keys of :data:`FLOOR_KEYS`, finite numbers ``>= 0`` in their shortest round-trip
form, each band ordered ``lo <= mean <= hi``, the requested draws and transport
method); otherwise a :class:`FloorCacheWarning`
says why, and the floors are computed and the file rewritten. Floors that are not what
the computation gives are never stored. A file or directory that cannot be read or
written costs a warning and the computation, never the run. JSON only, never a
deserialiser that runs code.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib.metadata
import json
import math
import os
import stat
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from harness.domains.base import FreeSpace
from harness.estimators.kde import KDE
from harness.files import UnreadableFile, read_bytes
from harness.grid import Grid
from harness.targets.densities import Box, GaussianMixture, Target, Uniform

FLOOR_VERSION = 1
"""Version of the floors' computation. Bump it whenever a change of code changes the
floors for the same inputs (:func:`harness.observers.swarm_metrics.floors`, the KDE, the
transport, the sampling of the densities of :data:`DESCRIBED`, the target measure,
:meth:`harness.observers.swarm.SwarmTruth.floors`): every stored floor is then recomputed once."""


FREE_SAMPLING = 1
"""Version of the draws on free space (:class:`harness.observers.swarm_metrics.FreeSampler`,
:func:`harness.observers.swarm_metrics.free_target_measure`), part of the inputs of a
floor on a domain with obstacles only, so the square's keys do not change with it."""


DESCRIBED = (Uniform, Box, GaussianMixture)
"""The density classes with a faithful content description: frozen dataclasses whose
fields are their parameters and whose sampling code is the project's own (covered by
:data:`FLOOR_VERSION`). Subclasses are not included: they may sample differently."""


PACKAGES = ("numpy", "scipy", "pot", "numba")
"""Packages whose code the floors run (their versions are part of the key)."""


SOURCES = ("computed", "cache")
"""Values of the ``theory`` record's ``swarm_floor_source``."""


BANDS = ("swarm_l2", "swarm_w2")
"""The distances whose floors are stored (:func:`harness.observers.swarm_metrics.floors`)."""


BAND_NUMBERS = ("mean", "lo", "hi")
"""The numbers of a floor's band (:class:`harness.observers.swarm_metrics.Band`): the
mean and the 2.5 and 97.5 percentiles of a distance, each finite and ``>= 0``, with
``lo <= mean <= hi``."""


FLOOR_KEYS = frozenset(
    {"swarm_w2_method"}
    | {f"{band}_floor_{field}" for band in BANDS for field in (*BAND_NUMBERS, "draws")}
)
"""The keys of a stored record's floors: the transport method, and for each distance
its band and its number of draws."""


RECORD_BYTES = 1 << 20
"""Largest cache file read (bytes); a record is about 2 kB. A larger file is never
loaded: it costs a warning and the computation."""


class FloorCacheWarning(UserWarning):
    """A stored floor that is not trusted, or a cache directory that cannot be used."""


def canonical(data: Any) -> str:
    """Canonical JSON of plain values: sorted keys, no spaces, floats as ``repr``.

    Raises:
        ValueError: for a value JSON cannot hold exactly (NaN, infinity, other types).
    """
    return json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=False)


def digest(text: str) -> str:
    """SHA-256 (hex) of ``text`` encoded as UTF-8."""
    return hashlib.sha256(text.encode()).hexdigest()


def array_digest(a: np.ndarray) -> str:
    """SHA-256 (hex) of an array's dtype, shape and C-ordered bytes."""
    a = np.ascontiguousarray(a)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def _plain(value: Any) -> Any:
    """``value`` as plain JSON values (tuples as lists); None when it has no exact form."""
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, list | tuple):
        items = [_plain(v) for v in value]
        return None if any(i is None for i in items) else items
    return None


def describe_density(density: object) -> dict[str, Any] | None:
    """A faithful description of a density's content: its class and parameters.

    ``{"class": "harness.targets.densities.GaussianMixture", "params": {"means": [[0.3, 0.3],
    ...], "stds": [...], "weights": [...], "floor": 0.2}}`` for a density of exactly one
    of the classes :data:`DESCRIBED` (the dataclass fields that its constructor takes,
    after its own checks); None for any other density, or a parameter without an exact
    JSON form.
    """
    cls = type(density)
    if cls not in DESCRIBED or not dataclasses.is_dataclass(density):
        return None
    params = {}
    for f in dataclasses.fields(density):
        if not f.init:
            continue
        value = _plain(getattr(density, f.name))
        if value is None:
            return None
        params[f.name] = value
    return {"class": f"{cls.__module__}.{cls.__qualname__}", "params": params}


def package_versions() -> dict[str, str]:
    """The installed versions of :data:`PACKAGES` (``"not installed"`` when absent)."""
    out = {}
    for name in PACKAGES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def grid_inputs(grid: Grid) -> dict[str, Any]:
    """Cells and bounds of a grid (length)."""
    return {
        "nx": grid.nx,
        "ny": grid.ny,
        "x0": float(grid.x0),
        "x1": float(grid.x1),
        "y0": float(grid.y0),
        "y1": float(grid.y1),
    }


def floor_inputs(
    *,
    target: Target,
    grid: Grid,
    kde: KDE,
    smoothed_target: np.ndarray,
    measure: dict[str, Any],
    n_robots: int,
    draws: int,
    seed: list[int],
) -> dict[str, Any] | None:
    """Everything the floors depend on, as plain JSON values (see the module docstring).

    Args:
        target: ``p_*`` (its density and cell values).
        grid: The simulation grid.
        kde: The KDE the floors evaluate ``swarm_l2`` with.
        smoothed_target: ``K_h p_*`` on the grid (1 / length^2).
        measure: The target measure of ``swarm_w2`` and the transport's settings, as
            plain values (:meth:`harness.observers.swarm.SwarmTruth.measure_inputs`).
        n_robots: ``N``.
        draws: Monte-Carlo draws ``D``.
        seed: The entropy of the floors' ``SeedSequence`` (``[seed, 2]``).

    Returns:
        The inputs, or None when the target has no faithful description
        (:func:`describe_density`): such floors are not cached. On a domain with
        obstacles (``target.free``) the floors draw from the target's cell values
        (:class:`harness.observers.swarm_metrics.FreeSampler`), so its density need not
        be described, and the inputs also hold free space (:func:`free_inputs`).
    """
    density = describe_density(target.density)
    if density is None and target.free is None:
        return None
    inputs: dict[str, Any] = {
        "version": FLOOR_VERSION,
        "packages": package_versions(),
        "target": {
            "density": density,
            "p_sha256": array_digest(target.p),
            "grid": grid_inputs(target.grid),
        },
        "grid": grid_inputs(grid),
        "n_robots": int(n_robots),
        "kde": {
            "bandwidth": float(kde.bandwidth),
            "mirror": bool(kde.mirror),
            "method": str(kde.method),
            "bin_factor": int(kde.bin_factor),
            "exact_max_robots": int(kde.exact_max_robots),
            "bins": [int(b) for b in kde.bins],
            "smoothed_target_sha256": array_digest(smoothed_target),
        },
        "measure": measure,
        "draws": int(draws),
        "seed": {"entropy": [int(s) for s in seed], "bit_generator": "PCG64"},
    }
    if target.free is not None:
        inputs["free"] = free_inputs(target.free)
    return inputs


def free_inputs(free: FreeSpace) -> dict[str, Any]:
    """Free space as the floors see it: the SHA-256 of its free cells, open faces and
    the robots' raster (which the draws reject against), the raster's size, and the
    version of the free-space sampling (:data:`FREE_SAMPLING`).
    """
    return {
        "sampling": FREE_SAMPLING,
        "cells_sha256": array_digest(free.cells.astype(np.uint8)),
        "face_x_sha256": array_digest(free.face_x.astype(np.uint8)),
        "face_y_sha256": array_digest(free.face_y.astype(np.uint8)),
        "raster_sha256": array_digest(free.raster.astype(np.uint8)),
        "raster": [int(n) for n in free.raster.shape],
    }


def floor_key(inputs: dict[str, Any]) -> str:
    """The key of a floor: SHA-256 (hex) of the canonical JSON of its inputs."""
    return digest(canonical(inputs))


class FloorCache:
    """Floors stored by content in ``directory``, one JSON file per key.

    Args:
        directory: Where the files live (``~`` expanded; created on the first write).
    """

    def __init__(self, directory: str | os.PathLike[str]) -> None:
        self.directory = Path(directory).expanduser()

    def path(self, key: str) -> Path:
        """The file of ``key``."""
        return self.directory / f"{key}.json"

    def get(self, inputs: dict[str, Any]) -> dict[str, str] | None:
        """The stored floors of ``inputs``, or None when there are none to trust.

        A missing file (or directory) is a plain miss. A file that is not a regular
        file or is larger than :data:`RECORD_BYTES` (neither is read), that does
        not parse, holds other inputs or another key, whose checksum does not match its
        floors, or whose floors are not what the computation gives
        (:func:`floor_problem`), is ignored with a :class:`FloorCacheWarning` (the
        caller recomputes and :meth:`put` replaces a regular file).
        """
        key = floor_key(inputs)
        path = self.path(key)
        try:
            data = read_bytes(path, RECORD_BYTES)
        except UnreadableFile as err:
            if not os.path.lexists(path):
                return None  # a plain miss (no file, or no directory)
            self._warn(f"cannot read {err}; computing the floors")
            return None
        record, reason = _trusted(data, key, inputs)
        if record is None:
            self._warn(f"ignoring {path}: {reason}; computing the floors and rewriting it")
            return None
        floors: dict[str, str] = record["floors"]
        return floors

    def put(self, inputs: dict[str, Any], floors: dict[str, str]) -> Path | None:
        """Store ``floors`` (the ``theory`` record's strings) under the key of ``inputs``:
        written whole to a temporary file in the directory, flushed to disk and renamed
        over ``<key>.json`` (atomic on POSIX), so a reader never sees a partial file and
        concurrent writers of one key both succeed. Only a regular file at that name is
        replaced; floors that are not what the computation gives
        (:func:`floor_problem`) are not stored.

        Returns:
            The file, or None when it was not written (a :class:`FloorCacheWarning`
            says why; the run goes on).
        """
        key = floor_key(inputs)
        path = self.path(key)
        problem = floor_problem(floors, inputs)
        if problem:
            self._warn(f"not storing the floors of {path}: {problem}")
            return None
        try:
            mode: int | None = os.lstat(path).st_mode
        except OSError:
            mode = None  # nothing there yet (or no directory: the write says why)
        if mode is not None and not stat.S_ISREG(mode):
            self._warn(
                f"not replacing {path}: not a regular file; the floors were computed, not stored"
            )
            return None
        record = {
            "key": key,
            "inputs": inputs,
            "floors": floors,
            "checksum": digest(canonical(floors)),
        }
        text = json.dumps(record, indent=1, allow_nan=False) + "\n"
        tmp: str | None = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{key}.", suffix=".tmp", dir=self.directory)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                os.fchmod(f.fileno(), 0o644)  # readable like other cache files (not 0600)
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
            tmp = None
            _fsync_dir(self.directory)
        except OSError as err:
            self._warn(f"cannot write {path} ({err}); the floors were computed, not stored")
            return None
        finally:
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
        return path

    def _warn(self, message: str) -> None:
        warnings.warn(f"floor cache: {message}", FloorCacheWarning, stacklevel=3)


def floor_problem(floors: object, inputs: dict[str, Any]) -> str:
    """What makes ``floors`` other than the computation of ``inputs`` gives, in words
    (empty when nothing does): a mapping of strings with exactly the keys
    :data:`FLOOR_KEYS`; the transport method of the inputs' measure; each distance's
    draws the inputs' ``draws``; each number of :data:`BAND_NUMBERS` finite, ``>= 0``
    with a positive sign (distances are never ``-0.0``) and written as its shortest
    round-trip ``repr``; each band ordered, ``lo <= mean <= hi``.

    The mean of the draws lies outside its 2.5 and 97.5 percentiles only for a
    distribution of the distance far more skewed than a floor's: such floors are used
    by the run that computed them but never stored, so the next run computes them again.
    """
    if not isinstance(floors, dict) or not all(isinstance(v, str) for v in floors.values()):
        return "the floors are not a mapping of strings"
    if set(floors) != FLOOR_KEYS:
        missing, extra = sorted(FLOOR_KEYS - set(floors)), sorted(set(floors) - FLOOR_KEYS)
        keys = f"missing {missing}, extra {extra}"[:200]
        return f"the floors' keys are not the computation's ({keys})"
    measure = inputs.get("measure")
    method = measure.get("method") if isinstance(measure, dict) else None
    if method is not None and floors["swarm_w2_method"] != method:
        return f"the transport method is {floors['swarm_w2_method'][:20]!r}, not {method!r}"
    for band in BANDS:
        if floors[f"{band}_floor_draws"] != str(inputs.get("draws")):
            draws = floors[f"{band}_floor_draws"][:20]
            return f"the {band} floor has {draws!r} draws, not {inputs.get('draws')}"
        for number in BAND_NUMBERS:
            text = floors[f"{band}_floor_{number}"]
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and math.copysign(1.0, value) > 0 and repr(value) == text):
                return f"{band}_floor_{number} is {text[:40]!r}, not a finite number >= 0"
        mean, lo, hi = (float(floors[f"{band}_floor_{number}"]) for number in BAND_NUMBERS)
        if not lo <= hi:
            return f"the {band} band is inverted (lo {lo!r} > hi {hi!r})"
        if not lo <= mean <= hi:
            return f"the {band} mean {mean!r} is outside its band [{lo!r}, {hi!r}]"
    return ""


def _trusted(data: bytes, key: str, inputs: dict[str, Any]) -> tuple[dict[str, Any] | None, str]:
    """The stored record in ``data`` when it is the floor of ``inputs`` under ``key``
    (UTF-8 JSON, the four fields, the same key and inputs, a checksum that matches the
    floors, floors the computation could give: :func:`floor_problem`); else None and
    why not.
    """
    try:
        record = json.loads(data.decode("utf-8"))
    except (ValueError, RecursionError) as err:  # UnicodeDecodeError, JSONDecodeError, depth
        return None, f"not JSON ({type(err).__name__})"
    if not isinstance(record, dict) or set(record) != {"key", "inputs", "floors", "checksum"}:
        return None, "not a floor record"
    if record["key"] != key:
        return None, f"it holds key {str(record['key'])[:16]}..."
    try:
        if canonical(record["inputs"]) != canonical(inputs):
            return None, "its inputs differ from the requested ones"
    except (TypeError, ValueError):
        return None, "its inputs are not plain JSON"
    floors = record["floors"]
    if not (isinstance(floors, dict) and all(isinstance(v, str) for v in floors.values())):
        return None, "the floors are not a mapping of strings"
    if record["checksum"] != digest(canonical(floors)):
        return None, "the checksum does not match its floors"
    problem = floor_problem(floors, inputs)
    if problem:
        return None, problem
    return record, ""


def _fsync_dir(directory: Path) -> None:
    """Flush the directory entry of a rename to disk (best effort: not every system can
    open a directory).
    """
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def cached(
    cache: FloorCache | None,
    inputs: dict[str, Any] | None,
    compute: Callable[[], dict[str, str]],
) -> tuple[dict[str, str], str]:
    """The floors of ``inputs``: from ``cache`` when it holds a trusted copy, else
    ``compute()`` (then stored). Without a cache or inputs (a target with no faithful
    description), always ``compute()``.

    Returns:
        The floors and where they came from, ``"cache"`` or ``"computed"``
        (:data:`SOURCES`).
    """
    if cache is not None and inputs is not None:
        found = cache.get(inputs)
        if found is not None:
            return found, "cache"
    floors = compute()
    if cache is not None and inputs is not None and floors:
        cache.put(inputs, floors)
    return floors, "computed"
