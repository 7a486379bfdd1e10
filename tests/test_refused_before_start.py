"""Every config the presets and the config groups compose runs or is refused before the
run starts: one line, exit 2, no run directory (docs/reliability.md). The checks that a
run would otherwise meet at step 0 or at its end: a run without a log, a metric the guard
requires that no observer gives, a component's copy of ``agents.n`` or ``sim.dt`` that
differs from it, a periodic law's period that is not whole steps, an int where a float is
compiled, a kernel narrower than a tenth of a cell, a kernel law's memory.
"""

import itertools
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from harness.api import CONFIG_DIR
from harness.runs.build import build
from harness.runs.checks import ConfigError
from harness.runs.run import run

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "grid.n=8",
    "agents.n=40",
    "log.floor_draws=2",
    "log.field_every=1",
    "log.positions_every=1",
    "log.progress=off",
]
"""A run of a few steps: 8 x 8 cells, 40 robots."""


def options(group: str) -> list[str]:
    """Every option of a config group in ``conf/``."""
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


def runs_or_is_refused(compose, overrides: list[str], out: Path, steps: int = 2) -> str:
    """Run ``overrides`` for ``steps`` steps into ``out`` as the app does: ``completed``, or
    the refusal's one line, checked to leave no directory.
    """
    cfg = compose(overrides)
    try:
        dt = float(cfg.sim.dt)
        cfg.sim.t_final = steps * dt
    except Exception:  # a config the build refuses for its sim block
        pass
    try:
        result = run(cfg, out)
    except ConfigError as err:
        line = str(err)
        assert line.startswith("invalid config: ") and "\n" not in line, (overrides, line)
        assert not out.exists(), (overrides, line)
        return line
    assert result.state == "completed", (overrides, result.reason)
    assert (out / "run.mcap").is_file()
    return "completed"


# ------------------------------------------------------------- a run that writes no log
NO_LOG = [["observers=[metrics]"], ["observers=[]"], ["~observers"], ["~observers.log"]]


@pytest.mark.parametrize("overrides", NO_LOG, ids=lambda o: o[0])
def test_a_run_that_would_write_no_log_is_refused_before_its_directory_exists(
    tmp_path, compose, overrides
):
    line = runs_or_is_refused(compose, [*TINY, *overrides], tmp_path / "run")
    assert line.startswith("invalid config: observers="), line
    assert "log" in line


def test_a_run_without_a_log_is_refused_on_the_command_line_with_exit_2(tmp_path):
    for i, bad in enumerate(("observers=[metrics]", "~observers.log")):
        out = tmp_path / f"run{i}"
        proc = subprocess.run(
            [sys.executable, "-m", "experiments.closed_loop", *TINY, bad, f"hydra.run.dir={out}"],
            capture_output=True,
            text=True,
            cwd=ROOT,
            timeout=120,
        )
        assert proc.returncode == 2, (bad, proc.stderr)
        assert proc.stderr.startswith("invalid config: observers="), proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert not out.exists()


def test_a_sweep_job_that_would_write_no_log_is_invalid(tmp_path, compose):
    from harness.runs.app import run_job
    from harness.runs.status import read_status

    out = tmp_path / "sweep" / "observers=[metrics]"
    run_job(compose([*TINY, "observers=[metrics]"]), out, 0, ["observers=[metrics]"])
    status = read_status(out)
    assert status["state"] == "invalid", status
    assert status["reason"].startswith("invalid config: observers="), status
    assert not (out / "run.mcap").exists()


def test_simulate_needs_no_log(compose):
    from harness.api import simulate

    overrides = [*TINY, "observers=[metrics]", "sim.dt=0.02", "sim.t_final=0.04"]
    steps = list(simulate(compose(overrides)))
    assert len(steps) == 3


# ------------------------------------------------------- what the guard requires
def test_the_guard_requires_only_metrics_an_observer_before_it_gives(refusal):
    line = refusal([*TINY, "observers.guard.required=[nosuch_metric]"])
    assert line is not None and line.startswith(
        "invalid config: observers.guard.required=['nosuch_metric']: "
    ), line
    assert "nosuch_metric" in line.split(": ", 2)[2]
    # the default (the log's always-numbers) with no observer before the guard to give them
    line = refusal([*TINY, "observers=[guard,log]"])
    assert line is not None and line.startswith("invalid config: observers.guard.required="), line
    for fine in ("observers.guard.required=[t,trace_P,swarm_l2]", "observers.guard.required=[]"):
        assert refusal([*TINY, fine]) is None, fine


