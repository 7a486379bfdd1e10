"""The continuification law (harness/control/continuification.py) and the DSMC-style
chain (harness/control/dsmc.py), each against statements made independently of its code:
a dense solve of the flux equation, the Fokker-Planck plant, a brute-force Markov
iteration of the expected distribution."""

import numpy as np
import pytest
import scipy.sparse as sp

from harness import api
from harness.control.continuification import ContinuificationControl, continuification_law
from harness.control.dsmc import ConsensusGuidance, consensus_columns, consensus_rate
from harness.control.guidance import chain_matrix, neighbour_table
from harness.control.heat import LangevinControl
from harness.fokker_planck import FokkerPlanck, rate
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.records import ControlInput, Estimate
from harness.targets.densities import DEFAULT_TARGET, Box, Target, Uniform


def dense_neumann_laplacian(grid: Grid) -> np.ndarray:
    """The 5-point Laplacian with zero flux through the walls, by loops over cells."""
    n = grid.size
    a = np.zeros((n, n))
    for r in range(grid.ny):
        for c in range(grid.nx):
            k = r * grid.nx + c
            for dr, dc, h in ((0, -1, grid.dx), (0, 1, grid.dx), (-1, 0, grid.dy), (1, 0, grid.dy)):
                if 0 <= r + dr < grid.ny and 0 <= c + dc < grid.nx:
                    a[k, (r + dr) * grid.nx + c + dc] += 1 / h**2
                    a[k, k] -= 1 / h**2
    return a


# ------------------------------------------------------------------- continuification
def test_continuification_flux_solves_the_flux_equation_against_a_dense_solve(rng):
    """On a 7 x 5 grid: the law's face flux of ``p_hat`` (its Scharfetter-Gummel flux
    with the noise, as the plant moves mass) has the divergence ``K (p_hat - p_*) -
    d_t p_*``, and its face flux is ``grad_h phi`` for the ``phi`` of a dense
    least-squares solve of the Neumann Poisson problem."""
    g = Grid(nx=7, ny=5)
    target = Target.from_density(g, DEFAULT_TARGET)
    p_hat = g.normalise(np.exp(rng.random(g.shape)))
    q_hat = g.gradient(p_hat)
    rate_target = rng.normal(size=g.shape)
    rate_target -= rate_target.mean()  # a target's rate has zero mass
    gain, sigma = 0.7, 3e-3
    v = continuification_law(p_hat, q_hat, target, gain, sigma, 0.01, rate=rate_target)
    source = gain * (p_hat - target.p) - rate_target
    phi, *_ = np.linalg.lstsq(dense_neumann_laplacian(g), source.ravel(), rcond=None)
    phi = phi.reshape(g.shape)
    # the plant's rate at p = p_hat: -div(flux) = -K (p_hat - p_*) + d_t p_*
    np.testing.assert_allclose(rate(g, p_hat, v, sigma), -source, atol=1e-10 * np.abs(source).max())
    # the flux is grad_h phi: check through sigma = 0, where it is p_upwind u
    v0 = continuification_law(p_hat, q_hat, target, gain, 0.0, 0.01, rate=rate_target)
    upwind_x = np.where(v0.face_x > 0, p_hat[:, :-1], p_hat[:, 1:]) * v0.face_x
    np.testing.assert_allclose(upwind_x, np.diff(phi, axis=1) / g.dx, atol=1e-10)
    upwind_y = np.where(v0.face_y > 0, p_hat[:-1, :], p_hat[1:, :]) * v0.face_y
    np.testing.assert_allclose(upwind_y, np.diff(phi, axis=0) / g.dy, atol=1e-10)


def test_continuification_at_the_target_is_the_noise_compensating_drift():
    """``p_hat = p_*``, ``q_hat = grad p_*``, static target: the field is the Langevin
    drift ``sigma grad log p_*`` (faces and centres), and 0 without noise."""
    g = Grid.square(16)
    target = Target.from_density(g, DEFAULT_TARGET)
    sigma = 2e-3
    v = continuification_law(target.p, target.grad, target, 0.5, sigma, 0.05)
    drift = LangevinControl(target, sigma).field(target.p, target.grad)
    scale = np.abs(drift.face_x).max()
    np.testing.assert_allclose(v.face_x, drift.face_x, atol=1e-12 * scale)
    np.testing.assert_allclose(v.face_y, drift.face_y, atol=1e-12 * scale)
    np.testing.assert_allclose(v.centres, drift.centres, rtol=1e-12)
    still = continuification_law(target.p, target.grad, target, 0.5, 0.0, 0.05)
    for part in (still.centres, still.face_x, still.face_y):
        assert np.abs(part).max() < 1e-12


