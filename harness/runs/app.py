"""What the Hydra app (``experiments/closed_loop.py``) and its config call: the resolvers
of ``conf/closed_loop.yaml``, the two callbacks it names, and
:func:`~harness.runs.app.checked`, :func:`~harness.runs.app.run_job` and
:func:`~harness.runs.app.finish_sweep`.

* :class:`CheckCallback` checks a single run (by building it) before Hydra writes
  anything, and claims its directory; the build is handed on to the run
  (:func:`checked`), so a run is built once.
* :func:`run_job` is one job of a multirun: it skips itself when its directory holds a
  log that counts (:mod:`harness.runs.resume`), otherwise builds and runs in a process
  of its own (:mod:`harness.runs.supervision`); it never raises on failure and keeps its
  ``job_status.json`` (:mod:`harness.runs.status`).
* :class:`SweepStatusCallback` shows the sweep's progress while it runs
  (:mod:`harness.runs.sweep_progress`, ``docs/sweep_progress.md``), passes SIGINT,
  SIGTERM and SIGHUP on to the running jobs, and prints and writes the status table
  when the multirun ends, exiting with status 1 when a job did not complete; after an
  interruption or a launcher failure the entry point writes it (:func:`finish_sweep`).

Why there is state across calls at all: Hydra instantiates the callbacks itself and
calls the task function with the config only; the task function never receives the
callback, and the entry point's handlers of an interrupted or failed sweep run after
Hydra has returned by an exception, when ``on_multirun_end`` never runs. What a
callback makes for later must therefore live where both can reach it, in this process:
the build :class:`CheckCallback` made, until the task function takes it (:data:`BUILDS`,
a :class:`~harness.runs.supervision.Handoff` keyed by the config hash, which also hands a
job's build to the process forked to run it), and the sweep this process launches
(:data:`SWEEP`, a :class:`Sweep`). Each is created once, here.

Job directories are named by the job's overrides (:func:`job_dir_name`, the resolver
``${densityloop.job_dir:...}`` of ``hydra.sweep.subdir``); a name too long for a file
system or holding a path separator is shortened and made unique with a hash. The
resolver ``${densityloop.pid:}`` (this process's id) keeps run and sweep directories
started in the same microsecond apart.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from harness.loop import Experiment
from harness.observers.base import probe
from harness.observers.log import LOG_FILE
from harness.observers.progress import automatic
from harness.parameters import ParameterError
from harness.runs.build import build
from harness.runs.checks import ConfigError, config_line
from harness.runs.identity import code_identity, config_hash
from harness.runs.resources import check_disk, disk_need
from harness.runs.resume import clear, judge
from harness.runs.run import RunResult, check_writes_log, run
from harness.runs.status import STATUS_FILE, as_int, read_status, report, write_status
from harness.runs.supervision import (
    Handoff,
    LockError,
    check_dir_name,
    claim_job_dir,
    claim_run_dir,
    run_isolated,
    say,
    stop_jobs,
    usable_dir,
)
from harness.runs.sweep_progress import MODES, SweepMonitor, count_jobs, read_run

MAX_NAME_BYTES = 200
"""Longest job directory name kept as is (file systems allow 255 bytes)."""


def job_dir_name(override_dirname: str) -> str:
    """The directory name of a job from Hydra's ``override_dirname``: unchanged when it
    is a safe file name of at most :data:`MAX_NAME_BYTES` bytes; otherwise a readable
    prefix, ``#`` and 16 hex digits of its SHA-256, so distinct points stay distinct.
    """
    name = override_dirname or "default"
    safe = "/" not in name and "\0" not in name and name not in (".", "..")
    if safe and len(name.encode()) <= MAX_NAME_BYTES:
        return name
    digest = hashlib.sha256(name.encode()).hexdigest()[:16]
    prefix = name.replace("/", "_").replace("\0", "_").encode()[:80].decode(errors="ignore")
    return f"{prefix.lstrip('.')}#{digest}"


OmegaConf.register_new_resolver("densityloop.job_dir", job_dir_name, replace=True)


OmegaConf.register_new_resolver("densityloop.pid", lambda: str(os.getpid()), replace=True)


BUILDS = Handoff()
"""The build made before the code that runs it: by :class:`CheckCallback` for the task
function (:func:`checked`), and by :func:`run_job` for the job's forked process."""


