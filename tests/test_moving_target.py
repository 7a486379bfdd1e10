"""Moving targets (``target=moving``, harness/targets/moving.py): the static run at speed 0, the
analytic ``d_t p_*``, the paper law's feedforward (harness/targets/feedforward.py) and its
tracking error against the derivation's prediction, the metrics against ``p_*(t)``, and
the laws that are refused.
"""

import numpy as np
import pytest
from mcap.stream_reader import StreamReader

from harness import api
from harness.control.heat import HeatControl, LangevinControl
from harness.control.paper import PaperControl, paper_law
from harness.estimators.kde import KDE
from harness.estimators.smoothing import smoothed_target
from harness.fokker_planck import FokkerPlanck, rate
from harness.grid import Grid
from harness.records import ControlInput, Estimate, RobotEstimates
from harness.runs.build import build
from harness.runs.run import run
from harness.targets.densities import DEFAULT_TARGET, Target
from harness.targets.feedforward import NeumannPoisson, sg_flux, sg_velocity, sg_velocity_reference
from harness.targets.moving import RotatingMixture, TargetPath
from harness.velocity import VelocityField, interpolate

SHORT = [
    "grid.n=10",
    "agents.n=100",
    "sim.t_final=0.1",
    "sim.dt=0.02",
    "log.progress=off",
    "log.floor_draws=2",
]


def moving(speed: float = 0.01, **kw: float) -> RotatingMixture:
    d = DEFAULT_TARGET
    return RotatingMixture(d.means, d.stds, d.weights, d.floor, speed=speed, **kw)


def payloads(path):
    """Every message of a log: channel, log and publish times, payload bytes."""
    with open(path, "rb") as f:
        return [
            (r.channel_id, r.log_time, r.publish_time, r.data)
            for r in StreamReader(f).records
            if type(r).__name__ == "Message"
        ]


# ---------------------------------------------------------------- speed 0 is the static run
def test_speed_zero_gives_the_static_runs_messages(tmp_path, compose):
    # every message of every channel is compared, payload bytes included; the metadata
    # records are not (the `config` record names target=moving and its keys)
    run(compose([*SHORT, "seed=5"]), tmp_path / "static")
    zero = ["target=moving", "target.speed=0", "control.feedforward=true"]
    run(compose([*SHORT, "seed=5", *zero]), tmp_path / "zero")
    run(compose([*SHORT, "seed=5", "target=moving", "target.speed=0.05"]), tmp_path / "fast")
    static, still = (payloads(tmp_path / n / "run.mcap") for n in ("static", "zero"))
    assert len(static) > 10 and static == still
    assert payloads(tmp_path / "fast" / "run.mcap") != static  # a moving target does differ


# ---------------------------------------------------------------- the target's path
def test_the_farthest_centre_moves_at_the_speed_on_a_closed_path():
    d = moving(0.02)
    r = [np.hypot(mx - 0.5, my - 0.5) for mx, my in d.means]
    h, t = 1e-4, 3.0
    a, b = np.array(d.centres(t - h)), np.array(d.centres(t + h))
    speeds = np.hypot(*(b - a).T) / (2 * h)
    assert speeds.max() == pytest.approx(0.02, rel=1e-7)
    assert speeds == pytest.approx(0.02 * np.array(r) / max(r), rel=1e-7)
    turn = 2 * np.pi / d.omega
    assert np.allclose(d.centres(turn), d.means, atol=1e-12)
    still = moving(0.0)
    assert still.at(5.0) is still._base  # speed 0: the static mixture itself


@pytest.mark.parametrize("t", [0.0, 7.3, 120.0])
def test_rate_is_the_time_derivative_of_the_target_on_the_grid(t):
    grid = Grid.square(24)
    d = moving(0.01)
    analytic = d.rate(grid, t)
    h = 1e-3
    fd = (d.at(t + h).on_grid(grid) - d.at(t - h).on_grid(grid)) / (2 * h)
    scale = np.abs(analytic).max()
    assert scale > 0.1  # the target does move
    assert np.abs(analytic - fd).max() < 1e-7 * scale
    assert abs(grid.integrate(analytic)) < 1e-14 * scale  # mass is conserved on the grid


def test_a_path_that_leaves_the_domain_and_bad_speeds_are_refused(refusal):
    message = refusal(["target=moving", "target.centre=[0.2,0.2]"])
    assert message is not None and message.startswith("invalid config: target.centre=")
    assert "\n" not in message
    message = refusal(["target=moving", "target.speed=-1"])
    assert message == "invalid config: target.speed=-1: a finite number >= 0"
    # a static target may sit anywhere: the rotation centre is then not checked
    assert refusal(["target=moving", "target.speed=0", "target.centre=[0.2,0.2]"]) is None


