"""Robots on a domain with obstacles: every plant's robots start in free space and never
enter an obstacle (on the robots' map, and in the exact geometry within one square of the
map), never cross a closed wall however long their steps, and diffuse to the uniform
density on free space; the mean field and its N -> infinity limit start from p_0 on the
free cells and keep their mass there.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from harness.compiled.obstacles import first_blocked
from harness.domains.obstacles import Obstacles
from harness.domains.rooms import Rooms
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.plants.agents import Agents
from harness.plants.double_integrators import DoubleIntegrators
from harness.plants.limit import Limit
from harness.plants.meanfield import MeanField
from harness.plants.obstacles import RobotMap
from harness.plants.unicycles import Unicycles
from harness.records import Command
from harness.targets.densities import Box, Uniform
from harness.velocity import VelocityField

GRID = Grid.square(20, 1.0)
PLANTS = {"agents": Agents, "unicycles": Unicycles, "double_integrators": DoubleIntegrators}
Z999 = 3.2905267314918945
"""Two-sided 99.9 % quantile of the standard normal."""


def random_layout(seed: int, resolution: int = 256) -> Obstacles:
    """Discs and polygons (triangles, quadrilaterals, thin bars) at random, covering
    well under half of the square."""
    rng = np.random.default_rng(seed)
    discs = [
        {"center": list(rng.uniform(0.1, 0.9, 2)), "radius": float(rng.uniform(0.03, 0.12))}
        for _ in range(rng.integers(1, 4))
    ]
    polygons = []
    for _ in range(rng.integers(1, 4)):
        c = rng.uniform(0.15, 0.85, 2)
        k = int(rng.integers(3, 6))
        # one angle in each of k equal sectors about c: a simple (star-shaped) polygon
        angles = (np.arange(k) + rng.uniform(0.1, 0.9, k)) * (2 * np.pi / k)
        radii = rng.uniform(0.03, 0.12, k)
        polygons.append((c + radii[:, None] * np.c_[np.cos(angles), np.sin(angles)]).tolist())
    # a thin bar, a few squares of the map wide, that a long step would jump
    x = float(rng.uniform(0.2, 0.8))
    y0, y1 = sorted(rng.uniform(0.05, 0.95, 2))
    width = 3.0 / resolution
    polygons.append([[x, y0], [x + width, y0], [x + width, y1], [x, y1]])
    return Obstacles(discs=discs, polygons=polygons, resolution=resolution)


def depth_inside(domain: Obstacles, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """How deep each point lies inside the exact obstacles (0 outside): the largest over
    the obstacles holding it of its distance to their boundary."""
    depth = np.zeros(x.shape)
    for (cx, cy), r in domain.discs:
        d = r - np.hypot(x - cx, y - cy)
        depth = np.maximum(depth, np.where(d >= 0, d, 0.0))
    for path, vertices in zip(domain._paths, domain.polygons, strict=True):
        inside = path.contains_points(np.c_[x, y])
        v = np.array(vertices)
        a, b = v, np.roll(v, -1, axis=0)
        ab = b - a
        t = ((x[:, None] - a[:, 0]) * ab[:, 0] + (y[:, None] - a[:, 1]) * ab[:, 1]) / (ab**2).sum(
            axis=1
        )
        t = np.clip(t, 0, 1)
        px, py = a[:, 0] + t * ab[:, 0], a[:, 1] + t * ab[:, 1]
        edge = np.hypot(x[:, None] - px, y[:, None] - py).min(axis=1)
        depth = np.maximum(depth, np.where(inside, edge, 0.0))
    return depth


def _plant(kind: str, domain, sigma: float, n: int, init=None, **params):
    free = domain.resolve(GRID)
    model = FokkerPlanck(GRID, sigma, free=free)
    return PLANTS[kind](
        grid=GRID, model=model, init=init or Uniform(), n=n, bandwidth=0.05, **params
    )


def _move(plant, kind: str, step: int, rng: np.random.Generator, v_scale: float) -> None:
    """One step: a random field through the compiled step (and, every other step for
    ideal integrators, random velocities per robot through the numpy one)."""
    swarm = plant.swarm
    crng = np.random.default_rng(1000 + step)
    if kind == "agents":
        if step % 2:
            swarm.step_robots(crng.uniform(-v_scale, v_scale, swarm.positions.shape), 0.05, rng)
        else:
            field = VelocityField.from_centres(crng.uniform(-v_scale, v_scale, (2, *GRID.shape)))
            swarm.step(field, 0.05, rng)
    elif kind == "unicycles" and step % 2:
        field = VelocityField.from_centres(crng.uniform(-v_scale, v_scale, (2, *GRID.shape)))
        swarm.move_field(field, 0.05, rng)
    else:
        swarm.move(crng.uniform(-v_scale, v_scale, swarm.positions.shape), 0.05, rng)


@pytest.mark.parametrize("kind", list(PLANTS))
def test_no_robot_enters_an_obstacle_on_random_layouts(kind) -> None:
    """Thirty random layouts, large noise (steps of about 0.1, many squares of the map)
    and fast random commands: after every step no robot is in a blocked square of the
    map, and none is deeper inside the exact geometry than one square's diagonal."""
    for seed in range(30):
        domain = random_layout(seed)
        plant = _plant(kind, domain, sigma=0.1, n=150)
        rng = np.random.default_rng(seed)
        plant.start(rng)
        robots = plant.obstacles
        assert robots is not None
        diagonal = np.sqrt(2) / domain.resolution
        for step in range(40):
            _move(plant, kind, step, rng, v_scale=3.0)
            x, y = plant.positions
            assert not robots.blocked(x, y).any(), (seed, step)
            assert depth_inside(domain, x, y).max() <= diagonal, (seed, step)
            assert GRID.contains(x, y).all()