class Sweep:
    """The sweep this (main) process launches, from :class:`SweepStatusCallback`'s
    ``on_multirun_start`` to its status table: its directory, its progress line, the
    signal stopping it, and whether its table is written.

    Attributes:
        directory: The sweep directory (None: no sweep runs in this process).
        monitor: The progress line's thread (None: not started).
        stopping: The name of the signal that stops the sweep (empty: none).
        written: Whether the status table is written.
    """

    directory: Path | None
    monitor: SweepMonitor | None
    stopping: str
    written: bool

    def __init__(self) -> None:
        self.forget()

    def forget(self) -> None:
        """No sweep runs in this process (yet)."""
        self.directory, self.monitor, self.stopping, self.written = None, None, "", False

    def start(self, directory: Path) -> None:
        """Record the sweep of ``directory``; in the main thread, take over SIGINT,
        SIGTERM and SIGHUP (:meth:`interrupt`).
        """
        self.directory = directory
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, self.interrupt)

    def show(self, monitor: SweepMonitor) -> None:
        """Start the sweep's progress line."""
        monitor.start()
        self.monitor = monitor

    def interrupt(self, signum: int, frame: Any) -> None:
        """The signal handler of the sweep's main process on SIGINT, SIGTERM or SIGHUP:
        stop the running jobs (SIGINT passed on as itself, the others as SIGTERM; each
        finalises its log as ``aborted``), then end the sweep with
        :class:`KeyboardInterrupt` (the launcher stops its workers; :func:`finish_sweep`
        writes the table). A second signal while stopping is ignored.
        """
        if self.stopping:
            return
        name = signal.Signals(signum).name
        self.stopping = name
        if self.directory is not None:
            forward = signal.SIGINT if signum == signal.SIGINT else signal.SIGTERM
            stop_jobs(self.directory, forward)
        raise KeyboardInterrupt(f"sweep stopped by {name}")

    def report(self, directory: Path, interrupted: str = "") -> int:
        """Stop the progress line (its last line comes before the table), then print and
        write the status table of ``directory`` (:func:`harness.runs.status.report`).

        Returns:
            The sweep's exit status (1 when a job did not complete or it was
            interrupted, 0 otherwise).
        """
        if self.monitor is not None:
            self.monitor.stop(bool(interrupted))
        self.written = True
        return report(directory, interrupted)

    def finish(self, reason: str = "") -> int | None:
        """Write the status table if a sweep runs and its table is not written yet
        (:meth:`report`, interrupted by ``reason`` or the signal that stopped it).

        Returns:
            The exit status, or None when there was nothing to write.
        """
        if self.directory is None or self.written:
            return None
        return self.report(self.directory, reason or self.stopping)


SWEEP = Sweep()
"""The sweep launched by this process (:class:`SweepStatusCallback` records it,
:func:`finish_sweep` ends it)."""


def finish_sweep(reason: str = "") -> int | None:
    """Write the status table of the sweep running in this process if it is not written
    yet (after an interruption or a launcher failure); returns the exit status (1 when a
    job did not complete, 0 otherwise), or None when no sweep was running.
    """
    return SWEEP.finish(reason)


