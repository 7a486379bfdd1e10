"""Raster targets (harness/targets/raster.py): ``target=ring``, ``target=picture``, and the
new options ``target=two_groups`` and ``init=between``.

The references are independent of the code under test: the annulus's area in closed
form, a brute-force midpoint sum of the continuous density written out here, cell
masses worked out by hand for a picture whose pixels the test writes, and a chi-square
test of the samples.
"""

from math import pi, sqrt

import numpy as np
import pytest
from PIL import Image
from scipy.stats import chi2

from harness import api
from harness.estimators.smoothing import cell_masses, smoothed_density
from harness.grid import Grid
from harness.parameters import ParameterError
from harness.targets.densities import Density, ExactCellMasses, ExactSmoothing
from harness.targets.raster import SHIPPED, Picture, Raster, Ring

GRIDS = [
    Grid.square(12),
    Grid.square(30),
    Grid(13, 7, -1.0, 2.0, 0.5, 1.7),  # cells and pixels not aligned, not a square
]


def random_raster(seed: int = 1, shape: tuple[int, int] = (7, 5), floor: float = 0.2) -> Raster:
    """Random weights, some pixels empty."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.0, 1.0, size=shape)
    w[rng.uniform(size=shape) < 0.3] = 0.0
    return Raster(w, floor)


def pixel_density(w: np.ndarray, floor: float, grid: Grid, x: np.ndarray, y: np.ndarray):
    """The raster's density written out independently: the pixel of ``(x, y)`` (row 0 at
    the top) by its weight's share over the pixel area, plus the floor."""
    rows, cols = w.shape
    width, height = grid.x1 - grid.x0, grid.y1 - grid.y0
    col = np.minimum(((x - grid.x0) * cols / width).astype(int), cols - 1)
    row = np.minimum(((grid.y1 - y) * rows / height).astype(int), rows - 1)
    share = w[row, col] / w.sum()
    return (1 - floor) * share / (width * height / (rows * cols)) + floor / (width * height)


@pytest.fixture(scope="module")
def ring() -> Ring:
    return Ring()


@pytest.fixture(scope="module")
def letters() -> Picture:
    return Picture()


def test_the_densities_follow_the_protocol_with_exact_masses_but_no_smoothing(ring, letters):
    for density in (ring, letters, random_raster()):
        assert isinstance(density, Density)
        assert isinstance(density, ExactCellMasses)
        assert not isinstance(density, ExactSmoothing)


@pytest.mark.parametrize("grid", GRIDS, ids=["12", "30", "rectangle"])
def test_cell_masses_sum_to_one_and_the_cell_values_integrate_to_one(grid, ring, letters):
    for density in (ring, letters, random_raster()):
        masses = density.cell_masses(grid)
        assert masses.shape == grid.shape
        assert masses.min() > 0
        assert masses.sum() == pytest.approx(1.0, abs=1e-13)
        assert grid.integrate(density.on_grid(grid)) == pytest.approx(1.0, abs=1e-13)
        np.testing.assert_allclose(density.on_grid(grid) * grid.cell_area, masses, rtol=1e-14)


def test_the_smoothing_falls_back_to_the_cell_values(ring):
    """No ``smoothed`` of its own: the harness's approximation from the cell values."""
    grid = Grid.square(24)
    smooth = smoothed_density(ring, grid, 0.04)
    assert np.isfinite(smooth).all() and smooth.min() > 0
    assert grid.integrate(smooth) == pytest.approx(1.0, abs=1e-3)
    np.testing.assert_array_equal(cell_masses(ring, grid), ring.cell_masses(grid))


def annulus_bound(inner: float, outer: float, resolution: int, k: int = 4) -> float:
    """A bound on the error of the area of an annulus counted by sub-square centres
    (``k x k`` a pixel, side ``s``): a misjudged sub-square is crossed by a circle, so it
    lies in the band ``|rho - r| <= s sqrt(2)``, and errs by at most its area."""
    s = 1.0 / (k * resolution)
    band = s * sqrt(2)
    circles = [r for r in (inner, outer) if r > 0]  # inner = 0: a disc, one circle
    return sum(pi * ((r + band) ** 2 - max(r - band, 0.0) ** 2) for r in circles)


