"""The failures a hostile tester found, by class, each with a test that fails when its
promise breaks (README, "What happens on bad input ..."): two writers of one log,
resume after a code change, the machine's real memory limits, a full disk in a sweep,
one line for every error, the live view's shutdown and bind failures, analysis of
foreign content, and values that would be rounded or dropped without a word.
"""

import multiprocessing
import os
import subprocess
import sys
from pathlib import Path

from harness.build import build
from harness.checks import ConfigError
from harness.jobs import verify_log
from harness.run import run

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["grid.n=8", "agents.n=50", "sim.t_final=0.06", "sim.dt=0.02", "log.progress=off"]


def cli(*args, cwd=ROOT, timeout=120, env=None):
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        env=env,
    )


def one_line_refusal(proc, *words):
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------ 1. two writers, one log
def _racer(exp, out, barrier, results):
    barrier.wait()
    try:
        results.put(run(exp, out).state)
    except ConfigError as err:
        results.put(f"refused: {err}")
    except BaseException as err:  # reported to the test, not raised in the child
        results.put(f"error: {type(err).__name__}: {err}")


def test_concurrent_runs_into_one_directory_write_one_log(tmp_path, compose):
    ctx = multiprocessing.get_context("fork")
    barrier, results = ctx.Barrier(3), ctx.Queue()
    cfg = compose([*SMALL[:-2], "sim.t_final=0.2", "sim.dt=0.02", "log.progress=off"])
    procs = [
        ctx.Process(target=_racer, args=(build(cfg), tmp_path, barrier, results)) for _ in range(3)
    ]
    for p in procs:
        p.start()
    outcomes = sorted(results.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(timeout=60)
    assert outcomes.count("completed") == 1, outcomes
    assert all(o.startswith("refused: invalid config: hydra.run.dir=") for o in outcomes[1:])
    check = verify_log(tmp_path / "run.mcap")
    assert check.intact and check.state == "completed", check


def _checked_and_waiting(cfg, ready, done):
    from harness.jobs import CheckCallback

    CheckCallback().on_run_start(cfg)  # passed its checks: about to open its log
    ready.set()
    done.wait(60)


def test_a_run_between_its_check_and_its_log_keeps_its_directory(tmp_path, compose):
    from omegaconf import OmegaConf

    out = tmp_path / "run"
    cfg = compose(SMALL)
    OmegaConf.set_struct(cfg, False)
    cfg.hydra = {"run": {"dir": str(out)}}
    ctx = multiprocessing.get_context("fork")
    ready, done = ctx.Event(), ctx.Event()
    first = ctx.Process(target=_checked_and_waiting, args=(cfg, ready, done))
    first.start()
    try:
        assert ready.wait(60)
        line = one_line_refusal(cli(*SMALL, "seed=5", f"hydra.run.dir={out}"), "hydra.run.dir")
        assert f"process {first.pid}" in line
        assert not (out / ".hydra").exists() and not (out / "run.mcap").exists()
    finally:
        done.set()
        first.join(timeout=60)
    # its lock (left by a process that is gone: fork children skip atexit) is taken over,
    # and released by a run that ends normally
    assert cli(*SMALL, f"hydra.run.dir={out}").returncode == 0
    assert (out / "run.mcap").exists() and not (out / ".run.lock").exists()
