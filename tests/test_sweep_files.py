"""A sweep's own files when something else stands in their place: a job's lock that is a
directory or names a process that is not its holder, and a job whose log is missing, a
dangling link or a link loop (:mod:`harness.runs.supervision`, :mod:`analysis.rows`).

Every claim that could wait runs in a process of its own with a time limit, so a claim
that spins or waits for ever fails the test instead of hanging it.
"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from harness.runs.app import job_dir_name
from harness.runs.checks import ConfigError
from harness.runs.status import read_status
from harness.runs.supervision import LOCK_FILE, RUN_LOCK, claim_job_dir, claim_run_dir

ROOT = Path(__file__).resolve().parents[1]
TINY = ["grid.n=10", "agents.n=100", "sim.t_final=0.1", "sim.dt=0.02"]
PROC = Path("/proc/self/stat").exists()
needs_proc = pytest.mark.skipif(not PROC, reason="needs Linux's /proc")


def python(code: str, timeout: float, **kwargs) -> subprocess.CompletedProcess:
    """Run ``code`` in a Python process of its own (killed after ``timeout`` s)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
        env=env,
        **kwargs,
    )


CLAIM = """
import sys, time
from pathlib import Path
from harness.runs.supervision import claim_job_dir
start = time.monotonic()
try:
    with claim_job_dir(Path(sys.argv[1])):
        print("claimed", flush=True)
except OSError as err:
    print(f"refused {type(err).__name__}: {err}", flush=True)
print(f"after {time.monotonic() - start:.1f}", flush=True)
"""


