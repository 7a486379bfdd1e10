"""The Python API: compose a config, run it to a log, or step it in memory.

    from harness import api

    cfg = api.compose(["grid.n=30", "sim.t_final=20"])    # what the command line composes
    log = api.run(cfg, "outputs/mine")                     # its run.mcap, loaded back
    log.metrics["phat_target_l2"]                          # one array per metric

    for rec, m in api.simulate(["control=heat", "sim.t_final=5"]):   # nothing written
        print(rec.t, m["phat_target_l2"])

:func:`compose` and :func:`run` give the same config and the same log as
``python -m experiments.closed_loop OVERRIDES hydra.run.dir=OUT_DIR``; :func:`simulate`
steps the same loop, with the same numbers, and yields each step's record and metrics
instead of logging them. Configs come from :data:`CONFIG_DIR`, which ships inside the
package, so all of this works from any directory and from an installed (non-editable)
package; ``hydra.searchpath=[file://DIR]`` adds a directory of your own components'
configs, as on the command line (``docs/extending.md``).
"""

from __future__ import annotations

import contextlib
import copy as copy_
from collections.abc import Iterator, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from analysis.load import RunLog, load_run
from harness.loop import Experiment, computing, trajectory
from harness.observers.base import Observer, RunContext, Status, computes
from harness.observers.log import METRIC_KEYS
from harness.records import StepRecord
from harness.runs.build import build
from harness.runs.run import run as run_to_log

__all__ = [
    "CONFIG_DIR",
    "Metrics",
    "RunLog",
    "StepRecord",
    "compose",
    "load_run",
    "options",
    "run",
    "simulate",
]

CONFIG_DIR: Path = (Path(__file__).parent / "conf").resolve()
"""The project's configs (``conf/`` at the repository root): ``harness/conf`` is a
symbolic link to it in the source tree and a copy of it in an installed package. The
command line (:mod:`experiments.closed_loop`) reads its configs from here too."""

Metrics = dict[str, float | None]
"""One step's metrics, keyed as :data:`harness.observers.log.METRIC_KEYS` (None where a metric
is not evaluated at that step or does not apply to the loop)."""


def compose(overrides: Sequence[str] = (), config_name: str = "closed_loop") -> DictConfig:
    """The config the command line composes from ``overrides``.

    Of Hydra's own node ``hydra`` only ``hydra.runtime.choices`` (the option chosen in
    each config group, which the log records, :func:`harness.runs.identity.choices`) and
    ``hydra.overrides.task`` (the overrides, from which the build reads an observer list
    as written, :func:`harness.runs.identity.chosen_observers`) are kept; the rest is
    left out, as in the config a command-line run receives.
    Works repeatedly in one process, from any current directory, and inside a running
    Hydra app or an initialised Hydra (whose global state is set aside and restored).

    Args:
        overrides: Hydra overrides, as on the command line (``"grid.n=30"``,
            ``"control=heat"``, ``"+experiment=smoke"``,
            ``"hydra.searchpath=[file:///abs/my_conf]"``).
        config_name: The primary config in :data:`CONFIG_DIR`.

    Returns:
        The composed config (not yet checked: :func:`run`, :func:`simulate` and
        :func:`harness.runs.build.build` check it).

    Raises:
        hydra.errors.HydraException, omegaconf.errors.OmegaConfBaseException: for an
            override that does not compose (an unknown key or option, a bad value).
    """
    from hydra import compose as hydra_compose

    with _configs():
        full = hydra_compose(config_name, overrides=list(overrides), return_hydra_config=True)
        chosen = OmegaConf.to_container(full.hydra.runtime.choices, resolve=False)
        task = OmegaConf.to_container(full.hydra.overrides.task, resolve=False)
        with open_dict(full):
            full.hydra = {"runtime": {"choices": chosen}, "overrides": {"task": task}}
        return full


@contextlib.contextmanager
def _configs() -> Iterator[None]:
    """Hydra initialised on :data:`CONFIG_DIR` for the block, any global Hydra state
    (a running app's) set aside and restored after it.
    """
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    global_hydra = GlobalHydra.instance()
    outer = global_hydra.hydra if global_hydra.is_initialized() else None
    global_hydra.clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            yield
    finally:
        global_hydra = GlobalHydra.instance()
        global_hydra.clear()
        if outer is not None:
            global_hydra.initialize(outer)