class SweepStatusCallback(Callback):
    """Shows the sweep's progress while it runs, passes signals on to the jobs, and
    prints and writes the status table when a multirun ends.

    Args:
        progress: The progress line (:mod:`harness.runs.sweep_progress`): ``auto`` (redrawn
            in place on a terminal, plain lines elsewhere or when ``CI`` is ``true``),
            ``tty``, ``plain`` or ``off``.
        progress_every: Least time between two plain lines (s).
    """

    def __init__(self, progress: str = "auto", progress_every: float = 10.0) -> None:
        self.progress, self.progress_every = progress, progress_every

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Check that the sweep directory can be created and written and the progress
        settings (one line and exit status 2 otherwise), remember the sweep, take over
        SIGINT, SIGTERM and SIGHUP and start the progress line.
        """
        SWEEP.forget()
        key = "hydra.callbacks.sweep_status"
        try:
            usable_dir("hydra.sweep.dir", Path(str(config.hydra.sweep.dir)))
            if self.progress not in MODES:
                raise ConfigError(f"{key}.progress", self.progress, f"one of {', '.join(MODES)}")
            every = self.progress_every
            if not isinstance(every, (int, float)) or isinstance(every, bool) or not every >= 0:
                raise ConfigError(f"{key}.progress_every", every, "a number of seconds >= 0")
        except ConfigError as err:
            print(err, file=sys.stderr)
            sys.exit(2)
        SWEEP.start(Path(str(config.hydra.sweep.dir)))
        monitor = SweepMonitor(
            Path(str(config.hydra.sweep.dir)),
            count_jobs(config),
            mode=self.progress,
            every=float(every),
            status_file=STATUS_FILE,
        )
        SWEEP.show(monitor)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Stop the progress line, collect the jobs' status files; exit 1 when a job did
        not complete.
        """
        status = SWEEP.report(Path(str(config.hydra.sweep.dir)))
        if status:
            sys.exit(status)


def checked(cfg: DictConfig) -> DictConfig | Experiment:
    """The build :class:`CheckCallback` made of ``cfg`` (handed on once, so a run is
    built once), else ``cfg`` itself.
    """
    exp = BUILDS.take(config_hash(cfg))
    return cfg if exp is None else exp