NOT_GIVEN_BY_THIS_RUN = [
    (["observers.guard.required=[consensus_l2]"], "consensus_l2"),
    (["observers.guard.required=[mean_degree,t]"], "mean_degree"),
    (["plant=meanfield", "observers.guard.required=[swarm_l2]"], "swarm_l2"),
    (["control=psg", "observers.guard.required=[limit_swarm_l2]"], "limit_swarm_l2"),
    (["observers.guard.required=[tracking_error]"], "tracking_error"),
    (["plant=unicycles", "observers.guard.required=[command_age]"], "command_age"),
    (["observers.guard.required=[command_disagreement]"], "command_disagreement"),
    (["estimator=exact", "observers.guard.required=[kde_l2]"], "kde_l2"),
    (["estimator=kde", "observers.guard.required=[trace_P]"], "trace_P"),
    (["estimator=smoothed", "observers.guard.required=[trace_Q_grad]"], "trace_Q_grad"),
    (["estimator=distributed", "observers.guard.required=[kde_l2]"], "kde_l2"),
]
"""Metrics some runs give and these do not: the network metrics without the decentralised
estimator, the robots' metrics without robots, the limit's without a law's mean field."""


@pytest.mark.parametrize(
    "overrides,metric", NOT_GIVEN_BY_THIS_RUN, ids=[m for _, m in NOT_GIVEN_BY_THIS_RUN]
)
def test_the_guard_requires_only_metrics_this_run_gives(refusal, overrides, metric):
    line = refusal([*TINY, *overrides])
    assert line is not None and line.startswith("invalid config: observers.guard.required="), line
    assert f"none gives {metric}" in line, line


def test_the_guard_may_require_network_metrics_of_the_decentralised_estimator(refusal):
    for fine in ("[consensus_l2]", "[mean_degree,central_gap_l2]", "[command_disagreement]",
                 "[trace_P,trace_Q_grad]"):  # fmt: skip
        overrides = [*TINY, "estimator=distributed", f"observers.guard.required={fine}"]
        assert refusal(overrides) is None, fine


def test_the_guard_may_require_what_the_filters_and_the_kde_give(refusal):
    kde_l2 = "observers.guard.required=[kde_l2]"
    for overrides in (
        ["observers.guard.required=[kde_l2,trace_P,trace_P_grad,effort]"],
        ["estimator=kde", kde_l2],
        ["plant=meanfield", "estimator=kde", kde_l2],
    ):
        assert refusal([*TINY, *overrides]) is None, overrides


UNCADENCED = [o for o in TINY if not o.startswith("log.positions_every")]
"""TINY without its cadence of the swarm metrics (every step)."""

CADENCED = [
    (["log.positions_every=10", "observers.guard.required=[swarm_l2]"], "log.positions_every=10"),
    (["log.positions_every=10", "observers.guard.required=[swarm_l2,swarm_l2]"],
     "log.positions_every=10"),
    (["log.positions_every=3", "observers.guard.required=[t,est_swarm_l2]"],
     "log.positions_every=3"),
    (["log.positions_every=1", "log.w2_every=5", "observers.guard.required=[swarm_w2]"],
     "log.w2_every=5"),
]  # fmt: skip


@pytest.mark.parametrize("overrides,cadence", CADENCED, ids=[o[-1] for o, _ in CADENCED])
def test_the_guard_requires_only_metrics_given_at_every_step(tmp_path, compose, overrides, cadence):
    """``swarm`` gives its metrics at its cadence: a guard requiring one at every step
    would end the run at the first step without it."""
    line = runs_or_is_refused(compose, [*UNCADENCED, *overrides], tmp_path / "run")
    assert line.startswith("invalid config: observers.guard.required=["), line
    assert f"only every {cadence.split('=')[1]} steps, {cadence}" in line, line


def test_a_metric_given_at_every_step_may_be_required(refusal):
    for fine in (
        ["log.positions_every=1", "log.w2_every=1", "observers.guard.required=[swarm_w2]"],
        ["log.positions_every=10", "observers.guard.required=[phat_smoothed_target_l2]"],
    ):
        assert refusal([*UNCADENCED, *fine]) is None, fine


LOG_WITHOUT_METRICS = ["observers=[log]", "observers=[log,metrics]", "observers=[guard,log]"]


