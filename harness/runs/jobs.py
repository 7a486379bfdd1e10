"""Jobs of a sweep: per-job status, resume by content, isolation, and the status table
at the end of a multirun; and the checks of a single run before Hydra writes anything.

Hydra cannot resume a sweep. Each job of a multirun therefore

* skips itself only when its directory holds a ``run.mcap`` that is complete, reads
  back whole (chunk CRCs checked, the message count equal to the summary's), has
  status ``completed``, and whose ``provenance`` record's ``config_sha256`` equals the
  hash of the job's resolved config (:func:`config_hash`) and its ``code_sha256`` the
  code's (:func:`~harness.runs.identity.code_identity`: commit, the diff's hash, package
  versions); otherwise it runs again and its ``job_status.json`` and the table say why
  (``rerun_reason``). A log is replaced only when it is a verified copy of what the
  rerun writes (same config and code, unfinished or not ``completed``); any other is
  moved aside (``run.previous-K.mcap``), never overwritten;
* runs in a process of its own (forked from the launcher's worker, which only waits),
  so a job killed by the kernel's out-of-memory killer or by hand costs only itself:
  it is recorded as ``killed`` and the other jobs go on;
* never raises: a failing job finalises its own log (status ``aborted``), records
  the error and returns;
* writes ``job_status.json`` next to its log: job number, overrides, state, reason,
  wall time (s) of its last real run, ``runs`` (how many times it actually ran), the
  config hash, the pid of its process while it runs, and for the progress line when it
  started and ended in which sweep and whether it was skipped.

:class:`SweepStatusCallback` (a Hydra callback) shows the sweep's progress while it
runs (jobs done, running, failed, of how many, the time elapsed and left;
:mod:`harness.runs.sweep_progress`, ``docs/sweep_progress.md``), collects the status files
when the multirun ends, prints a table (job, overrides, state, runs, wall time) and
writes it as ``sweep_status.csv`` and ``sweep_status.md`` in the sweep directory; it
exits with status 1 when a job did not complete (invalid, failed, killed, diverged).
SIGINT, SIGTERM and SIGHUP to the sweep's main process are passed on to the running
jobs (which finalise their logs as ``aborted``), and the table is written before the
sweep exits (:func:`finish_sweep`, called by the entry point).

Job directories are named by the job's overrides (:func:`job_dir_name`, the resolver
``${densityloop.job_dir:...}`` of ``hydra.sweep.subdir``); a name too long for a file
system or holding a path separator is shortened and made unique with a hash.
"""

from __future__ import annotations

import atexit
import contextlib
import csv
import hashlib
import io
import json
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numba
from hydra.experimental.callback import Callback
from mcap.reader import make_reader
from mcap.records import Message, Metadata
from mcap.stream_reader import StreamReader
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

from harness.observers.log import LOG_FILE
from harness.parameters import ParameterError
from harness.runs.build import Experiment, build
from harness.runs.checks import ConfigError, check_disk, config_line, disk_need
from harness.runs.identity import code_change, code_identity, config_hash
from harness.runs.run import RunResult, Terminated, run
from harness.runs.sweep_progress import MODES, SweepMonitor, count_jobs, read_run

STATUS_FILE = "job_status.json"


LOCK_FILE = ".job.lock"


MAX_NAME_BYTES = 200
"""Longest job directory name kept as is (file systems allow 255 bytes)."""


NOT_DONE = ("invalid", "aborted", "diverged", "killed", "running", "missing", "truncated")


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


@dataclass(frozen=True)
class LogCheck:
    """What :func:`verify_log` found: ``complete`` (a summary and a footer), ``intact``
    (every record read back with valid CRCs and the summary's message count),
    ``state`` (of the status record), ``config_hash`` (``config_sha256`` of the
    provenance record), ``problem`` (why it cannot be trusted, empty when it can) and
    ``provenance`` (the record, empty when not read).
    """

    complete: bool
    intact: bool
    state: str | None
    config_hash: str | None
    problem: str
    provenance: dict[str, str] = field(default_factory=dict)


