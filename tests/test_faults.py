"""The fault classes of the reliability contract (docs/reliability.md), each with a test that fails
when its promise breaks.

1 resume by content, 2 sweeps that survive their jobs (the SIGKILL fault injection is in
tests/test_sweeps.py), 3 refusal before running, 4 divergence guard, 5 signals,
6 overwrites, 7 loader and analysis on foreign content.
"""

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from analysis.load import LogWarning, load_run
from harness.runs import resources
from harness.runs.app import MAX_NAME_BYTES, job_dir_name, run_job
from harness.runs.build import build
from harness.runs.checks import ConfigError
from harness.runs.identity import config_hash
from harness.runs.resume import verify_log
from harness.runs.run import DiskFull, run
from harness.runs.status import collect

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["grid.n=8", "agents.n=50", "sim.t_final=0.06", "sim.dt=0.02", "log.progress=off"]


def messages_and_metadata(path):
    out = []
    with open(path, "rb") as f:
        for r in StreamReader(f).records:
            name = type(r).__name__
            if name == "Message":
                out.append((r.channel_id, r.log_time, r.data))
            elif name == "Metadata":
                out.append((r.name, tuple(sorted(r.metadata.items()))))
    return out


# ------------------------------------------------------------ 1. resume by content
@pytest.fixture(scope="module")
def done_log(tmp_path_factory, compose):
    out = tmp_path_factory.mktemp("done")
    cfg = compose(["sim.t_final=0.4", "grid.n=10", "agents.n=100", "log.progress=off"])
    assert run(cfg, out).state == "completed"
    return out / "run.mcap", config_hash(cfg)


def test_a_complete_log_verifies_and_carries_its_config_hash(done_log):
    log, digest = done_log
    check = verify_log(log)
    assert check.intact and check.state == "completed" and check.config_hash == digest


@settings(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), min_size=1, max_size=3))
def test_a_damaged_log_is_never_trusted(tmp_path_factory, done_log, flips):
    """Byte flips anywhere: either the log is found damaged, or every message and
    metadata record (config, status) reads back exactly as written."""
    log, _ = done_log
    data = bytearray(log.read_bytes())
    for where, xor in flips:
        data[int(where * (len(data) - 1))] ^= xor
    path = tmp_path_factory.mktemp("flip") / "run.mcap"
    path.write_bytes(bytes(data))
    check = verify_log(path)
    if check.intact:
        assert messages_and_metadata(path) == messages_and_metadata(log)