@pytest.mark.parametrize("observers", LOG_WITHOUT_METRICS)
def test_a_log_without_the_metrics_it_writes_every_step_is_refused(tmp_path, compose, observers):
    """The logger needs the log contract's always-numbers at every step from an
    observer before it: without them the log would read back as damaged."""
    line = runs_or_is_refused(compose, [*TINY, observers], tmp_path / "run")
    assert line.startswith("invalid config: observers"), line
    assert "none gives t, phi_l2" in line, line


def test_a_log_after_the_metrics_runs(refusal):
    assert refusal([*TINY, "observers=[metrics,log]"]) is None


NAMED_TWICE = [
    ("observers=[log,log]", "log comes twice)"),
    ("observers=[metrics,log,log]", "log comes twice)"),
    ("observers=[metrics,log,metrics]", "metrics comes twice)"),
    ("observers=[default,log]", "log comes twice; default holds it)"),
    ("observers=[default,default]", "metrics comes twice; default holds it)"),
]


@pytest.mark.parametrize("observers,why", NAMED_TWICE, ids=[o for o, _ in NAMED_TWICE])
def test_an_observer_named_twice_is_refused(tmp_path, compose, observers, why):
    """Hydra merges an observer named twice into one: the run would not be the list."""
    line = runs_or_is_refused(compose, [*TINY, observers], tmp_path / "run")
    named = observers.split("=")[1].strip("[]").split(",")
    assert line == (
        f"invalid config: observers={named!r}: a list that names each observer once ({why}"
    ), line


def test_observer_lists_naming_each_once_are_accepted(refusal):
    from harness.runs.build import OBSERVER_OPTIONS

    assert OBSERVER_OPTIONS == CONFIG_DIR / "observers"
    for fine in ("observers=[default]", "observers=[metrics,guard,log]"):
        assert refusal([*TINY, fine]) is None, fine


@pytest.mark.parametrize(
    "bad",
    ["observers.guard.required=[swarm_l2]", "observers=[log,log]", "observers=[log]"],
)
def test_observers_refused_on_the_command_line_exit_2_in_one_line(tmp_path, bad):
    out = tmp_path / "run"
    cadence = "log.positions_every=10"
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *UNCADENCED, cadence, bad,
         f"hydra.run.dir={out}"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    key = bad.split("=")[0]
    assert proc.stderr.startswith(f"invalid config: {key}="), proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not out.exists()


# ------------------------------------------------- copies of agents.n and sim.dt
COPIES = [
    (["control=ot", "control.robots=5"], "control.robots"),
    (["estimator.robots=5"], "estimator.robots"),
    (["estimator=distributed", "estimator.robots=5"], "estimator.robots"),
    (["plant=meanfield", "plant.robots=7"], "plant.robots"),
    (["plant.n=5"], "plant.n"),
    (["sim.dt=0.02", "plant.dt=0.04"], "plant.dt"),
    (["sim.dt=0.02", "plant=unicycles", "plant.dt=0.04", "link.period=0.04"], "plant.dt"),
    (["sim.dt=0.02", "estimator.dt=0.04"], "estimator.dt"),
    (["sim.dt=0.02", "control=continuification", "control.dt=0.04"], "control.dt"),
]


@pytest.mark.parametrize("overrides,key", COPIES, ids=[k for _, k in COPIES])
def test_a_components_copy_of_agents_n_or_sim_dt_must_equal_it(refusal, overrides, key):
    line = refusal([*TINY, *overrides])
    shared = "sim.dt" if key.endswith(".dt") else "agents.n"
    assert line is not None and line.startswith(f"invalid config: {key}="), line
    assert f"{shared} = " in line and "\n" not in line, line


def test_copies_equal_to_the_shared_keys_are_accepted(refusal):
    for overrides in (
        ["control=ot", "control.robots=40"],
        ["estimator.robots=40", "plant.n=40"],
        ["sim.dt=0.02", "plant.dt=0.02", "estimator.dt=0.02"],
    ):
        assert refusal([*TINY, *overrides]) is None, overrides


# -------------------------------------------------------- a periodic law's period
@pytest.mark.parametrize("law", ["psg", "psg_feedback", "dsmc", "ot"])
def test_a_periodic_laws_period_is_a_whole_number_of_steps(refusal, law):
    for period in ("0.03", "1e-9", "0.05"):
        line = refusal([*TINY, "sim.dt=0.02", f"control={law}", f"control.period={period}"])
        assert line == (
            f"invalid config: control.period={float(period)!r}: a whole number of steps of "
            "sim.dt = 0.02 s, at least 0.02 s"
        ), line
    for period in ("0.02", "0.06", "1"):
        line = refusal([*TINY, "sim.dt=0.02", f"control={law}", f"control.period={period}"])
        assert line is None, (period, line)


