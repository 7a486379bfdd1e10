"""The failures a hostile tester found, by class, each with a test that fails when its
promise breaks (docs/reliability.md): two writers of one log,
resume after a code change, the machine's real memory limits, a full disk in a sweep,
one line for every error, the live view's shutdown and bind failures, analysis of
foreign content, and values that would be rounded or dropped without a word.
"""

import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from harness.runs.build import build
from harness.runs.checks import ConfigError
from harness.runs.resume import verify_log
from harness.runs.run import run

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
    from harness.runs.app import CheckCallback

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


# ------------------------------------------------------------ 2. resume sees code changes
def test_sweep_resumed_after_a_code_change_reruns_every_job_whose_code_differs(
    tmp_path, compose, monkeypatch, capsys
):
    import json

    from analysis import sweep
    from harness.runs import identity
    from harness.runs.app import run_job

    repo = tmp_path / "code"
    (repo / "harness").mkdir(parents=True)
    (repo / "harness" / "law.py").write_text("ALPHA = 1\n")
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "harness/law.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    monkeypatch.setattr(identity, "ROOT", repo)  # the code under git is this repository
    jobs = {"a": compose(SMALL), "b": compose([*SMALL, "seed=3"])}
    sweep_dir = tmp_path / "sweep"

    def resume():
        for k, (name, cfg) in enumerate(jobs.items()):
            run_job(cfg, sweep_dir / name, k, [name])
        return {n: json.loads((sweep_dir / n / "job_status.json").read_text()) for n in jobs}

    assert {n: s["runs"] for n, s in resume().items()} == {"a": 1, "b": 1}
    assert {n: s["runs"] for n, s in resume().items()} == {"a": 1, "b": 1}  # same code
    (repo / "harness" / "law.py").write_text("ALPHA = 2\n")  # an edit, not committed
    before = (sweep_dir / "a" / "run.mcap").read_bytes()
    status = resume()
    assert {n: s["runs"] for n, s in status.items()} == {"a": 2, "b": 2}
    assert all("git_diff_sha256" in s["rerun_reason"] for s in status.values())
    assert (sweep_dir / "a" / "run.previous-1.mcap").read_bytes() == before
    # a log of the old code beside the new ones is not pooled into one study
    (sweep_dir / "a" / "run.mcap").replace(sweep_dir / "a" / "run.new.mcap")
    (sweep_dir / "a" / "run.previous-1.mcap").replace(sweep_dir / "a" / "run.mcap")
    capsys.readouterr()
    assert sweep.main([str(sweep_dir)]) == 2
    assert "different code" in capsys.readouterr().err


def test_resume_never_overwrites_an_unfinished_log_of_another_config(tmp_path, compose):
    import json

    from harness.runs.app import run_job

    out = tmp_path / "job"
    other = compose([*SMALL, "seed=9"])
    assert run(other, out).state == "completed"
    data = (out / "run.mcap").read_bytes()
    (out / "run.mcap").write_bytes(data[: len(data) // 2])  # killed mid-run
    run_job(compose(SMALL), out, 0, SMALL)
    status = json.loads((out / "job_status.json").read_text())
    assert (
        status["state"] == "completed" and "kept as run.previous-1.mcap" in status["rerun_reason"]
    )
    assert (out / "run.previous-1.mcap").read_bytes() == data[: len(data) // 2]


# ------------------------------------------------------------ 4. a full disk in a sweep
@pytest.fixture
def tiny_disk(tmp_path):
    disk = tmp_path / "tmpfs"
    disk.mkdir()
    cmd = ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)]
    if subprocess.run(cmd, capture_output=True).returncode != 0:
        pytest.skip("no tmpfs mount here")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)])


