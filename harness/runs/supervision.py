"""Job supervision: claiming a run's or a job's directory, running a job in a process of
its own, and stopping a sweep's running jobs.

* A single run claims its directory with ``.run.lock`` (:func:`claim_run_dir`) before
  Hydra writes anything, so two runs never share one; a job of a sweep holds
  ``.job.lock`` while it runs (:func:`claim_job_dir`), so a second process with the
  same directory (a concurrent sweep into the same ``hydra.sweep.dir``, or points
  differing only in presentation keys) waits for the first, saying once on standard
  error for whom, then resumes by content. A lock names its holder (:class:`Holder`):
  the process id, the process's start time and the boot id, so a lock whose process is
  gone is taken over even when its process id now belongs to another process (after a
  reboot, or a sweep killed with SIGKILL). A lock that is not a regular file and cannot
  be removed (a directory) is a :class:`LockError` naming it: the run is refused, the
  job fails with that reason, never a wait.
* A job runs in a process of its own (:func:`run_isolated`, forked from the launcher's
  worker, which only waits), so a job killed by the kernel's out-of-memory killer or by
  hand costs only itself: the worker records it as ``killed`` and the other jobs go on.
  The build reaches the child through a :class:`Handoff`, which the parent empties once
  the child has started.
* SIGINT, SIGTERM and SIGHUP to the worker are passed on to its job; the sweep's main
  process passes them on to every running job (:func:`stop_jobs`), which finalise their
  logs as ``aborted``.
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import os
import signal
import stat
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numba

from harness.files import SMALL_FILE_BYTES, read_text
from harness.loop import Experiment
from harness.runs.checks import ConfigError
from harness.runs.run import Terminated, run
from harness.runs.status import STATUS_FILE, alive, as_int, read_status, write_status

RUN_LOCK = ".run.lock"
"""The file (naming its holder, :class:`Holder`) by which a single run claims its
directory."""


LOCK_FILE = ".job.lock"
"""The file (naming its holder, :class:`Holder`) a job of a sweep holds while it runs."""


BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
"""Where Linux gives the boot id (a new one at every boot)."""


WAIT_S = 0.5
"""How often (s) a job waiting for its directory's lock looks at it again."""


class LockError(OSError):
    """A lock file that cannot be taken: not a regular file, and it cannot be removed
    (a directory), or a stale lock that cannot be removed; ``str()`` is one line naming
    the file.
    """


@dataclass(frozen=True)
class Holder:
    """Who holds a lock: a process id, and what tells that process from a later one
    given the same id.

    A lock file holds one line, ``PID START BOOT``: the process's start time (field 22
    of ``/proc/PID/stat``, clock ticks since boot) and the boot id, each ``-`` where
    there is no ``/proc`` to read them from. A lock holding only a process id is read
    too (``START`` and ``BOOT`` unknown).

    Attributes:
        pid: The process id (0: none, the lock is malformed or unreadable).
        start: The process's start time, "" when unknown.
        boot: The boot id of the system it ran on, "" when unknown.
    """

    pid: int
    start: str = ""
    boot: str = ""

    @classmethod
    def of(cls, pid: int) -> Holder:
        """The holder that process ``pid`` (running now) is."""
        return cls(pid, process_start(pid), boot_id())

    def line(self) -> str:
        """The lock file's text."""
        return f"{self.pid} {self.start or '-'} {self.boot or '-'}\n"

    @property
    def known(self) -> bool:
        """Whether the lock tells its process from a later one with the same id."""
        return bool(self.start or self.boot)

    def holds(self) -> bool:
        """Whether the process that wrote the lock is running: its process id is alive
        and, where the lock and the system say them, the boot id and start time are the
        ones the lock names (an alive process id is taken as the holder when they are
        unknown).
        """
        if self.pid <= 0 or not alive(self.pid):
            return False
        if self.boot and boot_id() not in ("", self.boot):
            return False  # written before a reboot
        return not self.start or process_start(self.pid) in ("", self.start)