def test_the_localisation_error_keeps_the_observed_robots_out_of_obstacles() -> None:
    """Seen positions (true ones plus a localisation error of 0.2) are kept out of the
    obstacles as a move from the true position would be."""
    domain = random_layout(3)
    plant = _plant("agents", domain, sigma=0.01, n=500, localisation_noise=0.2)
    plant.start(np.random.default_rng(0))
    seen = plant.observed
    assert seen is not None and not np.array_equal(seen, plant.positions)
    assert not plant.obstacles.blocked(*seen).any()


@pytest.mark.parametrize("kind", list(PLANTS))
def test_no_robot_crosses_a_closed_wall_thinner_than_its_steps(kind) -> None:
    """A wall of 2 squares of the map (0.008) from top to bottom, steps of about 0.3:
    robots started left of it all stay left, every step."""
    wall = [[0.5, -0.1], [0.508, -0.1], [0.508, 1.1], [0.5, 1.1]]
    domain = Obstacles(polygons=[wall], resolution=256)
    plant = _plant(kind, domain, sigma=1.0, n=400, init=Box(0.0, 0.45, 0.0, 1.0))
    rng = np.random.default_rng(7)
    plant.start(rng)
    for step in range(60):
        _move(plant, kind, step, rng, v_scale=5.0)
        assert (plant.positions[0] < 0.5).all(), step


def test_the_map_s_walk_finds_the_first_blocked_square_a_segment_enters() -> None:
    """Against dense sampling on random maps: the segment up to the reported entry point
    meets only free squares, the entry point lies on the reported square's face, and a
    segment reported clear has no sample in a blocked square."""
    rng = np.random.default_rng(5)
    r = 32
    s = 1.0 / r
    for _ in range(300):
        raster = (rng.uniform(size=(r, r)) < 0.08).astype(np.uint8)
        clear = (raster == 0).astype(np.uint8)
        while True:
            a = rng.uniform(0, 1, 2)
            col, row = int(a[0] / s), int(a[1] / s)
            if not raster[row, col]:
                break
        b = rng.uniform(0, 1, 2)
        t, axis, hc, hr = first_blocked(a[0], a[1], col, row, b[0], b[1], clear, 0.0, 0.0, s, s)
        u = np.linspace(0.0, 1.0, 20001)
        px, py = a[0] + u * (b[0] - a[0]), a[1] + u * (b[1] - a[1])
        sc, sr = np.minimum((px / s).astype(int), r - 1), np.minimum((py / s).astype(int), r - 1)
        blocked = raster[sr, sc] != 0
        if axis < 0:
            assert not blocked.any()
            continue
        assert raster[hr, hc] == 1
        before = u < t - 1e-9
        assert not blocked[before].any()
        hx, hy = a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])
        if axis == 0:
            assert min(abs(hx - hc * s), abs(hx - (hc + 1) * s)) < 1e-12
            assert hr * s - 1e-12 <= hy <= (hr + 1) * s + 1e-12
        else:
            assert min(abs(hy - hr * s), abs(hy - (hr + 1) * s)) < 1e-12
            assert hc * s - 1e-12 <= hx <= (hc + 1) * s + 1e-12


