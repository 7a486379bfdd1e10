"""Shared fixtures: grids and targets, seeded generators, and composed configs.

Configs are composed from ``conf/`` exactly as the app composes them
(:func:`harness.api.compose`); ``group_option`` parametrizes a test over every option of
every config group found in ``conf/``, so a new option is tested without editing tests.
"""

import copy
import functools
import os
from collections.abc import Callable, Sequence

import numpy as np
import pytest
from omegaconf import DictConfig

from harness.api import CONFIG_DIR, compose
from harness.grid import Grid
from harness.targets.densities import DEFAULT_TARGET, Target

# The tests' runs compute their finite-N floors (log.floor_cache defaults to this
# variable): no files in the user's cache, and two runs of a test log the same theory
# record. tests/test_floor_cache.py gives the cache a directory of its own.
os.environ["DENSITYLOOP_FLOOR_CACHE"] = ""


def _share_the_cores() -> None:
    """Under pytest-xdist, each worker's compiled loops get its share of the cores: ``W``
    workers each running ``C`` threads on ``C`` cores would make every parallel loop wait
    for descheduled threads. (``NUMBA_NUM_THREADS`` itself is left alone: numba refuses
    a change of it once its threads run, and the tests compare thread counts up to it.)"""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers <= 1:
        return
    import numba

    share = max(1, (os.cpu_count() or 1) // workers)
    numba.set_num_threads(min(share, numba.config.NUMBA_NUM_THREADS))


_share_the_cores()

GROUPS = ("plant", "estimator", "control", "target", "init", "experiment")
SMOKE = (
    "grid.n=12",
    "agents.n=200",
    "sim.t_final=0.2",
    "sim.dt=0.02",
    "log.field_every=3",
    "log.positions_every=4",
    "log.progress=off",
)
"""A seconds-long run of the default loop: 10 steps on a 12 x 12 grid with 200 robots."""


def group_options() -> list[tuple[str, str]]:
    """Every ``(group, option)`` pair in ``conf/``."""
    return [(g, p.stem) for g in GROUPS for p in sorted((CONFIG_DIR / g).glob("*.yaml"))]


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "group_option" in metafunc.fixturenames:
        pairs = group_options()
        metafunc.parametrize("group_option", pairs, ids=[f"{g}={o}" for g, o in pairs])


@functools.cache
def _composed(overrides: tuple[str, ...]) -> DictConfig:
    return compose(overrides)


def compose_cached(overrides: Sequence[str] = ()) -> DictConfig:
    """:func:`harness.api.compose`, each distinct list of overrides composed once per
    session (Hydra takes about 0.1 s a composition); a copy, so a test may change it.
    """
    return copy.deepcopy(_composed(tuple(overrides)))


@pytest.fixture(name="compose", scope="session")
def compose_fixture() -> Callable[..., DictConfig]:
    """``compose(overrides)``: the app's config with those overrides."""
    return compose_cached


@pytest.fixture(scope="session")
def refusal() -> Callable[[Sequence[str]], str | None]:
    """``refusal(overrides)``: the one-line refusal of a config (composition or build), or
    None when it is accepted.
    """
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from harness.runs.build import build
    from harness.runs.checks import ConfigError, describe

    def refuse(overrides: Sequence[str]) -> str | None:
        try:
            build(compose_cached(overrides))
        except ConfigError as err:
            return str(err)
        except (HydraException, OmegaConfBaseException) as err:
            return describe(err, list(overrides))
        return None

    return refuse


@pytest.fixture(scope="session")
def smoke() -> tuple[str, ...]:
    """The overrides of a seconds-long run (:data:`SMOKE`)."""
    return SMOKE


@pytest.fixture
def grid30() -> Grid:
    return Grid.square(30)


@pytest.fixture
def target30(grid30: Grid) -> Target:
    return Target.from_density(grid30, DEFAULT_TARGET)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)