def test_a_disk_full_during_a_sweep_records_the_reason_and_prints_the_table(
    tiny_disk, compose, monkeypatch, capfd
):
    import json

    from harness.runs.app import run_job
    from harness.runs.status import report

    # the disk fills up after the up-front check (another process writing)
    monkeypatch.setattr("harness.runs.run.check_disk", lambda *args: 0)
    rates = ["log.field_every=1", "log.positions_every=1", "log.progress=off"]
    cfg = compose(["grid.n=10", "agents.n=2000", "sim.t_final=2", *rates])
    (tiny_disk / "sweep_status.md").write_text("| an older table |\n")
    run_job(cfg, tiny_disk / "job", 0, ["seed=0"])
    status = json.loads((tiny_disk / "job" / "job_status.json").read_text())
    assert status["state"] == "aborted" and "disk full" in status["reason"], status
    capfd.readouterr()
    assert report(tiny_disk) == 1
    out, err = capfd.readouterr()
    assert "| aborted |" in out and "disk full" in out  # the table is printed
    assert "Traceback" not in err
    assert (tiny_disk / "sweep_status.md").stat().st_size > 0  # old or new, never empty
    assert not list(tiny_disk.rglob("*.tmp"))
    (tiny_disk / "job" / "run.mcap").unlink()  # room again: the table is written
    assert report(tiny_disk) == 1
    assert "| aborted |" in (tiny_disk / "sweep_status.md").read_text()


# ---------------------------------------------------- 7. analysis outputs, foreign content
@pytest.fixture(scope="module")
def small_log(tmp_path_factory):
    from conftest import compose_cached

    out = tmp_path_factory.mktemp("small")
    cfg = compose_cached([*SMALL[:-2], "sim.t_final=0.2", "sim.dt=0.02", "log.progress=off"])
    assert run(cfg, out).state == "completed"
    return out / "run.mcap"


def test_figures_are_written_atomically_and_never_share_a_name(tmp_path, small_log, monkeypatch):
    import shutil

    import matplotlib.pyplot as plt

    from analysis import figures
    from analysis.plotting import save_figure

    good = tmp_path / "f.pdf"
    good.write_bytes(b"%PDF good")
    fig = plt.figure()

    def interrupted(path, **kwargs):
        Path(path).write_bytes(b"%PDF half")
        raise KeyboardInterrupt  # SIGINT (or SIGTERM made an exception) while writing

    fig.savefig = interrupted
    with pytest.raises(KeyboardInterrupt):
        save_figure(fig, tmp_path, "f")
    assert good.read_bytes() == b"%PDF good" and {p.name for p in tmp_path.iterdir()} == {"f.pdf"}
    # two runs whose directories share a name: two sets of figures
    for parent in ("a", "b"):
        (tmp_path / parent / "run").mkdir(parents=True)
        shutil.copy(small_log, tmp_path / parent / "run" / "run.mcap")
    runs = [str(tmp_path / p / "run") for p in ("a", "b")]
    drawn = []  # the stems main draws figure 1 into (drawing itself takes seconds)
    monkeypatch.setattr(figures, "figure1", lambda run, out, stem: drawn.append(stem) or [])
    monkeypatch.setattr(figures, "figure2", lambda runs, out: [])
    assert figures.main([*runs, "--out", str(tmp_path / "figs"), "--no-gif"]) == 0
    assert len(set(drawn)) == 2 and all(s.startswith("fig1_run") for s in drawn)


# ---------------------------------------------------- 8. nothing rounded or dropped silently
@pytest.mark.parametrize(
    "overrides, key",
    [
        (["sim.t_final=0.25", "sim.dt=0.1"], "sim.t_final"),  # 2.5 steps
        (["sim.t_final=0.2", "sim.dt=0.11"], "sim.t_final"),  # 1.8 steps
        (["target.means=[[1.5,0.5],[0.3,0.3],[0.5,0.7]]"], "target.means"),
        (["target.means=[[0.5,-0.01],[0.3,0.3],[0.5,0.7]]"], "target.means"),
    ],
)
def test_values_that_would_be_rounded_or_dropped_are_refused(refusal, overrides, key):
    line = refusal([*SMALL[:2], "log.progress=off", *overrides])
    assert line is not None and line.startswith(f"invalid config: {key}="), line


def test_whole_step_counts_and_centres_on_the_boundary_are_accepted(refusal):
    for overrides in (
        ["sim.t_final=0.06", "sim.dt=0.02"],  # 2.9999999999999996 steps in floating point
        ["sim.t_final=100", "sim.dt=0.01"],
        ["target.means=[[1.0,0.0],[0.3,0.3],[0.5,0.7]]"],
    ):
        assert refusal([*SMALL[:2], *overrides]) is None, overrides


def test_a_law_whose_feedback_diffusivity_is_nan_is_refused(compose, monkeypatch):
    from harness.control.paper import PaperControl

    monkeypatch.setattr(PaperControl, "feedback_diffusivity", lambda self, p0: float("nan"))
    with pytest.raises(ConfigError, match=r"^invalid config: control=.*feedback_diffusivity"):
        build(compose(SMALL))