def verify_log(path: Path) -> LogCheck:
    """Read the whole log back: chunk CRCs checked, messages counted against the
    summary's statistics, status and config-hash records collected.
    """
    if not path.is_file():
        return LogCheck(False, False, None, None, "no log")
    prov: dict[str, str]
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as err:
        prov = _scan_provenance(path)
        problem = f"unfinished or unreadable ({err})"
        return LogCheck(False, False, None, prov.get("config_sha256"), problem, prov)
    if summary is None or summary.statistics is None:
        prov = _scan_provenance(path)
        problem = "unfinished (no summary)"
        return LogCheck(False, False, None, prov.get("config_sha256"), problem, prov)
    expected = summary.statistics.message_count
    state, digest, count = None, None, 0
    prov = {}
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True, record_size_limit=1 << 30).records:
                if isinstance(record, Message):
                    count += 1
                elif isinstance(record, Metadata) and record.name == "status":
                    state = record.metadata.get("state")
                elif isinstance(record, Metadata) and record.name == "provenance":
                    prov = dict(record.metadata)
                    digest = prov.get("config_sha256")
    except Exception as err:
        problem = f"damaged ({type(err).__name__}: {err})"
        return LogCheck(True, False, state, digest, problem, prov)
    if count != expected:
        problem = f"damaged ({count} messages read, the summary says {expected})"
        return LogCheck(True, False, state, digest, problem, prov)
    return LogCheck(True, True, state, digest, "", prov)


def _scan_provenance(path: Path) -> dict[str, str]:
    """The ``provenance`` record of a log read from its start as far as it reads (an
    unfinished log has it near its start); empty when not found.
    """
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True, record_size_limit=1 << 30).records:
                if isinstance(record, Metadata) and record.name == "provenance":
                    return dict(record.metadata)
    except Exception:  # unfinished or damaged from here on
        pass
    return {}


def log_state(path: Path) -> str | None:
    """The ``status`` record's state of a finished log, None when the file is missing,
    unfinished (no summary) or unreadable. Reads only the summary section.
    """
    return log_status(path)[0]


def log_status(path: Path) -> tuple[str | None, str]:
    """The ``status`` record's state and reason of a finished log; ``(None, "")`` when
    the file is missing, not a regular file, unfinished (no summary) or unreadable.
    Reads only the summary section.
    """
    if not path.is_file():
        return None, ""
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for record in reader.iter_metadata():
                if record.name == "status":
                    return record.metadata.get("state"), record.metadata.get("reason", "")
    except Exception:  # unfinished or damaged: not completed
        return None, ""
    return None, ""


def read_status(job_dir: Path) -> dict[str, Any]:
    """The job's ``job_status.json`` (empty dict when absent, unreadable or malformed)."""
    try:
        data = json.loads((job_dir / STATUS_FILE).read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError, UnicodeDecodeError):
        return {}


STATUS_BYTES = 4096
"""Size a ``job_status.json`` is padded to (trailing blanks, which JSON ignores), so a
later status fits in the blocks it holds when the disk is full."""


def write_status(job_dir: Path, **fields: Any) -> bool:
    """Merge ``fields`` into the job's ``job_status.json``: an atomic replace, or, when
    the disk is full, a rewrite in place of the blocks the file already holds (it is
    padded to :data:`STATUS_BYTES`). Never raises: a status that cannot be written at
    all is said in one line on standard error.

    Returns:
        Whether the status was written.
    """
    data = read_status(job_dir)
    data.update(fields)
    text = json.dumps(data, indent=1, sort_keys=True, default=str).encode()
    return write_file(job_dir / STATUS_FILE, text.ljust(STATUS_BYTES) + b"\n", "job status")


def write_file(path: Path, data: bytes, what: str) -> bool:
    """Write ``data`` to ``path`` atomically (a temporary file replaces it), else, when
    that fails (a full disk), over the old file in place if ``data`` fits in it (padded
    with blanks); never leaves a temporary file and never raises: a file that cannot be
    written is said in one line on standard error.

    Returns:
        Whether the file holds ``data``.
    """
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
        return True
    except OSError as err:
        first = err
        with contextlib.suppress(OSError):
            tmp.unlink()
    try:
        size = path.stat().st_size
        if len(data) <= size:
            with open(path, "r+b") as f:
                f.write(data.rstrip().ljust(size - 1) + b"\n")
            return True
    except OSError:
        pass
    print(f"cannot write the {what} {path}: {first.strerror or first}", file=sys.stderr)
    return False