# ------------------------------------------- ints where compiled code wants floats
def test_an_integer_for_a_float_reaches_the_components_as_that_float(compose):
    from harness.api import simulate

    base = [*TINY, "estimator=distributed", "sim.t_final=0.04"]
    as_int = [m for _, m in simulate(compose([*base, "grid.length=1"]))]
    as_float = [m for _, m in simulate(compose([*base, "grid.length=1.0"]))]
    assert as_int == as_float


def test_ints_become_floats_only_where_a_float_is_declared():
    from harness.runs.declared import as_declared

    class Part:
        def __init__(
            self,
            a: float,
            b: float | None,
            c: list[float],
            d: int,
            e: bool,
            f: str | float,
            g: float = 1.0,
        ) -> None: ...

    got = as_declared(Part, {"a": 1, "b": 2, "c": [1, 2.5], "d": 3, "e": True, "f": 4, "g": True})
    assert got == {"a": 1.0, "b": 2.0, "c": [1.0, 2.5], "d": 3, "e": True, "f": 4, "g": True}
    assert [type(got[k]) for k in "abdefg"] == [float, float, int, bool, int, bool]
    assert [type(v) for v in got["c"]] == [float, float]


# ------------------------------------------------------------- the kernel laws
@pytest.mark.parametrize("law", ["svgd", "mmd"])
def test_a_kernel_narrower_than_a_tenth_of_a_cell_is_refused(refusal, law):
    line = refusal([*TINY, f"control={law}", "control.length=1e-300"])
    assert line is not None and line.startswith("invalid config: control.length=1e-300: "), line
    assert "at least 0.1 x the cell size" in line
    assert refusal([*TINY, f"control={law}", "control.length=0.0125"]) is None


def test_a_tiny_kernel_length_is_one_line_on_the_command_line(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable, "-m", "experiments.closed_loop", *TINY, "control=svgd",
            "control.length=1e-300", f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2 and not out.exists()
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()], proc.stderr
    assert proc.stderr.startswith("invalid config: control.length=1e-300")


@pytest.mark.parametrize("law", ["svgd", "mmd"])
def test_the_kernel_laws_memory_estimate_bounds_what_they_allocate(compose, law):
    """tracemalloc sees numpy's allocations: the law's estimate bounds its peak while it
    is built and computes a command, for a bin_factor that makes the fine grid large."""
    import numpy as np

    from harness.protocols import memory_estimate
    from harness.records import ControlInput
    from harness.runs.build import TUNABLE

    cfg = compose([*TINY, "grid.n=12", f"control={law}", "control.bin_factor=24"])
    parts = build(compose([*TINY, "grid.n=12", f"control={law}"]))
    cls = type(parts.control)
    params = {k: v for k, v in dict(cfg.control).items() if k not in ("_target_", TUNABLE)}
    positions = np.random.default_rng(0).uniform(0.1, 0.9, (2, 40))
    tracemalloc.start()
    law_ = cls(target=parts.target, **params)
    field = law_.feedback(ControlInput(t=0.0, estimate=None, positions=positions))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert np.isfinite(field).all()
    estimate = memory_estimate(cls, parts.grid, params)
    assert estimate.parameter == "bin_factor"
    assert estimate.nbytes >= peak, (estimate.nbytes, peak)
    assert estimate.nbytes <= 4 * peak + (1 << 20), (estimate.nbytes, peak)  # not far above


def test_a_kernel_law_too_large_for_memory_is_refused_naming_bin_factor(compose):
    from harness.grid import Grid
    from harness.runs import resources

    cfg = compose(["control=svgd", "control.bin_factor=10000"])
    with pytest.raises(ConfigError, match=r"^invalid config: control.bin_factor=10000: .*memory"):
        resources.check_memory(cfg, Grid.square(30), (8 << 30, "test"))


# ---------------------------------------------- every config the groups compose
GROUP_OPTIONS = {g: options(g) for g in ("plant", "estimator", "control", "target", "init")}
DESIGNS = options("design")


