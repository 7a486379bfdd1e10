"""The sweep's status: each job's ``job_status.json``, the jobs collected from them, and
the status table at the end of a multirun.

Each job of a multirun writes ``job_status.json`` next to its log
(:func:`harness.runs.app.run_job`): job number, overrides, state, reason, wall time (s)
of its last real run, ``runs`` (how many times it actually ran), the config hash, the
pid of its process while it runs, why it ran again (``rerun_reason``), and for the
progress line (:mod:`harness.runs.sweep_progress`) when it started and ended, in which
sweep and whether it was skipped. The file is written atomically and padded to
:data:`STATUS_BYTES`, so a later status fits in place when the disk is full.

When the sweep ends, :func:`collect` reads every job's status (and the status record of
its log, which wins when the two disagree), and :func:`report` prints the table (job,
overrides, state, runs, wall time, reason, why it ran again) and writes it as
``sweep_status.csv`` and ``sweep_status.md`` in the sweep directory.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import sys
from pathlib import Path
from typing import Any

from harness.files import SMALL_FILE_BYTES, read_text
from harness.observers.log import LOG_FILE
from harness.runs.resume import log_status

STATUS_FILE = "job_status.json"
"""A job's status file, in its directory next to its ``run.mcap``."""


STATUS_BYTES = 4096
"""Size a ``job_status.json`` is padded to (trailing blanks, which JSON ignores), so a
later status fits in the blocks it holds when the disk is full."""


TABLE_FIELDS = ("job", "dir", "overrides", "state", "runs", "wall_s", "reason", "rerun_reason")
"""The columns of ``sweep_status.csv``, one row per job (:func:`collect`)."""


def read_status(job_dir: Path) -> dict[str, Any]:
    """The job's ``job_status.json`` (empty dict when absent, unreadable or malformed)."""
    try:
        data = json.loads(read_text(job_dir / STATUS_FILE, SMALL_FILE_BYTES))
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError, UnicodeDecodeError):
        return {}


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


def as_int(x: Any, default: int) -> int:
    """``x`` when it is an integer (not a bool), else ``default``: a number of a status
    file read as far as it makes sense.
    """
    return x if isinstance(x, int) and not isinstance(x, bool) else default


def _number(x: Any) -> float:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else float("nan")


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists (and is not a zombie)."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError, ValueError):  # none, or no process id
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


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
            pid = as_int(status.get("pid"), 0)
            if pid and alive(pid):
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
                "job": as_int(status.get("job"), -1),
                "dir": job_dir.name,
                "overrides": " ".join(str(o) for o in overrides),
                "state": state,
                "runs": as_int(status.get("runs"), 0),
                "wall_s": _number(status.get("wall_s")),
                "reason": reason,
                "rerun_reason": str(status.get("rerun_reason", "") or ""),
            }
        )
    rows.sort(key=lambda r: (as_int(r["job"], -1) % (10**9 + 1), str(r["dir"])))
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
    writer = csv.DictWriter(buffer, fieldnames=list(TABLE_FIELDS), extrasaction="ignore")
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


def report(sweep_dir: Path, interrupted: str = "") -> int:
    """Collect the jobs of ``sweep_dir``, print the table on standard output and write it
    (:func:`write_table`); say on standard error why the sweep was interrupted (when
    ``interrupted`` is not empty), which points were invalid and how to rerun the jobs
    that did not complete.

    Returns:
        The sweep's exit status: 1 when a job did not complete or the sweep was
        interrupted, 0 otherwise.
    """
    rows = collect(sweep_dir)
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
