import numpy as np
import pytest
import scipy.sparse as sp

from benchmarks.filter_accuracy import compare_filters
from harness.estimators.filters.common import FilterSettings, Integrator, MeasurementModel
from harness.estimators.filters.local import (
    LocalFilters,
    squared_transition,
    squared_transition_reference,
)
from harness.estimators.filters.poisson import WeightedPoisson
from harness.estimators.filters.reference import ReferenceDensityFilter, ReferenceGradientFilter
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.targets.densities import GaussianMixture
from harness.velocity import VelocityField


def test_squared_transition_is_the_diagonal_of_the_congruence(rng):
    g = Grid.square(6)
    a = FokkerPlanck(g, 1e-3).matrix(VelocityField.from_centres(rng.normal(size=(2, 6, 6))))
    d = rng.random(g.size)
    f1 = np.eye(g.size) + 0.02 * a.toarray()
    np.testing.assert_allclose(squared_transition(a, 0.02, d), np.diag(f1 @ np.diag(d) @ f1.T))
    cols = rng.random((g.size, 3))  # several columns: the compiled pass and numpy agree
    np.testing.assert_allclose(
        squared_transition(a, 0.02, cols), squared_transition_reference(a, 0.02, cols), rtol=1e-14
    )
    # rows without a stored diagonal, and duplicate entries, against the dense congruence
    import scipy.sparse as sp

    base = sp.random(g.size, g.size, density=0.1, random_state=1, format="csr")
    base.sort_indices()
    # every stored entry twice (half each): a CSR matrix with duplicates, as given
    rows = [base.indices[base.indptr[i] : base.indptr[i + 1]] for i in range(g.size)]
    vals = [base.data[base.indptr[i] : base.indptr[i + 1]] / 2 for i in range(g.size)]
    indptr = np.concatenate([[0], np.cumsum([2 * r.size for r in rows])])
    b = sp.csr_matrix(
        (np.concatenate([np.tile(v, 2) for v in vals]),
         np.concatenate([np.tile(r, 2) for r in rows]), indptr),
        shape=base.shape,
    )  # fmt: skip
    assert not b.has_canonical_format and (b.diagonal() == 0).any()
    f1 = np.eye(g.size) + 0.02 * b.toarray()
    np.testing.assert_allclose(squared_transition(b, 0.02, d), np.diag(f1 @ np.diag(d) @ f1.T))


def test_weighted_poisson_is_exact_under_huge_right_hand_sides(rng):
    """A right-hand side of size 1e200 (its squared norm overflows) gives the small
    problem's solution times the same factor, without a warning; a non-finite one is
    refused (the run then ends as diverged, with the reason)."""
    import warnings

    from harness.fokker_planck import NumericalError

    g = Grid(9, 7, 0.0, 1.0, 0.0, 0.8)
    gm = g.gradient_matrix.toarray()
    c = np.exp(rng.normal(size=2 * g.size))
    b = gm.T @ (c * rng.normal(size=2 * g.size))
    small = WeightedPoisson(g).solve(c, b)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        huge = WeightedPoisson(g).solve(c, b * 2.0**660)
    assert np.array_equal(huge, small * 2.0**660)
    bad = b.copy()
    bad[3] = np.inf
    with pytest.raises(NumericalError, match="not finite"):
        WeightedPoisson(g).solve(c, bad)


def test_weighted_poisson_solves_the_normal_equations(rng):
    g = Grid(9, 7, 0.0, 1.0, 0.0, 0.8)
    solver = WeightedPoisson(g)
    gm = g.gradient_matrix.toarray()
    for _ in range(3):  # lagged preconditioner reused across calls
        c = rng.uniform(0.05, 5.0, 2 * g.size)
        z = rng.normal(size=2 * g.size)
        delta = solver.solve(c, gm.T @ (c * z))
        expected = np.linalg.lstsq(np.sqrt(c)[:, None] * gm, np.sqrt(c) * z, rcond=None)[0]
        expected -= expected.mean()
        np.testing.assert_allclose(delta, expected, atol=1e-8 * np.abs(expected).max())


