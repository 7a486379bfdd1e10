"""The metrics, floors, log and figures of a run on a domain with obstacles.

The KDE on free space (``free=`` of :class:`harness.estimators.kde.KDE` and
:class:`harness.estimators.smoothing.Smoother`) is not what these tests check: where a test
builds the swarm observer or runs a loop on obstacles, the KDE and the smoother take
``free`` and use the rectangle's kernel (:func:`rectangle_kde`), and the parts of the
loop are let onto the domain (:func:`let_onto_obstacles`): the tests check the sampling,
the components, the transport measure, the theory record, the log and the figures.
"""

import numpy as np
import pytest
import scipy.linalg
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

import harness.observers.swarm as swarm_module
from analysis.load import load_run
from harness.domains.base import Domain
from harness.domains.obstacles import Obstacles
from harness.estimators.kde import KDE
from harness.estimators.smoothing import Smoother
from harness.grid import Grid
from harness.observers.log import METRIC_KEYS, METRICS_SCHEMA, obstacle_rectangles
from harness.observers.swarm import SwarmTruth, domain_keys
from harness.observers.swarm_metrics import Components, FreeSampler, free_target_measure
from harness.observers.theory import lyapunov, poincare_constant
from harness.runs.run import run
from harness.targets.densities import GaussianMixture, Target, Uniform


class _RectangleKDE(KDE):
    def __init__(self, *args, free=None, **kwargs):
        super().__init__(*args, **kwargs)


class _RectangleSmoother(Smoother):
    def __init__(self, *args, free=None, **kwargs):
        super().__init__(*args, **kwargs)


@pytest.fixture
def rectangle_kde(monkeypatch):
    """The swarm observer's KDE and smoother take ``free`` (and ignore it)."""
    monkeypatch.setattr(swarm_module, "KDE", _RectangleKDE)
    monkeypatch.setattr(swarm_module, "Smoother", _RectangleSmoother)


@pytest.fixture
def let_onto_obstacles(monkeypatch, rectangle_kde):
    """Every part runs on a domain with obstacles (for a log, not for its numbers)."""
    import harness.runs.domain

    monkeypatch.setattr(harness.runs.domain, "on_free_space", lambda part: True)


WALL = Obstacles(polygons=[[[0.32, -0.1], [0.48, -0.1], [0.48, 1.1], [0.32, 1.1]]], resolution=160)
"""A wall across the square: on a 10 x 10 grid columns 3 and 4 blocked, free space in
two components (columns 0-2, component 0, and 5-9, component 1)."""

DISC = Obstacles(discs=[{"center": [0.5, 0.45], "radius": 0.22}], resolution=256)
"""A large disc: on a 16 x 16 grid cells partly covered, 16 raster squares per cell side."""


class _Blocks(Domain):
    """Free space: the square ``[0, 0.5)^2`` and the square ``(0.7, 1]^2``."""

    name = "blocks"

    def blocked(self, x, y, length):
        x, y = np.asarray(x), np.asarray(y)
        return ~(((x < 0.5) & (y < 0.5)) | ((x > 0.7) & (y > 0.7)))


def test_component_fractions_count_robots_per_component_against_target_mass():
    grid = Grid.square(10)
    free = WALL.resolve(grid)
    assert free.n_components == 2
    assert (free.labels[:, :3] == 0).all() and (free.labels[:, 5:] == 1).all()
    target = Target.from_density(grid, Uniform(), free)
    comp = Components(target.p, free)
    np.testing.assert_allclose(comp.masses, [30 / 80, 50 / 80], rtol=1e-13)
    # three robots left, one right; (0.33, 0.5) lies in blocked column 3, nearest the
    # centre of free column 2 (0.25) rather than column 5 (0.55): left
    robots = np.array([[0.1, 0.2, 0.7, 0.33], [0.5, 0.2, 0.5, 0.5]])
    np.testing.assert_array_equal(comp.of(robots), [0, 0, 1, 0])
    fractions = comp.fractions(robots)
    np.testing.assert_allclose(fractions, [0.75, 0.25])
    assert comp.gap(fractions) == pytest.approx(0.75 - 0.375, abs=1e-15)