# ---------------------------------------------------------------- the laws
@pytest.mark.parametrize("law", ["mmd", "svgd", "psg", "psg_feedback", "ot"])
def test_laws_that_cannot_follow_a_moving_target_are_refused_in_one_line(refusal, law):
    message = refusal([f"control={law}", "target=moving", *SHORT])
    assert message is not None and message.startswith("invalid config: control=")
    assert "moving target" in message and "\n" not in message
    assert refusal([f"control={law}", "target=moving", "target.speed=0", *SHORT]) is None


@pytest.mark.parametrize("law", ["paper", "heat", "langevin"])
def test_field_laws_use_the_target_at_the_steps_time(law):
    grid = Grid.square(16)
    start = Target.from_density(grid, moving(0.01))
    path = TargetPath(start)
    t = 9.0
    now = path.at(t)
    make = {
        "paper": lambda tg: PaperControl(tg, alpha=0.003, sigma=5e-5, debias=True, bandwidth=0.04),
        "heat": lambda tg: HeatControl(tg, alpha=0.003, sigma=5e-5),
        "langevin": lambda tg: LangevinControl(tg, sigma=5e-5),
    }[law]
    p = Target.from_density(grid, DEFAULT_TARGET).p * 0.7 + 0.3
    est = Estimate(p, grid.gradient(p))
    expected = make(now)(ControlInput(t, est)).field
    given = make(start)(ControlInput(t, est, target=now, target_rate=path.rate(t))).field
    # without p_*(t) in the input (the agents plant's limit) the law follows its own path
    own = make(start)(ControlInput(t, est)).field
    static = make(Target.from_density(grid, DEFAULT_TARGET))(ControlInput(t, est)).field
    for field in (given, own):
        assert np.array_equal(field.centres, expected.centres)
        assert np.array_equal(field.face_x, expected.face_x)
    assert not np.allclose(static.centres, expected.centres)


# ---------------------------------------------------------------- the feedforward
def test_neumann_poisson_solves_the_five_point_laplacian(rng):
    grid = Grid(12, 9, 0.0, 1.0, 0.0, 0.7)
    f = rng.standard_normal(grid.shape)
    solver = NeumannPoisson(grid)
    phi = solver.solve(f)
    assert np.abs(solver.laplacian(phi) - (f - f.mean())).max() < 1e-11 * np.abs(f).max()
    assert abs(phi.mean()) < 1e-14


def test_sg_velocity_inverts_the_scharfetter_gummel_flux(rng):
    p_left, p_right = rng.uniform(0.1, 5.0, 400), rng.uniform(0.1, 5.0, 400)
    u = rng.normal(0, 0.05, 400) * rng.choice([1e-4, 1.0, 30.0], 400)
    for sigma in (5e-5, 1e-2, 0.0):
        flux = sg_flux(u, p_left, p_right, sigma, 1 / 30)
        back = sg_velocity(flux, p_left, p_right, sigma, 1 / 30)
        # a velocity far below sigma / h moves the flux only in its last bits: compare
        # the fluxes, and the velocities on the scale of the largest
        scale = np.abs(flux) + sigma * 30 * (p_left + p_right)
        assert np.all(np.abs(sg_flux(back, p_left, p_right, sigma, 1 / 30) - flux) < 1e-14 * scale)
        assert np.allclose(back, u, rtol=1e-12, atol=1e-14 * np.abs(u).max())
        reference = sg_velocity_reference(flux, p_left, p_right, sigma, 1 / 30)
        assert np.allclose(back, reference, rtol=1e-12, atol=1e-14 * np.abs(u).max())


@pytest.mark.parametrize("sigma", [5e-5, 1e-2, 0.0])
def test_feedforward_moves_the_target_at_its_rate_in_the_plants_discretisation(sigma):
    # with p_hat = p_*(t), q_hat = G p_*(t) the paper law's feedback vanishes; its drift
    # plus the feedforward must move p_* by exactly d_t p_* through the Fokker-Planck
    # step's own Scharfetter-Gummel fluxes: A(v + w) p_* = d_t p_* to round-off (the
    # Neumann solve amplifies round-off by the Laplacian's condition number, ~ n^2)
    grid = Grid.square(30)
    path = TargetPath(Target.from_density(grid, moving(0.01)))
    t = 4.0
    now, dp = path.at(t), path.rate(t)
    assert dp is not None
    inp = ControlInput(t, Estimate(now.p, grid.gradient(now.p)), target=now, target_rate=dp)
    scale = np.abs(dp).max()
    model = FokkerPlanck(grid, sigma)
    with_ff = PaperControl(path.start, alpha=0.003, sigma=sigma, feedforward=True)(inp).field
    assert np.abs(model.matrix(with_ff) @ now.p.ravel() - dp.ravel()).max() < 1e-11 * scale
    assert np.abs(rate(grid, now.p, with_ff, sigma) - dp).max() < 1e-11 * scale
    without = PaperControl(path.start, alpha=0.003, sigma=sigma)(inp).field
    assert np.abs(model.matrix(without) @ now.p.ravel()).max() < 1e-11 * scale  # p_* at rest
    # zero normal flux: a feedforward that leaks through the walls would change the mass
    assert abs(grid.integrate(rate(grid, now.p, with_ff, sigma))) < 1e-13 * scale


