"""Progress of a sweep while it runs: how many of its jobs are done, running and failed,
of how many, the time since it started and an estimate of the time left.

A :class:`SweepMonitor` runs as a thread in the process that launches the sweep (started
and stopped by :class:`harness.runs.app.SweepStatusCallback`). It reads nothing but the
jobs' ``job_status.json`` files in the sweep directory, so it works for every launcher
whose jobs write there: the joblib launcher's local workers and SLURM's (submitit) jobs
on other nodes alike. When it starts it writes ``.sweep_run`` into the sweep directory
(an id of this sweep, and whether its line is on a terminal); each job records the id in
its status file when it starts (``sweep_run``, ``started_at``) and when it ends
(``ended_at``; ``skipped`` when it was skipped by resume), so files left by an earlier
sweep into the same directory count as pending until their job runs again.

The line (see ``docs/sweep_progress.md``)::

    sweep: 3/8 jobs done (1 skipped), 2 running, 1 failed; elapsed 1 min 05 s, left ~42 s

* ``D/T jobs done``: ``D`` jobs of this sweep ended ``completed`` (those skipped by
  resume included) out of ``T``, the jobs of the sweep (``?`` when the sweeper is not
  Hydra's basic sweeper, whose job list cannot be computed in advance);
* ``(K skipped)``: of the done jobs, those whose complete log of the same config and
  code was kept (resume);
* ``R running``: jobs that have started and not ended (checking, building or running);
* ``F failed``: jobs that ended in any state but ``completed`` (invalid, aborted,
  diverged, killed), as in the status table at the end;
* ``elapsed``: wall-clock time since the sweep started (s, min, h);
* ``left``: the estimated wall-clock time until every job has ended, ``~`` marking an
  estimate (:func:`estimate`); ``–`` until a job of this sweep has run to its end, and
  on the last line of an interrupted sweep.

On a terminal (standard error a TTY, ``CI`` not set to ``true`` or ``1``, ``TERM`` not
``dumb``) it is one line redrawn in place every :data:`POLL_S` seconds; otherwise a
plain line when the counts change, at most one per ``every`` seconds, one at least every
:data:`HEARTBEAT_S` seconds, and always one when the sweep ends.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import json
import math
import os
import secrets
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from harness.files import SMALL_FILE_BYTES, read_text

RUN_FILE = ".sweep_run"
"""The file in the sweep directory naming the sweep that runs there (JSON: ``id``, and
``tty``, whether its progress line is on a terminal)."""


MODES = ("auto", "tty", "plain", "off")
"""Values of ``hydra.callbacks.sweep_status.progress``: ``auto`` (``tty`` on a terminal,
``plain`` elsewhere), ``tty`` (one line redrawn in place), ``plain`` (lines) or ``off``."""


POLL_S = 1.0
"""Seconds between two reads of the sweep directory (and redraws on a terminal)."""


FIRST_LINE_S = 3.0
"""The first line waits (at most this many seconds) for a job of the sweep to start, so
that it comes after the launcher's own lines."""


SETTLE_S = 2.0
"""A status file read less than this many seconds after it was modified is read again at
the next poll."""


HEARTBEAT_S = 300.0
"""Longest time (s) between two plain lines, counts changed or not."""


PHASES = ("pending", "running", "done", "skipped", "failed")
"""Where a job of the sweep is: not started in this sweep, started and not ended, ended
``completed`` after running, ended ``completed`` by being skipped (resume), ended in any
other state."""


@dataclass(frozen=True)
class JobTimes:
    """One job as the monitor sees it: its phase (:data:`PHASES`) and its start and end
    (Unix time, s; None when not recorded).
    """

    phase: str
    started: float | None = None
    ended: float | None = None


@dataclass(frozen=True)
class Progress:
    """Counts and times of a sweep at one moment (the fields of the line).

    Attributes:
        total: Jobs of the sweep (None when unknown).
        done: Jobs ended ``completed``, those skipped by resume included.
        skipped: Of ``done``, jobs skipped by resume.
        running: Jobs started and not ended.
        failed: Jobs ended in any other state.
        elapsed_s: Wall-clock time since the sweep started (s).
        left_s: Estimated wall-clock time until every job has ended (s); None before a
            job has run to its end, or when ``total`` is unknown.
    """

    total: int | None
    done: int
    skipped: int
    running: int
    failed: int
    elapsed_s: float
    left_s: float | None

    @property
    def pending(self) -> int | None:
        """Jobs not started in this sweep (None when ``total`` is unknown)."""
        if self.total is None:
            return None
        return max(self.total - self.done - self.running - self.failed, 0)