def test_resume_reruns_on_other_config_or_damage_and_never_overwrites(tmp_path, compose):
    out = tmp_path / "job"
    cfg = compose(SMALL)
    run_job(cfg, out, 0, SMALL)
    status = json.loads((out / "job_status.json").read_text())
    assert status["state"] == "completed" and status["runs"] == 1
    run_job(cfg, out, 0, SMALL)  # same config, intact log: skipped
    assert json.loads((out / "job_status.json").read_text())["runs"] == 1
    # the same directory with another config (as +experiment= would give): rerun, old kept
    other = compose([*SMALL[:-2], "sim.t_final=0.08", "log.progress=off"])
    first = (out / "run.mcap").read_bytes()
    run_job(other, out, 0, SMALL)
    status = json.loads((out / "job_status.json").read_text())
    assert status["runs"] == 2 and "another config" in status["rerun_reason"]
    assert (out / "run.previous-1.mcap").read_bytes() == first
    assert verify_log(out / "run.mcap").config_hash == config_hash(other)
    # damaged chunk bytes with an intact summary: rerun, and the reason says so
    data = bytearray((out / "run.mcap").read_bytes())
    with open(out / "run.mcap", "rb") as f:
        index = make_reader(f).get_summary().chunk_indexes[0]
    data[index.chunk_start_offset + index.chunk_length // 2] ^= 0x5A
    (out / "run.mcap").write_bytes(bytes(data))
    assert not verify_log(out / "run.mcap").intact
    run_job(other, out, 0, SMALL)
    status = json.loads((out / "job_status.json").read_text())
    assert status["runs"] == 3 and "damaged" in status["rerun_reason"]
    assert verify_log(out / "run.mcap").intact


# ------------------------------------------------------------ 2. sweeps: names, status files
@settings(max_examples=200, deadline=None)
@given(
    a=st.text(min_size=1, max_size=400),
    b=st.text(min_size=1, max_size=400),
)
def test_job_dir_names_are_safe_and_distinct(a, b):
    na, nb = job_dir_name(a), job_dir_name(b)
    for n in (na, nb):
        assert "/" not in n and "\0" not in n and n not in (".", "..")
        assert 0 < len(n.encode()) <= 255
    if a != b:
        assert na != nb


def test_long_override_gets_a_short_unique_name():
    long = ",".join(f"target.means=[[0.{i},0.{i}]]" for i in range(40))
    assert len(job_dir_name(long).encode()) <= MAX_NAME_BYTES
    assert job_dir_name(long) != job_dir_name(long + "0")


def test_collect_survives_malformed_status_files(tmp_path):
    for name, text in (
        ("a", "{not json"),
        ("b", '["a list"]'),
        ("c", json.dumps({"job": "x", "runs": "two", "state": 3, "overrides": "seed=1"})),
        ("d", json.dumps({"job": 1, "state": "running", "pid": 2**22 + 12345})),
    ):
        (tmp_path / name).mkdir()
        (tmp_path / name / "job_status.json").write_text(text)
    rows = {r["dir"]: r for r in collect(tmp_path)}
    assert set(rows) == {"a", "b", "c", "d"}
    assert rows["d"]["state"] == "killed"  # running with no process: killed
    assert all(r["state"] != "completed" for r in rows.values())


def test_sweep_with_an_invalid_point_lists_it_and_exits_nonzero(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            "-m",
            "grid.n=8,abc",
            *SMALL[1:],
            f"hydra.sweep.dir={tmp_path}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 1, proc.stderr
    rows = list(csv.DictReader(open(tmp_path / "sweep_status.csv")))
    assert sorted(r["state"] for r in rows) == ["completed", "invalid"]
    assert "invalid point" in proc.stderr and "grid.n" in proc.stderr


# ------------------------------------------------------------ 3. refusal before running
@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("+plant.foo=1", "plant.foo"),
        ("+estimator.foo=1", "estimator.foo"),
        ("+control.foo=1", "control.foo"),
        ("+grid.foo=1", "grid.foo"),
        ("+log.foo=1", "log.foo"),
        ("+filter.foo=1", "filter.foo"),
        ("+foo=1", "foo"),
        ("plant.n=${nosuch}", "plant.n"),
        ("~filter", "estimator.process_noise"),
        ("~grid", "grid"),
        ("~sim", "sim"),
        ("~plant", "plant"),
        ("target.stds=[0.1]", "target.stds"),
        ("target.weights=[1.0,1.0]", "target.weights"),
        ("kde.bandwidth=1e-100", "kde.bandwidth"),
        ("agents.n=10000000000", "agents.n"),
    ],
)
def test_bad_inputs_are_refused_in_one_line_naming_the_key(compose, override, key, refusal):
    message = refusal([override])
    assert message is not None and message.startswith(f"invalid config: {key}="), message
    assert "\n" not in message


NUMERIC = [
    "dynamics.sigma",
    "sim.dt",
    "sim.t_final",
    "kde.bandwidth",
    "grid.length",
    "control.alpha",
    "filter.process_noise",
    "filter.r_scale",
    "filter.r_floor",
    "filter.initial_variance",
    "init.x0",
    "init.x1",
    "target.floor",
]
EXTREME = st.sampled_from([5e-324, 1e-300, 1e-100, 1e-12, 1e12, 1e100, 1e300, -1e300, -1e-300])


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(key=st.sampled_from(NUMERIC), value=EXTREME, group=st.sampled_from(["agents", "meanfield"]))
def test_extreme_finite_values_are_refused_or_end_cleanly(
    tmp_path_factory, compose, key, value, group
):
    overrides = [f"plant={group}", "grid.n=8", "agents.n=30", "sim.dt=0.02", "log.progress=off"]
    overrides += ["sim.t_final=0.04", f"{key}={value!r}"]
    try:
        cfg = compose(overrides)
        build(cfg)
    except ConfigError as err:
        assert "\n" not in str(err) and str(err).startswith("invalid config:")
        return
    result = run(cfg, tmp_path_factory.mktemp("extreme"))
    assert result.state in ("completed", "diverged"), result.reason


def test_memory_estimate_bounds_the_measured_peak(compose):
    """tracemalloc sees numpy's allocations: the estimate is an upper bound of the peak
    while building and stepping, for robots and for the dense reference filters."""
    from harness.loop import trajectory

    for overrides in (
        ["agents.n=200000", "grid.n=16", "log.progress=off"],
        ["filter.engine=reference", "grid.n=12", "agents.n=100", "log.progress=off"],
    ):
        cfg = compose(overrides)
        tracemalloc.start()
        parts = build(cfg)
        steps = trajectory(parts)
        for _ in range(4):
            next(steps)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        estimate = resources.check_memory(cfg, parts.grid, available=(10**15, "test"))
        assert estimate >= peak, (overrides, estimate, peak)