# ---------------------------------------------------------------- tracking error
ALPHA, DT, SPEED, T_FINAL = 0.1, 0.02, 0.01, 10.0
TRACK = [
    "plant=meanfield",
    "estimator=exact",
    "target=moving",
    f"target.speed={SPEED}",
    "grid.n=16",
    f"sim.dt={DT}",
    f"control.alpha={ALPHA}",
    "init=uniform",
    "log.progress=off",
    "observers=[metrics]",
    f"sim.t_final={T_FINAL}",
]


def predicted_error(exp, t: float, feedforward: bool) -> float:
    """``||Phi||`` the derivation predicts at ``t`` (:meth:`PaperControl.feedforward_field`):
    the steady response ``L Phi = -s`` of the loop linearised about ``p_*(t)``, with ``L``
    the Jacobian of the plant's rate ``A(v(p)) p`` under the law (central differences
    column by column) and the input ``s = -d_t p_*`` without the feedforward, ``s = dt
    (A d_t p_* - d_t^2 p_* / 2)`` (the held command's truncation) with it.
    """
    grid, law, model = exp.grid, exp.control, exp.model
    path = TargetPath(exp.target)
    now, dp = path.at(t), path.rate(t)
    assert dp is not None
    w = law.at_target(now).feedforward_field(now, dp) if feedforward else None

    def velocity(p):
        v = paper_law(p, grid.gradient(p), now, law.alpha, law.sigma)
        if w is None:
            return v
        return VelocityField(v.centres + w.centres, v.face_x + w.face_x, v.face_y + w.face_y)

    m, eps = grid.size, 1e-6
    jac = np.empty((m, m))
    for j in range(m):
        e = np.zeros(m)
        e[j] = eps
        up, down = now.p + e.reshape(grid.shape), now.p - e.reshape(grid.shape)
        jac[:, j] = (model.matrix(velocity(up)) @ up.ravel()) - (
            model.matrix(velocity(down)) @ down.ravel()
        )
    jac /= 2 * eps
    if feedforward:
        h = 1e-3
        d = exp.target.density
        second = (d.rate(grid, t + h) - d.rate(grid, t - h)) / (2 * h)
        source = DT * (model.matrix(velocity(now.p)) @ dp.ravel() - second.ravel() / 2)
    else:
        source = -dp.ravel()
    jac[0, :], rhs = 1.0, -source  # the mass of Phi is zero
    rhs[0] = 0.0
    return grid.l2(np.linalg.solve(jac, rhs))


@pytest.fixture(scope="module")
def tracking():
    """Both loops' ``phi_l2`` against ``p_*(t)`` (every step) and their builds."""
    out = {}
    for ff in (False, True):
        overrides = [*TRACK, f"control.feedforward={str(ff).lower()}"]
        phi = np.array([m["phi_l2"] for _, m in api.simulate(overrides, copy=False)])
        out[ff] = (phi, build(api.compose(overrides)))
    return out