def job_phase(status: dict[str, Any], run_id: str) -> str:
    """The phase (:data:`PHASES`) of a job in the sweep ``run_id`` from its
    ``job_status.json``: ``pending`` when the file is of another sweep (or none).
    """
    if not run_id or status.get("sweep_run") != run_id:
        return "pending"
    if not _is_time(status.get("ended_at")):
        return "running"
    if status.get("state") != "completed":
        return "failed"
    return "skipped" if status.get("skipped") is True else "done"


def _is_time(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _time(x: Any) -> float | None:
    return float(x) if _is_time(x) else None


def job_times(status: dict[str, Any], run_id: str) -> JobTimes:
    """:class:`JobTimes` of a job from its ``job_status.json``."""
    phase = job_phase(status, run_id)
    if phase == "pending":
        return JobTimes(phase)
    return JobTimes(phase, _time(status.get("started_at")), _time(status.get("ended_at")))


def parallelism(jobs: Iterable[JobTimes], now: float) -> int:
    """The most jobs that ran at the same time (skipped jobs left out): the largest
    overlap of the intervals from each job's start to its end (``now`` while it runs).
    """
    events = []
    for job in jobs:
        if job.phase in ("running", "done", "failed") and job.started is not None:
            end = job.ended if job.ended is not None else now
            events.append((job.started, 1))
            events.append((max(end, job.started), -1))
    events.sort()  # at equal times an end (-1) comes before a start (+1)
    most = level = 0
    for _, step in events:
        level += step
        most = max(most, level)
    return most


def estimate(jobs: Sequence[JobTimes], total: int | None, now: float, elapsed_s: float) -> Progress:
    """Count the jobs and estimate the time left.

    With ``W`` the mean wall time (s, end minus start, each on its own host's clock) of
    the jobs of this sweep that ran and ended (done or failed; skipped jobs left out),
    ``P`` the most jobs seen running at once (:func:`parallelism`, at least 1), ``n``
    the pending jobs and ``a_i`` how long running job ``i`` has run::

        left = (n * W + sum_i max(W - a_i, 0)) / min(P, n + running)

    that is, the work left in job-seconds over the number of jobs that can still run at
    once; 0 when no job is pending or running.

    Args:
        jobs: The jobs seen in the sweep directory.
        total: Jobs of the sweep (None when unknown).
        now: Unix time (s).
        elapsed_s: Time since the sweep started (s).

    Returns:
        The counts and times; ``left_s`` None when no job of this sweep has run to its
        end yet or ``total`` is unknown.
    """
    count = {phase: 0 for phase in PHASES}
    for job in jobs:
        count[job.phase] += 1
    done = count["done"] + count["skipped"]
    seen = done + count["running"] + count["failed"]
    if total is not None:
        total = max(total, seen)
    walls = [
        max(j.ended - j.started, 0.0)
        for j in jobs
        if j.phase in ("done", "failed") and j.started is not None and j.ended is not None
    ]
    left: float | None = None
    if total is not None and total == seen and count["running"] == 0:
        left = 0.0
    elif total is not None and walls:
        wall = sum(walls) / len(walls)
        pending = total - seen
        ages = [
            max(now - j.started, 0.0)
            for j in jobs
            if j.phase == "running" and j.started is not None
        ]
        work = pending * wall + sum(max(wall - a, 0.0) for a in ages)
        slots = min(max(parallelism(jobs, now), 1), pending + count["running"])
        left = work / slots
    return Progress(
        total, done, count["skipped"], count["running"], count["failed"], elapsed_s, left
    )


def format_duration(seconds: float) -> str:
    """A duration with its units, rounded to the second: ``42 s``, ``3 min 05 s``,
    ``2 h 07 min`` (minutes rounded down).
    """
    s = max(round(seconds), 0)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def format_progress(p: Progress, dash: str = "–") -> str:
    """The progress line (fields defined in the module's docstring)."""
    total = "?" if p.total is None else str(p.total)
    if p.left_s is None:
        left = dash
    elif p.left_s == 0:
        left = "0 s"
    else:
        left = "~" + format_duration(p.left_s)
    return (
        f"sweep: {p.done}/{total} jobs done ({p.skipped} skipped), {p.running} running, "
        f"{p.failed} failed; elapsed {format_duration(p.elapsed_s)}, left {left}"
    )


@dataclass(frozen=True)
class Display:
    """How the progress line shows, resolved once from a :data:`MODES` value.

    Attributes:
        name: ``tty``, ``plain`` or ``off``.
        shown: Whether there is a line at all.
        in_place: Whether it is one line redrawn in place (a terminal) rather than lines.
    """

    name: str
    shown: bool
    in_place: bool


DISPLAYS = {
    "tty": Display("tty", shown=True, in_place=True),
    "plain": Display("plain", shown=True, in_place=False),
    "off": Display("off", shown=False, in_place=False),
}
"""The displays of the :data:`MODES` values other than ``auto``."""


def resolve_mode(mode: str, stream: TextIO) -> Display:
    """The display of a :data:`MODES` value: ``auto`` is ``tty`` when ``stream`` is a
    terminal, ``CI`` is not ``true`` or ``1`` and ``TERM`` is not ``dumb``, else
    ``plain``.
    """
    if mode in DISPLAYS:
        return DISPLAYS[mode]
    ci = os.environ.get("CI", "").strip().lower() in ("true", "1")
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError, OSError):
        tty = False
    terminal = tty and not ci and os.environ.get("TERM") != "dumb"
    return DISPLAYS["tty"] if terminal else DISPLAYS["plain"]


