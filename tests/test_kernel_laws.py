"""The kernel laws of the positions (harness/control/kernels.py): the MMD flow and SVGD.

Each check is against something the laws' code does not compute: the continuous target's
own density and score (closed forms of the mixture), plain sums written here or in the
module's ``*_reference`` functions (2-D image sums, not the separable binned path), the
KDE and the smoother of the harness, finite differences, and the Fokker-Planck step."""

import numpy as np
import pytest

from harness import api
from harness.control.kernels import image_kernel, slowest_rate
from harness.control.mmd import MMDControl, mmd_feedback_reference
from harness.control.paper import PaperControl
from harness.control.svgd import SVGDControl, svgd_feedback_reference
from harness.estimators.kde import KDE, kernel_1d
from harness.estimators.smoothing import Smoother
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.records import ControlInput, Estimate
from harness.runs.build import component
from harness.targets.densities import DEFAULT_TARGET, Box, GaussianMixture, Target
from harness.velocity import interpolate
from tests.conftest import SMOKE

SIGMA = 5e-5
LENGTH = 0.06
LAWS = {
    "mmd": lambda target, **kw: MMDControl(target, 0.0048, SIGMA, LENGTH, **kw),
    "svgd": lambda target, **kw: SVGDControl(target, 0.0064, SIGMA, LENGTH, **kw),
}
DEFAULT_TARGET_SHIFTED = GaussianMixture(
    means=((0.5, -0.1), (0.92, 0.08), (0.65, 0.14)),
    stds=(0.09, 0.07, 0.11),
    weights=(0.35, 0.25, 0.40),
)
NO_ESTIMATE = Estimate(np.zeros((30, 30)), np.zeros((2, 30, 30)))


def robots(positions):
    return ControlInput(0.0, NO_ESTIMATE, positions=positions)


def density(p):
    return ControlInput(0.0, NO_ESTIMATE, density=p)


def centres(grid: Grid) -> np.ndarray:
    x, y = grid.mesh
    return np.stack([x.ravel(), y.ravel()])