@pytest.mark.parametrize(
    "inner, outer, resolution", [(0.25, 0.35, 512), (0.0, 0.3, 64), (0.1, 0.12, 256)]
)
def test_the_ring_holds_the_annulus_area_within_its_rasterisation_error(inner, outer, resolution):
    """The density's plateau on the ring (in a pixel wholly inside it) is ``(1 - f) / A +
    f`` on the unit square, ``A`` the raster's annulus area, which must be ``pi (outer^2 -
    inner^2)`` up to the bound."""
    floor = 0.1
    ring = Ring(inner=inner, outer=outer, floor=floor, resolution=resolution)
    grid = Grid.square(16)
    plateau = ring.evaluate(np.array([0.5 + (inner + outer) / 2]), np.array([0.5]), grid)[0]
    area = (1 - floor) / (plateau - floor)
    exact = pi * (outer**2 - inner**2)
    bound = annulus_bound(inner, outer, resolution)
    assert abs(area - exact) <= bound
    assert ring.area == pytest.approx(area, rel=1e-12)
    assert ring.area_error_bound() == pytest.approx(bound, rel=1e-12)
    # outside the ring and (when there is one) in its hole, the floor alone
    assert ring.evaluate(np.array([0.02]), np.array([0.02]), grid)[0] == pytest.approx(floor)
    if inner > 0.02:
        hole = ring.evaluate(np.array([0.5 + inner / 2]), np.array([0.5]), grid)[0]
        assert hole == pytest.approx(floor)


def test_the_default_ring_is_far_closer_than_its_bound(ring):
    """Measured (the docstring quotes it): the errors of the crossed sub-squares cancel."""
    exact = pi * (0.35**2 - 0.25**2)
    assert abs(ring.area - exact) < 2e-5 < ring.area_error_bound() / 100


def test_the_ring_is_on_the_unit_square_of_the_image_stretched_over_the_domain():
    """Centre and radii in domain sides: on [0, 2]^2 the plateau is (1 - f) / (4 A) + f / 4."""
    ring = Ring(centre=(0.4, 0.5), inner=0.1, outer=0.2, floor=0.2, resolution=64)
    unit, double = Grid.square(8), Grid.square(8, 2.0)
    p_unit = ring.evaluate(np.array([0.55, 0.4]), np.array([0.5, 0.5]), unit)
    p_double = ring.evaluate(np.array([1.1, 0.8]), np.array([1.0, 1.0]), double)
    np.testing.assert_allclose(p_double, p_unit / 4, rtol=1e-12)
    assert p_unit[0] > p_unit[1] == pytest.approx(0.2)  # on the ring, then in its hole


@pytest.mark.parametrize("grid", [Grid(6, 9, 0.0, 1.3, -0.2, 0.9), Grid.square(5)])
def test_cell_masses_match_a_fine_midpoint_sum_of_the_continuous_density(grid):
    """Each cell summed on ``K x K`` midpoints of the density written out in the test.
    A sub-square errs only where a pixel edge crosses it, by at most ``h^2 max p``; at
    most ``(d / h + 1)`` sub-squares per edge line, ``e`` lines per cell."""
    raster = random_raster(seed=4)
    w = raster.weights
    k = 240
    hx, hy = grid.dx / k, grid.dy / k
    x = grid.x0 + (np.arange(grid.nx * k) + 0.5) * hx
    y = grid.y0 + (np.arange(grid.ny * k) + 0.5) * hy
    p = pixel_density(w, raster.floor, grid, x[None, :], y[:, None])
    brute = p.reshape(grid.ny, k, grid.nx, k).sum(axis=(1, 3)) * hx * hy
    rows, cols = w.shape
    lines = (int(np.ceil(grid.dx * cols / (grid.x1 - grid.x0))) + 1) + (
        int(np.ceil(grid.dy * rows / (grid.y1 - grid.y0))) + 1
    )
    bound = lines * (k + 1) * hx * hy * p.max()
    err = np.abs(raster.cell_masses(grid) - brute)
    assert err.max() <= bound
    assert err.max() < 2e-2 * brute.min()  # and small: the bound is not vacuous


def chi_square_p(density: Density, grid: Grid, n: int, seed: int) -> float:
    """The p-value of Pearson's chi-square test of ``n`` samples binned on the grid's
    cells against the cell masses (``M - 1`` degrees of freedom, every expected count
    far above 5)."""
    pts = density.sample(n, grid, np.random.default_rng(seed))
    assert pts.shape == (2, n)
    assert (pts[0] >= grid.x0).all() and (pts[0] <= grid.x1).all()
    assert (pts[1] >= grid.y0).all() and (pts[1] <= grid.y1).all()
    ex = np.linspace(grid.x0, grid.x1, grid.nx + 1)
    ey = np.linspace(grid.y0, grid.y1, grid.ny + 1)
    counts, _, _ = np.histogram2d(pts[1], pts[0], bins=[ey, ex])
    expected = n * density.cell_masses(grid)
    assert expected.min() > 5
    stat = float(((counts - expected) ** 2 / expected).sum())
    return float(chi2.sf(stat, grid.size - 1))