def test_pure_diffusion_approaches_the_uniform_density_on_free_space() -> None:
    """No command, 20 000 robots started in one corner diffuse for 40 time constants of
    the square's slowest mode: the fraction of robots in each quadrant, and in the band
    within 0.03 of an obstacle (where a biased reflection would pile them up or push
    them away: mirroring the move instead of the point at the face fails here), is its
    share of the map's free area, within binomial 99.9 % bounds. (Unicycles and double
    integrators under no command take these very moves: their noise is the same stream.)"""
    domain = Obstacles(
        discs=[{"center": [0.3, 0.62], "radius": 0.12}, {"center": [0.74, 0.3], "radius": 0.07}],
        polygons=[
            [[0.1, 0.2], [0.45, 0.25], [0.2, 0.35]],
            [[0.6, 0.7], [0.9, 0.7], [0.9, 0.74], [0.6, 0.74]],
        ],
        resolution=256,
    )
    n, dt, sigma = 20_000, 0.05, 0.02  # steps of sqrt(2 sigma dt) = 0.045
    plant = _plant("agents", domain, sigma=sigma, n=n, init=Box(0.0, 0.15, 0.85, 1.0))
    rng = np.random.default_rng(11)
    plant.start(rng)
    steps = int(40 / (np.pi**2 * sigma) / dt)
    for _ in range(steps):
        plant.swarm.step(VelocityField.zeros(GRID), dt, rng)
    raster = plant.obstacles.raster
    r = raster.shape[0]
    centres = (np.arange(r) + 0.5) / r
    cx, cy = np.meshgrid(centres, centres)
    free = raster == 0
    near = distance_transform_edt(free) / r <= 0.03
    regions = {
        "south-west": (cx < 0.5) & (cy < 0.5),
        "south-east": (cx >= 0.5) & (cy < 0.5),
        "north-west": (cx < 0.5) & (cy >= 0.5),
        "north-east": (cx >= 0.5) & (cy >= 0.5),
        "near obstacles": near,
    }
    row, col = plant.obstacles.squares(*plant.positions)
    for name, region in regions.items():
        share = (region & free).sum() / free.sum()
        count = region[row, col].sum()
        bound = Z999 * np.sqrt(n * share * (1 - share))
        assert abs(count - n * share) <= bound, (name, count / n, share)


def test_robots_start_in_free_space_from_the_initial_density_restricted_to_it() -> None:
    """On the rooms from the uniform p_0: no robot in the wall, and each room holds its
    share of the free area (binomial 99.9 %)."""
    rooms = Rooms(wall=0.3, resolution=512)
    n = 50_000
    plant = _plant("agents", rooms, sigma=0.01, n=n)
    plant.start(np.random.default_rng(2))
    x, y = plant.positions
    assert not plant.obstacles.blocked(x, y).any()
    assert not rooms.blocked(x, y, 1.0).any()
    raster = plant.obstacles.raster
    centres = (np.arange(raster.shape[0]) + 0.5) / raster.shape[0]
    left = (raster == 0) & (centres[None, :] < 0.3)
    share = left.sum() / (raster == 0).sum()
    assert abs((x < 0.3).sum() - n * share) <= Z999 * np.sqrt(n * share * (1 - share))


def test_an_initial_density_with_no_mass_on_the_robots_map_is_refused() -> None:
    """p_0 uniform inside a disc obstacle: the rejection gives up with a clear error."""
    domain = Obstacles(discs=[{"center": [0.5, 0.5], "radius": 0.2}], resolution=256)
    robots = RobotMap.of(domain.resolve(GRID))
    assert robots is not None
    with pytest.raises(ValueError, match="no mass there"):
        robots.sample(Box(0.45, 0.55, 0.45, 0.55), 10, np.random.default_rng(0))


@pytest.mark.parametrize("kind", list(PLANTS))
def test_a_million_robots_take_a_step_on_the_rooms(kind) -> None:
    """10^6 robots (the parallel build) start and step on the rooms, none in the wall."""
    plant = _plant(kind, Rooms(), sigma=0.01, n=1_000_000)
    rng = np.random.default_rng(0)
    plant.start(rng)
    _move(plant, kind, 0, rng, v_scale=1.0)
    assert not plant.obstacles.blocked(*plant.positions).any()


class _Still:
    """A law that always commands the zero field."""

    gives_field = True

    def __call__(self, inp) -> Command:
        return Command(VelocityField.zeros(GRID))


def test_the_mean_field_and_its_limit_start_on_free_cells_and_keep_their_mass_there() -> None:
    """p_0 uniform on the rooms: the mean-field plant's density and the limit's p_inf
    start at p_0 restricted to the free cells (0 in the wall, mass 1) and keep it so
    over steps; the measured density is 0 on blocked cells, where its noise is too."""
    free = Rooms().resolve(GRID)
    model = FokkerPlanck(GRID, 0.01, free=free)
    plant = MeanField(GRID, model, Uniform(), robots=1000, bandwidth=0.05)
    limit = Limit(GRID, model, Uniform(), _Still(), bandwidth=0.05, mirror=True)
    limit.start()
    expected = np.where(free.cells, 1.0, 0.0) / free.free_area
    rng = np.random.default_rng(0)
    for p in (plant.density, limit.density):
        np.testing.assert_allclose(p, expected, rtol=1e-12, atol=0)
    field = VelocityField.from_centres(rng.uniform(-0.5, 0.5, (2, *GRID.shape)))
    for _ in range(10):
        plant.advance(Command(field), None, 0.05, rng)
        limit.advance(0.05)
        measured = plant.measure(rng)
        assert (measured.p[~free.cells] == 0).all()
        for p in (plant.density, limit.density):
            assert (p[~free.cells] == 0).all()
            assert abs(GRID.integrate(p) - 1.0) < 1e-12