def mixture_score(points: np.ndarray, grid: Grid) -> np.ndarray:
    """``grad log p_*`` of the default target's continuous density, in closed form."""
    d = DEFAULT_TARGET
    x, y = points
    grad = np.zeros((2, x.size))
    for w, (mx, my), s in zip(d._w, d.means, d.stds, strict=True):
        bump = w * np.exp(-((x - mx) ** 2 + (y - my) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)
        grad += bump * np.stack([-(x - mx), -(y - my)]) / s**2
    grad *= (1 - d.floor) / d.mixture_mass(grid)
    return grad / d.evaluate(x, y, grid)


def midpoint_target(m: int, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature points (the centres of an ``m`` x ``m`` grid) and masses of the
    continuous target."""
    fine = Grid.square(m)
    pts = centres(fine)
    p = DEFAULT_TARGET.evaluate(pts[0], pts[1], grid)
    return pts, p * fine.cell_area / (p.sum() * fine.cell_area)


def images_kernel(px, py, ux, uy, length, grid, parity=(1, 1)):
    """The 2-D normalised Gaussian with its eight wall images, plainly: ``(P, S)``."""
    out = 0.0
    for sx, ix in ((1, ux), (parity[0], 2 * grid.x0 - ux), (parity[0], 2 * grid.x1 - ux)):
        for sy, iy in ((1, uy), (parity[1], 2 * grid.y0 - uy), (parity[1], 2 * grid.y1 - uy)):
            z2 = (px[:, None] - ix[None, :]) ** 2 + (py[:, None] - iy[None, :]) ** 2
            out = out + sx * sy * np.exp(-z2 / (2 * length**2)) / (2 * np.pi * length**2)
    return out


def perturbed(target: Target) -> np.ndarray:
    x, y = target.grid.mesh
    p = target.p * (1 + 0.3 * np.cos(np.pi * x) * np.cos(2 * np.pi * y))
    return p / target.grid.integrate(p)


# --- kernels ------------------------------------------------------------------------------


def test_image_kernel_is_the_kdes_mirrored_kernel_and_its_odd_twin_vanishes_on_walls(rng):
    u = np.concatenate([rng.uniform(0, 1, 40), [0.0, 0.01, 0.99, 1.0]])
    x = np.linspace(0.0, 1.0, 41)
    g, _, d_point = image_kernel(u, x, LENGTH, 0.0, 1.0, +1)
    kg, kdg = kernel_1d(u, x, LENGTH, 0.0, 1.0, True)
    np.testing.assert_allclose(g, kg, rtol=0, atol=1e-13 * kg.max())
    np.testing.assert_allclose(d_point, kdg, rtol=0, atol=1e-13 * np.abs(kdg).max())
    for parity in (+1, -1, 0):
        g, d_source, d_point = image_kernel(u, x, LENGTH, 0.0, 1.0, parity)
        h = 1e-6
        up = image_kernel(u + h, x, LENGTH, 0.0, 1.0, parity)[0]
        um = image_kernel(u - h, x, LENGTH, 0.0, 1.0, parity)[0]
        xp = image_kernel(u, x + h, LENGTH, 0.0, 1.0, parity)[0]
        xm = image_kernel(u, x - h, LENGTH, 0.0, 1.0, parity)[0]
        scale = np.abs(d_source).max()
        assert np.abs((up - um) / (2 * h) - d_source).max() < 1e-6 * scale
        assert np.abs((xp - xm) / (2 * h) - d_point).max() < 1e-6 * scale
    g = image_kernel(u, x, LENGTH, 0.0, 1.0, -1)[0]
    # the Dirichlet kernel vanishes with the point or the source on a wall (up to the
    # images left out, exp(-(L / l)^2 / 2) = 5e-61 of a peak here, and round-off)
    assert np.abs(g[:, [0, -1]]).max() < 1e-14 * g.max()
    assert np.abs(g[[-4, -1], :]).max() < 1e-14 * g.max()
    assert np.abs(image_kernel(u, x, LENGTH, 0.0, 1.0, +1)[2][:, [0, -1]]).max() < 1e-12


def test_kernel_length_and_gains_are_checked(target30):
    for law in (MMDControl, SVGDControl):
        with pytest.raises(ParameterError) as err:
            law(target30, 0.003, SIGMA, 0.2)
        assert err.value.name == "length"
        with pytest.raises(ParameterError) as err:
            law(target30, -1.0, SIGMA, LENGTH)
        with pytest.raises(ParameterError) as err:
            law(target30, 0.003, SIGMA, LENGTH, bin_factor=0)
        assert err.value.name == "bin_factor"
        assert law.gives_field and not law.own_estimates and not law.needs_robots


# --- the feedback vanishes at the target ---------------------------------------------------


@pytest.mark.parametrize("name", sorted(LAWS))
def test_mean_field_feedback_vanishes_at_the_target(name, target30):
    law = LAWS[name](target30)
    at_target = law.feedback(density(target30.p))
    away = law.feedback(density(perturbed(target30)))
    assert np.abs(away).max() > 1e-3  # length / s
    assert np.abs(at_target).max() < 1e-13 * np.abs(away).max()
    # and the field is then the compensation alone, sigma grad log p_* on the faces
    field = law(density(target30.p)).field
    g = target30.grid
    np.testing.assert_allclose(field.face_x, SIGMA * np.diff(target30.log_p, axis=1) / g.dx)


def expected_binning(nodes, grid: Grid, m: int = 1600) -> np.ndarray:
    """The expectation of the robots' linear-binning weights for robots drawn from the
    continuous target: each point of an m x m midpoint rule split over its four nodes."""
    pts, mass = midpoint_target(m, grid)
    bx, by = nodes.bins
    tx, ty = pts[0] * bx, pts[1] * by
    ix, iy = np.minimum(tx.astype(int), bx - 1), np.minimum(ty.astype(int), by - 1)
    fx, fy = tx - ix, ty - iy
    size, base = (bx + 1) * (by + 1), iy * (bx + 1) + ix
    w = sum(
        np.bincount(base + shift, mass * wt, size)
        for shift, wt in (
            (0, (1 - fx) * (1 - fy)),
            (1, fx * (1 - fy)),
            (bx + 1, (1 - fx) * fy),
            (bx + 2, fx * fy),
        )
    )
    return w.reshape(by + 1, bx + 1)


@pytest.mark.parametrize("name", sorted(LAWS))
def test_expected_robot_feedback_vanishes_at_the_target(name, target30, rng):
    """Robots drawn from the continuous p_* bin, in expectation, to the weights computed
    here; the law's feedback of them is zero up to the law's own quadrature of those
    weights (TARGET_REFINEMENT, ~1e-4 relative), far below the binning's bias (3e-3)."""
    law = LAWS[name](target30)
    w = expected_binning(law.nodes, target30.grid)
    swarm = law.feedback(robots(Box().sample(4000, target30.grid, rng)))
    assert np.abs(law.binned(w)).max() < 1e-3 * np.abs(swarm).max()


def test_stein_identity_holds_with_the_wall_images_and_fails_without(grid30):
    """The derivation of the wall method: int p_* [k_a s_a + d_a k_a] = 0 for the
    Dirichlet/Neumann kernels (boundary term zero), not for the plain Gaussian."""
    pts, mass = midpoint_target(150, grid30)
    score = mixture_score(pts, grid30)
    where = np.stack(np.meshgrid(np.linspace(0.0, 1.0, 9), np.linspace(0.0, 1.0, 9))).reshape(2, -1)
    stein = svgd_feedback_reference(where, pts, mass, score, grid30, 1.0, LENGTH)
    # one term alone, for the scale
    k = images_kernel(where[0], where[1], pts[0], pts[1], LENGTH, grid30, (-1, 1))
    term = (k * score[0]) @ mass
    assert np.abs(term).max() > 1.0
    assert np.abs(stein).max() < 1e-4 * np.abs(term).max()

    # plain Gaussian (no images): the boundary term oint k p_* n_x dS is left, here
    # taken along the two x-walls by the midpoint rule
    def gauss(ax, ay, ux, uy):
        z2 = (ax[:, None] - ux) ** 2 + (ay[:, None] - uy) ** 2
        return np.exp(-z2 / (2 * LENGTH**2)) / (2 * np.pi * LENGTH**2)

    plain = gauss(where[0], where[1], pts[0], pts[1])
    dk = (where[0][:, None] - pts[0]) / LENGTH**2 * plain
    plain_stein = (plain * score[0] + dk) @ mass
    wall_y = (np.arange(2000) + 0.5) / 2000
    boundary = 0.0
    for wall, normal in ((0.0, -1.0), (1.0, 1.0)):
        wall_x = np.full_like(wall_y, wall)
        p_wall = DEFAULT_TARGET.evaluate(wall_x, wall_y, grid30)
        boundary += normal * gauss(where[0], where[1], wall_x, wall_y) @ p_wall / 2000
    assert np.abs(boundary).max() > 1.0
    assert np.abs(plain_stein - boundary).max() < 1e-3 * np.abs(boundary).max()


# --- against plain sums and finite differences ---------------------------------------------


def test_mmd_of_robots_is_the_gradient_of_the_binned_kde_and_of_a_density_the_smoother(
    target30, rng
):
    law = LAWS["mmd"](target30)
    positions = Box().sample(3000, target30.grid, rng)
    _, grad = KDE(target30.grid, LENGTH, method="binned")(positions)
    # no robots: the target's term alone, +beta grad(k_l * p_*) as the binning sees it
    target_term = law.binned(np.zeros_like(law.target_weights))
    expected = -law.beta * grad + target_term
    np.testing.assert_allclose(law.feedback(robots(positions)), expected, atol=1e-12)
    p = perturbed(target30)
    smoother = Smoother(target30.grid, LENGTH)
    expected = -law.beta * (smoother.matrices(p)[1] - smoother.matrices(target30.p)[1])
    np.testing.assert_allclose(law.feedback(density(p)), expected, atol=1e-14)


def potential_gradient(xs, ys, sources, masses, grid, h=1e-5):
    """Central differences of sum_j m_j k(x, u_j) (plain sums with images) on xs x ys."""
    px, py = (a.ravel() for a in np.meshgrid(xs, ys))
    ux, uy = sources

    def phi(ax, ay):
        return images_kernel(ax, ay, ux, uy, LENGTH, grid) @ masses

    gx = (phi(np.clip(px + h, 0, 1), py) - phi(np.clip(px - h, 0, 1), py)) / (
        np.clip(px + h, 0, 1) - np.clip(px - h, 0, 1)
    )
    gy = (phi(px, np.clip(py + h, 0, 1)) - phi(px, np.clip(py - h, 0, 1))) / (
        np.clip(py + h, 0, 1) - np.clip(py - h, 0, 1)
    )
    return np.stack([gx, gy]).reshape(2, len(ys), len(xs))


def test_mmd_velocity_is_minus_beta_grad_of_its_potential(target30, rng):
    law = LAWS["mmd"](target30)
    g = target30.grid
    xs = np.concatenate([[0.003], rng.uniform(0, 1, 6), [0.998]])
    ys = np.concatenate([[0.002], rng.uniform(0, 1, 5), [0.999]])
    # mean-field form: the potential k_l * (p - p_*) of the cell masses, exactly
    p = perturbed(target30)
    cells = centres(g)
    grad = potential_gradient(xs, ys, cells, ((p - target30.p) * g.cell_area).ravel(), g)
    v = law.feedback_at(xs, ys, density=p)
    assert np.abs(v + law.beta * grad).max() < 1e-6 * np.abs(v).max()
    # robots: (1/N) sum_j k(x, X_j) - k_l * p_* (midpoint rule of the continuous p_*)
    positions = Box(0.0, 0.8, 0.1, 1.0).sample(300, g, rng)
    pts, mass = midpoint_target(120, g)
    grad = potential_gradient(xs, ys, positions, np.full(300, 1 / 300), g)
    grad -= potential_gradient(xs, ys, pts, mass, g)
    v = law.feedback_at(xs, ys, positions=positions)
    # the binning's error, O((s / l)^2), measured 0.4 % of the largest velocity
    assert np.abs(v + law.beta * grad).max() < 1.5e-2 * np.abs(v).max()


@pytest.mark.parametrize("start", ["box", "target"])
def test_binned_svgd_matches_the_plain_sum(start, target30, rng):
    """Binned sums at the centres against the O(N n^2) plain sum over 400 robots
    (their scores from the law's spline; the plain sum has no target term, which is
    zero by Stein's identity up to the binning's own bias, subtracted by the law)."""
    law = LAWS["svgd"](target30)
    g = target30.grid
    init = Box() if start == "box" else DEFAULT_TARGET
    positions = init.sample(400, g, rng)
    v = law.feedback(robots(positions)).reshape(2, -1)
    ref = svgd_feedback_reference(
        centres(g), positions, np.full(400, 1 / 400), law.score(positions), g, law.eps, LENGTH
    )
    rms = np.sqrt(np.mean(ref**2))
    # measured: 0.5 % (box) and 1 % (target) of the rms, 1 % of the largest
    assert np.sqrt(np.mean((v - ref) ** 2)) < 2.5e-2 * rms
    assert np.abs(v - ref).max() < 4e-2 * np.abs(ref).max()


@pytest.mark.parametrize("start", ["box", "target"])
@pytest.mark.parametrize("name", sorted(LAWS))
def test_robots_following_the_grid_field_against_the_exact_per_robot_sum(
    name, start, target30, rng
):
    """The robots interpolate the centres bilinearly; the exact law sums over the robots
    at each robot. The difference is the interpolation's (dx^2 / 8 times the second
    derivatives at the kernel's scale) plus the binning's."""
    law = LAWS[name](target30)
    g = target30.grid
    init = Box() if start == "box" else DEFAULT_TARGET
    positions = init.sample(400, g, rng)
    moved = interpolate(g, law.feedback(robots(positions)), positions)
    w = np.full(400, 1 / 400)
    if name == "mmd":
        pts, mass = midpoint_target(90, g)
        exact = mmd_feedback_reference(positions, positions, pts, mass, g, law.beta, LENGTH)
    else:
        score = law.score(positions)
        exact = svgd_feedback_reference(positions, positions, w, score, g, law.eps, LENGTH)
    error = np.sqrt(np.mean((moved - exact) ** 2)) / np.sqrt(np.mean(exact**2))
    # measured at N = 400 (rms relative): 4 % (box), 8 % (target: the feedback is then
    # the swarm's fluctuation alone, at the kernel's scale)
    assert error < (0.07 if start == "box" else 0.14)


@pytest.mark.parametrize("name", sorted(LAWS))
def test_rectangular_grid_against_the_plain_sums(name, rng):
    """dx != dy, nx != ny and a domain not at the origin: the axes do not mix."""
    g = Grid(37, 23, 0.2, 1.2, -0.3, 0.3)
    target = Target.from_density(g, DEFAULT_TARGET_SHIFTED)
    law = LAWS[name](target)
    positions = Box(0.2, 1.0, -0.3, 0.2).sample(300, g, rng)
    v = law.feedback(robots(positions)).reshape(2, -1)
    w = np.full(300, 1 / 300)
    if name == "mmd":
        fine = Grid(74, 46, 0.2, 1.2, -0.3, 0.3)
        pts = centres(fine)
        mass = DEFAULT_TARGET_SHIFTED.on_grid(fine).ravel() * fine.cell_area
        ref = mmd_feedback_reference(centres(g), positions, pts, mass, g, law.beta, LENGTH)
    else:
        ref = svgd_feedback_reference(
            centres(g), positions, w, law.score(positions), g, law.eps, LENGTH
        )
    assert np.sqrt(np.mean((v - ref) ** 2)) < 2.5e-2 * np.sqrt(np.mean(ref**2))
    assert np.abs(law.feedback(density(target.p))).max() == 0.0
    assert np.abs(law.feedback_at(np.array([0.2, 1.2]), g.y, positions=positions)[0]).max() < (
        1e-12 * np.abs(v).max()
    )


@pytest.mark.parametrize("name", sorted(LAWS))
def test_normal_velocity_vanishes_at_the_walls(name, target30, rng):
    law = LAWS[name](target30)
    g = target30.grid
    positions = rng.uniform(0.0, 1.0, (2, 500))
    positions[:, :100] = rng.uniform(0.0, 0.02, (2, 100))  # crowd a corner
    for given in ({"positions": positions}, {"density": perturbed(target30)}):
        across_x = law.feedback_at(np.array([0.0, 1.0]), g.y, **given)
        across_y = law.feedback_at(g.x, np.array([0.0, 1.0]), **given)
        scale = np.abs(law.feedback_at(g.x, g.y, **given)).max()
        assert np.abs(across_x[0]).max() < 1e-12 * scale
        assert np.abs(across_y[1]).max() < 1e-12 * scale
        # the tangential components do not vanish there
        assert np.abs(across_x[1]).max() > 1e-3 * scale
        assert np.abs(across_y[0]).max() > 1e-3 * scale


def test_svgd_score_is_the_targets(target30, rng):
    law = LAWS["svgd"](target30)
    pts = rng.uniform(0.0, 1.0, (2, 4000))
    exact = mixture_score(pts, target30.grid)
    rms = np.sqrt(np.mean(exact**2))
    assert np.sqrt(np.mean((law.score(pts) - exact) ** 2)) < 1e-5 * rms


@pytest.mark.parametrize("name", sorted(LAWS))
def test_a_target_given_by_cell_values_only(name, target30, rng):
    """Without a continuous density the robot form takes exp of the spline of log p_*'s
    cell values as the target: the score is then the spline's (1.5 % rms from the closed
    form on the paper's grid), and the laws run as before."""
    values = Target.from_values(target30.grid, target30.p)
    assert values.density is None
    law = LAWS[name](values)
    assert np.abs(law.feedback(density(target30.p))).max() < 1e-16
    v = law.feedback(robots(Box().sample(500, target30.grid, rng)))
    assert np.isfinite(v).all() and np.abs(v).max() > 1e-3
    with_density = LAWS[name](target30)
    assert np.abs(law.target_weights - with_density.target_weights).max() < 2e-3 * (
        with_density.target_weights.max()
    )
    if name == "svgd":
        pts = rng.uniform(0.0, 1.0, (2, 4000))
        exact = mixture_score(pts, target30.grid)
        error = np.sqrt(np.mean((law.score(pts) - exact) ** 2))
        assert error < 2e-2 * np.sqrt(np.mean(exact**2))


# --- fixed points with noise, default gains --------------------------------------------------


@pytest.mark.parametrize("name", sorted(LAWS))
def test_noise_compensation_makes_the_target_the_fixed_point(name):
    g = Grid.square(16)
    target = Target.from_density(g, DEFAULT_TARGET)
    sigma, dt = 2e-3, 0.05
    model = FokkerPlanck(g, sigma)
    drift = {}
    for compensate in (True, False):
        cls = MMDControl if name == "mmd" else SVGDControl
        law = cls(target, 0.01, sigma, LENGTH, noise_compensation=compensate)
        p = target.p
        for _ in range(100):
            p = model.step(p, law(density(p)).field, dt)
        drift[compensate] = g.l2(p - target.p) / g.l2(target.p)
    assert drift[True] < 1e-12
    assert drift[False] > 1e-3


def test_default_gains_match_the_papers_slowest_decay_rate(compose, target30):
    """The defaults of conf/control/{mmd,svgd}.yaml give the mean-field loop linearised
    about the default target the slowest decay rate of the paper's law at its default
    gain (33.9 s), on the paper's grid and noise."""
    paper = slowest_rate(PaperControl(target30, 0.003, SIGMA), target30, SIGMA)
    assert 1 / paper == pytest.approx(33.9, rel=0.01)
    for name in ("mmd", "svgd"):
        cfg = compose([f"control={name}"])
        law = component(cfg, "control", target=target30)
        assert law.length == LENGTH
        assert slowest_rate(law, target30, SIGMA) == pytest.approx(paper, rel=0.01)


# --- closed loops through the config ---------------------------------------------------------


@pytest.mark.parametrize("estimator", ["filters", "kde"])
@pytest.mark.parametrize("name", sorted(LAWS))
def test_closed_loop_with_robots_runs(name, estimator, compose):
    cfg = compose([f"control={name}", "plant=agents", f"estimator={estimator}", *SMOKE])
    steps = list(api.simulate(cfg))
    assert len(steps) == 11
    first, last = steps[0][0], steps[-1][0]
    assert first.command.field is not None and first.command.robots is None
    assert all(rec.command.is_finite() for rec, _ in steps)
    assert np.abs(last.positions - first.positions).max() > 0
    assert all(np.isfinite(m["phi_l2"]) for _, m in steps)


@pytest.mark.parametrize("plant", ["meanfield", "agents"])
@pytest.mark.parametrize("name", sorted(LAWS))
def test_mean_field_run_from_the_target_stays_there(name, plant, compose):
    """Started at p_* the mean-field density (the meanfield plant's state, the agents
    plant's N -> infinity limit) stays at p_* to round-off: the feedback vanishes there
    exactly and the face drift makes p_* the Fokker-Planck step's steady state."""
    cfg = compose([f"control={name}", f"plant={plant}", "estimator=kde", *SMOKE])
    cfg.init = cfg.target
    steps = list(api.simulate(cfg, t_final=1.0, copy=False))
    assert len(steps) == 51
    key = "phi_l2" if plant == "meanfield" else "limit_target_l2"
    values = [m[key] for _, m in steps if m[key] is not None]
    assert len(values) > 5 and max(values) < 1e-12