@pytest.mark.parametrize("start", [Uniform(), Box()])
def test_continuification_meanfield_loop_decays_at_the_rate_k(start):
    """Exact estimates on the Fokker-Planck plant with noise: ``||p - p_*||`` follows
    ``exp(-K t)`` within 15 % over 20 time constants' worth of decay, from a positive
    start and from the paper's box (zero outside it, where the floor acts)."""
    g = Grid.square(16)
    target = Target.from_density(g, DEFAULT_TARGET)
    gain, sigma, dt = 0.5, 2e-3, 0.05
    op = FokkerPlanck(g, sigma)
    p = start.on_grid(g)
    e0 = g.l2(p - target.p)
    for k in range(1, 401):
        p = op.step(p, continuification_law(p, g.gradient(p), target, gain, sigma, 0.05), dt)
        if k % 40 == 0:
            ratio = g.l2(p - target.p) / e0 / np.exp(-gain * k * dt)
            assert 0.85 < ratio < 1.15, (k, ratio)
    assert g.l2(p - target.p) < 1e-4 * e0
    assert g.integrate(p) == pytest.approx(1.0, rel=1e-10)


def test_continuification_refuses_a_gain_beyond_the_step_bound(grid30, target30):
    with pytest.raises(ParameterError) as err:
        ContinuificationControl(target30, gain=200.0, sigma=0.0, dt=0.01)
    assert err.value.name == "gain"
    ContinuificationControl(target30, gain=100.0, sigma=0.0, dt=0.01)  # K dt = 1


def test_continuification_follows_a_moving_target_with_its_rate(target30, rng):
    """The input's ``d_t p_*`` enters the Poisson problem: the command equals the law
    evaluated with that rate, and the law itself keeps none."""
    law = ContinuificationControl(target30, gain=0.2, sigma=0.0)
    grid = target30.grid
    moved = Target.from_values(grid, grid.normalise(target30.p + 0.1))
    r = rng.normal(size=grid.shape)
    r -= r.mean()
    est = Estimate(moved.p * 1.1, moved.grad)
    inp = ControlInput(t=1.0, estimate=est, positions=None, target=moved, target_rate=r)
    got = law(inp).field
    want = continuification_law(est.p_hat, est.q_hat, moved, 0.2, 0.0, 0.05, rate=r)
    np.testing.assert_allclose(got.face_x, want.face_x, rtol=1e-12, atol=1e-15)
    assert law._rate is None


def test_continuification_is_refused_on_a_domain_with_obstacles(compose):
    from harness.runs.build import build
    from harness.runs.checks import ConfigError

    cfg = compose(["control=continuification", "domain=rooms", "grid.n=12", "agents.n=50"])
    with pytest.raises(ConfigError) as err:
        build(cfg)
    line = str(err.value)
    assert line.startswith("invalid config: domain=") and "\n" not in line, line
    assert "control=continuification runs on (no obstacles)" in line, line


# ------------------------------------------------------------------------------- DSMC
def dsmc_law(n: int = 10, gain: float = 0.5) -> ConsensusGuidance:
    g = Grid.square(n)
    return ConsensusGuidance(Target.from_density(g, DEFAULT_TARGET), gain=gain)


