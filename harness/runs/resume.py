"""Resume by content: whether the log a job's directory holds counts as the job done.

Hydra cannot resume a sweep, so each job decides from what its directory holds
(:func:`judge`, called by :func:`harness.runs.app.run_job`). It is done only when its
``run.mcap`` is complete, reads back whole (chunk CRCs checked, the message count equal
to the summary's, :func:`verify_log`), has status ``completed``, and the ``provenance``
record's ``config_sha256`` equals the hash of the job's resolved config
(:func:`~harness.runs.identity.config_hash`) and its ``code_sha256`` the code's
(:func:`~harness.runs.identity.code_identity`: commit, the diff's hash, package
versions). Otherwise the job runs again, and :attr:`Verdict.why` says why (for the
job's ``rerun_reason``). A log is replaced only when it is a verified copy of what the
rerun writes (same config and code, unfinished or not ``completed``); any other is moved
aside (``run.previous-K.mcap``), never overwritten (:func:`clear`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Message, Metadata
from mcap.stream_reader import StreamReader

from harness.runs.identity import code_change


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


@dataclass(frozen=True)
class Verdict:
    """What :func:`judge` decided about a job's log.

    Attributes:
        done: The log counts: the job is skipped.
        why: Why the job runs again (empty when ``done``).
        replaceable: The log is a verified copy of what the rerun writes (same config
            and code, unfinished or not ``completed``): the rerun may delete it; any
            other log is set aside.
    """

    done: bool
    why: str
    replaceable: bool


def judge(log: Path, config_sha256: str, code: dict[str, str]) -> Verdict:
    """Whether ``log`` counts as the job done, for the job's config hash and the code
    that runs now.

    Args:
        log: The job's ``run.mcap`` (it need not exist).
        config_sha256: The hash of the job's resolved config
            (:func:`~harness.runs.identity.config_hash`).
        code: The code's identity now (:func:`~harness.runs.identity.code_identity`).
    """
    check = verify_log(log)
    same_config = check.config_hash == config_sha256
    changed = code_change(check.provenance, code) if check.provenance else ""
    if check.intact and check.state == "completed" and same_config and not changed:
        return Verdict(done=True, why="", replaceable=False)
    if not check.intact:
        why = check.problem
    elif not same_config:
        why = "the log holds another config"
    elif changed:
        why = changed
    else:
        why = f"the log's status is {check.state}"
    replaceable = same_config and not changed and bool(check.provenance)
    return Verdict(False, why, replaceable and check.state != "completed")


def clear(log: Path, verdict: Verdict) -> str:
    """Make way for the rerun's log: a replaceable log (:attr:`Verdict.replaceable`) is
    deleted (the rerun writes it whole), any other is moved aside (:func:`set_aside`).

    Returns:
        Why the job runs again (:attr:`Verdict.why`), with where the old log was kept.
    """
    if not (log.exists() or log.is_symlink()):
        return verdict.why
    if verdict.replaceable:
        log.unlink()
        return verdict.why
    return f"{verdict.why} (kept as {set_aside(log).name})"


def set_aside(log: Path) -> Path:
    """Move a log out of the way (``run.previous-K.mcap``, the first ``K`` free); its
    new path.
    """
    k = 1
    while (log.parent / f"run.previous-{k}.mcap").exists():
        k += 1
    target = log.parent / f"run.previous-{k}.mcap"
    log.rename(target)
    return target