def test_swarm_observer_logs_component_fractions_on_obstacles_only(rectangle_kde):
    grid = Grid.square(10)
    free = WALL.resolve(grid)
    target = Target.from_density(grid, Uniform(), free)
    obs = SwarmTruth(grid, target, 10, 0.1, True, "auto", every=1, w2_every=1, init=Uniform())
    assert domain_keys(free) == (
        "component_fraction_gap",
        "component_fraction_0",
        "component_fraction_1",
        "start_fraction",
        "start_target_mass",
    )
    assert set(domain_keys(free)) <= set(obs.gives)
    square = SwarmTruth(grid, Target.from_density(grid, Uniform()), 10, 0.1, True, "auto", 1, 1)
    assert domain_keys(None) == () and not any("component_fraction" in k for k in square.gives)


def test_floor_draws_on_free_space_have_the_targets_cell_masses_and_avoid_obstacles():
    grid = Grid.square(16)
    free = DISC.resolve(grid)
    density = GaussianMixture(means=((0.3, 0.3), (0.7, 0.6)), stds=(0.15, 0.2), weights=(0.5, 0.5))
    target = Target.from_density(grid, density, free)
    n = 400_000
    x = FreeSampler(target.p, free).sample(n, grid, np.random.default_rng(1))
    r = free.raster.shape[0]
    inside = free.raster[(x[1] * r).astype(int), (x[0] * r).astype(int)]
    assert not inside.any()  # no robot in an obstacle of the robots' map
    counts, _, _ = np.histogram2d(x[1], x[0], bins=grid.ny, range=[[0, 1], [0, 1]])
    expected = target.p * grid.cell_area * n
    assert counts[~free.cells].sum() == 0
    c, e = counts[free.cells], expected[free.cells]
    chi2 = ((c - e) ** 2 / e).sum()
    dof = free.cells.sum() - 1
    assert chi2 < dof + 5 * np.sqrt(2 * dof)


def _brute_force_draw(target, free, grid, n, rng):
    """N robots from ``p_*`` on free space by rejection from the uniform square: a point
    in a free cell ``c`` and a free raster square is kept with probability proportional to
    ``p_*(c) / f_c``, ``f_c`` the free fraction of the cell on the raster.
    """
    r = free.raster.shape[0]
    per = r // grid.nx
    frac = 1.0 - free.raster.reshape(grid.ny, per, grid.nx, per).mean(axis=(1, 3))
    weight = np.where(free.cells, target.p / np.where(frac > 0, frac, 1.0), 0.0)
    weight /= weight.max()
    out = np.empty((2, 0))
    while out.shape[1] < n:
        u = rng.random((2, 4 * n))
        col, row = (u[0] * grid.nx).astype(int), (u[1] * grid.ny).astype(int)
        ok = ~free.raster[(u[1] * r).astype(int), (u[0] * r).astype(int)].astype(bool)
        ok &= rng.random(4 * n) < weight[row, col]
        out = np.hstack([out, u[:, ok]])
    return out[:, :n]


def test_floors_on_free_space_equal_a_brute_force_monte_carlo(rectangle_kde):
    grid = Grid.square(16)
    free = DISC.resolve(grid)
    target = Target.from_density(grid, Uniform(), free)
    obs = SwarmTruth(grid, target, 10, 0.08, True, "auto", every=1, w2_every=1, floor_draws=2)
    n, draws = 300, 150
    floors = obs.floors(n, np.random.default_rng(3), draws)
    measure = obs.measure(n)
    rng = np.random.default_rng(4)
    l2, w2 = np.empty(draws), np.empty(draws)
    for i in range(draws):
        x = _brute_force_draw(target, free, grid, n, rng)
        l2[i] = grid.l2(obs.kde(x)[0] - obs.smoothed_target)
        w2[i] = swarm_module.swarm_w2(x, measure)
    for name, values in (("swarm_l2", l2), ("swarm_w2", w2)):
        mean = float(floors[f"{name}_floor_mean"])
        se = values.std(ddof=1) * np.sqrt(2 / draws)  # two independent means
        assert abs(mean - values.mean()) < 4 * se, (name, mean, values.mean(), se)


