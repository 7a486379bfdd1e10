import os
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from hypothesis import given, settings
from hypothesis import strategies as st

from harness import exact_solutions
from harness.control.paper import paper_law
from harness.fokker_planck import (
    _MAX_SERIES_TERMS,
    FokkerPlanck,
    NumericalError,
    bernoulli,
    implicit_solve,
    jacobi_solve,
    rate,
    red_black_solve,
    series_terms,
)
from harness.grid import Grid
from harness.targets.densities import Box, Target, Uniform
from harness.velocity import VelocityField


def random_velocity(grid, rng, scale):
    return VelocityField.from_centres(rng.normal(scale=scale, size=(2, *grid.shape)))


def random_density(grid, rng):
    p = rng.random(grid.shape) + 1e-3
    return grid.normalise(p)


def test_bernoulli_limits():
    z = np.array([-800.0, -30.0, -1e-9, 0.0, 1e-9, 30.0, 800.0])
    b = bernoulli(z)
    assert np.all(np.isfinite(b)) and np.all(b >= 0)
    np.testing.assert_allclose(b[[1, 5]], [30 / (1 - np.exp(-30)), 30 / np.expm1(30)], rtol=1e-12)
    np.testing.assert_allclose(b[2:5], 1.0, atol=1e-8)
    assert b[0] == pytest.approx(800.0) and b[-1] == 0.0


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(4, 24),
    sigma=st.sampled_from([0.0, 1e-5, 5e-5, 1e-2]),
    scale=st.sampled_from([1e-3, 0.1, 10.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_reference_rate_matches_sparse_matrix(n, sigma, scale, seed):
    rng = np.random.default_rng(seed)
    g = Grid(n, n + 3, 0.0, 1.0, 0.0, 1.3)
    v = random_velocity(g, rng, scale)
    p = random_density(g, rng)
    op = FokkerPlanck(g, sigma)
    expected = rate(g, p, v, sigma)
    np.testing.assert_allclose(
        op.rate(p, v), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max()
    )


@pytest.mark.parametrize("n", [8, 30, 128])
def test_matrix_columns_sum_to_zero_and_off_diagonals_nonnegative(n, rng):
    g = Grid.square(n)
    a = FokkerPlanck(g, 5e-5).matrix(random_velocity(g, rng, 0.5))
    assert np.abs(np.asarray(a.sum(axis=0))).max() < 1e-10 * np.abs(a.diagonal()).max()
    off = a.copy()
    off.setdiag(0)
    assert off.min() >= 0


@settings(max_examples=30, deadline=None)
@given(
    n=st.sampled_from([4, 16, 30, 64, 128]),
    dt=st.sampled_from([1e-3, 0.01, 0.05]),
    sigma=st.sampled_from([0.0, 5e-5, 1e-3]),
    scale=st.sampled_from([1e-3, 0.1, 3.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_step_conserves_mass_and_positivity(n, dt, sigma, scale, seed):
    rng = np.random.default_rng(seed)
    g = Grid.square(n)
    op = FokkerPlanck(g, sigma)
    p = random_density(g, rng)
    for _ in range(3):
        v = random_velocity(g, rng, scale)
        p_next = op.step(p, v, dt)
        assert abs(g.integrate(p_next) - g.integrate(p)) <= 1e-12 * g.integrate(p)
        assert p_next.min() >= -1e-14 * p.max()
        p = p_next


@pytest.mark.parametrize("scale", [1e-3, 0.05, 30.0])
def test_neumann_series_and_lu_paths_agree(scale, rng):
    g = Grid.square(20)
    op = FokkerPlanck(g, 5e-5)
    v = random_velocity(g, rng, scale)
    p = random_density(g, rng)
    np.testing.assert_allclose(op.step(p, v, 0.01), op.step_lu(p, v, 0.01), rtol=1e-11, atol=1e-13)


def test_compiled_neumann_series_has_the_bits_of_the_sparse_products(rng):
    """The compiled series sums each row's stored entries in scipy's order: the same
    bits as the sparse-product statement, for one and several columns and for a matrix
    with duplicate entries; ``implicit_solve`` without the grid's shape takes it and
    agrees with the sparse LU."""
    from harness.compiled.fokker_planck import neumann_series
    from harness.fokker_planck import neumann_series_reference

    g = Grid(7, 5, 0.0, 1.0, 0.0, 0.8)
    a = FokkerPlanck(g, 1e-3).matrix(random_velocity(g, rng, 0.3))
    doubled = sp.csr_matrix(
        (np.repeat(a.data / 2, 2), np.repeat(a.indices, 2), 2 * a.indptr), shape=a.shape
    )
    assert not doubled.has_canonical_format
    for mat in (a, doubled):
        for rhs in (rng.random(g.size), rng.random((g.size, 3))):
            ref = neumann_series_reference(mat, 0.01, rhs, 6)
            cols = rhs.reshape(g.size, -1)
            out = neumann_series(mat.indptr, mat.indices, mat.data, 0.01, cols, 6)
            assert np.array_equal(out.reshape(rhs.shape), ref)
    rhs = rng.random((g.size, 2))
    lu = spla.splu((sp.identity(g.size, format="csc") - 0.01 * a).tocsc()).solve(rhs)
    np.testing.assert_allclose(implicit_solve(a, 0.01, rhs), lu, rtol=1e-13)


def test_operators_share_a_read_only_pattern(grid30, rng):
    """Each ``A(v)`` has its own values and the model's index arrays, which no consumer
    can change in place."""
    op = FokkerPlanck(grid30, 5e-5)
    a = op.matrix(random_velocity(grid30, rng, 0.1))
    b = op.matrix(random_velocity(grid30, rng, 0.1))
    assert a.indices is b.indices and a.data is not b.data
    assert not np.array_equal(a.data, b.data)
    with pytest.raises(ValueError, match="read-only"):
        a.indices[0] = 1
    kept = b.data.copy()
    a.data *= 2.0
    assert np.array_equal(b.data, kept)


def test_step_raises_on_non_finite_input(grid30):
    op = FokkerPlanck(grid30, 5e-5)
    v = VelocityField.zeros(grid30)
    v.centres[0, 3, 3] = np.nan
    bad = VelocityField(v.centres, v.face_x, v.face_y)
    bad.face_x[3, 3] = np.nan
    with pytest.raises(NumericalError, match="non-finite"):
        op.step(Uniform().on_grid(grid30), bad, 0.01)
    p = Uniform().on_grid(grid30)
    p[0, 0] = np.inf
    with pytest.raises(NumericalError):
        op.step(p, VelocityField.zeros(grid30), 0.01)
    with pytest.raises(ValueError):
        op.step(p, VelocityField.zeros(grid30), 0.0)
    with pytest.raises(ValueError):
        FokkerPlanck(grid30, -1.0)


def test_target_is_discrete_steady_state_without_feedback(grid30, target30):
    op = FokkerPlanck(grid30, 5e-5)
    v = paper_law(target30.p, grid30.gradient(target30.p), target30, alpha=0.0, sigma=5e-5)
    residual = op.rate(target30.p, v)
    # relative to the size of the individual terms: the diffusion rate of p_*
    scale = np.abs(op.rate(target30.p, VelocityField.zeros(grid30))).max()
    assert np.abs(residual).max() < 1e-10 * scale
    # and for alpha > 0 with exact estimates at p = p_*
    v = paper_law(target30.p, grid30.gradient(target30.p), target30, alpha=0.1, sigma=5e-5)
    assert np.abs(op.rate(target30.p, v)).max() < 1e-10 * scale


def test_uniform_start_relaxes_to_target_without_feedback(grid30, target30):
    sigma, dt = 1e-3, 0.05
    op = FokkerPlanck(grid30, sigma)
    v = paper_law(target30.p, grid30.gradient(target30.p), target30, alpha=0.0, sigma=sigma)
    p = Uniform().on_grid(grid30)
    errors = [grid30.l2(p - target30.p)]
    for _ in range(200):
        p = op.step(p, v, dt)  # v does not depend on p when alpha = 0
        errors.append(grid30.l2(p - target30.p))
    assert np.all(np.diff(errors) < 0)
    assert errors[-1] < 0.5 * errors[0]


def lyapunov(grid, p, target):
    return 0.5 * grid.integrate((p - target.p) ** 2 / target.p)


@pytest.mark.parametrize("n,alpha,dt,steps", [(30, 0.003, 0.01, 300), (16, 0.1, 5e-4, 400)])
def test_lyapunov_never_increases_in_closed_loop(n, alpha, dt, steps):
    from harness.control.field import sampled_data_dt_bound
    from harness.targets.densities import DEFAULT_TARGET

    grid = Grid.square(n)
    target = Target.from_density(grid, DEFAULT_TARGET)
    sigma = 5e-5
    op = FokkerPlanck(grid, sigma)
    p = Box().on_grid(grid)
    # Both cases are within the sampled-data bound for the start's largest feedback
    # diffusivity alpha max(p/p_*) (the paper's setting by a factor of about 4)
    bound = sampled_data_dt_bound(grid, alpha * float(np.max(p / target.p)), None, sigma)
    assert dt <= bound
    values = [lyapunov(grid, p, target)]
    for _ in range(steps):
        v = paper_law(p, grid.gradient(p), target, alpha, sigma)
        p = op.step(p, v, dt)
        values.append(lyapunov(grid, p, target))
    increments = np.diff(values)
    assert increments.max() <= 1e-14 * values[0], increments.max()
    assert values[-1] < 0.7 * values[0]


def test_feedback_beyond_sampled_data_bound_oscillates(grid30, target30):
    """The bound is real: far beyond it the held feedback overshoots at grid scale."""
    op = FokkerPlanck(grid30, 5e-5)
    p = Box().on_grid(grid30)
    values = [lyapunov(grid30, p, target30)]
    for _ in range(20):
        p = op.step(p, paper_law(p, grid30.gradient(p), target30, 0.1, 5e-5), 0.05)
        values.append(lyapunov(grid30, p, target30))
    assert np.diff(values).max() > 0


@pytest.mark.parametrize("kx,ky", [(1, 0), (1, 2), (3, 1)])
def test_cosine_mode_decays_at_discrete_eigenvalue(kx, ky):
    g = Grid(24, 20, 0.0, 1.0, 0.0, 0.8)
    sigma, dt = 2e-3, 0.02
    op = FokkerPlanck(g, sigma)
    mode = exact_solutions.cosine_mode(g, kx, ky)
    lam = exact_solutions.discrete_decay_rate(g, kx, ky, sigma)
    np.testing.assert_allclose(op.rate(mode, VelocityField.zeros(g)), -lam * mode, atol=1e-12 * lam)
    p = 1.0 + 0.5 * mode
    for n in range(1, 21):
        p = op.step(p, VelocityField.zeros(g), dt)
        amplitude = g.inner(p - 1.0, mode) / g.inner(mode, mode)
        assert amplitude == pytest.approx(0.5 / (1 + dt * lam) ** n, rel=1e-11)


def test_discrete_eigenvalue_converges_to_sigma_pi_squared_at_second_order():
    sigma = 1.0
    errors = []
    for n in (8, 16, 32, 64):
        g = Grid.square(n)
        mode = exact_solutions.cosine_mode(g, 1, 0)
        # measured from the operator itself, not the closed form
        lam = -g.inner(FokkerPlanck(g, sigma).rate(mode, VelocityField.zeros(g)), mode) / g.inner(
            mode, mode
        )
        errors.append(abs(lam - exact_solutions.continuum_decay_rate(g, 1, 0, sigma)))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(orders, 2.0, atol=0.05)


def test_box_start_is_stable_for_sweep_extremes():
    # grid 128, alpha 0.1, dt 0.05: the implicit step stays positive and finite
    g = Grid.square(128)
    from harness.targets.densities import DEFAULT_TARGET

    target = Target.from_density(g, DEFAULT_TARGET)
    op = FokkerPlanck(g, 5e-5)
    p = Box().on_grid(g)
    for _ in range(5):
        v = paper_law(p, g.gradient(p), target, alpha=0.1, sigma=5e-5)
        p = op.step(p, v, 0.05)
    assert np.isfinite(p).all() and p.min() >= 0
    assert g.integrate(p) == pytest.approx(1.0, rel=1e-12)


# --- the Jacobi-split series (fast implicit step) against the sparse LU reference ---


def _mid_run_velocity(g, rng):
    """The paper's law (alpha = 0.003) halfway between a KDE of the initial box and p_*."""
    from harness.estimators.kde import KDE
    from harness.targets.densities import DEFAULT_TARGET

    target = Target.from_density(g, DEFAULT_TARGET)
    y, _ = KDE(g, 0.04)(Box().sample(1024, g, rng))
    p = 0.5 * (y + target.p)
    return p, paper_law(p, g.gradient(p), target, 0.003, 5e-5)


@pytest.mark.parametrize("shape", [(40, 33), (4, 5), (256, 256)])
@pytest.mark.parametrize("sigma", [5e-5, 0.0, 1e-300, 3.0])
@pytest.mark.parametrize("scale", [0.3, 1e-9, 0.0, 1e3])
def test_matrix_equals_bincount_reference_bit_for_bit(shape, sigma, scale, rng):
    # Peclet numbers from 0 (exactly) through the |Pe| < 1e-6 branch to overflow of
    # expm1 (sigma = 1e-300), the upwind limit sigma = 0, and the parallel build (256^2)
    g = Grid(*shape, 0.0, 1.0, 0.0, 0.7)
    op = FokkerPlanck(g, sigma)
    ny, nx = g.shape
    v = VelocityField(
        rng.normal(scale=scale, size=(2, ny, nx)),
        rng.normal(scale=scale, size=(ny, nx - 1)),
        rng.normal(scale=scale, size=(ny - 1, nx)),
    )
    fast, ref = op.matrix(v), op.matrix_reference(v)
    assert np.array_equal(fast.data, ref.data)
    assert np.array_equal(fast.indices, ref.indices) and np.array_equal(fast.indptr, ref.indptr)


def test_parallel_assembly_does_not_depend_on_thread_count(rng):
    import numba

    from harness.compiled.fokker_planck import assemble_operator

    g = Grid.square(96)
    op = FokkerPlanck(g, 5e-5)
    v = random_velocity(g, rng, 0.01)
    args = (v.face_x, v.face_y, *op._open, 5e-5, g.dx, g.dy, op._pattern.indptr)
    before = numba.get_num_threads()
    try:
        results = []
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            results.append(assemble_operator.parallel(*args))
    finally:
        numba.set_num_threads(before)
    reference = op.matrix_reference(v).data
    assert np.array_equal(results[0], reference) and np.array_equal(results[1], reference)
    assert np.array_equal(assemble_operator.serial(*args), reference)


def test_serial_and_parallel_builds_have_their_own_cache_entries(tmp_path):
    """numba's disk cache keys an entry by name, line and bytecode, not by the flags:
    two plain ``njit(cache=True)`` builds of one function load each other's code. A
    build made by :func:`harness.compiled.build` after the other one was cached must
    compile afresh (a cache miss), and load its own entry next time (a hit)."""
    import subprocess
    import sys

    (tmp_path / "twobuilds.py").write_text(
        "import numba\n"
        "from harness.compiled import build\n\n"
        "def total(x):\n"
        "    s = 0.0\n"
        "    for i in numba.prange(x.size):\n"
        "        s += x[i]\n"
        "    return s\n\n"
        "serial = build(total, parallel=False)\n"
        "parallel = build(total, parallel=True)\n"
    )
    run = (
        "import sys, numpy as np, twobuilds\n"
        "k = getattr(twobuilds, sys.argv[1])\n"
        "assert k(np.ones(10)) == 10.0\n"
        "print(sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values()))\n"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(Path(__file__).parents[1])])

    def hits_misses(name: str) -> list[int]:
        out = subprocess.run(
            [sys.executable, "-c", run, name], env=env, capture_output=True, text=True,
            check=True,
        )  # fmt: skip
        return [int(w) for w in out.stdout.split()]

    assert hits_misses("serial") == [0, 1]
    assert hits_misses("parallel") == [0, 1]  # not the serial build's entry
    assert hits_misses("parallel") == [1, 0]
    assert hits_misses("serial") == [1, 0]


@pytest.mark.parametrize("n", [128, 256])
def test_implicit_step_matches_sparse_lu_at_paper_settings(n, rng):
    g = Grid.square(n)
    op = FokkerPlanck(g, 5e-5)
    p, v = _mid_run_velocity(g, rng)
    a = op.matrix(v)
    # the red-black path is the one taken here (the plain series would need > 12 terms)
    assert series_terms(0.01 * 2 * np.abs(a.diagonal()).max()) > _MAX_SERIES_TERMS
    fast = op.step(p, v, 0.01)
    ref = op.step_lu(p, v, 0.01)
    assert np.abs(fast - ref).max() <= 1e-10 * np.abs(ref).max()
    assert abs(g.integrate(fast) - g.integrate(p)) <= 1e-12 * g.integrate(p)
    assert fast.min() >= 0.0


@pytest.mark.parametrize("solver", ["jacobi", "red_black"])
@settings(max_examples=30, deadline=None)
@given(
    n=st.sampled_from([16, 64, 128]),
    dt=st.sampled_from([0.01, 0.05, 0.2]),
    sigma=st.sampled_from([0.0, 5e-5, 1e-3]),
    scale=st.sampled_from([0.01, 0.1, 1.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_implicit_solvers_are_positive_mass_exact_and_match_lu(solver, n, dt, sigma, scale, seed):
    """The Jacobi series and red-black Gauss-Seidel with their mass correction."""
    rng = np.random.default_rng(seed)
    g = Grid.square(n)
    op = FokkerPlanck(g, sigma)
    a = op.matrix(random_velocity(g, rng, scale))
    p = random_density(g, rng).ravel()
    # rhs with zeros too: positivity must hold where the density vanishes
    p[rng.random(p.size) < 0.2] = 0.0
    x = jacobi_solve(a, dt, p) if solver == "jacobi" else red_black_solve(a, dt, p, g.nx)
    if x is None:  # more terms than the LU threshold: nothing to compare
        return
    ref = spla.splu((sp.identity(g.size, format="csc") - dt * a).tocsc()).solve(p)
    assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()
    assert abs(x.sum() - p.sum()) <= 1e-12 * p.sum()
    assert x.min() >= 0.0


def test_red_black_columns_swept_together_match_lu(rng):
    """Several right-hand sides in one set of sweeps (a density, a signed field and a
    zero column, as the filters' predict passes them) on a rectangular grid: each
    column matches sparse LU, keeps its mass, the zero column stays zero, and a
    non-negative column stays non-negative."""
    g = Grid(48, 40, 0.0, 1.2, 0.0, 1.0)
    op = FokkerPlanck(g, 5e-5)
    a = op.matrix(random_velocity(g, rng, 0.5))
    dens = random_density(g, rng).ravel()
    rhs = np.column_stack([dens, rng.normal(size=g.size), np.zeros(g.size)])
    x = red_black_solve(a, 0.05, rhs, g.nx)
    assert x is not None and x.shape == rhs.shape
    ref = spla.splu((sp.identity(g.size, format="csc") - 0.05 * a).tocsc()).solve(rhs)
    for col in range(2):
        assert np.abs(x[:, col] - ref[:, col]).max() <= 1e-10 * np.abs(ref[:, col]).max()
    np.testing.assert_allclose(x.sum(axis=0), rhs.sum(axis=0), atol=1e-12 * np.abs(rhs).sum())
    assert np.array_equal(x[:, 2], np.zeros(g.size))
    assert x[:, 0].min() >= 0.0


def test_jacobi_solve_signed_rhs_and_columns_match_lu(rng):
    g = Grid.square(64)
    op = FokkerPlanck(g, 5e-5)
    a = op.matrix(random_velocity(g, rng, 0.5))
    rhs = rng.normal(size=(g.size, 2))
    x = implicit_solve(a, 0.05, rhs)
    ref = spla.splu((sp.identity(g.size, format="csc") - 0.05 * a).tocsc()).solve(rhs)
    assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()
    np.testing.assert_allclose(x.sum(axis=0), rhs.sum(axis=0), atol=1e-12 * np.abs(rhs).sum())


@pytest.mark.parametrize("solver", ["jacobi_series", "red_black"])
def test_implicit_solvers_do_not_depend_on_thread_count(rng, solver):
    """The parallel build with 1 and 2 threads and the serial build give the same bits
    (the Jacobi series and red-black Gauss-Seidel)."""
    import numba

    from harness.compiled import fokker_planck

    builds = getattr(fokker_planck, solver)
    parallel, serial = builds.parallel, builds.serial
    g = Grid.square(128)
    op = FokkerPlanck(g, 5e-5)
    p, v = _mid_run_velocity(g, rng)
    a = op.matrix(v)
    if solver == "red_black":  # two columns, swept together
        rhs = np.column_stack([p.ravel(), rng.random(g.size)])
        args = (a.indptr, a.indices, a.data, 0.01, rhs, g.nx, 1e-15, 200)
    else:
        args = (a.indptr, a.indices, a.data, 0.01, p.ravel(), 1e-15, 200)
    before = numba.get_num_threads()
    try:
        results = []
        for threads in (1, 2):
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            results.append(parallel(*args)[0])
    finally:
        numba.set_num_threads(before)
    assert np.array_equal(results[0], results[1])
    assert np.array_equal(results[0], serial(*args)[0])


def test_jacobi_solve_refuses_when_too_many_terms(rng):
    g = Grid.square(64)
    a = FokkerPlanck(g, 1e-2).matrix(random_velocity(g, rng, 1.0))
    assert jacobi_solve(a, 10.0, Uniform().on_grid(g).ravel()) is None
    # and the step falls back to the sparse LU solve
    op = FokkerPlanck(g, 1e-2)
    p = Uniform().on_grid(g)
    v = random_velocity(g, rng, 1.0)
    np.testing.assert_allclose(op.step(p, v, 10.0), op.step_lu(p, v, 10.0), rtol=1e-12)


def test_red_black_needs_about_half_the_jacobi_sweeps_on_a_rectangle(rng):
    """Rectangular grid (the colouring follows the rows of nx cells): the solution
    matches LU, and the sweeps are at most 60 % of the Jacobi series' terms."""
    from harness.compiled.fokker_planck import jacobi_series, red_black

    g = Grid(48, 40, 0.0, 1.2, 0.0, 1.0)
    a = FokkerPlanck(g, 5e-5).matrix(random_velocity(g, rng, 1.0))
    p = random_density(g, rng).ravel()
    x, sweeps, res = red_black(a.indptr, a.indices, a.data, 0.05, p[:, None], g.nx, 1e-15, 400)
    x = x[:, 0]
    _, terms, _ = jacobi_series(a.indptr, a.indices, a.data, 0.05, p, 1e-15, 400)
    ref = spla.splu((sp.identity(g.size, format="csc") - 0.05 * a).tocsc()).solve(p)
    assert res <= 1e-15
    assert np.abs(x - ref).max() <= 1e-12 * np.abs(ref).max()
    assert sweeps <= 0.6 * terms, (sweeps, terms)


def test_red_black_refuses_a_wrong_row_length(rng):
    """The colouring needs the grid's nx: a wrong one is refused, not solved wrongly."""
    g = Grid(37, 23)
    a = FokkerPlanck(g, 5e-5).matrix(random_velocity(g, rng, 1.0))
    p = random_density(g, rng).ravel()
    assert red_black_solve(a, 0.01, p, g.nx) is not None
    for wrong in (g.nx + 1, g.ny, 1):
        with pytest.raises(ValueError, match="5-point"):
            red_black_solve(a, 0.01, p, wrong)


def test_red_black_at_its_sweep_limit_returns_the_iterate_and_its_residual(rng):
    from harness.compiled.fokker_planck import red_black

    g = Grid.square(32)
    a = FokkerPlanck(g, 5e-5).matrix(random_velocity(g, rng, 1.0))
    p = random_density(g, rng).ravel()
    system = (sp.identity(g.size, format="csr") - 0.2 * a).tocsr()
    x, sweeps, res = red_black(a.indptr, a.indices, a.data, 0.2, p[:, None], g.nx, 1e-15, 2)
    x = x[:, 0]
    assert sweeps == 2 and res > 1e-15
    residual = np.abs(p - system @ x).sum() / np.abs(p).sum()
    assert residual == pytest.approx(res, rel=1e-9)


def test_check_density_refuses_lost_mass_and_negative_values(grid30):
    """The step's check (one compiled pass) raises on a mass change above the tolerance
    and on a value below -1e-12 of the largest, and passes round-off below either."""
    from harness.fokker_planck import check_density

    before = np.full(grid30.shape, 1.0 / grid30.area)
    check_density(grid30, before, before * (1 + 1e-10), 1e-9)  # within the tolerance
    with pytest.raises(NumericalError, match="mass changed"):
        check_density(grid30, before, before * (1 + 1e-8), 1e-9)

    def moved(field, value):  # cell (3, 4) set to value, its mass moved to (3, 5)
        out = field.copy()
        out[3, 5] += out[3, 4] - value
        out[3, 4] = value
        return out

    check_density(grid30, before, moved(before, -1e-13 * before.max()), 1e-9)  # round-off
    with pytest.raises(NumericalError, match="negative"):
        check_density(grid30, before, moved(before, -1e-10 * before.max()), 1e-9)
    # the threshold follows the largest value before the step, not after
    peak = before.copy()
    peak[0, 0] *= 1e4
    check_density(grid30, peak, moved(peak, -1e-10 * before.max()), 1e-9)
