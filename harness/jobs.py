"""Jobs of a sweep: per-job status, resume, and the status table at the end of a
multirun; and the check of a single run's config before Hydra writes anything.

Hydra cannot resume a sweep. Each job of a multirun therefore

* skips itself when its directory already holds a ``run.mcap`` whose status record
  says ``completed`` (re-running the same sweep into the same ``hydra.sweep.dir``
  reruns only the jobs that failed, were killed or never ran);
* never raises: a failing job finalises its own log (status ``aborted``), records
  the error and returns, so the other jobs go on;
* writes ``job_status.json`` next to its log: job number, overrides, state, reason,
  wall time (s) of its last real run, and ``runs``, how many times it actually ran.

:class:`SweepStatusCallback` (a Hydra callback) collects these files when the
multirun ends, prints a table (job, overrides, state, wall time) and writes it as
``sweep_status.csv`` and ``sweep_status.md`` in the sweep directory; it exits with
status 1 when a job did not complete.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path
from typing import Any

import numba
from hydra.experimental.callback import Callback
from mcap.reader import make_reader
from omegaconf import DictConfig

from harness.build import build
from harness.checks import ConfigError
from harness.run import RunResult, Terminated, run

STATUS_FILE = "job_status.json"


def log_state(path: Path) -> str | None:
    """The ``status`` record's state of a finished log, None when the file is missing,
    unfinished (no summary) or unreadable. Reads only the summary section.
    """
    if not path.is_file():
        return None
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            for record in reader.iter_metadata():
                if record.name == "status":
                    return record.metadata.get("state")
    except Exception:  # unfinished or damaged: not completed
        return None
    return None


def read_status(job_dir: Path) -> dict[str, Any]:
    """The job's ``job_status.json`` (empty dict when absent or unreadable)."""
    try:
        data = json.loads((job_dir / STATUS_FILE).read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def write_status(job_dir: Path, **fields: Any) -> None:
    """Merge ``fields`` into the job's ``job_status.json`` (atomic replace)."""
    data = read_status(job_dir)
    data.update(fields)
    tmp = job_dir / (STATUS_FILE + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
    tmp.replace(job_dir / STATUS_FILE)


def collect(sweep_dir: Path) -> list[dict[str, Any]]:
    """One row per job directory below ``sweep_dir`` (job, overrides, state, wall_s)."""
    rows = []
    for status_file in sorted(sweep_dir.glob(f"*/{STATUS_FILE}")):
        job_dir = status_file.parent
        status = read_status(job_dir)
        state = log_state(job_dir / "run.mcap") or status.get("state", "missing")
        rows.append(
            {
                "job": status.get("job", ""),
                "dir": job_dir.name,
                "overrides": " ".join(status.get("overrides", [])),
                "state": state,
                "runs": status.get("runs", 0),
                "wall_s": status.get("wall_s", float("nan")),
                "reason": status.get("reason", ""),
            }
        )
    rows.sort(key=lambda r: (r["job"] if isinstance(r["job"], int) else 10**9, r["dir"]))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """Markdown table of the rows."""
    lines = ["| job | overrides | state | runs | wall time (s) |", "|---|---|---|---|---|"]
    for r in rows:
        wall = r["wall_s"]
        wall_text = f"{wall:.1f}" if isinstance(wall, (int, float)) else str(wall)
        lines.append(
            f"| {r['job']} | {r['overrides']} | {r['state']} | {r['runs']} | {wall_text} |"
        )
    return "\n".join(lines)


def write_table(sweep_dir: Path, rows: list[dict[str, Any]]) -> None:
    """``sweep_status.csv`` and ``sweep_status.md`` in the sweep directory."""
    with open(sweep_dir / "sweep_status.csv", "w", newline="") as f:
        writer = csv.DictWriter(
            f, fieldnames=["job", "dir", "overrides", "state", "runs", "wall_s", "reason"]
        )
        writer.writeheader()
        writer.writerows(rows)
    (sweep_dir / "sweep_status.md").write_text(format_table(rows) + "\n")


class SweepStatusCallback(Callback):
    """Prints and writes the status table when a multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Collect the jobs' status files; exit 1 when a job did not complete."""
        sweep_dir = Path(config.hydra.sweep.dir)
        rows = collect(sweep_dir)
        write_table(sweep_dir, rows)
        print(f"\nsweep {sweep_dir}: {len(rows)} jobs")
        print(format_table(rows))
        bad = [r for r in rows if r["state"] != "completed"]
        if bad:
            print(
                f"{len(bad)} job(s) did not complete; re-run the same command with "
                f"hydra.sweep.dir={sweep_dir} to rerun only those",
                file=sys.stderr,
            )
            sys.exit(1)


class CheckCallback(Callback):
    """Checks a single run's config (by building its components) before Hydra creates
    the output directory; a refused value prints its one line and exits with status 2.
    """

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Build the components once to check them; nothing is written."""
        try:
            build(config)
        except ConfigError as err:
            print(err, file=sys.stderr)
            sys.exit(2)


def run_job(cfg: DictConfig, out: Path, job: int, overrides: list[str]) -> RunResult | None:
    """One job of a multirun: skip when complete, never raise on failure, keep status.

    Returns the run's result, or None when the job was skipped, invalid or failed (its
    ``job_status.json`` says which).

    Raises:
        KeyboardInterrupt, Terminated: after recording ``aborted``, so the sweep stops.
    """
    ident = {"job": job, "overrides": overrides}
    if log_state(out / "run.mcap") == "completed":
        write_status(out, state="completed", **ident)
        print(f"job {job}: already completed, skipped ({out})")
        return None
    try:
        build(cfg)
    except ConfigError as err:
        print(err, file=sys.stderr)
        write_status(out, state="invalid", reason=str(err), **ident)
        return None
    # one core per job: the sweep runs a job per core, so the per-robot kernels stay serial
    numba.set_num_threads(1)
    runs = read_status(out).get("runs", 0) + 1
    write_status(out, state="running", runs=runs, reason="", **ident)
    try:
        result = run(cfg, out)
    except (KeyboardInterrupt, Terminated):
        write_status(out, state="aborted", reason="interrupted")
        raise
    except Exception as err:  # recorded, not raised: the other jobs go on
        write_status(out, state="aborted", reason=f"{type(err).__name__}: {err}")
        print(f"job {job} failed: {type(err).__name__}: {err}", file=sys.stderr)
        return None
    write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s)
    return result