def claim_elsewhere(job_dir: Path, timeout: float = 60) -> subprocess.CompletedProcess:
    """Claim ``job_dir`` in a process of its own (:data:`CLAIM`)."""
    return subprocess.run(
        [sys.executable, "-c", CLAIM, str(job_dir)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


@pytest.fixture
def sleeper():
    """A live process that is no job of any sweep (its pid stands for a reused pid)."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    time.sleep(0.1)  # a process started after it starts at another clock tick
    yield proc
    proc.kill()
    proc.wait()


@pytest.mark.parametrize("inside", ["empty", "a file inside"])
def test_a_directory_in_place_of_a_job_lock_is_an_error_naming_it_never_a_retry(tmp_path, inside):
    lock = tmp_path / LOCK_FILE
    lock.mkdir()
    if inside != "empty":
        (lock / "x").write_text("1")
    proc = claim_elsewhere(tmp_path, timeout=30)
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("refused LockError: "), proc.stdout + proc.stderr
    assert str(lock) in lines[0] and "a directory" in lines[0], lines
    assert float(lines[1].split()[1]) < 5, lines
    assert lock.is_dir(), "the directory was removed"


def test_a_directory_in_place_of_a_run_lock_refuses_the_run_in_a_line_naming_it(tmp_path):
    lock = tmp_path / RUN_LOCK
    lock.mkdir()
    with pytest.raises(ConfigError) as refused:
        claim_run_dir(tmp_path)
    line = str(refused.value)
    assert line.startswith("invalid config: hydra.run.dir="), line
    assert str(lock) in line and "a directory" in line and "\n" not in line, line


@pytest.mark.parametrize("kind", ["fifo", "dangling link", "link loop", "link to /dev/zero"])
def test_a_fifo_or_link_in_place_of_a_job_lock_is_taken_over(tmp_path, kind):
    lock = tmp_path / LOCK_FILE
    if kind == "fifo":
        os.mkfifo(lock)
    elif kind == "dangling link":
        lock.symlink_to(tmp_path / "nowhere")
    elif kind == "link loop":
        lock.symlink_to(tmp_path / "other")
        (tmp_path / "other").symlink_to(lock)
    else:
        lock.symlink_to("/dev/zero")
    proc = claim_elsewhere(tmp_path, timeout=30)
    assert proc.stdout.splitlines()[0] == "claimed", proc.stdout + proc.stderr
    assert not os.path.lexists(lock), "the lock was not released"


def test_a_sweep_job_whose_lock_is_a_directory_fails_with_that_reason_and_the_others_run(
    tmp_path,
):
    """The job is ``failed`` in the status table with a reason naming the lock, the
    other job completes, and the sweep ends (exit 1) without waiting."""
    jobs = {s: job_dir_name(",".join(sorted([*TINY, f"seed={s}"]))) for s in (1, 2)}
    lock = tmp_path / jobs[1] / LOCK_FILE
    lock.mkdir(parents=True)
    cmd = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        *TINY,
        "log.progress=off",
        "seed=1,2",
        f"hydra.sweep.dir={tmp_path}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=240)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    said = [ln for ln in proc.stderr.splitlines() if str(lock) in ln]
    assert len(said) == 1 and said[0].startswith("job "), proc.stderr
    table = {r["dir"]: r for r in csv.DictReader(open(tmp_path / "sweep_status.csv"))}
    assert table[jobs[1]]["state"] == "failed", table
    assert str(lock) in table[jobs[1]]["reason"], table
    assert table[jobs[2]]["state"] == "completed", table
    assert (tmp_path / jobs[2] / "run.mcap").is_file()
    assert not (tmp_path / jobs[1] / "run.mcap").exists()
    assert read_status(tmp_path / jobs[1])["state"] == "failed"


def _proc_field_22(pid: int) -> str:
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]


@needs_proc
def test_a_job_lock_names_its_holder_by_pid_start_time_and_boot_id(tmp_path):
    boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    with claim_job_dir(tmp_path):
        text = (tmp_path / LOCK_FILE).read_text()
    assert text.split() == [str(os.getpid()), _proc_field_22(os.getpid()), boot], text
    assert not (tmp_path / LOCK_FILE).exists()


def _left_behind(job_dir: Path) -> str:
    """The lock a job's process leaves when it is killed with SIGKILL while it holds it."""
    code = CLAIM.replace('print("claimed", flush=True)', "time.sleep(120)")
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(job_dir)],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    lock = job_dir / LOCK_FILE
    deadline = time.monotonic() + 60
    while not (lock.exists() and lock.read_text().strip()) and time.monotonic() < deadline:
        time.sleep(0.05)
    holder.send_signal(signal.SIGKILL)
    holder.wait()
    assert lock.exists(), "the holder never claimed the directory"
    return lock.read_text()


@needs_proc
@pytest.mark.parametrize("reused", ["pid", "pid, after a reboot"])
def test_a_lock_whose_pid_now_belongs_to_another_process_is_taken_over(tmp_path, sleeper, reused):
    """A lock left by a killed job, its pid now that of a live, unrelated process (the
    sleeper): the claim takes it over at once, saying nothing."""
    fields = _left_behind(tmp_path).split()
    fields[0] = str(sleeper.pid)
    if reused != "pid" and len(fields) == 3:
        fields[2] = "00000000-0000-0000-0000-000000000000"
    (tmp_path / LOCK_FILE).write_text(" ".join(fields) + "\n")
    proc = claim_elsewhere(tmp_path, timeout=30)
    lines = proc.stdout.splitlines()
    assert lines[0] == "claimed", proc.stdout + proc.stderr
    assert float(lines[1].split()[1]) < 5, lines
    assert "waiting" not in proc.stderr, proc.stderr


@pytest.mark.parametrize("form", ["named", "a pid only"])
def test_a_wait_for_a_live_holder_is_said_once_naming_the_pid_and_the_lock(tmp_path, sleeper, form):
    """The lock of a live holder (as the claim writes it, or an older lock holding only
    a pid) is waited for, and the wait said once on standard error; the claim goes on
    when the holder ends."""
    lock = tmp_path / LOCK_FILE
    if form == "named":
        with claim_job_dir(tmp_path):  # this process's lock, given to the sleeper
            fields = lock.read_text().split()
        fields[0] = str(sleeper.pid)
        if len(fields) == 3:
            fields[1] = _proc_field_22(sleeper.pid) if PROC else "-"
        text = " ".join(fields)
    else:
        text = str(sleeper.pid)
    lock.write_text(text + "\n")
    start = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-c", CLAIM, str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    watchdog = threading.Timer(60, sleeper.kill)  # the claim goes on, whatever it says
    watchdog.start()
    try:
        first = proc.stderr.readline() if proc.stderr else ""  # said while it waits
        waited = proc.poll() is None and sleeper.poll() is None
        sleeper.kill()
        sleeper.wait()
        out, err = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        proc.kill()
    assert waited, "the claim did not wait for a live holder, or said nothing while it did"
    assert out.splitlines()[0] == "claimed", out + err
    assert time.monotonic() - start < 30
    said = [ln for ln in [first, *err.splitlines()] if ln.strip()]
    assert len(said) == 1, err
    assert f"process {sleeper.pid}" in said[0] and str(lock) in said[0], said
    if form != "named":
        assert "names only a process id" in said[0], said


@pytest.mark.parametrize("log", ["missing", "dangling link", "link loop", "fifo"])
def test_a_job_whose_log_is_missing_dangling_or_a_link_loop_counts_as_not_completed(
    tmp_path, compose, capsys, log
):
    """The broken job is a row ``unreadable: no run log at ...`` beside the completed
    one, and the analysis counts it as not completed, without making any config key
    vary; directories that are no job's (the analysis output, a link loop) are no
    rows."""
    from analysis.rows import analyse
    from analysis.sweep import main
    from harness.runs.run import run

    sweep = tmp_path / "sweep"
    run(compose([*TINY, "log.progress=off"]), sweep / "ok")
    broken = sweep / "broken"
    (broken / ".hydra").mkdir(parents=True)
    (broken / "job_status.json").write_text('{"state": "completed"}')
    target = broken / "run.mcap"
    if log == "dangling link":
        target.symlink_to(tmp_path / "nowhere.mcap")
    elif log == "link loop":
        target.symlink_to(broken / "x")
        (broken / "x").symlink_to(target)
    elif log == "fifo":
        os.mkfifo(target)
    (sweep / "analysis").mkdir()
    (sweep / "loop").symlink_to(sweep / "loop")
    rows, _ = analyse(sweep)
    states = {r["dir"]: r["state"] for r in rows}
    assert set(states) == {"ok", "broken"}, states
    assert states["ok"] == "completed"
    assert states["broken"] == f"unreadable: no run log at {target}", states
    out = tmp_path / "an"
    capsys.readouterr()
    assert main([str(sweep), "--out", str(out)]) == 0
    assert "2 jobs, 1 not completed" in capsys.readouterr().out
    csv_rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert sorted(r["dir"] for r in csv_rows) == ["broken", "ok"]
    header = list(csv_rows[0])
    assert header[0] == "law", f"a job without a log made config columns: {header}"


def test_a_lock_appears_whole_and_leaves_no_file_of_its_own(tmp_path, monkeypatch):
    """The lock is linked into place already naming its holder: at the moment its name
    exists it reads as this process (no window in which it reads empty, i.e. stale)."""
    from harness.runs import supervision

    seen = []
    real_link = os.link

    def watching_link(src, dst, *args, **kwargs):
        real_link(src, dst, *args, **kwargs)
        seen.append(supervision.read_lock(Path(dst)))  # the instant the name exists

    monkeypatch.setattr(supervision.os, "link", watching_link)
    with claim_job_dir(tmp_path):
        assert seen and seen[0].pid == os.getpid() and seen[0].holds()
        assert sorted(p.name for p in tmp_path.iterdir()) == [LOCK_FILE]
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("pid", ["4294967296", "99999999999999999999999", "4194305"])
def test_a_lock_naming_an_impossible_process_id_names_no_holder(tmp_path, pid):
    """No process has such an id: the lock is stale and taken over, never an error."""
    from harness.runs.status import alive
    from harness.runs.supervision import read_lock

    lock = tmp_path / LOCK_FILE
    lock.write_text(f"{pid} 1 2\n")
    assert read_lock(lock).pid == 0
    assert alive(int(pid)) is False
    with claim_job_dir(tmp_path):
        assert read_lock(lock).pid == os.getpid()


def test_a_link_to_another_job_is_counted_once(tmp_path):
    from analysis.rows import job_dirs

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "job_status.json").write_text("{}")
    (tmp_path / "c").symlink_to(tmp_path / "b", target_is_directory=True)
    assert [p.name for p in job_dirs(tmp_path)] == ["a", "b"]


def test_a_lock_is_still_taken_on_a_file_system_without_hard_links(tmp_path, monkeypatch):
    from harness.runs import supervision

    def no_links(src, dst, *args, **kwargs):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(supervision.os, "link", no_links)
    with claim_job_dir(tmp_path):
        assert supervision.read_lock(tmp_path / LOCK_FILE).pid == os.getpid()
    assert not any(tmp_path.iterdir())