def _int(x: Any, default: int) -> int:
    return x if isinstance(x, int) and not isinstance(x, bool) else default


def _number(x: Any) -> float:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else float("nan")


def collect(sweep_dir: Path) -> list[dict[str, Any]]:
    """One row per job directory below ``sweep_dir`` (job, dir, overrides, state, runs,
    wall_s, reason, rerun_reason: why its last run was not skipped). A job still marked
    ``running`` when the sweep is over was killed; a log whose status disagrees with the
    job's file wins; malformed status files are read as far as they make sense.
    """
    rows = []
    dirs = {p.parent for p in sweep_dir.glob(f"*/{STATUS_FILE}")}
    dirs |= {p.parent for p in sweep_dir.glob(f"*/{LOG_FILE}")}
    for job_dir in sorted(dirs):
        status = read_status(job_dir)
        state = status.get("state") if isinstance(status.get("state"), str) else "missing"
        reason = str(status.get("reason", "") or "")
        if not status:
            reason = "job_status.json missing or unreadable"
        elif state == "missing" and not reason:
            reason = "the job started but recorded no outcome"
        logged, logged_reason = log_status(job_dir / LOG_FILE)
        if state == "running":
            pid = _int(status.get("pid"), 0)
            if pid and _alive(pid):
                pass
            elif logged is not None:  # its status could not be written, its log's could
                state, reason = logged, logged_reason or reason
            else:
                state, reason = "killed", reason or "the job's process ended without a status"
        elif state == "completed" and logged is None:
            state = "missing"
            reason = "the job's status says completed, but its run.mcap is missing or unreadable"
        elif logged is not None and state in ("completed", "missing") and logged != state:
            state = logged
        overrides = status.get("overrides", [])
        if not isinstance(overrides, list):
            overrides = [str(overrides)]
        rows.append(
            {
                "job": _int(status.get("job"), -1),
                "dir": job_dir.name,
                "overrides": " ".join(str(o) for o in overrides),
                "state": state,
                "runs": _int(status.get("runs"), 0),
                "wall_s": _number(status.get("wall_s")),
                "reason": reason,
                "rerun_reason": str(status.get("rerun_reason", "") or ""),
            }
        )
    rows.sort(key=lambda r: (_int(r["job"], -1) % (10**9 + 1), str(r["dir"])))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of the rows."""
    lines = [
        "| job | overrides | state | runs | wall time (s) | reason | rerun because |",
        "|---|---|---|---|---|---|---|",
    ]

    def cell(text: Any) -> str:
        return str(text or "").replace("|", "/").replace("\n", " ")[:200]

    for r in rows:
        wall = r["wall_s"]
        wall_text = f"{wall:.1f}" if isinstance(wall, (int, float)) else str(wall)
        lines.append(
            f"| {r['job']} | {r['overrides']} | {r['state']} | {r['runs']} | {wall_text} "
            f"| {cell(r.get('reason'))} | {cell(r.get('rerun_reason') if r['runs'] > 1 else '')} |"
        )
    return "\n".join(lines)


def write_table(sweep_dir: Path, rows: list[dict[str, Any]]) -> bool:
    """``sweep_status.csv`` and ``sweep_status.md`` in the sweep directory, each written
    atomically (:func:`write_file`: a full disk leaves the old table whole, and says so
    in one line).

    Returns:
        Whether both were written.
    """
    buffer = io.StringIO()
    writer = csv.DictWriter(
        buffer,
        fieldnames=["job", "dir", "overrides", "state", "runs", "wall_s", "reason", "rerun_reason"],
        extrasaction="ignore",
    )
    writer.writeheader()
    writer.writerows(rows)
    try:
        sweep_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        print(f"cannot write the sweep table into {sweep_dir}: {err.strerror}", file=sys.stderr)
        return False
    done = write_file(sweep_dir / "sweep_status.csv", buffer.getvalue().encode(), "sweep table")
    md = (format_table(rows) + "\n").encode()
    return write_file(sweep_dir / "sweep_status.md", md, "sweep table") and done


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (and is not a zombie)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


_ACTIVE: dict[str, Any] = {}
"""The sweep running in this (main) process: its directory and whether its table is
written; see :func:`finish_sweep`."""


def running_jobs(sweep_dir: Path) -> list[int]:
    """Pids of the jobs of ``sweep_dir`` whose status says ``running``."""
    pids = []
    for status_file in sweep_dir.glob(f"*/{STATUS_FILE}"):
        status = read_status(status_file.parent)
        pid = _int(status.get("pid"), 0)
        if status.get("state") == "running" and pid and pid != os.getpid() and _alive(pid):
            pids.append(pid)
    return pids


def stop_jobs(sweep_dir: Path, signum: int, wait_s: float = 30.0) -> None:
    """Send ``signum`` to every running job of the sweep and wait (up to ``wait_s``)
    for them to finalise their logs.
    """
    pids = running_jobs(sweep_dir)
    for pid in pids:
        with contextlib.suppress(OSError):
            os.kill(pid, signum)
    deadline = time.monotonic() + wait_s
    while pids and time.monotonic() < deadline:
        pids = [p for p in pids if _alive(p)]
        time.sleep(0.05)


def _main_signal(signum: int, frame: Any) -> None:
    """The sweep's main process on SIGINT, SIGTERM or SIGHUP: stop the running jobs
    (each finalises its log as ``aborted``), then end the sweep with KeyboardInterrupt
    (the launcher stops its workers; :func:`finish_sweep` writes the table).
    """
    sweep_dir = _ACTIVE.get("dir")
    if _ACTIVE.get("stopping"):
        return
    _ACTIVE["stopping"] = signal.Signals(signum).name
    if sweep_dir is not None:
        forward = signal.SIGINT if signum == signal.SIGINT else signal.SIGTERM
        stop_jobs(Path(sweep_dir), forward)
    raise KeyboardInterrupt(f"sweep stopped by {signal.Signals(signum).name}")


def finish_sweep(reason: str = "") -> int | None:
    """Write the status table of the sweep running in this process if it is not written
    yet (after an interruption or a launcher failure); returns the exit status (1 when a
    job did not complete, 0 otherwise), or None when no sweep was running.
    """
    sweep_dir = _ACTIVE.get("dir")
    if sweep_dir is None or _ACTIVE.get("written"):
        return None
    return _report(Path(sweep_dir), reason or str(_ACTIVE.get("stopping") or ""))


def _report(sweep_dir: Path, interrupted: str = "") -> int:
    monitor = _ACTIVE.get("monitor")
    if monitor is not None:
        monitor.stop(bool(interrupted))  # its last line comes before the table
    rows = collect(sweep_dir)
    _ACTIVE["written"] = True
    print(f"\nsweep {sweep_dir}: {len(rows)} jobs")
    print(format_table(rows), flush=True)
    write_table(sweep_dir, rows)
    bad = [r for r in rows if r["state"] != "completed"]
    if interrupted:
        print(f"sweep interrupted: {interrupted}", file=sys.stderr)
    if bad or interrupted:
        invalid = [r for r in rows if r["state"] == "invalid"]
        for r in invalid:
            print(f"invalid point {r['dir']}: {r['reason']}", file=sys.stderr)
        print(
            f"{len(bad)} job(s) did not complete; re-run the same command with "
            f"hydra.sweep.dir={sweep_dir} to rerun only those",
            file=sys.stderr,
        )
        return 1
    return 0


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
        _ACTIVE.clear()
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
        _ACTIVE["dir"] = str(config.hydra.sweep.dir)
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, _main_signal)
        monitor = SweepMonitor(
            Path(str(config.hydra.sweep.dir)),
            count_jobs(config),
            mode=self.progress,
            every=float(every),
            status_file=STATUS_FILE,
        )
        monitor.start()
        _ACTIVE["monitor"] = monitor

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Stop the progress line, collect the jobs' status files; exit 1 when a job did
        not complete.
        """
        _ACTIVE.setdefault("dir", str(config.hydra.sweep.dir))
        status = _report(Path(config.hydra.sweep.dir))
        if status:
            sys.exit(status)