@pytest.mark.parametrize(
    "which, grid",
    [
        ("ring", Grid.square(16)),
        ("letters", Grid.square(20)),
        ("raster", Grid(9, 11, -1.0, 2.0, 0.5, 1.7)),
    ],
)
def test_the_samples_follow_the_cell_masses(which, grid, ring, letters):
    """200000 samples at a fixed seed: a correct sampler fails at level 1e-3 for one seed
    in a thousand; a sampler off by a pixel, a flipped image or a lost floor gives a
    p-value of zero to round-off at this n."""
    density = {"ring": ring, "letters": letters, "raster": random_raster()}[which]
    assert chi_square_p(density, grid, 200_000, seed=11) > 1e-3


def test_a_flipped_sampler_would_be_caught(letters):
    """The chi-square test has the power to tell the picture from its mirror image."""
    grid = Grid.square(20)
    flipped = Raster(letters.weights[::-1], letters.floor)
    pts = flipped.sample(200_000, grid, np.random.default_rng(11))
    ex = np.linspace(0, 1, 21)
    counts, _, _ = np.histogram2d(pts[1], pts[0], bins=[ex, ex])
    expected = 200_000 * letters.cell_masses(grid)
    stat = float(((counts - expected) ** 2 / expected).sum())
    assert chi2.sf(stat, grid.size - 1) < 1e-100


def write_png(path, pixels: np.ndarray) -> str:
    Image.fromarray(pixels.astype(np.uint8), mode="L").save(path)
    return str(path)


def test_a_picture_has_the_masses_worked_out_by_hand(tmp_path):
    """A 4 x 4 picture: black top-left, 80 % dark (grey 51) bottom-right, white elsewhere.
    Weights 1 and 0.8 of total 1.8; floor 0.1 spread over 16 cells."""
    pixels = np.full((4, 4), 255)
    pixels[0, 0] = 0
    pixels[3, 3] = 51
    pic = Picture(path=write_png(tmp_path / "two.png", pixels), floor=0.1)
    masses = pic.cell_masses(Grid.square(4))
    expected = np.full((4, 4), 0.1 / 16)
    expected[3, 0] += 0.9 * 1.0 / 1.8  # grid row 3 is the top, column 0 the left
    expected[0, 3] += 0.9 * 0.8 / 1.8  # grid row 0 is the bottom
    np.testing.assert_allclose(masses, expected, rtol=1e-12)
    # on 8 x 8 cells each pixel splits into four equal cells
    fine = pic.cell_masses(Grid.square(8))
    np.testing.assert_allclose(fine[6:, :2], np.full((2, 2), 0.9 / 1.8 / 4 + 0.1 / 64), rtol=1e-12)
    np.testing.assert_allclose(fine[:2, 6:], np.full((2, 2), 0.9 * 0.8 / 1.8 / 4 + 0.1 / 64))
    np.testing.assert_allclose(fine[2:6, 2:6], 0.1 / 64, rtol=1e-12)
    # on 6 x 6 cells, the top-left pixel [0, 0.25] x [0.75, 1] covers cell (5, 0) wholly
    # ([0, 1/6] x [5/6, 1]) and half of each of its neighbours: (1/6 x 1/12) / (1/16)
    third = pic.cell_masses(Grid.square(6))
    pixel_mass = 0.9 / 1.8
    assert third[5, 0] == pytest.approx(pixel_mass * (1 / 36) * 16 + 0.1 / 36, rel=1e-12)
    assert third[5, 1] == pytest.approx(pixel_mass * (1 / 72) * 16 + 0.1 / 36, rel=1e-12)
    assert third[4, 1] == pytest.approx(pixel_mass * (1 / 144) * 16 + 0.1 / 36, rel=1e-12)
    # without invert the light pixels carry the mass: weights 0, 0.2 and 14 whites
    light = Picture(path=str(tmp_path / "two.png"), floor=0.5, invert=False)
    total = 14 + 51 / 255
    assert light.cell_masses(Grid.square(4))[3, 1] == pytest.approx(0.5 / total + 0.5 / 16)


