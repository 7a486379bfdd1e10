"""The sweep's progress line (harness/runs/sweep_progress.py): counts and the time left from
fake status files and a fake clock, against arithmetic done by hand; plain and terminal
output; and two small real sweeps whose last line is read from their captured output.
"""

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from analysis.configs import logged_config
from analysis.load import load_run
from harness.api import CONFIG_DIR
from harness.runs.sweep_progress import (
    RUN_FILE,
    SweepMonitor,
    count_jobs,
    format_duration,
    read_run,
)

ROOT = Path(__file__).resolve().parents[1]
RUN = "r1"


class Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class Stream(io.StringIO):
    def __init__(self, tty: bool) -> None:
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def status(sweep: Path, name: str, **fields) -> None:
    (sweep / name).mkdir(exist_ok=True)
    text = json.dumps({"job": 0, "overrides": [name], **fields}).ljust(4096)
    (sweep / name / "job_status.json").write_text(text + "\n")


def monitor(sweep: Path, clock: Clock, total: int | None, mode: str = "plain", every=10.0):
    stream = Stream(tty=mode == "tty")
    m = SweepMonitor(sweep, total, mode=mode, every=every, stream=stream, clock=clock)
    m.run_id = RUN
    return m, stream


def test_counts_and_time_left_from_status_files(tmp_path):
    clock = Clock(95.0)  # the sweep starts at t = 95 s
    m, stream = monitor(tmp_path, clock, total=7)
    ended = {"sweep_run": RUN, "skipped": False}
    status(tmp_path, "a", state="completed", started_at=100.0, ended_at=110.0, **ended)
    status(tmp_path, "b", state="aborted", started_at=100.0, ended_at=120.0, **ended)
    status(
        tmp_path,
        "c",
        state="completed",
        started_at=121.0,
        ended_at=121.5,
        sweep_run=RUN,
        skipped=True,
    )  # skipped by resume: done, but not in the mean wall time nor the parallelism
    status(tmp_path, "d", state="running", started_at=115.0, ended_at=None, sweep_run=RUN)
    status(tmp_path, "e", state="completed", started_at=1.0, ended_at=2.0, sweep_run="r0")
    status(tmp_path, "f", state="invalid")  # a file of an older version: pending
    clock.t = 125.0
    p = m.snapshot()
    # 7 jobs: a and c done (c skipped), b failed, d running, e, f and one unseen pending
    assert (p.total, p.done, p.skipped, p.running, p.failed, p.pending) == (7, 2, 1, 1, 1, 3)
    assert p.elapsed_s == 30.0
    # W = (10 + 20) / 2 = 15 s; at most 2 ran at once (a and b, then b and d);
    # work = 3 pending * 15 + (15 - 10 s that d has run) = 50 job-s over min(2, 4) slots
    assert p.left_s == pytest.approx(25.0)
    m.tick()
    assert stream.getvalue() == (
        "sweep: 2/7 jobs done (1 skipped), 1 running, 1 failed; elapsed 30 s, left ~25 s\n"
    )
    # d has run longer than W: it adds nothing, 3 * 15 / 2
    clock.t = 140.0
    assert m.snapshot().left_s == pytest.approx(22.5)


def test_time_left_is_unknown_until_a_job_ends_and_zero_when_all_have(tmp_path):
    clock = Clock(0.0)
    m, _ = monitor(tmp_path, clock, total=2)
    status(tmp_path, "a", state="running", started_at=1.0, ended_at=None, sweep_run=RUN)
    status(tmp_path, "b", state="completed", started_at=0.5, ended_at=3.0, sweep_run=RUN,
           skipped=True)  # fmt: skip
    clock.t = 4.0
    assert m.snapshot().left_s is None  # only a skipped job has ended
    before = (tmp_path / "a" / "job_status.json").stat()
    status(tmp_path, "a", state="diverged", started_at=1.0, ended_at=5.0, sweep_run=RUN)
    # rewritten in place within one tick of the file system's clock: same inode, size
    # and time stamp; read again all the same (it changed less than SETTLE_S ago)
    os.utime(tmp_path / "a" / "job_status.json", ns=(before.st_atime_ns, before.st_mtime_ns))
    clock.t = 6.0
    p = m.snapshot()
    assert (p.done, p.failed, p.running, p.left_s) == (1, 1, 0, 0.0)
    # the last line of an interrupted sweep has no estimate
    m2, stream = monitor(tmp_path, clock, total=3)
    m2.tick(final=True, interrupted=True)
    assert stream.getvalue().endswith("left –\n")
    assert "1/3 jobs done (1 skipped), 0 running, 1 failed" in stream.getvalue()