def read_run(sweep_dir: Path) -> dict[str, Any]:
    """The sweep running in ``sweep_dir`` (:data:`RUN_FILE`: ``id``, ``tty``); empty
    when none is recorded or the file is unreadable.
    """
    try:
        data = json.loads(read_text(Path(sweep_dir) / RUN_FILE, SMALL_FILE_BYTES))
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return data if isinstance(data, dict) and isinstance(data.get("id"), str) else {}


def count_jobs(config: Any) -> int | None:
    """The number of jobs Hydra's basic sweeper makes of a multirun's config (its
    ``hydra.sweeper.params`` and the command line's overrides, as the sweeper combines
    them); None for another sweeper or overrides that cannot be expanded here.
    """
    try:
        from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
        from hydra.core.global_hydra import GlobalHydra
        from hydra.core.override_parser.overrides_parser import OverridesParser

        sweeper = config.hydra.sweeper
        if sweeper.get("_target_") != f"{BasicSweeper.__module__}.{BasicSweeper.__name__}":
            return None
        params = sweeper.get("params") or {}
        arguments = [f"{k}={v}" for k, v in params.items()]
        arguments += [str(o) for o in config.hydra.overrides.task]
        loader = None
        if GlobalHydra.instance().is_initialized():
            loader = GlobalHydra.instance().config_loader()
        parsed = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
        return sum(len(batch) for batch in BasicSweeper.split_arguments(parsed, None))
    except Exception:  # an unknown total is shown as "?"
        return None


_DRAWING = threading.Lock()
"""Held while a monitor writes its line, and across a fork (a job forked by the basic
launcher from this process never inherits the stream's lock taken mid-write)."""


if hasattr(os, "register_at_fork"):
    os.register_at_fork(
        before=_DRAWING.acquire,
        after_in_parent=_DRAWING.release,
        after_in_child=_DRAWING.release,
    )