def options(
    group: str, overrides: Sequence[str] = (), config_name: str = "closed_loop"
) -> list[str]:
    """The options of config group ``group`` (``"control"``: every law), sorted, from
    :data:`CONFIG_DIR` and any directory ``overrides`` add with ``hydra.searchpath``.
    """
    from hydra.core.global_hydra import GlobalHydra

    with _configs():
        loader = GlobalHydra.instance().config_loader()
        found = loader.get_group_options(group, config_name=config_name, overrides=list(overrides))
        return sorted(found)


def _config(config: DictConfig | Sequence[str]) -> DictConfig:
    """``config`` itself, or the config composed from these overrides."""
    if isinstance(config, DictConfig):
        return config
    if isinstance(config, str):
        raise TypeError("pass a config or a sequence of overrides, not a single string")
    return compose(config)


def run(config: DictConfig | Sequence[str], out_dir: str | Path) -> RunLog:
    """Run a closed loop to ``out_dir / "run.mcap"``, as the command line does, and load
    the log back.

    Args:
        config: A config (:func:`compose`) or the overrides to compose one from.
        out_dir: The run directory (created if missing; must not hold a ``run.mcap``).

    Returns:
        The log (:func:`analysis.load.load_run`); ``log.state`` is ``completed``, or
        ``diverged`` when the numbers broke down (the reason is in
        ``log.metadata["status"]``).

    Raises:
        harness.runs.checks.ConfigError: before anything is written, for a value that is not
            allowed, an existing log in ``out_dir`` or a log larger than the free disk.
        harness.runs.run.DiskFull: when the disk fills during the run.
        KeyboardInterrupt, Exception: re-raised after the log is finalised ``aborted``.
    """
    out = Path(out_dir)
    result = run_to_log(_config(config), out)
    return load_run(result.log_path)


def simulate(
    config: DictConfig | Sequence[str], t_final: float | None = None, *, copy: bool = True
) -> Iterator[tuple[StepRecord, Metrics]]:
    """Step a closed loop in memory: each step's record and metrics, nothing written.

    The loop, its random stream and its metrics are those of :func:`run` with the same
    config, so the metrics equal the logged ones. The config is checked (and the loop
    built) when this is called, before the first step.

    Args:
        config: A config (:func:`compose`) or the overrides to compose one from.
        t_final: Simulated time (s), in place of ``sim.t_final``; yields
            ``round(t_final / sim.dt) + 1`` steps, ``t = 0`` first.
        copy: Yield a copy of each record. The loop overwrites some of a record's arrays
            in place at the next step (the robots' positions; each robot's estimates in
            a decentralised loop); with ``copy=False`` a record is valid only until the
            next one is drawn, which saves the copy.

    Returns:
        An iterator of ``(record, metrics)`` per step.

    Raises:
        harness.runs.checks.ConfigError: for a value that is not allowed (at the call).
        harness.fokker_planck.NumericalError: while iterating, at the step where
            :func:`run` would end ``diverged`` for a non-finite estimate, command or
            metric or a mass drift.
    """
    cfg = _config(config)
    if t_final is not None:
        cfg = copy_.deepcopy(cfg)
        cfg.sim.t_final = float(t_final)
    exp = build(cfg)
    return _steps(exp, copy)


def _steps(exp: Experiment, copy: bool) -> Iterator[tuple[StepRecord, Metrics]]:
    """The steps of :func:`simulate`: the trajectory (:func:`harness.loop.trajectory`)
    seen by the observers that compute (:func:`harness.observers.base.computes`: the
    metrics, the swarm metrics, the motion, the estimator's numbers, the divergence
    guard); none that writes or shows.
    """
    watching = [o for o in exp.observers.values() if computes(o)]
    context = RunContext(Path.cwd())
    state, reason = "aborted", "the caller stopped iterating"
    started: list[Observer] = []
    try:
        with computing():
            for observer in watching:
                started.append(observer)
                observer.initialize(context)
        for rec, values in trajectory(exp, watching):
            # every key of the log's /metrics, None where no observer gave it (as logged)
            yield (copy_.deepcopy(rec) if copy else rec), {**dict.fromkeys(METRIC_KEYS), **values}
        state, reason = "completed", ""
    except Exception as err:
        state, reason = "aborted", f"{type(err).__name__}: {err}"
        raise
    finally:
        for observer in reversed(started):
            observer.finalize(Status(state, reason, 0.0))
