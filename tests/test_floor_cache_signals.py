"""A stop request while the finite-N floors compute (the swarm observer's start, with or
without a floor cache) is honoured at once: SIGINT, SIGTERM or SIGHUP stops the run
within a second or two, between two draws, and its log is finalised ``aborted``; a
sweep stopped in that phase finalises every job's log and lists no job as running.

Each case makes floors that would take half a minute or more, and signals once they run.
"""

import csv
import json
import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import pytest

import harness.observers.swarm_metrics
from analysis.load import LogWarning, load_run
from harness.runs.run import Terminated, run
from tests.conftest import SMOKE

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

LONG_FLOORS = [*SMOKE, "log.floor_draws=6000"]
"""A smoke run whose floors take about 30 s (5 ms a draw of 200 robots)."""

ISSUE = ["agents.n=3000", "log.floor_draws=3000", "log.floor_cache="]
"""The floors of the reproduction: 3000 draws of 3000 robots, about 2 minutes."""

PROMPT_S = 2.0
"""Longest time from the signal to the end of the run (s); the floors take 30 s or more."""


@pytest.fixture
def floors_started(monkeypatch) -> threading.Event:
    """Set when harness.observers.swarm_metrics.floors (the computation) starts."""
    started = threading.Event()
    compute = harness.observers.swarm_metrics.floors

    def announced(*args, **kwargs):
        started.set()
        return compute(*args, **kwargs)

    monkeypatch.setattr(harness.observers.swarm_metrics, "floors", announced)
    return started