def pairwise() -> list[list[str]]:
    """Configs covering every pair of plant, estimator and control options (each
    estimator with each law, the plant ``(estimator + law) mod plants``), with the
    targets, starts and decentralised designs taken in turn, the domain's side written
    as the int 1; and each design with the paper's law."""
    plants, estimators, laws = (GROUP_OPTIONS[g] for g in ("plant", "estimator", "control"))
    rows = []
    for i, (e, c) in enumerate(itertools.product(range(len(estimators)), range(len(laws)))):
        row = [
            f"plant={plants[(e + c) % len(plants)]}",
            f"estimator={estimators[e]}",
            f"control={laws[c]}",
            f"target={GROUP_OPTIONS['target'][i % len(GROUP_OPTIONS['target'])]}",
            f"init={GROUP_OPTIONS['init'][(i // 3) % len(GROUP_OPTIONS['init'])]}",
            "grid.length=1",  # the default side written as an int, as YAML allows
        ]
        if estimators[e] == "distributed":
            row.append(f"+design={DESIGNS[c % len(DESIGNS)]}")
        rows.append(row)
    # each design with a loop it can run (robots that move by their own estimates)
    rows += [["estimator=distributed", "control=paper", f"+design={d}"] for d in DESIGNS]
    return rows


def preset_points(preset: str, first_only: bool) -> list[list[str]]:
    """The sweep points of a study preset (its ``hydra.sweeper.params``, as Hydra's basic
    sweeper expands them), each as its overrides."""
    from hydra import initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    declared = OmegaConf.load(CONFIG_DIR / "experiment" / f"{preset}.yaml")
    params = OmegaConf.select(declared, "hydra.sweeper.params", default=None) or {}
    outer = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            loader = GlobalHydra.instance().config_loader()  # expands glob(...) of a group
            parser = OverridesParser.create(config_loader=loader)
            parsed = parser.parse_overrides([f"{k}={v}" for k, v in params.items()])
    finally:
        GlobalHydra.instance().clear()
        if outer is not None:
            GlobalHydra.instance().initialize(outer)
    points = [list(p) for batch in BasicSweeper.split_arguments(parsed, None) for p in batch]
    return (points[:1] if first_only else points) or [[]]


def test_every_option_of_every_group_runs_or_is_refused_in_one_line(tmp_path, compose):
    """Each config of :func:`pairwise` runs or is refused; and every option of every
    group runs in at least one of them (a refusal is no way out for a whole option)."""
    ran: set[str] = set()
    for i, overrides in enumerate(pairwise()):
        if runs_or_is_refused(compose, [*overrides, *TINY], tmp_path / f"{i}") == "completed":
            ran.update(o.lstrip("+") for o in overrides)
    every = {f"{g}={o}" for g, opts in GROUP_OPTIONS.items() for o in opts}
    every |= {f"design={d}" for d in DESIGNS}
    assert not every - ran, sorted(every - ran)


PRESETS = options("experiment")


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_runs_or_is_refused_in_one_line(tmp_path, compose, preset):
    for i, point in enumerate(preset_points(preset, first_only=True)):
        runs_or_is_refused(compose, [f"+experiment={preset}", *point, *TINY], tmp_path / f"{i}")


@pytest.mark.slow
@pytest.mark.parametrize("preset", PRESETS)
def test_every_point_of_every_preset_runs_or_is_refused_in_one_line(tmp_path, compose, preset):
    """Every point of every study preset at tiny size (make test-slow)."""
    for i, point in enumerate(preset_points(preset, first_only=False)):
        runs_or_is_refused(compose, [f"+experiment={preset}", *point, *TINY], tmp_path / f"{i}")


@pytest.mark.slow
@pytest.mark.parametrize("plant", GROUP_OPTIONS["plant"])
def test_every_combination_of_options_runs_or_is_refused_in_one_line(tmp_path, compose, plant):
    """Every estimator, law, target and start with each plant (make test-slow)."""
    combos = itertools.product(
        *(GROUP_OPTIONS[g] for g in ("estimator", "control", "target", "init"))
    )
    for i, (e, c, t, s) in enumerate(combos):
        overrides = [f"plant={plant}", f"estimator={e}", f"control={c}", f"target={t}", f"init={s}"]
        runs_or_is_refused(compose, [*overrides, *TINY], tmp_path / f"{i}")


# ------------------------------------------- a refused combination names its options
@pytest.mark.parametrize(
    "overrides, line",
    [
        (["estimator=distributed", "control=svgd"], "control='svgd'"),
        (["estimator=distributed", "plant=meanfield"], "plant='meanfield'"),
        (["target=moving", "control=ot"], "control='ot'"),
        (["target=moving", "control=dsmc"], "control='dsmc'"),
    ],
)
def test_a_refused_combination_names_the_option_chosen_not_its_class(refusal, overrides, line):
    got = refusal([*TINY, *overrides])
    assert got is not None and got.startswith(f"invalid config: {line}: "), got