def test_feedforward_tracks_a_rotating_target_far_better(tracking):
    without, with_ff = tracking[False][0], tracking[True][0]
    tail = slice(len(without) * 3 // 4, None)
    assert with_ff[tail].max() < 0.01 * without[tail].min()
    # with the feedforward the error decays (at about the static rate) to its residual
    assert with_ff[len(with_ff) // 5] > 100 * with_ff[-1]


@pytest.mark.parametrize("feedforward", [False, True])
def test_tracking_error_settles_at_the_predicted_size(tracking, feedforward):
    phi, exp = tracking[feedforward]
    predicted = predicted_error(exp, T_FINAL, feedforward)
    assert phi[-1] == pytest.approx(predicted, rel=0.2)


# ---------------------------------------------------------------- metrics against p_*(t)
def test_metrics_compare_with_the_target_at_the_steps_time():
    overrides = [*SHORT, "target=moving", "target.speed=0.05", "log.positions_every=1"]
    overrides += ["kde.debias=true"]
    exp = build(api.compose(overrides))
    path = TargetPath(exp.target)
    checked = 0
    for rec, m in api.simulate(overrides, t_final=0.1):
        now = path.at(rec.t)
        g = exp.grid
        assert m["phi_l2"] == pytest.approx(g.l2(rec.p_true - now.p), rel=1e-12)
        smooth = smoothed_target(now, 0.04, True).p
        assert m["phat_smoothed_target_l2"] == pytest.approx(
            g.l2(rec.estimate.p_hat - smooth), rel=1e-12
        )
        swarm = KDE(g, 0.04, mirror=True, method="auto")(rec.positions)[0]
        assert m["swarm_l2"] == pytest.approx(g.l2(swarm - smooth), rel=1e-12)
        checked += 1
    assert checked == 6


def test_swarm_floor_changes_little_along_a_turn():
    # the floors are drawn from p_*(0) (harness.observers.swarm.SwarmTruth): the mean finite-N
    # floor of swarm_l2 along a turn stays within the Monte-Carlo spread of its estimate
    grid = Grid.square(30)
    d = moving(0.01)
    kde = KDE(grid, 0.04, mirror=True)
    n, draws = 1024, 40
    means = []
    for k in range(4):
        mix = d.at(k * (np.pi / 2) / d.omega)
        smooth = mix.smoothed(grid, 0.04, True)
        rng = np.random.default_rng([7, k])
        values = [grid.l2(kde(mix.sample(n, grid, rng))[0] - smooth) for _ in range(draws)]
        means.append((np.mean(values), np.std(values) / np.sqrt(draws)))
    base, spread = means[0]
    for mean, err in means[1:]:
        assert abs(mean - base) < 3 * np.hypot(spread, err)


def test_robots_with_their_own_estimates_get_the_feedforward_too(rng):
    # every robot holding the same estimate moves as a robot that interpolates the
    # broadcast field, feedforward included (harness.control.own_estimates)
    grid = Grid.square(16)
    path = TargetPath(Target.from_density(grid, moving(0.01)))
    t = 2.0
    now, dp = path.at(t), path.rate(t)
    p = 0.8 * now.p + 0.2
    n = 50
    own = RobotEstimates(np.tile(p.ravel(), (n, 1)), None)
    est = Estimate(p, grid.gradient(p), robots=own)
    positions = rng.uniform(0.0, 1.0, (2, n))
    law = PaperControl(path.start, alpha=0.003, sigma=5e-5, feedforward=True)
    command = law(ControlInput(t, est, positions, target=now, target_rate=dp))
    assert command.robots is not None and command.field is not None
    expected = interpolate(grid, command.field.centres, positions)
    assert np.allclose(command.robots, expected, rtol=1e-12, atol=1e-15)
    plain = PaperControl(path.start, alpha=0.003, sigma=5e-5)
    without = plain(ControlInput(t, est, positions, target=now, target_rate=dp)).robots
    assert not np.allclose(command.robots, without)


def test_moving_target_is_logged_at_the_field_rate(tmp_path) -> None:
    """`/fields/p_target` of a moving target: p_*(t) (float32) at every field step."""
    log = api.run([*SHORT, "target=moving", "target.speed=0.05", "log.field_every=2"], tmp_path)
    series = log.fields["/fields/p_target"]
    exp = build(api.compose([*SHORT, "target=moving", "target.speed=0.05"]))
    path = TargetPath(exp.target)
    assert series.t.size > 2
    for t, values in zip(series.t, series.values, strict=True):
        np.testing.assert_allclose(values[0], path.at(float(t)).p, rtol=1e-6)
    assert np.abs(series.values[-1] - series.values[0]).max() > 1e-3  # it does move


def test_the_docs_say_a_moving_target_is_logged_at_the_field_rate() -> None:
    """docs/targets.md and docs/log.md describe `/fields/p_target` of a moving target as
    the code writes it (the test above): at the field rate, not once.
    """
    import re
    from pathlib import Path

    docs = Path(__file__).resolve().parents[1] / "docs"
    for name in ("targets.md", "log.md"):
        text = " ".join((docs / name).read_text().split())
        said = [s for s in re.split(r"(?<=[.;|])\s", text) if "/fields/p_target" in s]
        assert said, f"docs/{name} does not describe /fields/p_target"
        for sentence in said:
            if "once" in sentence:
                assert "field rate" in sentence, f"docs/{name}: {sentence}"