def test_w2_measure_on_free_space_holds_the_targets_mass_in_free_cells_only():
    grid = Grid.square(16)
    free = DISC.resolve(grid)
    target = Target.from_density(grid, Uniform(), free)
    for refine in (1, 4):
        m = free_target_measure(target.p, free, grid, refine)
        assert m.weights.sum() == pytest.approx(1.0, abs=1e-13)
        col = (m.points[:, 0] / grid.dx).astype(int)
        row = (m.points[:, 1] / grid.dy).astype(int)
        assert free.cells[row, col].all()
        masses = np.zeros(grid.shape)
        np.add.at(masses, (row, col), m.weights)
        np.testing.assert_allclose(masses, target.p * grid.cell_area, atol=1e-15)
    # a coarser measure grid merges atoms at their centroids, keeping the mass
    coarse = Grid.square(8)
    m = free_target_measure(target.p, free, coarse, 1)
    assert m.weights.sum() == pytest.approx(1.0) and len(m.weights) <= 64


def _dense_poincare_spectrum(grid, p, free):
    """Generalised eigenvalues of ``-div(p grad f) = lambda p f`` on the free cells,
    assembled cell by cell over the open faces."""
    idx = {cell: k for k, cell in enumerate(zip(*np.nonzero(free.cells), strict=True))}
    k = np.zeros((len(idx), len(idx)))
    for (j, i), a in idx.items():
        for dj, di, open_, h in ((0, 1, free.face_x, grid.dx), (1, 0, free.face_y, grid.dy)):
            if j + dj < grid.ny and i + di < grid.nx and open_[j, i]:
                b = idx[(j + dj, i + di)]
                c = 0.5 * (p[j, i] + p[j + dj, i + di]) / h**2
                k[a, a] += c
                k[b, b] += c
                k[a, b] -= c
                k[b, a] -= c
    m = np.diag([p[j, i] for (j, i) in idx])
    return np.sort(scipy.linalg.eigh(k, m, eigvals_only=True))


def test_poincare_constant_on_free_space_is_the_first_rate_within_components():
    grid = Grid.square(10)
    free = _Blocks().resolve(grid)
    assert free.n_components == 2 and free.cells.sum() == 25 + 9
    target = Target.from_values(grid, np.ones(grid.shape), free)
    lam = poincare_constant(grid, target.p, free)
    # uniform p_* on a 5 x 5 and a 3 x 3 block of cells with no-flux faces: the discrete
    # Neumann eigenvalues (4 / dx^2) sin^2(pi k / 2m); the first non-zero is the 5 x 5's
    assert lam == pytest.approx(4 / grid.dx**2 * np.sin(np.pi / 10) ** 2, rel=1e-9)
    wavy = Target.from_density(grid, GaussianMixture(((0.25, 0.25),), (0.3,), (1.0,)), free)
    spectrum = _dense_poincare_spectrum(grid, wavy.p, free)
    assert spectrum[1] == pytest.approx(0.0, abs=1e-9)
    assert poincare_constant(grid, wavy.p, free) == pytest.approx(spectrum[2], rel=1e-8)


def test_lyapunov_on_free_space_sums_over_free_cells():
    grid = Grid.square(10)
    free = WALL.resolve(grid)
    target = Target.from_density(grid, Uniform(), free)
    p = np.where(free.cells, 1.0 + 0.1 * grid.mesh[0], 0.0)
    value = lyapunov(grid, p, target.p, free)
    cells = free.cells
    expected = 0.5 * ((p - target.p)[cells] ** 2 / target.p[cells]).sum() * grid.cell_area
    assert np.isfinite(value) and value == pytest.approx(expected, rel=1e-14)


def test_obstacle_rectangles_cover_exactly_the_blocked_raster_squares():
    grid = Grid.square(16)
    free = DISC.resolve(grid)
    rects = obstacle_rectangles(free)
    r = free.raster.shape[0]
    painted = np.zeros((r, r), dtype=int)
    for x0, y0, x1, y1 in np.rint(rects * r).astype(int):
        painted[y0:y1, x0:x1] += 1
    np.testing.assert_array_equal(painted, free.raster)  # each blocked square once