def _proc_text(path: Path) -> str:
    """The text of a ``/proc`` file ("" when there is none or it cannot be read)."""
    try:
        return read_text(path, SMALL_FILE_BYTES).strip()
    except OSError:
        return ""


def boot_id() -> str:
    """This system's boot id ("" without ``/proc``)."""
    return _proc_text(BOOT_ID)


def process_start(pid: int) -> str:
    """The start time of process ``pid`` (field 22 of ``/proc/PID/stat``, clock ticks
    since boot; "" when it cannot be read).
    """
    fields = _proc_text(Path(f"/proc/{pid}/stat")).rsplit(")", 1)[-1].split()
    return fields[19] if len(fields) > 19 and fields[19].isdigit() else ""


PID_MAX = 1 << 22
"""Largest process id Linux gives (``PID_MAX_LIMIT`` on 64-bit systems); a lock naming a
larger one names no process."""


def read_lock(lock: Path) -> Holder:
    """The holder a lock file names (pid 0 when it is not a regular file, cannot be
    read or is malformed: no holder).
    """
    try:
        fields = read_text(lock, SMALL_FILE_BYTES).split()
    except OSError:
        return Holder(0)
    if not fields or not fields[0].isdigit() or len(fields) > 3 or len(fields[0]) > 10:
        return Holder(0)
    if int(fields[0]) > PID_MAX:
        return Holder(0)  # no process has such an id
    start, boot = (*fields[1:], "-", "-")[:2]
    return Holder(int(fields[0]), "" if start == "-" else start, "" if boot == "-" else boot)