def test_dense_filter_estimate_grows_as_cells_squared_and_is_refused(compose):
    from harness.estimators.filters.estimator import FilterEstimator
    from harness.grid import Grid

    dense = [
        FilterEstimator.memory_estimate(Grid.square(n), engine="reference").nbytes for n in (16, 32)
    ]
    local = [
        FilterEstimator.memory_estimate(Grid.square(n), engine="local").nbytes for n in (16, 32)
    ]
    assert dense[1] / dense[0] > 12 and local[1] / local[0] < 10  # M^2 against ~M^1.5
    grid64 = Grid.square(64)
    with pytest.raises(ConfigError, match=r"filter.engine='reference'.*memory.*GB"):
        resources.check_memory(
            compose(["filter.engine=reference", "grid.n=64"]), grid64, (10**9, "t")
        )


def test_log_estimate_bounds_the_log_and_a_full_disk_is_refused(tmp_path, compose, monkeypatch):
    cfg = compose(["grid.n=10", "agents.n=300", "sim.t_final=0.4", "log.progress=off"])
    run(cfg, tmp_path / "a")
    built = build(cfg)
    estimate, _ = built.observers["log"].disk_bytes(300)
    assert estimate >= (tmp_path / "a" / "run.mcap").stat().st_size
    monkeypatch.setattr(
        resources.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(1, 1, 1000)
    )
    with pytest.raises(ConfigError, match=r"log.*would need about"):
        run(cfg, tmp_path / "b")
    assert not (tmp_path / "b").exists()


def cli(*args, cwd=ROOT, timeout=120):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
        env=env,
    )


def test_cli_refuses_unread_keys_and_resource_bombs_without_output(tmp_path):
    for bad, words in (("+grid.foo=1", "nothing reads"), ("agents.n=10000000000", "memory")):
        proc = cli(bad, f"hydra.run.dir={tmp_path / 'x'}")
        assert proc.returncode == 2, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and words in proc.stderr
        assert "Traceback" not in proc.stderr and not (tmp_path / "x").exists()


# ------------------------------------------------------------ 4. divergence guard
def test_huge_finite_estimates_end_diverged_not_completed(tmp_path, compose, monkeypatch):
    from harness.estimators.kde import KDEEstimator
    from harness.records import Estimate

    original = KDEEstimator.step

    def blown(self, inp):
        est = original(self, inp)
        return Estimate(est.p_hat * 1e300, est.q_hat)

    monkeypatch.setattr(KDEEstimator, "step", blown)
    result = run(compose(["estimator=kde", *SMALL]), tmp_path)
    assert result.state == "diverged" and "non-finite" in result.reason
    assert load_run(tmp_path).state == "diverged"


def test_singular_factorisation_ends_diverged(tmp_path, compose, monkeypatch):
    from harness.fokker_planck import FokkerPlanck

    def singular(self, *args, **kwargs):
        raise RuntimeError("Factor is exactly singular")

    monkeypatch.setattr(FokkerPlanck, "step", singular)
    result = run(compose(SMALL), tmp_path)
    assert result.state == "diverged" and "singular" in result.reason
    assert load_run(tmp_path).state == "diverged"


# ------------------------------------------------------------ 5. signals
def start_long(tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "experiments.closed_loop",
            "sim.t_final=1000",
            "grid.n=16",
            "log.field_every=1",
            "log.progress=off",
            f"hydra.run.dir={tmp_path}",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    log = tmp_path / "run.mcap"
    deadline = time.time() + 120
    while time.time() < deadline and (not log.exists() or log.stat().st_size < 1_500_000):
        time.sleep(0.05)
    assert log.exists()
    return proc, log


@pytest.mark.parametrize("gap", [0.0, 0.001, 0.005, 0.05])
def test_repeated_signals_never_leave_an_unfinalised_log(tmp_path, gap):
    proc, log = start_long(tmp_path)
    proc.send_signal(signal.SIGINT)
    time.sleep(gap)
    for _ in range(3):
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        assert load_run(log).state == "aborted"


def test_sighup_finalises_like_sigterm(tmp_path):
    proc, log = start_long(tmp_path)
    proc.send_signal(signal.SIGHUP)
    proc.wait(timeout=60)
    assert proc.returncode != 0
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        run_log = load_run(log)
    assert run_log.state == "aborted" and "SIGHUP" in run_log.metadata["status"]["reason"]


# ------------------------------------------------------------ 6. overwrites, full disk
def test_existing_log_is_never_overwritten(tmp_path):
    out = tmp_path / "run"
    assert cli(*SMALL, f"hydra.run.dir={out}").returncode == 0
    before = (out / "run.mcap").read_bytes()
    proc = cli(*SMALL, f"hydra.run.dir={out}")
    assert proc.returncode == 2 and "hydra.run.dir" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert (out / "run.mcap").read_bytes() == before


def test_default_run_dirs_are_unique_within_one_second(tmp_path):
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "experiments.closed_loop", *SMALL],
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for _ in range(2)
    ]
    for p in procs:
        assert p.wait(timeout=120) == 0, p.stderr.read()
    logs = list((tmp_path / "outputs" / "closed_loop").glob("*/run.mcap"))
    assert len(logs) == 2