def test_metric_values_that_are_not_finite_numbers_are_warned_about(tmp_path, capsys):
    import warnings

    import numpy as np
    from mcap.writer import Writer

    from analysis import sweep
    from analysis.load import LogWarning, load_run

    rows = [
        b'{"t": 0.0, "phi_l2": 1.0, "eps_l2": 0.1, "eps_g_l2": 0.1}',
        b'{"t": 0.5, "phi_l2": 1e400, "eps_l2": true, "eps_g_l2": 0.1}',
        b'{"t": null, "phi_l2": 0.5, "eps_l2": 0.1, "eps_g_l2": 0.1}',
        b'{"t": 1.0, "phi_l2": 0.25, "eps_l2": 0.1, "eps_g_l2": "0.1"}',
        b'{"t": 1.5, "phi_l2": 0.2, "eps_l2": 0.1, "eps_g_l2": null}',
    ]
    for job in ("a", "b"):
        path = tmp_path / job / "run.mcap"
        path.parent.mkdir()
        with open(path, "wb") as f:
            w = Writer(f)
            w.start()
            cid = w.register_channel("/metrics", "json", w.register_schema("m", "jsonschema", b""))
            for i, row in enumerate(rows):
                w.add_message(cid, i, row, i)
            w.add_metadata("config", {"yaml": f"seed: {job == 'a'}\n"})
            w.add_metadata("status", {"state": "completed", "reason": ""})
            w.finish()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = load_run(tmp_path / "a")
    said = " ".join(str(w.message) for w in caught if w.category is LogWarning)
    assert "eps_g_l2 (1)" in said and "eps_l2 (1)" in said and "phi_l2 (1)" in said
    assert "skipped 1 damaged" in said  # the message without a time
    np.testing.assert_array_equal(log.metrics["t"], [0.0, 0.5, 1.0, 1.5])
    np.testing.assert_array_equal(log.metrics["eps_l2"], [0.1, np.nan, 0.1, 0.1])
    assert np.isnan(log.metrics["phi_l2"][1]) and np.isnan(log.metrics["eps_g_l2"][3])
    assert sweep.main([str(tmp_path)]) == 0
    assert "not finite numbers" in capsys.readouterr().err


# ------------------------------------------------------------ 3. the machine's real limits
def _tree(root, files):
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


@pytest.mark.parametrize(
    "files, source",
    [
        (  # cgroup v1: the limit on the parent group (400 MB, 100 MB used)
            {
                "proc/self/cgroup": "5:pids:/\n4:memory:/slurm/job7\n0::/\n",
                "sys/fs/cgroup/memory/memory.limit_in_bytes": "9223372036854771712\n",
                "sys/fs/cgroup/memory/memory.usage_in_bytes": "5000000000\n",
                "sys/fs/cgroup/memory/slurm/memory.limit_in_bytes": "400000000\n",
                "sys/fs/cgroup/memory/slurm/memory.usage_in_bytes": "100000000\n",
                "sys/fs/cgroup/memory/slurm/job7/memory.limit_in_bytes": "9223372036854771712\n",
                "sys/fs/cgroup/memory/slurm/job7/memory.usage_in_bytes": "90000000\n",
            },
            "/sys/fs/cgroup/memory/slurm/memory.limit_in_bytes",
        ),
        (  # cgroup v2, nested: the systemd slice limits, the scope does not
            {
                "proc/self/cgroup": "0::/user.slice/run-1.scope\n",
                "sys/fs/cgroup/user.slice/memory.max": "500000000\n",
                "sys/fs/cgroup/user.slice/memory.current": "200000000\n",
                "sys/fs/cgroup/user.slice/run-1.scope/memory.max": "max\n",
                "sys/fs/cgroup/user.slice/run-1.scope/memory.current": "1000\n",
            },
            "/sys/fs/cgroup/user.slice/memory.max",
        ),
    ],
    ids=["cgroup-v1-parent", "cgroup-v2-nested"],
)
def test_memory_limits_of_every_cgroup_level_are_found(tmp_path, compose, files, source):
    from harness.grid import Grid
    from harness.runs import resources

    files["proc/meminfo"] = "MemTotal: 64000000 kB\nMemAvailable: 60000000 kB\n"
    have = resources.memory_available(_tree(tmp_path, files))
    assert have is not None and have[0] == 300_000_000 and source in have[1]
    cfg = compose([*SMALL[:1], "agents.n=10000000", *SMALL[2:]])  # about 2 GB
    with pytest.raises(ConfigError, match="agents.n=10000000: .*" + source):
        resources.check_memory(cfg, Grid(8, 8), have)


