import csv
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from analysis.load import LogWarning, load_run
from analysis.rows import analyse, value

ROOT = Path(__file__).resolve().parents[1]
TINY = ["grid.n=10", "agents.n=100", "sim.t_final=0.1", "sim.dt=0.02", "log.progress=off"]


def multirun(sweep_dir, *overrides, check=True):
    cmd = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        *overrides,
        f"hydra.sweep.dir={sweep_dir}",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    if check:
        assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def job_dirs(sweep_dir):
    return sorted(p.parent for p in Path(sweep_dir).glob("*/run.mcap"))


@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_two_job_multirun_gives_two_complete_logs(tmp_path, launcher):
    extra = ["hydra.launcher.timeout_min=10"] if launcher == "submitit_local" else []
    proc = multirun(tmp_path, "seed=1,2", *TINY, f"hydra/launcher={launcher}", *extra)
    dirs = job_dirs(tmp_path)
    assert len(dirs) == 2
    names = sorted(d.name for d in dirs)  # named by their overrides
    assert names[0].endswith("seed=1,sim.dt=0.02,sim.t_final=0.1") and "seed=2" in names[1]
    assert "log.progress" not in names[0]
    for d in dirs:
        assert load_run(d).state == "completed"
    table = (tmp_path / "sweep_status.md").read_text()
    assert table.count("| completed |") == 2 and "seed=1" in proc.stdout


