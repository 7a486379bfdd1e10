import numpy as np
import pytest

from harness.densities import DEFAULT_TARGET, Target
from harness.grid import Grid


@pytest.fixture
def grid30() -> Grid:
    return Grid.square(30)


@pytest.fixture
def target30(grid30: Grid) -> Target:
    return Target.from_density(grid30, DEFAULT_TARGET)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)