@pytest.fixture
def obstacles_log(tmp_path, compose, smoke, let_onto_obstacles):
    cfg = compose(["domain=obstacles", *smoke, "control=heat", "sim.t_final=0.08"])
    result = run(cfg, tmp_path)
    assert result.state == "completed", result.reason
    return tmp_path


def test_a_run_log_with_obstacles_loads_with_its_domain(obstacles_log, compose, smoke):
    from harness.domains.obstacles import Obstacles as Domain_

    cfg = compose(["domain=obstacles", *smoke])
    domain = Domain_(cfg.domain.discs, cfg.domain.polygons, cfg.domain.resolution)
    free = domain.resolve(Grid.square(cfg.grid.n))
    log = load_run(obstacles_log)
    assert log.state == "completed" and log.recovery is None
    np.testing.assert_array_equal(log.domain.free, free.cells)
    assert log.domain.extent() == (0.0, 1.0, 0.0, 1.0)
    np.testing.assert_allclose(log.domain.rectangles, obstacle_rectangles(free))
    assert log.metadata["domain"]["n_components"] == str(free.n_components)
    assert set(METRIC_KEYS) | set(domain_keys(free)) == set(log.metrics)
    gap = log.metrics["component_fraction_gap"]
    assert np.isfinite(gap).any() and (gap[np.isfinite(gap)] >= 0).all()
    assert np.isfinite(log.metrics["lyapunov"]).all()


def test_the_obstacles_decode_with_foxglove_scene_update_schema(obstacles_log):
    with open(obstacles_log / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        found = list(reader.iter_decoded_messages(topics=["/domain/obstacles", "/domain/mask"]))
    by_topic = {channel.topic: (schema, msg) for schema, channel, _, msg in found}
    schema, scene = by_topic["/domain/obstacles"]
    assert schema.name == "foxglove.SceneUpdate" and schema.encoding == "protobuf"
    (entity,) = scene.entities
    assert entity.frame_id == "world" and entity.id == "obstacles" and len(entity.cubes) > 0
    schema, mask = by_topic["/domain/mask"]
    assert schema.name == "foxglove.Grid" and mask.frame_id == "world"
    assert len(found) == 2  # once each


def test_a_square_log_has_no_domain_topics_and_loads_without_them(tmp_path, compose, smoke):
    result = run(compose([*smoke, "sim.t_final=0.04"]), tmp_path)
    assert result.state == "completed"
    log = load_run(tmp_path)
    assert log.domain is None and "domain" not in log.metadata
    assert set(log.metrics) == set(METRIC_KEYS)
    with open(tmp_path / "run.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    topics = {c.topic for c in summary.channels.values()}
    assert not any(t.startswith("/domain") for t in topics)
    schema = next(s for s in summary.schemas.values() if s.name == "densityloop.Metrics")
    import json

    assert json.loads(schema.data) == METRICS_SCHEMA


def test_figures_fill_the_obstacles_grey_beneath_fields_and_robots(obstacles_log, tmp_path):
    import matplotlib.pyplot as plt

    from analysis import figures

    log = load_run(obstacles_log)
    fig, ax = plt.subplots()
    figures.draw_obstacles(ax, log)
    (patches,) = ax.collections
    assert patches.get_zorder() < 0  # beneath images (zorder 0) and points (1)
    np.testing.assert_allclose(patches.get_facecolor()[0][:3], [0.6] * 3)
    assert len(patches.get_paths()) == len(log.domain.rectangles)
    masked = figures.on_free(log, log.fields["/fields/p_hat"].values[-1, 0])
    np.testing.assert_array_equal(np.ma.getmaskarray(masked), ~log.domain.free)
    plt.close(fig)
    out = tmp_path / "figs"
    assert figures.main([str(obstacles_log), "--out", str(out), "--no-gif"]) == 0
    assert (out / "fig1.png").exists() and (out / "fig2.png").exists()