def test_the_address_space_limit_is_a_memory_limit(tmp_path):
    import resource

    limit = 6 << 30

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}
    args = [*SMALL[:1], "agents.n=40000000", *SMALL[2:], f"hydra.run.dir={tmp_path / 'x'}"]
    proc = subprocess.run(
        [sys.executable, "-m", "experiments.closed_loop", *args],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        env=env,
        preexec_fn=cap,
    )
    one_line_refusal(proc, "agents.n=40000000", "RLIMIT_AS")
    assert not (tmp_path / "x").exists()


# ------------------------------------------------------------ 5. one line for every error
PLUGIN = """
class Boom:
    def __init__(self, **kwargs):
        raise RuntimeError("the plugin's constructor failed")


class BoomIO:
    def __init__(self, **kwargs):
        raise OSError(5, "the plugin's device failed")
"""


SLOW = pytest.mark.slow  # more of the same path; the fast suite keeps one of each kind


@pytest.mark.parametrize(
    "args, words",
    [
        pytest.param(
            ["~control", "+control._target_=boom.Boom"],
            ["RuntimeError", "constructor failed"],
            id="plugin-RuntimeError",
        ),
        pytest.param(
            ["~control", "+control._target_=boom.BoomIO"],
            ["OSError", "device failed"],
            id="plugin-OSError",
            marks=SLOW,
        ),
        pytest.param(
            ["control._target_=nosuchmodule.Law"],
            ["control._target_", "No module named"],
            id="missing-module",
        ),
        pytest.param(["grid.n==5"], ["invalid config: grid.n="], id="syntax"),
        pytest.param(
            ["grid.n=" + "5" * 5000],
            ["invalid config: grid.n=", "5000 characters"],
            id="5000-digits",
        ),
        pytest.param(
            ["+" + "k" * 3000 + "=1"],
            ["invalid config: +kkk", "3001 characters"],
            id="3000-char-key",
            marks=SLOW,
        ),
        pytest.param(
            ["target.floor=é"], ["invalid config: target.floor="], id="non-ascii", marks=SLOW
        ),
        pytest.param(
            ["hydra.run.dir={tmp}/" + "a" * 300],
            ["hydra.run.dir", "255 bytes"],
            id="300-char-dir",
            marks=SLOW,
        ),
        pytest.param(
            ["hydra.run.dir=/dev/null"], ["hydra.run.dir", "created and written"], id="dev-null"
        ),
        pytest.param(
            ["hydra.run.dir={tmp}/file/run"],
            ["hydra.run.dir", "Not a directory"],
            id="under-a-file",
            marks=SLOW,
        ),
        pytest.param(
            ["-m", "seed=1,2", "hydra.sweep.dir={tmp}/file/sweep"],
            ["hydra.sweep.dir"],
            id="sweep-under-a-file",
        ),
    ],
)
def test_errors_before_the_first_step_are_one_line_with_exit_2(tmp_path, args, words):
    (tmp_path / "plugins").mkdir()
    (tmp_path / "plugins" / "boom.py").write_text(PLUGIN)
    (tmp_path / "file").write_text("a file, not a directory\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if not any(a.startswith("hydra.") for a in args):
        args.append(f"hydra.run.dir={tmp_path / 'out'}")
    env = {"PYTHONPATH": f"{ROOT}:{tmp_path / 'plugins'}", "HYDRA_FULL_ERROR": "0"}
    flags = [a for a in args if a == "-m"]
    proc = cli(*flags, *SMALL, *[a for a in args if a != "-m"], env=env)
    one_line_refusal(proc, *words)
    assert proc.stdout.strip() == ""  # every reason on standard error
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob("*/.hydra"))