def test_full_disk_mid_run_is_one_line_and_leaves_what_was_written(tmp_path, compose, monkeypatch):
    # the up-front estimate would refuse these runs; the disk fills up after the start
    # (another process writing) is what is tested here
    monkeypatch.setattr("harness.runs.run.check_disk", lambda *args: 0)
    cfg = compose(
        [
            "grid.n=10",
            "agents.n=2000",
            "sim.t_final=2",
            "log.field_every=1",
            "log.positions_every=1",
            *SMALL[-1:],
        ]
    )
    (tmp_path / "run.mcap").symlink_to("/dev/full")
    with pytest.raises(DiskFull) as info:
        run(cfg, tmp_path, overwrite=True)
    assert "\n" not in str(info.value) and "disk full" in str(info.value)
    small = tmp_path / "tmpfs"
    small.mkdir()
    mounted = (
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(small)]).returncode
        == 0
    )
    if not mounted:
        pytest.skip("no tmpfs mount here: only the /dev/full half ran")
    try:
        with pytest.raises(DiskFull):
            run(cfg, small, overwrite=True)
        with pytest.warns(LogWarning):
            log = load_run(small / "run.mcap")
        assert len(log.metrics["t"]) > 5
    finally:
        subprocess.run(["umount", str(small)])


# ------------------------------------------------------------ 7. loader and analysis
def fake_log(path, rows, theory=None, config="grid:\n  n: 8\n", empty_grid=False):
    from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
    from mcap_protobuf.schema import register_schema

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("densityloop.Metrics", "jsonschema", b"{}")
        cid = w.register_channel("/metrics", "json", sid)
        for i, row in enumerate(rows):
            w.add_message(cid, i, json.dumps(row).encode(), i)
        if empty_grid:
            gsid = register_schema(w, GridMsg)
            gcid = w.register_channel("/fields/p_hat", "protobuf", gsid)
            w.add_message(gcid, 0, GridMsg().SerializeToString(), 0)
        w.add_metadata("config", {"yaml": config})
        if theory is not None:
            w.add_metadata("theory", theory)
        w.add_metadata("status", {"state": "completed", "reason": ""})
        w.finish()


def test_rows_missing_a_metric_stay_aligned_with_nan(tmp_path):
    rows = [{"t": 0.0, "phi_l2": 1.0}, {"t": 1.0}, {"t": 2.0, "phi_l2": 3.0, "extra": 7.0}]
    fake_log(tmp_path / "run.mcap", rows)
    log = load_run(tmp_path)
    np.testing.assert_array_equal(log.metrics["t"], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(log.metrics["phi_l2"], [1.0, np.nan, 3.0])
    np.testing.assert_array_equal(log.metrics["extra"], [np.nan, np.nan, 7.0])


def test_empty_grid_is_skipped_with_a_warning(tmp_path):
    fake_log(tmp_path / "run.mcap", [{"t": 0.0}], empty_grid=True)
    with pytest.warns(LogWarning, match="skipped 1 damaged"):
        log = load_run(tmp_path)
    assert "/fields/p_hat" not in log.fields


def test_analysis_warns_on_foreign_metadata_and_refuses_mixed_sweeps(tmp_path, capsys):
    from analysis import sweep

    rows = [{"t": float(t), "phi_l2": np.exp(-t), "eps_l2": 0.1, "eps_g_l2": 0.1} for t in range(8)]
    for n in (8, 16):
        fake_log(
            tmp_path / "one" / f"n{n}" / "run.mcap",
            rows,
            {"rate_exact": "fast"},
            f"grid:\n  n: {n}\n",
        )
    assert sweep.main([str(tmp_path / "one")]) == 0
    err = capsys.readouterr().err
    assert "rate_exact='fast' is not a number" in err
    csv_rows = list(csv.DictReader(open(tmp_path / "one" / "analysis" / "sweep.csv")))
    assert [r["rate_theory"] for r in csv_rows] == ["nan", "nan"]
    # two sweeps in one directory: over grid.n and, separately, over agents.n, the study
    # declared (as its preset does) over agents.n
    study = "analysis:\n  figure: agents_n\n  primary: [agents.n]\n"
    for name, cfg in (
        ("a", "grid:\n  n: 8\nagents:\n  n: 10\n"),
        ("b", "grid:\n  n: 16\nagents:\n  n: 10\n"),
        ("c", "grid:\n  n: 8\nagents:\n  n: 20\n"),
    ):
        fake_log(tmp_path / "two" / name / "run.mcap", rows, None, cfg + study)
    assert sweep.main([str(tmp_path / "two")]) == 2
    err = capsys.readouterr().err
    assert "more than one sweep" in err and "grid.n" in err