def aborted_log(directory: Path) -> str:
    """The reason of the finalised log in ``directory``, which must read back whole with
    status ``aborted``.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        log = load_run(directory)
    assert log.state == "aborted", log.state
    return str(log.metadata["status"]["reason"])


def _signal_in_floors(started: threading.Event, signals: list[int], gap_s: float) -> list[float]:
    """Start a thread that sends ``signals`` to this process, ``gap_s`` apart, once the
    floors have computed for 0.2 s; the time it sent the first is appended to the list
    returned.
    """
    sent: list[float] = []

    def send() -> None:
        if not started.wait(120):
            return
        time.sleep(0.2)  # well inside the floors
        sent.append(time.monotonic())
        for i, sig in enumerate(signals):
            time.sleep(gap_s if i else 0.0)
            os.kill(os.getpid(), sig)

    threading.Thread(target=send, daemon=True).start()
    return sent


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"]
)
def test_a_signal_while_the_floors_compute_stops_the_run_at_once_with_an_aborted_log(
    tmp_path, compose, floors_started, sig
):
    sent = _signal_in_floors(floors_started, [sig], 0.0)
    with pytest.raises(Terminated):
        run(compose(LONG_FLOORS), tmp_path)
    took = time.monotonic() - sent[0]
    assert took < PROMPT_S, f"stopped {took:.1f} s after the signal"
    reason = aborted_log(tmp_path)
    assert "at step 0" in reason and signal.Signals(sig).name in reason, reason


def test_a_second_signal_stops_the_floors_inside_a_long_draw(
    tmp_path, compose, floors_started, monkeypatch
):
    """A draw that takes 30 s (its transport sleeps): the first SIGINT waits for the
    draw to end, the second stops it at once."""
    transport = harness.observers.swarm_metrics.swarm_w2
    draws: list[int] = []

    def slow_first(*args, **kwargs):
        draws.append(1)
        if len(draws) == 1:
            time.sleep(30)
        return transport(*args, **kwargs)

    monkeypatch.setattr(harness.observers.swarm_metrics, "swarm_w2", slow_first)
    sent = _signal_in_floors(floors_started, [signal.SIGINT, signal.SIGINT], 0.3)
    with pytest.raises(KeyboardInterrupt):
        run(compose([*SMOKE, "log.floor_draws=10"]), tmp_path)
    took = time.monotonic() - sent[0]
    assert len(draws) == 1 and took < 0.3 + PROMPT_S, f"stopped {took:.1f} s after SIGINT"
    assert "second signal SIGINT" in aborted_log(tmp_path)


def _wait_for(condition, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "the run never reached its floors"
        time.sleep(0.05)


def _stopped_within(proc: subprocess.Popen, sig: int, timeout: float) -> float:
    """Send ``sig`` to ``proc`` and the seconds until it ended (killed and failed after
    ``timeout``).
    """
    sent = time.monotonic()
    proc.send_signal(sig)
    try:
        proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"still running {timeout:g} s after {signal.Signals(sig).name}")
    return time.monotonic() - sent


def test_sigint_while_the_floors_compute_exits_130_within_seconds(tmp_path):
    out = tmp_path / "x"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            f"hydra.run.dir={out}",
            "log.progress=off",
            "+experiment=smoke",
            *ISSUE,
        ],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for(lambda: (out / "run.mcap").exists())  # the log is open: the start comes next
    time.sleep(1.5)  # the start of 3000 robots takes a fraction of this
    took = _stopped_within(proc, signal.SIGINT, timeout=20)
    assert proc.returncode == 130
    assert took < 5, f"exited {took:.1f} s after SIGINT"
    assert "at step 0" in aborted_log(out)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT],
                         ids=["SIGTERM", "SIGHUP", "SIGINT"])  # fmt: skip
def test_signals_repeated_until_the_program_ends_still_give_exit_status_130(tmp_path, sig):
    """The first signal stops the run in its floors; the same signal every 20 ms after it,
    through the log's finalisation and the interpreter's shutdown, changes nothing: the
    program exits with status 130 (not killed by the signal) and the log is ``aborted``.
    """
    out = tmp_path / "x"
    proc = subprocess.Popen(
        [sys.executable, "-m", "experiments.closed_loop", f"hydra.run.dir={out}",
         "log.progress=off", *LONG_FLOORS, "log.floor_cache="],
        cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    _wait_for(lambda: (out / "run.mcap").exists())
    time.sleep(1.0)  # in the floors (30 s of them)
    deadline = time.monotonic() + 30
    while proc.poll() is None and time.monotonic() < deadline:
        proc.send_signal(sig)
        time.sleep(0.02)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, (proc.returncode, err)
    assert err.startswith("interrupted: ") and len(err.strip().splitlines()) == 1, err
    assert "at step 0" in aborted_log(out)


def test_sigterm_to_a_sweep_while_its_floors_compute_aborts_every_job(tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            "-m",
            "seed=1,2",
            f"hydra.sweep.dir={tmp_path}",
            "log.progress=off",
            "hydra.callbacks.sweep_status.progress=off",
            "+experiment=smoke",
            *ISSUE,
        ],
        cwd=ROOT,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )

    def both_running() -> bool:
        jobs = [p.parent for p in tmp_path.glob("*/job_status.json")]
        ready = 0
        for job in jobs:
            try:
                status = json.loads((job / "job_status.json").read_text())
            except ValueError:
                continue
            ready += bool(status.get("pid")) and (job / "run.mcap").exists()
        return ready == 2

    _wait_for(both_running, timeout=180)
    time.sleep(1.5)
    took = _stopped_within(proc, signal.SIGTERM, timeout=60)
    assert proc.returncode != 0
    assert took < 10, f"the sweep ended {took:.1f} s after SIGTERM"
    rows = list(csv.DictReader(open(tmp_path / "sweep_status.csv")))
    assert [r["state"] for r in rows] == ["aborted", "aborted"], rows
    for job in {p.parent for p in tmp_path.glob("*/run.mcap")}:
        assert "SIGTERM" in aborted_log(job)


STUBBORN_JOB = """
import signal, sys, time
seen = []
def on_signal(signum, frame):
    seen.append(signum)
    if len(seen) == 2:  # a run stops inside a long computation on the second request
        sys.exit(0)
signal.signal(signal.SIGTERM, on_signal)
print("ready", flush=True)
while True:
    time.sleep(0.01)
"""


def test_a_job_that_does_not_stop_on_the_first_signal_is_sent_a_second(tmp_path):
    """A job inside a computation longer than the grace (a long step) stops on the
    second request: the sweep sends it one rather than wait out its 30 s."""
    from harness.runs.status import write_status
    from harness.runs.supervision import stop_jobs

    job = subprocess.Popen([sys.executable, "-c", STUBBORN_JOB], stdout=subprocess.PIPE, text=True)
    try:
        assert job.stdout is not None and job.stdout.readline().strip() == "ready"
        (tmp_path / "job").mkdir()
        write_status(tmp_path / "job", state="running", pid=job.pid)
        start = time.monotonic()
        stop_jobs(tmp_path, signal.SIGTERM, wait_s=15)
        took = time.monotonic() - start
        assert job.wait(timeout=1) == 0, "the job was never sent a second signal"
        assert took < 8, f"the job stopped {took:.1f} s after the first signal"
    finally:
        job.kill()
        job.wait()