class CheckCallback(Callback):
    """Checks a single run's config (by building it), that its directory can be created
    and holds no log yet, that no other run is using it, and that the disk has room for
    the log, before Hydra writes anything into it; a refused value (or anything else
    this check raises) prints its one line and exits with status 2. The build is
    handed on to the run (:func:`checked`), and the directory stays claimed
    (:func:`~harness.runs.supervision.claim_run_dir`) until the process ends.
    """

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Build the run to check it, then claim its directory."""
        BUILDS.drop()
        try:
            with quiet_hydra_utils():
                parts = build(config)
            check_writes_log(parts)
            out = Path(str(config.hydra.run.dir))
            check_dir_name("hydra.run.dir", out)
            if (out / LOG_FILE).exists() or (out / LOG_FILE).is_symlink():
                raise ConfigError(
                    "hydra.run.dir",
                    str(out),
                    "a directory without a run.mcap (it holds one already: not overwritten)",
                )
            check_disk(disk_need(parts), out)
            probe_observers(parts)
            claim_run_dir(out)
        except ConfigError as err:
            print(config_line(err), file=sys.stderr)
            sys.exit(2)
        except Exception as err:  # Hydra would turn it into a warning and run on
            print(f"cannot start: {one_line(err)}", file=sys.stderr)
            sys.exit(2)
        BUILDS.give(config_hash(config), parts)


@contextlib.contextmanager
def quiet_hydra_utils() -> Iterator[None]:
    """Silence the logger of ``hydra.utils``, which writes the reason an object cannot
    be loaded to standard output; the refusal says it on standard error instead.
    """
    logger = logging.getLogger("hydra.utils")
    before = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = before


def probe_observers(exp: Experiment) -> None:
    """Ask every observer that can (``probe()``: the live view's address and port)
    whether it will start, before anything is written.

    Raises:
        ConfigError: naming the public key of the refused parameter.
    """
    for name, observer in exp.observers.items():
        try:
            probe(observer)
        except ParameterError as err:
            key = exp.keys.get(f"observers.{name}.{err.name}", f"observers.{name}.{err.name}")
            raise ConfigError(key, err.value, err.allowed) from None


def one_line(err: BaseException) -> str:
    """``Type: first line of the message`` of an exception."""
    text = (str(err).strip().splitlines() or [""])[0]
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def run_job(
    cfg: DictConfig, out: Path, job: int, overrides: list[str], sweep_dir: Path | None = None
) -> RunResult | None:
    """One job of a multirun: skip when its log counts (:func:`harness.runs.resume.judge`);
    otherwise run it in a process of its own; never raise on failure; keep status. A
    job whose directory's lock cannot be taken (a directory named ``.job.lock``) is
    ``failed``, with the reason naming the lock, and nothing of it runs.

    The job's ``job_status.json`` (:mod:`harness.runs.status`) also says when it started
    and ended (``started_at``, ``ended_at``: Unix time, s), whether it was ``skipped``
    and of which sweep it is (``sweep_run``, from the sweep directory's
    :data:`~harness.runs.sweep_progress.RUN_FILE`), for the sweep's progress line
    (:mod:`harness.runs.sweep_progress`); while that line is on a terminal, the run's own
    bar with ``log.progress=auto`` is off.

    Args:
        cfg: The job's config.
        out: The job's directory.
        job: The job's number in the sweep.
        overrides: The job's overrides.
        sweep_dir: The sweep directory (default: the parent of ``out``).

    Returns:
        None always (the job's ``job_status.json`` and log hold the outcome).
    """
    out.mkdir(parents=True, exist_ok=True)
    digest = config_hash(cfg)
    now_code = code_identity()
    ident = {"job": job, "overrides": overrides, "config_sha256": digest}
    sweep = read_run(out.parent if sweep_dir is None else sweep_dir)
    tty = sweep.get("tty") is True
    if tty and automatic(OmegaConf.select(cfg, "log.progress")):
        with read_write(cfg), open_dict(cfg):
            OmegaConf.update(cfg, "log.progress", "off")  # the sweep's line is on the terminal
    try:
        with claim_job_dir(out, tty=tty):
            started = {"sweep_run": sweep.get("id", ""), "started_at": time.time()}
            write_status(out, **started, ended_at=None, skipped=False, **ident)
            try:
                _resume_or_run(cfg, out, ident, now_code, tty)
            finally:
                write_status(out, ended_at=time.time())
    except LockError as err:  # a lock that cannot be taken: this job fails, the others run
        reason = f"cannot claim its directory: {err}"
        say(f"job {job}: {reason}", sys.stderr, tty=tty)
        now = {"sweep_run": sweep.get("id", ""), "started_at": time.time()}
        now.update(ended_at=now["started_at"], skipped=False, state="failed", reason=reason)
        write_status(out, **now, pid=0, **ident)
    return None


def _resume_or_run(
    cfg: DictConfig, out: Path, ident: dict[str, Any], now_code: dict[str, str], tty: bool
) -> None:
    """The body of :func:`run_job`, with the job's directory claimed."""
    job, digest = ident["job"], ident["config_sha256"]
    log = out / LOG_FILE
    verdict = judge(log, digest, now_code)
    if verdict.done:
        write_status(out, state="completed", reason="", rerun_reason="", skipped=True, **ident)
        say(f"job {job}: already completed, skipped ({out})", tty=tty)
        return
    try:
        with quiet_hydra_utils():
            built = build(cfg)
        check_writes_log(built)
        BUILDS.give(digest, built)
    except ConfigError as err:
        say(config_line(err), sys.stderr, tty=tty)
        write_status(out, state="invalid", reason=config_line(err), pid=0, **ident)
        return
    why = clear(log, verdict)  # a log that does not count is never overwritten
    runs = as_int(read_status(out).get("runs"), 0) + 1
    write_status(out, state="running", runs=runs, reason="", rerun_reason=why, pid=0, **ident)
    try:
        code = run_isolated(BUILDS, digest, out, tty=tty)  # the child inherits the build
    except OSError as err:  # no process could be forked: run here
        say(f"job {job}: cannot fork ({err}); running in the worker", sys.stderr, tty=tty)
        code = 0
        try:
            exp = BUILDS.take(digest)
            result = run(cfg if exp is None else exp, out)
            write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s)
        except Exception as err2:
            write_status(out, state="aborted", reason=f"{type(err2).__name__}: {err2}")
    if code < 0:
        name = signal.Signals(-code).name
        hint = " (the out-of-memory killer?)" if -code == signal.SIGKILL else ""
        write_status(out, state="killed", reason=f"killed by {name}{hint}", pid=0)
        say(f"job {job} was killed by {name}{hint}", sys.stderr, tty=tty)
    elif read_status(out).get("state") == "running":
        write_status(out, state="aborted", reason=f"exited with status {code}", pid=0)