def test_resume_reruns_only_the_broken_job(tmp_path):
    multirun(tmp_path, "seed=1,2", *TINY)
    first, second = job_dirs(tmp_path)
    # a job killed mid-run leaves a log without its summary: cut it short
    data = (second / "run.mcap").read_bytes()
    (second / "run.mcap").write_bytes(data[: len(data) // 2])
    proc = multirun(tmp_path, "seed=1,2", *TINY)
    runs = {
        d.name: json.loads((d / "job_status.json").read_text())["runs"] for d in (first, second)
    }
    assert runs == {first.name: 1, second.name: 2}
    assert "already completed, skipped" in proc.stdout
    assert load_run(second).state == "completed"
    rows = list(csv.DictReader(open(tmp_path / "sweep_status.csv")))
    assert [r["state"] for r in rows] == ["completed", "completed"]


def test_failing_job_does_not_lose_the_others(tmp_path):
    # grid.n=3 fails inside its job (multirun jobs validate themselves); grid.n=8 runs
    proc = multirun(tmp_path / "bad", "grid.n=8,3", *TINY[1:], check=False)
    assert proc.returncode == 1  # the table says a job did not complete
    rows = list(csv.DictReader(open(tmp_path / "bad" / "sweep_status.csv")))
    states = sorted(r["state"] for r in rows)
    assert states == ["completed", "invalid"]


def test_analysis_cli_on_a_tiny_sweep(tmp_path):
    multirun(tmp_path, "seed=1,2,3", *TINY)
    out = tmp_path / "an"
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(tmp_path), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 3
    assert {r["seed"] for r in rows} == {"1", "2", "3"}
    for col in (
        "state",
        "phi_tail_mean",
        "phi_tail_sup",
        "eps_sup",
        "rate_fit",
        "rate_theory",
        "wall_s",
    ):
        assert col in rows[0]
    assert all(r["state"] == "completed" for r in rows)
    assert (out / "convergence.png").stat().st_size > 5000
    assert (out / "convergence.pdf").is_file()
    bad = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(tmp_path / "none")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert bad.returncode == 2 and "no sweep directory" in bad.stderr


def test_iss_curve_is_monotone_and_zero_error_rate_meets_poincare_bound(tmp_path):
    """Mean-field plant, injected errors: the tail sup of ||Phi|| grows with delta; with
    delta = 0 the measured decay rate is at least 0.9 times (alpha + sigma) lambda (the
    linearised rate; the nonlinear term alpha p only adds to it)."""
    multirun(
        tmp_path,
        "plant=meanfield",
        "estimator=injected",
        "estimator.delta=0.0,0.01,0.03,0.1",
        "grid.n=16",
        "sim.t_final=120",
        "sim.dt=0.02",
        "log.field_every=1000",
        "log.progress=off",
    )
    rows, _ = analyse(tmp_path)
    rows.sort(key=lambda r: float(value(r, "estimator.delta")))
    assert [r["state"] for r in rows] == ["completed"] * 4
    sups = np.array([r["phi_tail_sup"] for r in rows])
    assert np.all(np.diff(sups) > 0), sups
    zero = rows[0]
    assert zero["rate_fit"] >= 0.9 * zero["rate_theory"], (zero["rate_fit"], zero["rate_theory"])
    # and the injected error has the size asked for
    np.testing.assert_allclose([r["eps_sup"] for r in rows[1:]], [0.01, 0.03, 0.1], rtol=1e-6)


def test_joblib_job_is_byte_identical_to_a_serial_run(tmp_path):
    from mcap.stream_reader import StreamReader

    def payloads(path):
        with open(path, "rb") as f:
            return [
                (r.channel_id, r.log_time, r.data)
                for r in StreamReader(f).records
                if type(r).__name__ == "Message"
            ]

    serial = tmp_path / "serial"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            "seed=5",
            *TINY,
            f"hydra.run.dir={serial}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    multirun(tmp_path / "sweep", "seed=5,6", *TINY)
    (job,) = [d for d in job_dirs(tmp_path / "sweep") if "seed=5" in d.name]
    a, b = payloads(serial / "run.mcap"), payloads(job / "run.mcap")
    assert len(a) > 10 and a == b


def test_analysis_groups_by_the_logged_config_not_the_command_line(tmp_path):
    """Laws are told apart by the options their logs record (the choices record), not by
    the command line or a class name; a class path the option names is not an axis."""
    multirun(tmp_path, "control=paper,heat", *TINY, "plant=meanfield", "estimator=exact")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every log records its choices: no warning
        rows, _ = analyse(tmp_path)
    assert sorted(r["law"] for r in rows) == ["heat", "paper"]
    assert {value(r, "plant") for r in rows} == {"meanfield"}
    from analysis.rows import varied

    keys = varied(rows)
    assert "control._target_" not in keys and "seed" not in keys
    assert "control.density_floor" in keys  # the heat law's own key


def _wait_for_running_job(sweep_dir, needle, timeout=180):
    """The pid of the job process of the job whose directory contains ``needle``, once
    its log is being written."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        for status_file in Path(sweep_dir).glob("*/job_status.json"):
            if needle not in status_file.parent.name:
                continue
            try:
                status = json.loads(status_file.read_text())
            except ValueError:
                continue
            log = status_file.parent / "run.mcap"
            if status.get("state") == "running" and status.get("pid") and log.exists():
                if log.stat().st_size > 200_000:
                    return status["pid"], status_file.parent
        time.sleep(0.05)
    raise AssertionError("the job never started")


LONG = ["grid.n=10", "agents.n=100", "sim.dt=0.02", "log.progress=off", "log.field_every=1"]


def test_sigkill_of_a_job_costs_only_that_job_and_rerun_runs_only_it(tmp_path):
    """Fault injection: the out-of-memory killer's SIGKILL to the process running one job
    of a joblib sweep; the other jobs finish, the table is written, and re-running the
    same command runs only the killed job."""
    cmd = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        "sim.t_final=0.1,0.2,30",
        *LONG,
        f"hydra.sweep.dir={tmp_path}",
        "hydra.launcher.n_jobs=2",
    ]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    pid, victim = _wait_for_running_job(tmp_path, "sim.t_final=30")
    os.kill(pid, signal.SIGKILL)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1, err
    rows = {r["dir"]: r for r in csv.DictReader(open(tmp_path / "sweep_status.csv"))}
    assert len(rows) == 3
    assert rows[victim.name]["state"] == "killed" and "SIGKILL" in rows[victim.name]["reason"]
    others = [r for d, r in rows.items() if d != victim.name]
    assert [r["state"] for r in others] == ["completed", "completed"]
    runs_before = {d: r["runs"] for d, r in rows.items()}
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    rows = {r["dir"]: r for r in csv.DictReader(open(tmp_path / "sweep_status.csv"))}
    assert {d: r["runs"] for d, r in rows.items()} == {
        d: str(int(n) + (d == victim.name)) for d, n in runs_before.items()
    }
    assert all(r["state"] == "completed" for r in rows.values())


def test_sigterm_to_the_sweep_stops_its_jobs_and_writes_the_table(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "experiments.closed_loop",
        "-m",
        "seed=1,2",
        "sim.t_final=1000",
        *LONG,
        f"hydra.sweep.dir={tmp_path}",
    ]
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    _wait_for_running_job(tmp_path, "seed=")
    time.sleep(1.0)
    statuses = [json.loads(p.read_text()) for p in tmp_path.glob("*/job_status.json")]
    pids = [s["pid"] for s in statuses if s.get("pid")]
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=120)
    assert proc.returncode != 0
    for p in pids:  # no orphaned job keeps running
        assert (
            not Path(f"/proc/{p}").exists() or "Z" in Path(f"/proc/{p}/stat").read_text().split()[2]
        )
    rows = list(csv.DictReader(open(tmp_path / "sweep_status.csv")))
    assert len(rows) >= 1 and all(r["state"] != "completed" for r in rows)
    for d in job_dirs(tmp_path):
        with warnings.catch_warnings():
            warnings.simplefilter("error", LogWarning)
            assert load_run(d).state == "aborted"


def test_the_declared_figure_is_drawn_and_an_unknown_one_refused(tmp_path):
    """The analysis block a sweep's jobs log picks the figure, whatever the keys vary."""
    from analysis.configs import logged_config

    declared = tmp_path / "declared"
    multirun(
        declared,
        "agents.n=100,120",
        *TINY[:1],
        *TINY[2:],
        "+analysis.figure=agents_n",
        "+analysis.primary=[agents.n]",
        "+analysis.tail=0.5",
    )
    (job, _) = job_dirs(declared)
    assert logged_config(load_run(job))["analysis"] == {
        "figure": "agents_n",
        "primary": ["agents.n"],
        "tail": 0.5,
    }
    out = tmp_path / "an"
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(declared), "--out", str(out)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert (out / "agents_n.png").is_file() and not (out / "convergence.png").exists()

    unknown = tmp_path / "unknown"
    multirun(unknown, "seed=1", *TINY, "+analysis.figure=nosuch")
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.sweep", str(unknown)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert "analysis.figure='nosuch': no such figure (one of iss_gain," in proc.stderr
    assert not (unknown / "analysis").exists()


def test_declarations_are_checked():
    from functools import partial

    from analysis.declaration import DeclarationError
    from analysis.declaration import declaration as declared
    from analysis.sweep import FIGURES

    declaration = partial(declared, figures=FIGURES)
    assert declaration({"grid.n": 30}).figure == "convergence"
    decl = declaration({"analysis.figure": "iss_gain", "analysis.primary": ["law"]})
    assert (decl.figure, decl.primary, decl.tail) == ("iss_gain", ("law",), 0.25)
    for flat, text in (
        ({"analysis.figure": "nosuch"}, "analysis.figure='nosuch': no such figure"),
        ({"analysis.figure": "agents_n", "analysis.tial": 0.5}, "analysis.tial=0.5: not a key"),
        ({"analysis.figure": "agents_n", "analysis.tail": 2}, "analysis.tail=2: a fraction"),
        ({"analysis.figure": "agents_n", "analysis.primary": "agents.n"}, "a list of config"),
        ({"analysis": "agents_n"}, "analysis='agents_n': a block with figure"),
    ):
        with pytest.raises(DeclarationError, match=text):
            declaration(flat)


def _fake_log(path, config, choices=None):
    """A log of three metric rows with a ``config`` record and, when given, ``choices``."""
    from mcap.writer import Writer

    path.parent.mkdir(parents=True)
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/metrics", "json", w.register_schema("m", "jsonschema", b""))
        for i in range(4):
            w.add_message(cid, i, json.dumps({"t": float(i), "phi_l2": 2.0**-i}).encode(), i)
        w.add_metadata("config", {"yaml": config})
        if choices is not None:
            w.add_metadata("choices", choices)
        w.add_metadata("status", {"state": "completed", "reason": ""})
        w.finish()


def test_a_log_without_choices_names_components_by_class_with_one_warning(tmp_path):
    """Logs written before the choices record: the law and the groups' columns hold the
    class names of their _target_, and the analysis says so once for all of them."""
    from analysis.rows import varied
    from analysis.run_stats import SweepWarning

    for job, (law, plant) in enumerate((("HeatControl", "Agents"), ("PaperControl", "Unicycles"))):
        config = f"control:\n  _target_: old.{law}\nplant:\n  _target_: old.{plant}\n"
        _fake_log(tmp_path / "old" / f"{job}" / "run.mcap", config)
    with pytest.warns(SweepWarning) as caught:
        rows, _ = analyse(tmp_path / "old")
    said = [str(w.message) for w in caught if w.category is SweepWarning]
    assert len(said) == 1 and "2 of 2 logs" in said[0] and "class names" in said[0]
    assert [(r["law"], value(r, "plant")) for r in rows] == [
        ("HeatControl", "Agents"),
        ("PaperControl", "Unicycles"),
    ]
    assert varied(rows) == ["plant"]  # the class paths are named by the options

    config = "control:\n  _target_: a.Law\nplant:\n  _target_: a.Plant\n"
    _fake_log(tmp_path / "new" / "0" / "run.mcap", config, {"control": "mine", "plant": "p"})
    log = load_run(tmp_path / "new" / "0")
    assert log.choices == {"control": "mine", "plant": "p"} and log.has_choices
    with warnings.catch_warnings():
        warnings.simplefilter("error", SweepWarning)
        (row,), _ = analyse(tmp_path / "new")
    assert (row["law"], value(row, "plant")) == ("mine", "p")
    assert load_run(tmp_path / "old" / "0").choices == {}