def test_dsmc_columns_are_stochastic_for_any_masses(rng):
    law = dsmc_law()
    for masses in (rng.random(100), rng.random(100) ** 8, np.eye(100)[37]):
        m = masses / masses.sum()
        cols = law.columns_of_masses(m)
        assert (cols >= 0).all()
        np.testing.assert_allclose(cols.sum(axis=1), 1.0, rtol=0, atol=1e-14)
        dense = chain_matrix(law.cells, law.exists, cols).toarray()
        np.testing.assert_allclose(dense.sum(axis=0), 1.0, rtol=0, atol=1e-14)
        assert (dense >= 0).all()
        # only moves to 4-neighbours, and never both ways on an edge
        adjacency = np.abs(np.subtract.outer(np.arange(100) // 10, np.arange(100) // 10))
        adjacency = adjacency + np.abs(np.subtract.outer(np.arange(100) % 10, np.arange(100) % 10))
        off = dense - np.diag(np.diag(dense))
        assert (off[adjacency > 1] == 0).all()
        assert not ((off > 0) & (off.T > 0)).any()


def test_dsmc_columns_by_loops_match(rng):
    """The entries against a loop over cells: ``M_ij = (kappa / 4) min(v_i, v_j) (m_j /
    v_j - m_i / v_i)+ / m_j`` between neighbours."""
    law = dsmc_law(n=6, gain=0.8)
    g, v = law.grid, law.masses.ravel()
    m = rng.random(g.size)
    m /= m.sum()
    want = np.zeros((g.size, g.size))
    for j in range(g.size):
        r, c = divmod(j, g.nx)
        for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            if 0 <= r + dr < g.ny and 0 <= c + dc < g.nx:
                i = (r + dr) * g.nx + c + dc
                drop = max(m[j] / v[j] - m[i] / v[i], 0.0)
                want[i, j] = 0.8 / 4 * min(v[i], v[j]) * drop / m[j]
        want[j, j] = 1 - want[:, j].sum()
    got = chain_matrix(law.cells, law.exists, law.columns_of_masses(m)).toarray()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_dsmc_matrix_is_the_identity_at_the_target():
    law = dsmc_law(n=12)
    cols = law.columns_of_masses(law.masses.ravel())
    assert (cols[:, 0] == 1.0).all() and (cols[:, 1:] == 0.0).all()
    # through the estimate: p_hat whose cell masses are the target's
    p_hat = law.masses / law.grid.cell_area
    np.testing.assert_array_equal(law.matrix(p_hat).toarray(), np.eye(law.grid.size))


@pytest.mark.parametrize("gain", [0.5, 1.0])
def test_dsmc_expected_distribution_reaches_the_target_within_the_consensus_bound(gain):
    """Brute force: ``m <- M(m) m`` with the matrix rebuilt from the exact distribution
    every period, from all mass in one corner cell. The bound (derived in
    :func:`consensus_rate`): ``||r(k) - 1||_V <= rho^k ||r(0) - 1||_V``, ``rho`` from the
    dense eigenvalues of ``(kappa / 4) V^{-1/2} L V^{-1/2}``, and ``||m - v||_1 <= ||r -
    1||_V``. Checked at every period; after 3000 periods (``rho^3000 ~ 3e-13`` at
    ``kappa = 0.5``) the distribution is the target to 1e-9."""
    law = dsmc_law(n=10, gain=gain)
    v = law.masses.ravel()
    rho = consensus_rate(v, law.cells, law.exists, gain)
    assert 0.9 < rho < 1.0
    m = np.zeros_like(v)
    m[0] = 1.0
    norm0 = np.sqrt(np.sum(v * (m / v - 1) ** 2))
    for k in range(1, 3001):
        matrix = chain_matrix(law.cells, law.exists, law.columns_of_masses(m))
        m = matrix @ m
        assert m.min() >= 0 and m.sum() == pytest.approx(1.0, abs=1e-12)
        norm = np.sqrt(np.sum(v * (m / v - 1) ** 2))
        assert np.abs(m - v).sum() <= norm * (1 + 1e-12)
        # + 1e-11: ratio drops of at most ROUND_OFF = 1e-12 move nothing
        assert norm <= rho**k * norm0 * (1 + 1e-9) + 1e-11
    assert np.abs(m - v).sum() < 1e-9


def test_dsmc_consensus_rate_matches_the_iteration_of_its_linear_form():
    """``rho`` is the slowest decay: a start along the second eigenvector decays at
    exactly ``rho`` per period under the chain."""
    law = dsmc_law(n=6, gain=0.5)
    v = law.masses.ravel()
    cells, exists = neighbour_table(law.grid)
    rho = consensus_rate(v, cells, exists, 0.5)
    n = v.size
    lap = sp.lil_matrix((n, n))
    for k in range(1, 5):
        for j in np.flatnonzero(exists[:, k]):
            i = cells[j, k]
            lap[i, j] -= min(v[i], v[j])
            lap[j, j] += min(v[i], v[j])
    s = 0.125 * np.diag(1 / np.sqrt(v)) @ lap.toarray() @ np.diag(1 / np.sqrt(v))
    _, vec = np.linalg.eigh(0.5 * (s + s.T))
    r = 1 + 0.1 * vec[:, 1] / np.sqrt(v) / np.abs(vec[:, 1] / np.sqrt(v)).max()
    m = v * r
    m_next = chain_matrix(cells, exists, consensus_columns(m, v, cells, exists, 0.5)) @ m
    ratio = np.sqrt(np.sum(v * (m_next / v - 1) ** 2) / np.sum(v * (r - 1) ** 2))
    assert ratio == pytest.approx(rho, rel=1e-9)


def test_dsmc_closed_loop_moves_the_swarm_toward_the_target():
    """Through the real config: 3000 robots on 6 x 6 cells, KDE estimates, 20 periods."""
    runs = api.simulate(
        ["control=dsmc", "grid.n=6", "agents.n=3000", "estimator=kde", "sim.dt=0.05",
         "control.period=0.25", "dynamics.sigma=0.0", "log.progress=off"],
        t_final=5.0,
    )  # fmt: skip
    l2 = [m["swarm_l2"] for _, m in runs]
    assert l2[-1] < 0.7 * l2[0]


def test_continuification_tracks_a_moving_target_through_its_rate(monkeypatch):
    """Mean-field plant, exact estimates, the rotating target: with ``-d_t p_*`` in the
    flux equation the tracking error settles an order of magnitude below the lag of the
    same law without it (about ``|d_t p_*| / K``)."""
    overrides = [
        "control=continuification", "control.gain=1.0", "target=moving",
        "target.speed=0.05", "plant=meanfield", "estimator=exact", "grid.n=16",
        "log.progress=off",
    ]  # fmt: skip

    def tail() -> float:
        errors = [m["phat_target_l2"] for _, m in api.simulate(overrides, t_final=12.0)]
        return float(np.mean(errors[-200:]))

    with_rate = tail()
    monkeypatch.setattr(ContinuificationControl, "feedforward_field", lambda *a: None)
    without = tail()
    assert with_rate < 0.01 and with_rate < 0.2 * without, (with_rate, without)