@pytest.mark.parametrize("shape", [(9, 7), (6, 11), (4, 5)])
def test_weighted_laplacian_is_the_sparse_product(shape, rng):
    """The matrix-free ``G^T diag(c) G x`` equals the product with the sparse gradient
    matrix, on grids wider than tall, taller than wide and of the smallest width (4)."""
    from harness.compiled.filters import weighted_laplacian

    nx, ny = shape
    g = Grid(nx, ny, 0.0, 1.0, 0.0, 0.7)
    gm = g.gradient_matrix
    c = np.exp(rng.normal(size=2 * g.size))
    x = rng.normal(size=g.size)
    out = np.empty(g.shape)
    weighted_laplacian(x.reshape(g.shape), c[: g.size].reshape(g.shape),
                       c[g.size :].reshape(g.shape), g.dx, g.dy, out)  # fmt: skip
    expected = gm.T @ (c * (gm @ x))
    np.testing.assert_allclose(out.ravel(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_band_cholesky_solve_matches_lapack(rng):
    """The compiled banded forward and back substitution solves the system LAPACK's
    banded Cholesky factor is of (``cho_solve_banded`` and a dense solve agree)."""
    import scipy.linalg as sla

    from harness.compiled.filters import band_cholesky_solve

    m, w = 40, 6
    dense = np.zeros((m, m))
    for k in range(w + 1):  # a random symmetric band, made diagonally dominant
        vals = rng.normal(size=m - k)
        dense += np.diag(vals, -k) + (np.diag(vals, k) if k else 0.0)
    dense += np.diag(np.abs(dense).sum(axis=1) + 1.0)
    ab = np.array([np.concatenate([np.diag(dense, -k), np.zeros(k)]) for k in range(w + 1)])
    factor = sla.cholesky_banded(ab, lower=True)
    b = rng.normal(size=m)
    x = band_cholesky_solve(np.ascontiguousarray(factor.T), b)
    np.testing.assert_allclose(x, sla.cho_solve_banded((factor, True), b), rtol=1e-13)
    np.testing.assert_allclose(dense @ x, b, rtol=0, atol=1e-12 * np.abs(b).max())


@pytest.mark.parametrize("shape", [(9, 7), (7, 10), (4, 5)])
def test_compiled_band_operator_is_the_sparse_product(shape, rng):
    """The pinned operator's band, assembled in one compiled pass from the weights,
    equals the band read off the sparse product ``G^T diag(c) G`` (cells numbered along
    the longer side, cell 0 pinned), and its factor solves the pinned dense system."""
    import scipy.linalg as sla

    from harness.compiled.filters import pinned_band_operator

    nx, ny = shape
    g = Grid(nx, ny, 0.0, 1.0, 0.0, 0.8)
    solver = WeightedPoisson(g)
    c = rng.uniform(0.1, 10.0, 2 * g.size)
    cx, cy = c[: g.size].reshape(g.shape), c[g.size :].reshape(g.shape)
    ab = pinned_band_operator(cx, cy, g.dx, g.dy, solver._position, solver._width)
    ref = solver._band_operator_reference(c, solver._width)
    np.testing.assert_allclose(ab, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    # the dense pinned system from the sparse product, in the band's ordering
    gm = g.gradient_matrix
    dense = (gm.T @ sp.diags(c) @ gm).toarray()
    dense[0, :], dense[:, 0], dense[0, 0] = 0.0, 0.0, 1.0
    order = solver._order
    dense = dense[np.ix_(order, order)]
    factor = np.ascontiguousarray(sla.cholesky_banded(ab, lower=True).T)
    b = rng.normal(size=g.size)
    from harness.compiled.filters import band_cholesky_solve

    x = band_cholesky_solve(factor, b)
    np.testing.assert_allclose(dense @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())


@pytest.mark.parametrize("shape", [(9, 7), (7, 10)])
def test_compiled_poisson_iteration_matches_the_sparse_lu_reference(shape, rng):
    """The compiled small-grid solve (banded factor of an earlier ``c``, cells numbered
    along the longer side) and the numpy iteration with a fresh sparse LU give the same
    solution to the iteration's tolerance, over calls that reuse and renew the factor."""
    nx, ny = shape
    g = Grid(nx, ny, 0.0, 1.0, 0.0, 0.8)
    solver = WeightedPoisson(g, refactor_after=3)
    gm = g.gradient_matrix
    c = rng.uniform(0.5, 5.0, 2 * g.size)
    for _ in range(6):
        c = c * rng.uniform(0.7, 1.4, c.size)  # coefficients drift: the factor lags
        b = gm.T @ (c * rng.normal(size=2 * g.size))
        fast = solver.solve(c, b)
        ref = solver.solve_reference(c, b)
        assert abs(fast.mean()) <= 1e-14 * np.abs(ref).max()
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-8 * np.abs(ref).max())
    assert solver.factorizations >= 2  # the lagged factor was renewed at least once
    assert solver._factor is not None
    assert solver._factor.shape == (g.size, 2 * min(nx, ny) + 1)  # the narrower band


@pytest.mark.parametrize("shape", [(12, 9), (33, 40)])
def test_band_projection_by_truncated_matrices_is_the_transform_projection(shape, rng):
    """``Pi`` by the band's rows of the DCT matrices equals ``Pi`` by full fast
    transforms, for one column and several, and is an orthogonal projector."""
    from harness.estimators.filters.common import BandLimit

    nx, ny = shape
    g = Grid(nx, ny, 0.0, 1.0, 0.0, 0.9)
    band = BandLimit(g, 2.5 / 0.08)
    assert not band.is_identity and band.bases[1].shape[0] < nx
    for f in (rng.normal(size=g.size), rng.normal(size=(g.size, 3))):
        fast, ref = band(f), band.reference(f)
        assert fast.shape == f.shape
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
        np.testing.assert_allclose(band(fast), fast, rtol=0, atol=1e-13 * np.abs(ref).max())
    u, w = rng.normal(size=g.size), rng.normal(size=g.size)
    assert abs(band(u) @ w - u @ band(w)) <= 1e-12 * np.linalg.norm(u) * np.linalg.norm(w)


def test_local_filters_equal_reference_without_transport():
    """A = 0 (no velocity, no diffusion) and q = 0: the local covariance structure is
    exact, so both filters reproduce the dense reference."""
    rng = np.random.default_rng(3)
    g = Grid.square(8)
    settings = FilterSettings(process_noise=0.0, initial_variance=3.0)
    model = MeasurementModel(500, 0.08, settings)
    zero = VelocityField.zeros(g)
    fast = LocalFilters(g, 0.0, 0.05, model)
    ref_p = ReferenceDensityFilter(g, 0.0, 0.05, model)
    ref_q = ReferenceGradientFilter(g, 0.0, 0.05, model, integrator=Integrator.build(g))
    p = GaussianMixture(means=((0.3, 0.6),), stds=(0.15,), weights=(1,)).on_grid(g)
    y, yg = p + 0.2 * rng.normal(size=g.shape), g.gradient(p) + rng.normal(size=(2, *g.shape))
    fast.initialize(y, yg)
    ref_p.initialize(y)
    ref_q.initialize(yg)
    for _ in range(20):
        y = p + 0.2 * rng.normal(size=g.shape)
        yg = g.gradient(p) + rng.normal(size=(2, *g.shape))
        p_fast, q_fast = fast.step(y, yg, zero)
        p_ref = ref_p.step(y, zero)
        q_ref = ref_q.step(yg, y, zero)
    np.testing.assert_allclose(p_fast, p_ref, atol=1e-10 * np.abs(p_ref).max())
    np.testing.assert_allclose(np.diag(ref_p.kf.P), fast.d, rtol=1e-10)
    # the reference keeps a tiny part outside the range of G; compare within it
    gm = g.gradient_matrix.toarray()
    q_ref_in_range = gm @ (np.linalg.pinv(gm) @ q_ref.ravel())
    np.testing.assert_allclose(q_fast.ravel(), q_ref_in_range, atol=1e-8 * np.abs(q_ref).max())


def test_fast_filters_track_reference_in_closed_loop():
    """Accuracy bar on a short closed loop (n = 12, 150 steps): the fast estimate's
    distance to the reference estimate stays below 10 % of the reference's own
    error against the mean-field truth, density and gradient."""
    c = compare_filters(n=12, steps=150, seed=2)
    worst_p, worst_q = c.ratios(skip=1)
    print(f"n = 12: worst ratios {worst_p:.4f} (density), {worst_q:.4f} (gradient)")
    assert worst_p < 0.1, worst_p
    assert worst_q < 0.1, worst_q


@pytest.mark.slow
def test_fast_filters_track_reference_at_paper_grid():
    c = compare_filters(n=30, steps=300, seed=0)
    worst_p, worst_q = c.ratios(skip=1)
    print(f"n = 30: worst ratios {worst_p:.4f} (density), {worst_q:.4f} (gradient)")
    assert worst_p < 0.1 and worst_q < 0.1, (worst_p, worst_q)


def test_weighted_poisson_fast_transform_preconditioner(rng):
    """The DCT-preconditioned path (grids above lu_max_cells) solves the same
    normal equations as a dense least-squares fit."""
    g = Grid(24, 20, 0.0, 1.0, 0.0, 0.8)
    solver = WeightedPoisson(g, lu_max_cells=0)
    gm = g.gradient_matrix.toarray()
    x, y = g.mesh
    for rough in (0.0, 1.0):
        smooth = 1.0 + 0.8 * np.sin(3 * x) * np.cos(2 * y)
        c = np.concatenate([smooth, smooth]).ravel() * (1 + rough * rng.uniform(0, 4, 2 * g.size))
        z = rng.normal(size=2 * g.size)
        delta = solver.solve(c, gm.T @ (c * z))
        expected = np.linalg.lstsq(np.sqrt(c)[:, None] * gm, np.sqrt(c) * z, rcond=None)[0]
        expected -= expected.mean()
        np.testing.assert_allclose(delta, expected, atol=1e-8 * np.abs(expected).max())


def _paper_loop_tail(n: int, seconds: float, seed: int = 0) -> tuple[float, float]:
    """The paper's agent loop with both fast filters (N = 1024, h = 0.04, dt = 0.01):
    mean of ||p_hat - p_*|| over the second half of the run, and its maximum."""
    from harness.control.paper import paper_law
    from harness.estimators.kde import KDE
    from harness.plants.agents import Swarm
    from harness.targets.densities import DEFAULT_TARGET, Box, Target

    sigma, dt, alpha = 5e-5, 0.01, 0.003
    rng = np.random.default_rng(seed)
    g = Grid.square(n)
    target = Target.from_density(g, DEFAULT_TARGET)
    swarm = Swarm(g, Box().sample(1024, g, rng), sigma)
    kde = KDE(g, 0.04)
    truth = FokkerPlanck(g, sigma)
    filters = LocalFilters(g, sigma, dt, MeasurementModel(1024, 0.04, FilterSettings()))
    p = Box().on_grid(g)
    y, yg = kde(swarm.positions)
    p_hat, q_hat = filters.initialize(y, yg)
    errors = []
    for _ in range(round(seconds / dt)):
        v = paper_law(p_hat, q_hat, target, alpha, sigma)
        a = truth.matrix(v)
        swarm.step(v, dt, rng)
        p = truth.step(p, v, dt, a)
        y, yg = kde(swarm.positions)
        p_hat, q_hat = filters.step(y, yg, v, a)
        errors.append(g.l2(p_hat - target.p))
    errors = np.array(errors)
    return float(errors[errors.size // 2 :].mean()), float(errors.max())


@pytest.mark.slow
def test_paper_loop_with_filters_converges_under_grid_refinement():
    """Fine grids at the paper's dt: the loop that diverged at n = 128 (grid-scale
    modes of the filters amplified by the held feedback) is stable, and its tail
    error at n = 64 and n = 128 (same seed) agree within 10 %."""
    tail_64, worst_64 = _paper_loop_tail(64, 10.0)
    tail_128, worst_128 = _paper_loop_tail(128, 10.0)
    print(f"tail ||p_hat - p_*||: {tail_64:.4f} (n = 64), {tail_128:.4f} (n = 128)")
    # stable: the error never exceeds its start (about 1.0 for the box start)
    assert max(worst_64, worst_128) < 1.05
    assert abs(tail_64 - tail_128) <= 0.1 * tail_128, (tail_64, tail_128)


def _band_basis(g: Grid, bp) -> np.ndarray:
    """The band's non-constant orthonormal DCT-II modes as columns, built one by one."""
    import scipy.fft as sfft

    cols = []
    for a, b in zip(bp.a, bp.b, strict=True):
        unit = np.zeros(g.shape)
        unit[b, a] = 1.0
        cols.append(sfft.idctn(unit, type=2, norm="ortho").ravel())
    return np.array(cols).T


@pytest.mark.parametrize("shape", [(24, 20), (41, 37)])
def test_band_poisson_is_the_galerkin_solve_of_the_dense_operator(shape, rng):
    """The Gram matrix from the transforms of C equals ``B^T G^T diag(C) G B`` formed
    with the sparse gradient matrix, and the solve is that system's, on a rectangular
    grid with rough weights; for constant weights it is the grid solve projected."""
    from harness.estimators.filters.common import BandLimit
    from harness.estimators.filters.poisson import BandPoisson

    nx, ny = shape
    g = Grid(nx, ny, 0.0, 1.0, 0.0, 0.8)
    band = BandLimit(g, 2.5 / 0.06)
    assert not band.is_identity
    bp = BandPoisson(g, band)
    # the coarser grid needs the transforms' extension, the finer reads the quarter only
    assert bp._quarter_suffices == (shape == (41, 37))
    basis = _band_basis(g, bp)
    gm = g.gradient_matrix.toarray()
    c = np.exp(rng.normal(size=2 * g.size))
    dense = basis.T @ gm.T @ (c[:, None] * gm @ basis)
    np.testing.assert_allclose(bp.gram(c), dense, atol=1e-12 * np.abs(dense).max())
    np.testing.assert_allclose(
        bp.gram_reference(c), bp.gram(c), rtol=0, atol=1e-13 * np.abs(dense).max()
    )
    b = gm.T @ (c * rng.normal(size=2 * g.size))
    expected = basis @ np.linalg.solve(dense, basis.T @ b)
    np.testing.assert_allclose(bp.solve(c, b), expected, atol=1e-10 * np.abs(expected).max())
    const = np.full(2 * g.size, 3.0)
    b = gm.T @ (const * rng.normal(size=2 * g.size))
    grid_solve = band(WeightedPoisson(g).solve(const, b))
    scale = np.abs(grid_solve).max()
    np.testing.assert_allclose(bp.solve(const, b), grid_solve, atol=1e-10 * scale)


def test_band_gram_does_not_depend_on_thread_count(rng):
    """The parallel Gram build with 1 and 2 threads and its serial build write the
    same bits in the upper triangle (each entry is computed on its own)."""
    import numba

    from harness.compiled.filters import band_gram
    from harness.estimators.filters.common import BandLimit
    from harness.estimators.filters.poisson import BandPoisson

    g = Grid.square(64)
    bp = BandPoisson(g, BandLimit(g, 2.5 / 0.04))
    c = np.exp(rng.normal(size=2 * g.size))
    ex, ey = bp._extended(c[: g.size]), bp._extended(c[g.size :])
    args = (ex, ey, bp.a, bp.b, bp._wx, bp._wy)
    k = bp.modes
    upper = np.triu(np.ones((k, k), dtype=bool))
    results = []
    before = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            out = np.zeros((k, k))
            band_gram(*args, out)
            results.append(out[upper])
    finally:
        numba.set_num_threads(before)
    serial = np.zeros((k, k))
    band_gram.serial(*args, serial)
    assert np.array_equal(results[0], results[1])
    assert np.array_equal(results[0], serial[upper])
    np.testing.assert_allclose(
        results[0], bp.gram_reference(c)[upper], rtol=0, atol=1e-13 * np.abs(results[0]).max()
    )


def test_fine_grid_filters_solve_the_gradient_update_in_the_band():
    """Above 1024 cells with a band limit the filters use the band solve; below, or
    with every mode kept, the grid solve."""
    model = MeasurementModel(1024, 0.04, FilterSettings())
    assert LocalFilters(Grid.square(30), 5e-5, 0.01, model).band_poisson is None
    assert LocalFilters(Grid.square(40), 5e-5, 0.01, model).band_poisson is not None
    every = MeasurementModel(1024, 0.04, FilterSettings(band_limit=np.inf))
    assert LocalFilters(Grid.square(40), 5e-5, 0.01, every).band_poisson is None


@pytest.mark.slow
def test_fast_filters_with_the_band_solve_track_reference():
    """The accuracy bar on a grid where the band solve is used (n = 34: 1156 cells)."""
    c = compare_filters(n=34, steps=150, seed=2)
    worst_p, worst_q = c.ratios(skip=1)
    print(f"n = 34: worst ratios {worst_p:.4f} (density), {worst_q:.4f} (gradient)")
    assert worst_p < 0.1 and worst_q < 0.1, (worst_p, worst_q)


def test_band_transition_variance_is_the_dense_congruence(rng):
    """The compiled variance prediction with the band's correlations equals
    ``diag(F1 S R S F1^T)`` with the dense correlation matrices of the band-limited
    white field (from the dense projector ``Pi``, full cosine transforms) and of its
    gradient components (``G_c Pi G_c^T`` with the grid's gradient matrix)."""
    from harness.estimators.filters.common import BandLimit
    from harness.estimators.filters.local import transition_variance, transition_variance_reference

    g = Grid(14, 12, 0.0, 1.0, 0.0, 0.9)
    band = BandLimit(g, 25.0)
    assert not band.is_identity
    ny, nx = g.shape
    v = VelocityField(
        rng.normal(scale=0.3, size=(2, ny, nx)),
        rng.normal(scale=0.3, size=(ny, nx - 1)),
        rng.normal(scale=0.3, size=(ny - 1, nx)),
    )
    a = FokkerPlanck(g, 1e-3).matrix(v)
    d = rng.uniform(0.5, 2.0, (g.size, 3))
    pi = band.matrix()
    gm = g.gradient_matrix.toarray()
    dense = []
    for cov in (pi, gm[: g.size] @ pi @ gm[: g.size].T, gm[g.size :] @ pi @ gm[g.size :].T):
        s = np.sqrt(np.diag(cov))
        dense.append(cov / np.outer(s, s))
    fast = transition_variance(a, 0.05, d, band.correlations(), nx)
    np.testing.assert_allclose(fast, transition_variance_reference(a, 0.05, d, dense), rtol=1e-12)
    # one correlation for every column (the density's)
    one = transition_variance(a, 0.05, d, band.correlations()[:1], nx)
    ref_one = transition_variance_reference(a, 0.05, d, dense[:1])
    np.testing.assert_allclose(one, ref_one, rtol=1e-12)
    # without the band it is the white congruence (F1 o F1) d
    white = transition_variance(a, 0.05, d, None, nx)
    np.testing.assert_array_equal(white, squared_transition(a, 0.05, d))


def test_band_limited_variance_decays_at_the_band_rate_on_every_grid():
    """Under pure diffusion a band-limited white field's variance decays by about
    ``dt sigma kappa_c^2`` per step (the mean of ``2 dt sigma |kappa|^2`` over the
    disc), whatever the grid; the white per-cell model by ``1 - (1 - 4 r)^2 - 4 r^2``
    with ``r = dt sigma / dx^2``, about four times faster for each halving of dx."""
    from harness.estimators.filters.common import BandLimit
    from harness.estimators.filters.local import transition_variance

    sigma, dt, cutoff = 5e-5, 0.01, 2.5 / 0.04
    band_rate, white_rate = {}, {}
    for n in (64, 128):
        g = Grid.square(n)
        band = BandLimit(g, cutoff)
        a = FokkerPlanck(g, sigma).matrix(VelocityField.zeros(g))
        d = np.ones((g.size, 1))
        inner = np.zeros(g.shape, dtype=bool)
        inner[n // 4 : 3 * n // 4, n // 4 : 3 * n // 4] = True
        out = transition_variance(a, dt, d, band.correlations()[:1], n).reshape(g.shape)
        white = squared_transition(a, dt, d).reshape(g.shape)
        band_rate[n] = float(np.mean(1.0 - out[inner]))
        white_rate[n] = float(np.mean(1.0 - white[inner]))
        assert band_rate[n] == pytest.approx(dt * sigma * cutoff**2, rel=0.08)
        r = dt * sigma * n**2  # dt sigma / dx^2: interior rows of F1 are 1 - 4 r and r
        assert white_rate[n] == pytest.approx(1.0 - ((1 - 4 * r) ** 2 + 4 * r**2), rel=1e-9)
    assert band_rate[128] == pytest.approx(band_rate[64], rel=0.05)


def test_band_transition_variance_does_not_depend_on_thread_count(rng):
    """From ``PARALLEL_MIN_CELLS`` cells on the rows run in parallel; one thread, two
    threads and the serial build give the same bits."""
    import numba

    from harness import compiled
    from harness.compiled.filters import band_transition_variance, band_transition_variance_rows
    from harness.estimators.filters.common import BandLimit

    g = Grid.square(256)
    assert g.size >= compiled.PARALLEL_MIN_CELLS
    rho = BandLimit(g, 2.5 / 0.04).correlations()
    ny, nx = g.shape
    v = VelocityField.from_centres(rng.normal(scale=0.01, size=(2, ny, nx)))
    a = FokkerPlanck(g, 5e-5).matrix(v)
    d = rng.uniform(0.5, 2.0, (g.size, 3))
    args = (a.indptr, a.indices, a.data, 0.01, d, rho, nx)
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread: nothing to compare")
    before = numba.get_num_threads()
    try:
        outs = []
        for threads in (1, 2):
            numba.set_num_threads(threads)
            outs.append(band_transition_variance(*args))
    finally:
        numba.set_num_threads(before)
    assert np.array_equal(outs[0], outs[1])
    dp = np.vstack([d, np.zeros((1, 3))])
    serial = np.empty_like(d)
    band_transition_variance_rows.serial(
        a.indptr, a.indices, a.data, 0.01, dp, np.sqrt(dp), rho, nx, serial
    )
    assert np.array_equal(outs[0], serial)


def test_band_correlations_are_the_dense_projectors_entries():
    """``rho[k, o, i]`` is the correlation of cell ``i`` with ``i + offset`` in the dense
    ``Pi`` (full cosine transforms) and in ``G_c Pi G_c^T``; 0 off the grid; within
    [-1, 1]; and 1 at no offset would be the diagonal (checked through symmetry)."""
    from harness.estimators.filters.common import BAND_OFFSETS, BandLimit

    g = Grid(14, 12, 0.0, 1.0, 0.0, 0.9)
    band = BandLimit(g, 25.0)
    rho = band.correlations()
    assert rho.shape == (3, len(BAND_OFFSETS), g.size + 1)
    assert np.all(rho[:, :, -1] == 0.0)
    pi = band.matrix()
    gm = g.gradient_matrix.toarray()
    ny, nx = g.shape
    for k, cov in enumerate(
        (pi, gm[: g.size] @ pi @ gm[: g.size].T, gm[g.size :] @ pi @ gm[g.size :].T)
    ):
        s = np.sqrt(np.diag(cov))
        for o, (oy, ox) in enumerate(BAND_OFFSETS):
            for i in range(g.size):
                y, x = divmod(i, nx)
                if 0 <= y + oy < ny and 0 <= x + ox < nx:
                    j = (y + oy) * nx + x + ox
                    assert rho[k, o, i] == pytest.approx(cov[i, j] / (s[i] * s[j]), abs=1e-12)
                else:
                    assert rho[k, o, i] == 0.0
    assert np.abs(rho).max() <= 1.0


@pytest.mark.parametrize("n", [16, 256])
def test_band_transition_variance_refuses_couplings_that_wrap_a_row(n):
    """A coupling of a row's first cell to the previous row's last (not a grid
    neighbour, though ``i - 1``) is refused, by the serial and the parallel build."""
    from harness.estimators.filters.common import BandLimit
    from harness.estimators.filters.local import transition_variance

    g = Grid.square(n)
    rho = BandLimit(g, 2.5 / 0.04).correlations()
    a = FokkerPlanck(g, 5e-5).matrix(VelocityField.zeros(g))
    i = 2 * n  # x = 0 of the third row
    wrap = sp.csr_matrix(([1.0], ([i], [i - 1])), shape=a.shape)
    d = np.ones((g.size, 1))
    transition_variance(a, 0.01, d, rho[:1], n)  # the operator itself is fine
    with pytest.raises(ValueError, match="5-point"):
        transition_variance((a + wrap).tocsr(), 0.01, d, rho[:1], n)
    with pytest.raises(ValueError, match="shape"):
        transition_variance(a, 0.01, d, rho[:, :5], n)