class SweepMonitor:
    """Shows a sweep's progress (:func:`format_progress`) while it runs, from a thread
    that reads the jobs' status files in the sweep directory.

    Args:
        sweep_dir: The sweep directory (``hydra.sweep.dir``).
        total: Jobs of the sweep (None when unknown: shown as ``?``).
        mode: One of :data:`MODES`.
        every: Least time between two plain lines (s).
        status_file: The name of a job's status file in its directory.
        stream: Where the line goes (standard error by default).
        clock: Unix time (s); a fake one in tests.
        poll_s: Time between two reads of the directory (s).
    """

    def __init__(
        self,
        sweep_dir: Path,
        total: int | None,
        mode: str = "auto",
        every: float = 10.0,
        status_file: str = "job_status.json",
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.time,
        poll_s: float = POLL_S,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, not {mode!r}")
        self.sweep_dir, self.total, self.every = Path(sweep_dir), total, float(every)
        self.status_file, self.clock, self.poll_s = status_file, clock, poll_s
        self.stream = stream if stream is not None else sys.stderr
        self.display = resolve_mode(mode, self.stream)
        self.mode = self.display.name
        self.run_id = secrets.token_hex(8)
        self.t0 = clock()
        self._files: dict[Path, tuple[tuple[int, int, int], JobTimes]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._finished = False
        self._last_line: float | None = None
        self._last_counts: tuple[int, ...] | None = None
        self._lock = threading.Lock()
        encoding = getattr(self.stream, "encoding", None) or "utf-8"
        try:
            "–".encode(encoding)
            self.dash = "–"
        except (UnicodeEncodeError, LookupError):
            self.dash = "-"

    def start(self) -> None:
        """Record the sweep (:data:`RUN_FILE`) and start the thread; nothing when the
        mode is ``off``, or when the file cannot be written (said in one line).
        """
        if not self.display.shown:
            return
        run = json.dumps({"id": self.run_id, "tty": self.display.in_place})
        tmp = self.sweep_dir / f"{RUN_FILE}.{os.getpid()}.tmp"
        try:
            tmp.write_text(run + "\n")
            tmp.replace(self.sweep_dir / RUN_FILE)
        except OSError as err:
            with contextlib.suppress(OSError):
                tmp.unlink()
            print(f"no sweep progress: cannot write {RUN_FILE} ({err.strerror})", file=sys.stderr)
            return
        self.t0 = self.clock()
        self._thread = threading.Thread(target=self._loop, name="sweep-progress", daemon=True)
        self._thread.start()
        atexit.register(self.stop)

    def snapshot(self, reread: bool = False) -> Progress:
        """Read the status files that may have changed since the last call (all of them
        when ``reread``) and count.

        A file is read again when its inode, modification time or size changed, or when
        it was last read less than :data:`SETTLE_S` after it was modified (a file system
        stamps times coarsely: two writes within one tick can leave the same stamp).
        """
        seen: set[Path] = set()
        try:
            paths = list(self.sweep_dir.glob(f"*/{self.status_file}"))
        except OSError:
            paths = list(self._files)
        for path in paths:
            seen.add(path)
            try:
                st = path.stat()
            except OSError:
                continue
            key = (st.st_ino, st.st_mtime_ns, st.st_size)
            cached = self._files.get(path)
            if not reread and cached is not None and cached[0] == key:
                continue
            if time.time() - st.st_mtime < SETTLE_S:
                key = (-1, 0, 0)  # not settled: read it again next time
            try:
                status = json.loads(read_text(path, SMALL_FILE_BYTES))
            except (OSError, ValueError, UnicodeDecodeError):
                continue  # being replaced: read it next time
            if isinstance(status, dict):
                self._files[path] = (key, job_times(status, self.run_id))
        for gone in set(self._files) - seen:
            del self._files[gone]
        now = self.clock()
        return estimate([t for _, t in self._files.values()], self.total, now, now - self.t0)

    def tick(self, final: bool = False, interrupted: bool = False) -> None:
        """Read the directory and draw or print a line if one is due (always when
        ``final``; then a terminal's line is ended with a newline, and the time left of
        an ``interrupted`` sweep is shown as unknown).
        """
        with self._lock:
            if self._finished:
                return
            progress = self.snapshot(reread=final)
            if interrupted:
                progress = dataclasses.replace(progress, left_s=None)
            now = self.clock()
            counts = (progress.done, progress.skipped, progress.running, progress.failed)
            if final:
                due = True
            elif self._last_line is None:
                started = progress.done + progress.running + progress.failed > 0
                due = started or now - self.t0 >= FIRST_LINE_S
            elif self.display.in_place:
                due = True
            else:
                since = now - self._last_line
                due = since >= HEARTBEAT_S or (counts != self._last_counts and since >= self.every)
            if due:
                self._write(format_progress(progress, self.dash), final)
                self._last_line, self._last_counts = now, counts
            if final:
                self._finished = True

    def stop(self, interrupted: bool = False) -> None:
        """Stop the thread and show the last line (its time left unknown when the sweep
        was ``interrupted``); safe to call more than once.
        """
        if self._thread is None or self._finished:
            return
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self.tick(final=True, interrupted=interrupted)

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.tick()
            except Exception as err:  # never take the sweep down for its progress line
                print(f"sweep progress stopped: {type(err).__name__}: {err}", file=sys.stderr)
                return

    def _write(self, line: str, final: bool) -> None:
        with _DRAWING, contextlib.suppress(OSError, ValueError):  # a closed stream: no line
            if self.display.in_place:
                try:
                    width = os.get_terminal_size(self.stream.fileno()).columns
                except (OSError, ValueError, AttributeError):
                    width = 80
                line = line[: max(width - 1, 1)]
                self.stream.write("\r" + line + "\x1b[K" + ("\n" if final else ""))
            else:
                self.stream.write(line + "\n")
            self.stream.flush()