def test_sigterm_before_the_run_starts_is_one_line(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "experiments.closed_loop", *SMALL, f"hydra.run.dir={tmp_path}/x"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(0.3)  # loading its modules
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip().startswith("interrupted: received SIGTERM")
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


# ------------------------------------------------------------ 6. the live view
def test_a_stalled_client_holds_the_live_view_only_briefly():
    pytest.importorskip("websockets")
    from test_live import Client, metrics_schema

    from harness.observers.live import LiveServer

    server = LiveServer(port=0, backlog=1024)
    server.channel("/metrics", *metrics_schema())
    with Client(server.url, {"/metrics"}, read=False) as client:
        client.wait_for(lambda: server.subscribed("/metrics"), "the subscription")
        for i in range(2000):
            server.publish("/metrics", i, bytes(100_000))
        start = time.monotonic()
        server.close()  # the server would wait tens of seconds for the client's queue
        assert time.monotonic() - start < LiveServer.STOP_S + 1.0


def test_live_view_that_cannot_start_leaves_nothing_and_names_its_key(tmp_path):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        for arg, key in (
            (f"log.live_port={port}", "log.live_port"),
            ("log.live_host=no-such-host.invalid", "log.live_host"),
        ):
            out = tmp_path / key
            proc = cli(
                *SMALL, "log.live=true", f"log.live_port={port}", arg, f"hydra.run.dir={out}"
            )
            one_line_refusal(proc, f"invalid config: {key}=")
            assert not out.exists()  # no .hydra, no closed_loop.log, no run.mcap


# foreign content for every analysis entry point (hypothesis)
RAW_NUMBERS = ["1e400", "-1e400", "NaN", "Infinity", "true", "null", '"0.5"', "[1, 2]", "{}"]
METRIC_NAMES = ["phi_l2", "eps_l2", "eps_g_l2", "phat_target_l2", "swarm_l2", "x", "y", "t_p_hat"]


def _alias_bomb(levels, fan):
    lines = ["l0: &l0 [" + ", ".join(["x"] * fan) + "]"]
    for i in range(1, levels):
        lines.append(f"l{i}: &l{i} [" + ", ".join([f"*l{i - 1}"] * fan) + "]")
    return "\n".join(lines) + "\n"


yaml_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(st.sampled_from(["grid", "n", "kde", "debias", "sigma", "seed"]), inner)
    ),
    max_leaves=20,
)
configs = st.one_of(
    st.builds(
        lambda d: yaml.safe_dump(d),
        st.fixed_dictionaries(
            {},
            optional={
                "grid": st.dictionaries(st.sampled_from(["n", "length"]), yaml_values),
                "kde": st.dictionaries(st.sampled_from(["debias", "bandwidth"]), yaml_values),
                "dynamics": st.dictionaries(st.just("sigma"), yaml_values),
                "analysis": st.dictionaries(st.sampled_from(["figure", "primary"]), yaml_values),
                "seed": yaml_values,
            },
        ),
    ),
    st.builds(_alias_bomb, st.integers(2, 12), st.integers(2, 10)),
    st.just("a: &a [1, *a]\n"),
    st.just("a: &a\n  b: *a\n"),
    st.integers(10, 3000).map(lambda k: "[" * k + "]" * k),
    st.text(max_size=200),
)
metric_values = st.one_of(
    st.floats(-1e3, 1e3).map(repr), st.sampled_from(RAW_NUMBERS), st.integers().map(str)
)
metric_rows = st.lists(
    st.fixed_dictionaries(
        {"t": st.one_of(st.floats(0, 100).map(repr), st.sampled_from(RAW_NUMBERS))},
        optional={k: metric_values for k in METRIC_NAMES},
    ),
    max_size=6,
)
fields = st.dictionaries(
    st.sampled_from(["/fields/p_hat", "/fields/p_target", "/fields/velocity"]),
    st.tuples(st.integers(1, 3), st.integers(1, 3), st.integers(1, 2), st.integers(1, 3)),
) | st.builds(  # the shapes the figures draw, on grids of 2 or 3 cells a side
    lambda ny, nx, count: {
        "/fields/p_hat": (ny, nx, 1, count),
        "/fields/p_target": (ny, nx, 1, 1),
        "/fields/velocity": (ny, nx, 2, count),
    },
    st.integers(2, 3),
    st.integers(2, 3),
    st.integers(1, 3),
)
foreign_logs = st.fixed_dictionaries(
    {
        "config": configs,
        "rows": metric_rows,
        "fields": fields,
        "theory": st.dictionaries(
            st.sampled_from(["rate_exact", "swarm_l2_floor_mean"]), st.text(max_size=8)
        ),
        "code": st.sampled_from(["one", "two"]),
    }
)