def _create_lock(lock: Path) -> bool:
    """Create ``lock`` exclusively, naming this process; False when it exists.

    The lock is written whole to a file of this process's own and hard-linked into
    place (``link`` fails when the name exists), so no other claimer ever reads it empty
    and takes it for stale. Where the file cannot be written (a full disk), the lock is
    created empty with ``O_EXCL``, as a lock naming no holder.
    """
    own = lock.with_name(f"{lock.name}.{os.getpid()}.tmp")
    try:
        try:
            own.unlink(missing_ok=True)
            fd = os.open(own, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            try:
                os.write(fd, Holder.of(os.getpid()).line().encode())
            finally:
                os.close(fd)
        except OSError:  # a full disk or a file system without room: an unnamed lock
            try:
                os.close(os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
            except FileExistsError:
                return False
            return True
        try:
            os.link(own, lock)
        except FileExistsError:
            return False
        except OSError:  # a file system without hard links: created, then written
            return _create_lock_in_place(lock)
        return True
    finally:
        with contextlib.suppress(OSError):
            own.unlink()


def _create_lock_in_place(lock: Path) -> bool:
    """Create ``lock`` exclusively and write this process into it (for a file system
    without hard links; a claimer may then read it empty for an instant); False when
    it exists.
    """
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    try:
        with contextlib.suppress(OSError):  # a full disk: the lock exists, unnamed
            os.write(fd, Holder.of(os.getpid()).line().encode())
    finally:
        os.close(fd)
    return True


def _stale_or_holder(lock: Path) -> Holder | None:
    """Look at the existing ``lock``: None when it was stale (no holder, or its holder
    is gone or is this process) and has been removed, or is gone already; else the
    running holder.

    Raises:
        LockError: for a lock that cannot be removed (a directory), naming it.
    """
    try:
        before = os.lstat(lock)
    except FileNotFoundError:
        return None
    holder = read_lock(lock)
    if holder.pid != os.getpid() and holder.holds():
        return holder
    try:
        now = os.lstat(lock)
        if (now.st_dev, now.st_ino) == (before.st_dev, before.st_ino):
            lock.unlink()  # stale (the same file that was read): its process is gone
    except FileNotFoundError:
        pass
    except OSError as err:
        raise LockError(
            f"{lock} is {_kind(before.st_mode)} and cannot be removed "
            f"({err.strerror or err}): remove it by hand"
        ) from None
    return None


def _kind(mode: int) -> str:
    """What a lock file that cannot be removed is, in words."""
    if stat.S_ISREG(mode):
        return "a stale lock"
    if stat.S_ISDIR(mode):
        return "a directory, not a lock file,"
    return "not a regular file, so not a lock file,"


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


def claim_run_dir(out: Path) -> None:
    """Create ``out`` and claim it for this process: ``.run.lock`` created exclusively
    (a lock whose process is gone is taken over, :class:`Holder`) and removed when the
    process ends; the run's log is created exclusively too (:func:`harness.runs.run.run`).

    Raises:
        ConfigError: for a directory that cannot be created or written (a path under a
            file, a read-only file system, ``/dev/null``), one another running process
            has claimed, or one whose lock cannot be removed (a directory named
            ``.run.lock``).
    """
    lock = out / RUN_LOCK
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not out.is_dir():
            raise NotADirectoryError(20, "not a directory", str(out))
        while not _create_lock(lock):
            holder = _stale_or_holder(lock)
            if holder is not None:
                raise ConfigError(
                    "hydra.run.dir",
                    str(out),
                    f"a directory no other run is using (process {holder.pid} runs there)",
                )
    except LockError as err:
        raise ConfigError(
            "hydra.run.dir", str(out), f"a directory whose {RUN_LOCK} can be taken ({err})"
        ) from None
    except OSError as err:
        raise ConfigError(
            "hydra.run.dir",
            str(out),
            f"a directory that can be created and written ({err.strerror})",
        ) from None
    atexit.register(_release, lock, os.getpid())


def _release(lock: Path, pid: int) -> None:
    """Remove ``lock`` if process ``pid`` (this one, not a forked child) holds it."""
    if os.getpid() == pid and read_lock(lock).pid == pid:
        with contextlib.suppress(OSError):
            lock.unlink()


@contextlib.contextmanager
def claim_job_dir(out: Path, *, tty: bool = False) -> Iterator[None]:
    """Hold the job directory's lock file (:data:`LOCK_FILE`) while the job runs: a
    second process with the same directory waits for the first (looking every
    :data:`WAIT_S` s), saying once on standard error which process it waits for, then
    resumes by content. A lock whose process is gone (:meth:`Holder.holds`) is taken
    over.

    Args:
        out: The job's directory.
        tty: Whether the sweep's progress line is on a terminal (:func:`say`).

    Raises:
        LockError: for a lock that cannot be removed (a directory named
            :data:`LOCK_FILE`), naming it; nothing has run then.
    """
    lock = out / LOCK_FILE
    waited_for: Holder | None = None
    while not _create_lock(lock):
        holder = _stale_or_holder(lock)
        if holder is None:
            continue
        if holder != waited_for:
            waited_for = holder
            line = f"waiting for process {holder.pid}, which holds {lock}"
            if not holder.known:
                line += " (it names only a process id: remove it if that is no sweep's job)"
            say(line, sys.stderr, tty=tty)
        time.sleep(WAIT_S)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            lock.unlink()


class Handoff:
    """A build on its way from where it was made to where it runs, keyed by the hash of
    its config (:func:`~harness.runs.identity.config_hash`), so a run is built once.

    It holds at most one build: this process runs one run at a time. The one instance
    is :data:`harness.runs.app.BUILDS` (why Hydra needs one: :mod:`harness.runs.app`).
    A forked job's child takes its copy; the parent drops its own once the child has
    started (:func:`run_isolated`), since keeping it would double the pages the child
    writes to.
    """

    def __init__(self) -> None:
        self._key = ""
        self._build: Experiment | None = None

    def give(self, key: str, build: Experiment) -> None:
        """Hold ``build`` for the config of hash ``key``, dropping any other held."""
        self._key, self._build = key, build

    def take(self, key: str) -> Experiment | None:
        """The build held for ``key``, handed on once (None when there is none)."""
        if self._build is None or key != self._key:
            return None
        build, self._key, self._build = self._build, "", None
        return build

    def drop(self) -> None:
        """Drop the build held, if any."""
        self._key, self._build = "", None


def say(text: str, stream: TextIO | None = None, *, tty: bool = False) -> None:
    """Print a job's line (on standard output by default); when the sweep's progress
    line is on a terminal (``tty``) and ``stream`` is that terminal, clear that line
    first (it is redrawn below).
    """
    stream = sys.stdout if stream is None else stream
    clear = ""
    if tty:
        with contextlib.suppress(AttributeError, ValueError, OSError):
            clear = "\r\x1b[K" if stream.isatty() else ""
    print(clear + text, file=stream, flush=True)


def _child(builds: Handoff, key: str, out: Path, tty: bool) -> None:
    """The job's own process: run the build handed to it and record the outcome; exit
    status 0 after any recorded outcome (a killed process has none).
    """
    with contextlib.suppress(OSError):  # the out-of-memory killer picks a job, not the sweep
        Path("/proc/self/oom_score_adj").write_text("500")
    # one core per job: the sweep runs a job per core, so the compiled loops stay serial
    numba.set_num_threads(1)
    try:
        exp = builds.take(key)
        if exp is None:
            raise LookupError(f"no build handed on for config {key}")
        result = run(exp, out)
    except (KeyboardInterrupt, Terminated) as err:
        write_status(out, state="aborted", reason=f"interrupted: {err}".strip(), pid=0)
        os._exit(3)
    except Exception as err:  # recorded, not raised: the other jobs go on
        write_status(out, state="aborted", reason=f"{type(err).__name__}: {err}", pid=0)
        say(f"job failed: {type(err).__name__}: {err}", sys.stderr, tty=tty)
        os._exit(1)
    write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s, pid=0)
    os._exit(0)


def run_isolated(builds: Handoff, key: str, out: Path, *, tty: bool = False) -> int:
    """Run the build ``builds`` holds for ``key`` in a forked process and wait for it;
    the child writes its outcome into the job's status, the parent its pid. Signals to
    this process are passed on to the job.

    Args:
        builds: The hand-off holding the build (emptied here once the child started).
        key: The hash of the build's config.
        out: The job's directory.
        tty: Whether the sweep's progress line is on a terminal (:func:`say`).

    Returns:
        The child's exit code (negative: killed by that signal).

    Raises:
        OSError: when no process can be forked (the build is still held then).
    """
    ctx = multiprocessing.get_context("fork")
    proc = ctx.Process(target=_child, args=(builds, key, out, tty), daemon=False)
    proc.start()  # the child holds its copy of the build from here on
    builds.drop()
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


def running_jobs(sweep_dir: Path) -> list[int]:
    """Pids of the jobs of ``sweep_dir`` whose status says ``running``."""
    pids = []
    for status_file in sweep_dir.glob(f"*/{STATUS_FILE}"):
        status = read_status(status_file.parent)
        pid = as_int(status.get("pid"), 0)
        if status.get("state") == "running" and pid and pid != os.getpid() and alive(pid):
            pids.append(pid)
    return pids


def stop_jobs(sweep_dir: Path, signum: int, wait_s: float = 30.0, again_s: float = 5.0) -> None:
    """Send ``signum`` to every running job of the sweep and wait (up to ``wait_s``)
    for them to finalise their logs. A job still running ``again_s`` after the signal is
    sent it a second time: a run stops at its next step or draw of its floors on the
    first, and at once, inside a long computation, on the second
    (:class:`~harness.runs.run.StopRequest`); either way it finalises its log.
    """
    pids = running_jobs(sweep_dir)
    for pid in pids:
        with contextlib.suppress(OSError):
            os.kill(pid, signum)
    start = time.monotonic()
    repeated = False
    while pids and time.monotonic() < start + wait_s:
        pids = [p for p in pids if alive(p)]
        if pids and not repeated and time.monotonic() >= start + again_s:
            repeated = True
            for pid in pids:
                with contextlib.suppress(OSError):
                    os.kill(pid, signum)
        time.sleep(0.05)