def test_plain_lines_on_changes_at_most_every_n_seconds_and_a_last_one(tmp_path):
    clock = Clock(0.0)
    m, stream = monitor(tmp_path, clock, total=3, every=10.0)
    clock.t = 1.0
    m.tick()  # nothing started, before FIRST_LINE_S: no line yet
    assert stream.getvalue() == ""
    status(tmp_path, "a", state="running", started_at=1.5, ended_at=None, sweep_run=RUN)
    clock.t = 2.0
    m.tick()  # a job started: the first line
    status(tmp_path, "a", state="completed", started_at=1.5, ended_at=4.0, sweep_run=RUN)
    clock.t = 5.0
    m.tick()  # changed, but 3 s after the last line: not yet
    clock.t = 12.5
    m.tick()  # 10.5 s after the last line
    clock.t = 30.0
    m.tick()  # nothing changed: no line (the heartbeat is 300 s)
    clock.t = 400.0
    m.tick()  # the heartbeat
    lines = stream.getvalue().splitlines()
    assert [ln.split(";")[0] for ln in lines] == [
        "sweep: 0/3 jobs done (0 skipped), 1 running, 0 failed",
        "sweep: 1/3 jobs done (0 skipped), 0 running, 0 failed",
        "sweep: 1/3 jobs done (0 skipped), 0 running, 0 failed",
    ]
    assert lines[1].endswith("elapsed 12 s, left ~5 s")  # 2 pending * 2.5 s / 1 slot
    assert lines[2].endswith("elapsed 6 min 40 s, left ~5 s")
    assert "\r" not in stream.getvalue()


def test_terminal_line_is_redrawn_in_place_and_ended_with_a_newline(tmp_path, monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.setenv("TERM", "xterm")
    clock = Clock(0.0)
    stream = Stream(tty=True)
    m = SweepMonitor(tmp_path, None, mode="auto", stream=stream, clock=clock)
    assert m.mode == "tty"
    m.run_id = RUN
    status(tmp_path, "a", state="running", started_at=0.0, ended_at=None, sweep_run=RUN)
    m.tick()
    m.tick()
    m.tick(final=True)
    m.tick(final=True)  # the last line is drawn once
    text = stream.getvalue()
    assert text.count("\r") == 3 and text.count("\n") == 1 and text.endswith("\x1b[K\n")
    assert "sweep: 0/? jobs done (0 skipped), 1 running, 0 failed; elapsed 0 s, left –" in text
    monkeypatch.setenv("CI", "true")  # CI: plain lines even on a terminal
    assert SweepMonitor(tmp_path, 1, stream=Stream(tty=True)).mode == "plain"


def test_durations_carry_their_units():
    assert [format_duration(s) for s in (0.4, 59.4, 65, 3599.6, 7260)] == [
        "0 s",
        "59 s",
        "1 min 05 s",
        "1 h 00 min",
        "2 h 01 min",
    ]


def test_total_is_the_basic_sweepers_product():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("closed_loop", ["+experiment=laws_n"], return_hydra_config=True)
        # conf/experiment/laws_n.yaml: 4 values of agents.n, every law (control=glob(*)), 2 seeds
        laws = len(list((CONFIG_DIR / "control").glob("*.yaml")))
        assert count_jobs(cfg) == 4 * laws * 2
        cfg.hydra.overrides.task.append("seed=0,1,2")  # the command line's replaces it
        assert count_jobs(cfg) == 4 * laws * 3
        cfg.hydra.overrides.task.append("control=glob(*)")  # every file of conf/control
        assert count_jobs(cfg) == 4 * len(list((CONFIG_DIR / "control").glob("*.yaml"))) * 3
    other = OmegaConf.create({"hydra": {"sweeper": {"_target_": "x.Optuna"}}})
    assert count_jobs(other) is None


TINY = ["grid.n=10", "agents.n=100", "sim.t_final=0.1", "sim.dt=0.02"]


def sweep(sweep_dir, *overrides):
    cmd = [sys.executable, "-m", "experiments.closed_loop", "-m", *overrides]
    cmd.append(f"hydra.sweep.dir={sweep_dir}")
    proc = subprocess.run(cmd, capture_output=True, cwd=ROOT, timeout=300)  # \r kept
    proc.stdout, proc.stderr = proc.stdout.decode(), proc.stderr.decode()
    return proc


def last_line(stderr: str) -> str:
    parts = [p.replace("\x1b[K", "") for p in stderr.replace("\r", "\n").split("\n")]
    return [p for p in parts if p.startswith("sweep: ")][-1]


def test_real_sweeps_end_with_every_job_counted(tmp_path):
    # on a terminal (forced): the line is redrawn in place; the runs' own bars are off
    proc = sweep(tmp_path, "seed=1,2", *TINY, "hydra.callbacks.sweep_status.progress=tty")
    assert proc.returncode == 0, proc.stderr
    assert "\r" in proc.stderr and proc.stderr.count("sweep: ") >= 1
    line = last_line(proc.stderr)
    assert line.startswith("sweep: 2/2 jobs done (0 skipped), 0 running, 0 failed; elapsed ")
    assert line.endswith("left 0 s")
    assert read_run(tmp_path)["tty"] is True and (tmp_path / RUN_FILE).is_file()
    for job in tmp_path.glob("*/run.mcap"):
        assert logged_config(load_run(job.parent))["log"]["progress"] == "off"
    # captured (not a terminal): plain lines; both done jobs skipped, both new ones
    # invalid (jobs in this process: the basic launcher, no worker to start)
    proc = sweep(tmp_path, "seed=1,2", "grid.n=10,3", *TINY[1:], "hydra/launcher=basic")
    assert proc.returncode == 1, proc.stderr
    assert "\r" not in proc.stderr
    line = last_line(proc.stderr)
    assert line.startswith("sweep: 2/4 jobs done (2 skipped), 0 running, 2 failed; elapsed ")
    assert line.endswith("left 0 s")
    assert proc.stderr.index(line) < proc.stderr.index("2 job(s) did not complete")
