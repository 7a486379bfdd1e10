"""Observers as components: built from conf/observers in order, each with the run-time
arguments it names; finalised in reverse order whatever happens; a run built once."""

import math
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from omegaconf import OmegaConf

from harness.fokker_planck import NumericalError
from harness.observers.base import RunContext, Status
from harness.observers.guard import DivergenceGuard
from harness.runs.app import CheckCallback, checked
from harness.runs.build import build
from harness.runs.run import run

ORDER = ["metrics", "swarm", "motion", "estimator", "guard", "live", "log", "progress"]


def test_default_observers_are_built_in_config_order(compose, smoke):
    exp = build(compose(list(smoke)))
    assert list(exp.observers) == ORDER
    # each got the run-time arguments its constructor names
    assert exp.observers["log"].total_steps == exp.steps == 10
    assert exp.observers["swarm"].grid is exp.grid
    assert exp.observers["metrics"].control is exp.control


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("log.progress=sometimes", "log.progress"),
        ("log.field_every=0", "log.field_every"),
        ("log.live_port=70000", "log.live_port"),
        ("log.floor_draws=1", "log.floor_draws"),
    ],
)
def test_an_observer_refuses_its_own_bad_value_naming_the_public_key(refusal, override, key):
    message = refusal([override])
    assert message is not None and message.startswith(f"invalid config: {key}="), message


def test_the_guard_refuses_non_finite_and_missing_numbers():
    guard = DivergenceGuard(["t"])
    guard.handle(None, {"t": 0.0, "x": None})  # None allowed where not required
    with pytest.raises(NumericalError, match="non-finite"):
        guard.handle(None, {"t": 0.0, "x": math.inf})
    with pytest.raises(NumericalError, match="missing"):
        guard.handle(None, {"t": None})


class Recorder:
    """An observer that records its calls in a shared list; it may fail on finalize."""

    calls: ClassVar[list] = []

    def __init__(self, name: str = "recorder", fail: bool = False) -> None:
        self.name, self.fail = name, fail

    def initialize(self, run: RunContext) -> None:
        Recorder.calls.append((self.name, "initialize"))

    def handle(self, rec, values) -> None:
        if rec.step == 0:
            Recorder.calls.append((self.name, "handle", sorted(values)[:1]))

    def finalize(self, status: Status) -> None:
        Recorder.calls.append((self.name, "finalize", status.state))
        if self.fail:
            raise RuntimeError("finalize failed")


def _calls() -> list:
    """The call list of the Recorder class Hydra instantiates (this file imported as
    ``tests.test_observers``, which may be another module object than pytest's)."""
    import importlib

    cls = importlib.import_module("tests.test_observers").Recorder
    cls.calls = []
    return cls.calls


def _with_recorders(cfg, fail_first: bool):
    first = {"_target_": "tests.test_observers.Recorder", "name": "first", "fail": fail_first}
    last = {"_target_": "tests.test_observers.Recorder", "name": "last"}
    cfg.observers = OmegaConf.merge(
        OmegaConf.create({"first": first}), cfg.observers, OmegaConf.create({"last": last})
    )
    return cfg


def test_observers_see_steps_in_order_and_finalise_in_reverse(compose, smoke, tmp_path):
    calls = _calls()
    result = run(_with_recorders(compose(list(smoke)), False), tmp_path)
    assert result.state == "completed"
    names = [c[:2] for c in calls]
    assert names[:2] == [("first", "initialize"), ("last", "initialize")]
    assert names[-2:] == [("last", "finalize"), ("first", "finalize")]
    # the first sees the step before any metric is in; the last sees them all
    handles = [c for c in calls if c[1] == "handle"]
    assert handles == [("first", "handle", []), ("last", "handle", ["command_age"])]


def test_a_failing_finalize_does_not_stop_the_others(compose, smoke, tmp_path):
    calls = _calls()
    with pytest.raises(RuntimeError, match="finalize failed"):
        run(_with_recorders(compose(list(smoke)), True), tmp_path)
    # the log (finalised before "first") is complete and says completed
    from analysis.load import load_run

    assert load_run(tmp_path).state == "completed"
    assert calls[-1] == ("first", "finalize", "completed")


def test_the_check_callback_hands_its_build_on(compose, smoke, tmp_path):
    cfg = compose(list(smoke))
    full = OmegaConf.create(OmegaConf.to_container(cfg))
    full.hydra = {"run": {"dir": str(tmp_path / "run")}}
    CheckCallback().on_run_start(full)
    built = checked(cfg)
    assert not isinstance(built, type(cfg))  # the callback's build, not the config
    assert checked(cfg) is cfg  # handed on once
    result = run(built, tmp_path / "run")
    assert result.state == "completed"
    assert Path(result.log_path).exists()


def test_the_log_of_a_built_experiment_equals_the_log_of_its_config(compose, smoke, tmp_path):
    from analysis.diff import first_difference

    cfg = compose(list(smoke))
    run(cfg, tmp_path / "a")
    run(build(cfg), tmp_path / "b")
    n, diff = first_difference(tmp_path / "a" / "run.mcap", tmp_path / "b" / "run.mcap")
    assert diff is None and n > 0


def test_simulate_runs_only_the_observers_that_compute(compose, smoke, tmp_path, monkeypatch):
    from harness import api

    monkeypatch.chdir(tmp_path)
    steps = list(api.simulate(compose(list(smoke))))
    assert len(steps) == 11
    assert list(tmp_path.iterdir()) == []  # nothing written
    _, values = steps[-1]
    assert np.isfinite(values["phat_target_l2"])


def test_a_multi_seed_study_is_not_split_by_the_observers_seed():
    """``observers.swarm.seed: ${seed}`` varies with the seed in the logged config; the
    sweep analysis reads the public key only."""
    from analysis.sweep import mixed, varied

    rows = [
        {"cfg:agents.n": n, "cfg:seed": s, "cfg:observers.swarm.seed": s}
        for n in (256, 1024)
        for s in (0, 1)
    ]
    assert varied(rows) == ["agents.n", "seed"]
    assert mixed(rows, ["agents.n"]) == []


def test_an_experiment_runs_once(compose, smoke, tmp_path):
    exp = build(compose(list(smoke)))
    assert run(exp, tmp_path / "a").state == "completed"
    with pytest.raises(ValueError, match="has run already"):
        run(exp, tmp_path / "b")


def test_a_logger_that_cannot_write_at_the_start_still_closes_its_log(
    compose, smoke, tmp_path, monkeypatch
):
    import errno

    import harness.observers.log
    from analysis.load import load_run
    from harness.runs.run import DiskFull

    def full(self, p):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(harness.observers.log.McapLogger, "write_target", full)
    with pytest.raises(DiskFull):
        run(compose(list(smoke)), tmp_path)
    log = load_run(tmp_path)
    assert log.state == "aborted"
    assert "could not start" in log.metadata["status"]["reason"]


def test_an_explicit_own_estimates_is_kept():
    from harness.control.paper import PaperControl

    class Declared(PaperControl):
        own_estimates = True

        def field(self, p_hat, q_hat):
            return super().field(p_hat, q_hat)

    class Undeclared(PaperControl):
        def field(self, p_hat, q_hat):
            return super().field(p_hat, q_hat)

    assert Declared.own_estimates and not Undeclared.own_estimates