def test_the_shipped_letters_are_a_256_square_grey_picture(letters):
    image = Image.open(SHIPPED / "letters.png")
    assert (image.size, image.mode) == ((256, 256), "L")
    dark = letters.weights > 0.5
    assert 0.1 < dark.mean() < 0.3  # the letters' ink
    assert not dark[:40].any() and not dark[-40:].any()  # a white margin above and below
    assert dark[:, :128].any() and dark[:, 128:].any()  # D on the left, L on the right


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda tmp: Picture(path=str(tmp / "missing.png")), "path"),
        (lambda tmp: Picture(path=str(tmp / "text.png")), "path"),
        (lambda tmp: Picture(path=str(tmp)), "path"),
        (lambda tmp: Picture(path=str(tmp / "white.png")), "path"),
        (lambda tmp: Picture(path=str(tmp / "white.png"), invert=False, floor=0.0), "floor"),
        (lambda tmp: Picture(shipped="nothing"), "shipped"),
        (lambda tmp: Picture(floor=0), "floor"),
        (lambda tmp: Picture(floor=1.5), "floor"),
        (lambda tmp: Picture(invert="yes"), "invert"),
        (lambda tmp: Ring(floor=0), "floor"),
        (lambda tmp: Ring(floor=1.5), "floor"),
        (lambda tmp: Ring(inner=0.3, outer=0.3), "outer"),
        (lambda tmp: Ring(inner=0.4, outer=0.3), "outer"),
        (lambda tmp: Ring(inner=-0.1), "inner"),
        (lambda tmp: Ring(centre=(0.2, 0.5)), "outer"),  # the ring leaves the domain
        (lambda tmp: Ring(centre=(0.5, 1.5)), "centre"),
        (lambda tmp: Ring(centre=(0.5,)), "centre"),
        (lambda tmp: Ring(resolution=8), "resolution"),
        (lambda tmp: Raster(np.zeros((4, 4))), "weights"),
        (lambda tmp: Raster(-np.ones((4, 4))), "weights"),
        (lambda tmp: Raster(np.full((4, 4), np.nan)), "weights"),
        (lambda tmp: Raster(np.ones(4)), "weights"),
        (lambda tmp: Raster(np.ones((4, 4)), floor=0.0), "floor"),
    ],
    ids=[
        "missing-file", "not-a-png", "a-directory", "all-white", "floor-checked-first",
        "unknown-shipped", "floor-0", "floor-1.5", "invert-not-bool", "ring-floor-0",
        "ring-floor-1.5", "inner-equals-outer", "inner-above-outer", "inner-negative",
        "ring-leaves-the-domain", "centre-outside", "centre-not-a-pair", "resolution-8",
        "all-zero", "negative", "nan", "one-dimensional", "raster-floor-0",
    ],
)  # fmt: skip
def test_bad_inputs_are_refused_naming_the_key(tmp_path, make, name):
    (tmp_path / "text.png").write_text("not a picture\n")
    write_png(tmp_path / "white.png", np.full((8, 8), 255))
    with pytest.raises(ParameterError) as err:
        make(tmp_path)
    assert err.value.name == name
    assert "\n" not in str(err.value)


def test_a_ring_leaving_the_domain_is_refused_on_the_command_line(refusal):
    line = refusal(["target=ring", "target.outer=0.6", "grid.n=12", "agents.n=40"])
    assert line is not None and line.startswith("invalid config: target.outer=0.6: a radius <= 0.5")
    line = refusal(["target=picture", "target.path=/nonexistent/p.png", "grid.n=12"])
    assert line is not None and line.startswith("invalid config: target.path='/nonexistent/p.png'")


@pytest.mark.parametrize(
    "overrides",
    [
        ["target=ring"],
        ["target=picture"],
        ["target=two_groups"],
        ["target=two_groups", "init=between"],
        ["init=between"],
        ["target=ring", "domain=rooms"],
        ["target=picture", "domain=rooms", "init=left_room"],
    ],
    ids=lambda o: " ".join(o),
)
def test_every_new_option_composes_and_runs(overrides):
    """The smoke run for three steps of 0.02 s (0.05 s is not a whole number of steps)."""
    cfg = api.compose([*overrides, "+experiment=smoke"])
    steps = list(api.simulate(cfg, t_final=0.06))
    assert [rec.step for rec, _ in steps] == [0, 1, 2, 3]
    for _, metrics in steps:
        assert np.isfinite(metrics["phat_target_l2"])
        assert metrics["swarm_l2"] is None or np.isfinite(metrics["swarm_l2"])
    assert np.isfinite(steps[0][1]["swarm_l2"])