def write_foreign(path, log):
    import numpy as np
    from foxglove_schemas_protobuf.Grid_pb2 import Grid as GridMsg
    from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
    from mcap.writer import Writer
    from mcap_protobuf.schema import register_schema

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/metrics", "json", w.register_schema("m", "jsonschema", b""))
        for i, row in enumerate(log["rows"]):
            text = "{" + ", ".join(f'"{k}": {v}' for k, v in row.items()) + "}"
            w.add_message(cid, i, text.encode(), i)
        gsid = register_schema(w, GridMsg)
        for topic, (ny, nx, k, count) in log["fields"].items():
            gcid = w.register_channel(topic, "protobuf", gsid)
            for j in range(count):
                msg = GridMsg(column_count=nx, cell_stride=4 * k, row_stride=4 * k * nx)
                msg.cell_size.x = msg.cell_size.y = 1.0 / nx
                for c in range(k):
                    msg.fields.append(
                        PackedElementField(
                            name=f"f{c}", offset=4 * c, type=PackedElementField.FLOAT32
                        )
                    )
                msg.data = np.linspace(0.1, 2, ny * nx * k).astype("<f4").tobytes()
                w.add_message(gcid, j, msg.SerializeToString(), j)
        w.add_metadata("config", {"yaml": log["config"]})
        w.add_metadata("theory", log["theory"])
        w.add_metadata("provenance", {"code_sha256": log["code"]})
        w.add_metadata("status", {"state": "completed", "reason": ""})
        w.finish()


@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
@given(logs=st.lists(foreign_logs, min_size=1, max_size=2))
def test_every_analysis_entry_point_works_or_says_one_line_on_foreign_logs(tmp_path_factory, logs):
    import contextlib
    import io
    import tracemalloc
    import warnings

    from analysis import (
        agent_figures,
        configs,
        convergence,
        diff,
        figures,
        frontier,
        laws,
        peclet,
        robots,
        sweep,
    )
    from analysis.load import LogError, load_run

    root = tmp_path_factory.mktemp("foreign")
    paths = [root / f"job{i}" / "run.mcap" for i in range(len(logs))]
    for path, log in zip(paths, logs, strict=True):
        write_foreign(path, log)
    no_drawing = pytest.MonkeyPatch()  # draw every figure, skip rendering it (seconds)
    for module in (figures, convergence, agent_figures, laws, robots, frontier):
        no_drawing.setattr(module, "save_figure", lambda fig, out, stem, dpi=120: [])
    no_drawing.setattr(figures, "animation", lambda run, out, stem: out / f"{stem}.gif")
    calls = [
        lambda: sweep.main([str(root)]),
        lambda: sweep.main([str(root), "--mixed-code"]),
        lambda: peclet.main([str(root)]),
        lambda: figures.main([*map(str, paths), "--out", str(root / "figs")]),
        lambda: diff.main([str(paths[0]), str(paths[-1])]),
    ]
    tracemalloc.start()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for path in paths:
                try:
                    run_log = load_run(path)
                except LogError:
                    continue
                configs.logged_config(run_log)
                run_log.to_xarray()
            for call in calls:
                err = io.StringIO()
                start = time.monotonic()
                with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                    status = call()
                assert status in (0, 1, 2)
                errors = [ln for ln in err.getvalue().splitlines() if ln.startswith("error")]
                assert len(errors) <= 1 and (status != 2 or len(errors) == 1), err.getvalue()
                assert time.monotonic() - start < 60
        assert tracemalloc.get_traced_memory()[1] < 500e6  # peak bytes
    finally:
        tracemalloc.stop()
        no_drawing.undo()


def test_a_fifo_or_device_in_place_of_a_log_is_never_read_or_trusted(tmp_path, small_log):
    import json

    from analysis import diff
    from harness.runs.status import collect

    fifo = tmp_path / "fifo" / "run.mcap"
    fifo.parent.mkdir()
    os.mkfifo(fifo)
    assert diff.main([str(small_log), str(fifo)]) == 2  # not a read that never ends
    job = tmp_path / "sweep" / "job"
    job.mkdir(parents=True)
    (job / "run.mcap").symlink_to("/dev/null")
    (job / "job_status.json").write_text(json.dumps({"job": 0, "state": "completed", "runs": 1}))
    (row,) = collect(tmp_path / "sweep")
    assert row["state"] == "missing" and "run.mcap" in row["reason"]