_CHECKED: dict[str, Experiment] = {}
"""Builds made by :class:`CheckCallback`, by config hash, until the run takes them."""


def checked(cfg: DictConfig) -> DictConfig | Experiment:
    """The build :class:`CheckCallback` made of ``cfg`` (handed on once, so a run is
    built once), else ``cfg`` itself.
    """
    return _CHECKED.pop(config_hash(cfg), cfg)


class CheckCallback(Callback):
    """Checks a single run's config (by building it), that its directory can be created
    and holds no log yet, that no other run is using it, and that the disk has room for
    the log, before Hydra writes anything into it; a refused value (or anything else
    this check raises) prints its one line and exits with status 2. The build is
    handed on to the run (:func:`checked`), and the directory stays claimed
    (:func:`claim_run_dir`) until the process ends.
    """

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Build the run to check it, then claim its directory."""
        _CHECKED.clear()
        try:
            with quiet_hydra_utils():
                parts = build(config)
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
        _CHECKED[config_hash(config)] = parts


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
        probe = getattr(observer, "probe", None)
        if probe is None:
            continue
        try:
            probe()
        except ParameterError as err:
            key = exp.keys.get(f"observers.{name}.{err.name}", f"observers.{name}.{err.name}")
            raise ConfigError(key, err.value, err.allowed) from None


def one_line(err: BaseException) -> str:
    """``Type: first line of the message`` of an exception."""
    text = (str(err).strip().splitlines() or [""])[0]
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def check_dir_name(key: str, path: Path) -> None:
    """Refuse a directory path with a name too long for a file system (255 bytes) or a
    NUL byte, before anything is created.

    Raises:
        ConfigError: naming ``key``.
    """
    for part in Path(path).parts:
        if "\0" in part or len(part.encode(errors="surrogateescape")) > 255:
            raise ConfigError(
                key, str(path)[:80] + "...", "a path whose names are at most 255 bytes"
            )


def usable_dir(key: str, path: Path) -> None:
    """Create ``path`` (with its parents) and check that a file can be created in it.

    Raises:
        ConfigError: naming ``key``, for a name too long, a path under a file, a device
            (``/dev/null``), or a read-only or full file system.
    """
    check_dir_name(key, path)
    probe = path / f".probe.{os.getpid()}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not path.is_dir():
            raise NotADirectoryError(20, "not a directory", str(path))
        probe.touch()
        probe.unlink()
    except OSError as err:
        raise ConfigError(
            key, str(path), f"a directory that can be created and written ({err.strerror})"
        ) from None


RUN_LOCK = ".run.lock"
"""The file (holding the process id) by which a single run claims its directory."""


def claim_run_dir(out: Path) -> None:
    """Create ``out`` and claim it for this process: ``.run.lock`` created exclusively
    (a lock left by a process that is gone is taken over) and removed when the process
    ends; the run's log is created exclusively too (:class:`harness.runs.run.run`).

    Raises:
        ConfigError: for a directory that cannot be created or written (a path under a
            file, a read-only file system, ``/dev/null``), or one another running
            process has claimed.
    """
    lock = out / RUN_LOCK
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not out.is_dir():
            raise NotADirectoryError(20, "not a directory", str(out))
        while True:
            try:
                fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                break
            except FileExistsError:
                holder = _lock_holder(lock)
                if holder and holder != os.getpid() and _alive(holder):
                    raise ConfigError(
                        "hydra.run.dir",
                        str(out),
                        f"a directory no other run is using (process {holder} runs there)",
                    ) from None
                with contextlib.suppress(FileNotFoundError):
                    lock.unlink()  # stale: its process is gone
        try:
            os.write(fd, str(os.getpid()).encode())
        finally:
            os.close(fd)
    except OSError as err:
        raise ConfigError(
            "hydra.run.dir",
            str(out),
            f"a directory that can be created and written ({err.strerror})",
        ) from None
    atexit.register(_release, lock, os.getpid())


def _lock_holder(lock: Path) -> int:
    """The process id in a lock file (0 when unreadable)."""
    try:
        return int(lock.read_text().strip() or "0")
    except (OSError, ValueError):
        return 0


def _release(lock: Path, pid: int) -> None:
    """Remove ``lock`` if process ``pid`` (this one, not a forked child) holds it."""
    if os.getpid() == pid and _lock_holder(lock) == pid:
        with contextlib.suppress(OSError):
            lock.unlink()


@contextlib.contextmanager
def _claim(out: Path) -> Iterator[None]:
    """Hold the job directory's lock file while the job runs: a second process with the
    same directory (a concurrent sweep into the same ``hydra.sweep.dir``, or points
    differing only in presentation keys) waits for the first, then resumes by content.
    """
    lock = out / LOCK_FILE
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileExistsError:
            try:
                holder = int(lock.read_text().strip() or "0")
            except (OSError, ValueError):
                holder = 0
            if holder and holder != os.getpid() and _alive(holder):
                time.sleep(0.5)
                continue
            with contextlib.suppress(OSError):
                lock.unlink()  # stale: its process is gone
    try:
        with contextlib.suppress(OSError):  # a full disk: the lock exists, unnamed
            os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        yield
    finally:
        with contextlib.suppress(OSError):
            lock.unlink()


def _set_aside(log: Path) -> Path:
    """Move a complete log out of the way (``run.previous-K.mcap``); its new path."""
    k = 1
    while (log.parent / f"run.previous-{k}.mcap").exists():
        k += 1
    target = log.parent / f"run.previous-{k}.mcap"
    log.rename(target)
    return target


_PENDING: list[Experiment] = []
"""The build a forked job runs: the child takes it, the parent drops it once the child
has started (the parent keeping it would double the pages the child writes to)."""


def _child(out: Path) -> None:
    """The job's own process: run the pending build and record the outcome; exit status
    0 after any recorded outcome (a killed process has none).
    """
    with contextlib.suppress(OSError):  # the out-of-memory killer picks a job, not the sweep
        Path("/proc/self/oom_score_adj").write_text("500")
    # one core per job: the sweep runs a job per core, so the compiled loops stay serial
    numba.set_num_threads(1)
    try:
        result = run(_PENDING.pop(), out)
    except (KeyboardInterrupt, Terminated) as err:
        write_status(out, state="aborted", reason=f"interrupted: {err}".strip(), pid=0)
        os._exit(3)
    except Exception as err:  # recorded, not raised: the other jobs go on
        write_status(out, state="aborted", reason=f"{type(err).__name__}: {err}", pid=0)
        _say(f"job failed: {type(err).__name__}: {err}", sys.stderr)
        os._exit(1)
    write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s, pid=0)
    os._exit(0)


def _run_isolated(out: Path) -> int:
    """Run :func:`_child` on the pending build in a forked process and wait for it; its
    exit code (negative: killed by that signal). Signals to this process are passed on
    to the job.
    """
    ctx = multiprocessing.get_context("fork")
    proc = ctx.Process(target=_child, args=(out,), daemon=False)
    proc.start()  # the child holds its copy of the pending build from here on
    _PENDING.clear()
    assert proc.pid is not None
    write_status(out, pid=proc.pid)
    previous = {}
    if threading.current_thread() is threading.main_thread():

        def forward(signum: int, frame: Any) -> None:
            with contextlib.suppress(OSError):
                os.kill(proc.pid, signum)  # type: ignore[arg-type]

        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            previous[sig] = signal.signal(sig, forward)
    try:
        proc.join()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return proc.exitcode if proc.exitcode is not None else -1


_JOB: dict[str, bool] = {"tty": False}
"""Whether the sweep of the job running in this process shows its line on a terminal."""


def _say(text: str, stream: TextIO | None = None) -> None:
    """Print a job's line (on standard output by default); when the sweep's progress line
    is on the terminal it goes to, clear that line first (it is redrawn below).
    """
    stream = sys.stdout if stream is None else stream
    clear = ""
    if _JOB["tty"]:
        with contextlib.suppress(AttributeError, ValueError, OSError):
            clear = "\r\x1b[K" if stream.isatty() else ""
    print(clear + text, file=stream, flush=True)


def run_job(
    cfg: DictConfig, out: Path, job: int, overrides: list[str], sweep_dir: Path | None = None
) -> RunResult | None:
    """One job of a multirun: skip when its log is complete, intact and of this config;
    otherwise run it in a process of its own; never raise on failure; keep status.

    The job's ``job_status.json`` also says when it started and ended (``started_at``,
    ``ended_at``: Unix time, s), whether it was ``skipped`` and of which sweep it is
    (``sweep_run``, from the sweep directory's :data:`~harness.runs.sweep_progress.RUN_FILE`),
    for the sweep's progress line (:mod:`harness.runs.sweep_progress`); while that line is on
    a terminal, the run's own bar with ``log.progress=auto`` is off.

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
    _JOB["tty"] = sweep.get("tty") is True
    if sweep.get("tty") is True and OmegaConf.select(cfg, "log.progress") == "auto":
        with read_write(cfg), open_dict(cfg):
            OmegaConf.update(cfg, "log.progress", "off")  # the sweep's line is on the terminal
    with _claim(out):
        started = {"sweep_run": sweep.get("id", ""), "started_at": time.time()}
        write_status(out, **started, ended_at=None, skipped=False, **ident)
        try:
            _resume_or_run(cfg, out, ident, digest, now_code)
        finally:
            write_status(out, ended_at=time.time())
    return None


def _resume_or_run(
    cfg: DictConfig, out: Path, ident: dict[str, Any], digest: str, now_code: dict[str, str]
) -> None:
    """The body of :func:`run_job`, with the job's directory claimed."""
    job = ident["job"]
    log = out / LOG_FILE
    check = verify_log(log)
    same_config = check.config_hash == digest
    changed = code_change(check.provenance, now_code) if check.provenance else ""
    if check.intact and check.state == "completed" and same_config and not changed:
        write_status(out, state="completed", reason="", rerun_reason="", skipped=True, **ident)
        _say(f"job {job}: already completed, skipped ({out})")
        return
    if not check.intact:
        why = check.problem
    elif not same_config:
        why = "the log holds another config"
    elif changed:
        why = changed
    else:
        why = f"the log's status is {check.state}"
    try:
        with quiet_hydra_utils():
            _PENDING[:] = [build(cfg)]
    except ConfigError as err:
        _say(config_line(err), sys.stderr)
        write_status(out, state="invalid", reason=config_line(err), pid=0, **ident)
        return
    if log.exists() or log.is_symlink():
        if same_config and not changed and check.provenance and check.state != "completed":
            log.unlink()  # a verified copy, unfinished: the rerun writes it whole
        else:
            moved = _set_aside(log)  # anything else is never overwritten
            why += f" (kept as {moved.name})"
    runs = _int(read_status(out).get("runs"), 0) + 1
    write_status(out, state="running", runs=runs, reason="", rerun_reason=why, pid=0, **ident)
    try:
        code = _run_isolated(out)  # the child inherits the build
    except OSError as err:  # no process could be forked: run here
        _say(f"job {job}: cannot fork ({err}); running in the worker", sys.stderr)
        code = 0
        try:
            result = run(_PENDING.pop(), out)
            write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s)
        except Exception as err2:
            write_status(out, state="aborted", reason=f"{type(err2).__name__}: {err2}")
    if code < 0:
        name = signal.Signals(-code).name
        hint = " (the out-of-memory killer?)" if -code == signal.SIGKILL else ""
        write_status(out, state="killed", reason=f"killed by {name}{hint}", pid=0)
        _say(f"job {job} was killed by {name}{hint}", sys.stderr)
    elif read_status(out).get("state") == "running":
        write_status(out, state="aborted", reason=f"exited with status {code}", pid=0)
