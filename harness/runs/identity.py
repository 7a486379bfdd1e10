"""What identifies a run in its log: the resolved config, its hash, Hydra's choices and
the provenance.

:func:`config_hash` and :func:`code_identity` decide together whether a sweep's job is
done already (:mod:`harness.runs.resume`): a log counts only for the same config computed by
the same code; :func:`provenance` says which code, packages and machine made the log.
"""

from __future__ import annotations

import datetime as dt_
import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from harness.files import UnreadableFile, read_bytes
from harness.runs.checks import PRESENTATION_KEYS

PACKAGES = (
    "numpy",
    "scipy",
    "numba",
    "filterpy",
    "mcap",
    "mcap-protobuf-support",
    "foxglove-schemas-protobuf",
    "hydra-core",
    "omegaconf",
    "densityloop",
)


class RunIdentity:
    """What the log's ``config``, ``choices`` and ``provenance`` records hold, made when
    the log opens from the resolved config taken at build.

    Args:
        data: The resolved config without ``hydra``, as plain containers (not modified).
        seed: The run's seed.
        choices: Hydra's choices, the option of each config group (:func:`choices`).
    """

    def __init__(self, data: dict[str, Any], seed: int, choices: dict[str, str]) -> None:
        self.data, self.seed, self.choices = data, seed, dict(choices)

    @property
    def config_yaml(self) -> str:
        """The ``config`` record: the resolved config (YAML)."""
        return OmegaConf.to_yaml(self.data)

    @property
    def config_sha256(self) -> str:
        """The config's hash (:func:`config_hash`)."""
        return _hash(self.data)

    def provenance(self) -> dict[str, str]:
        """The ``provenance`` record, taken when the run starts: git commit and dirty
        flag, package versions, Python, seed, host, start time and ``config_sha256``.
        """
        return {**provenance(self.seed), "config_sha256": self.config_sha256}

    def records(self) -> dict[str, dict[str, str]]:
        """The metadata records the log opens with, in order: ``config`` (key ``yaml``),
        ``choices`` (config group -> option) and ``provenance`` (taken now).
        """
        return {
            "config": {"yaml": self.config_yaml},
            "choices": dict(self.choices),
            "provenance": self.provenance(),
        }


def cpu_model() -> str:
    """The CPU's model name (the first ``model name`` of ``/proc/cpuinfo``, else
    :func:`platform.processor` or the machine type).
    """
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for text in cpuinfo.read_text(errors="replace").splitlines():
            if text.startswith("model name"):
                return text.split(":", 1)[1].strip()
    return cpu


def choices(cfg: DictConfig) -> dict[str, str]:
    """Hydra's choices: the option chosen in each config group of the project
    (``{"plant": "agents", "control": "paper", "experiment": "smoke", ...}``; Hydra's own
    groups ``hydra/...`` left out; ``null`` for a group set to nothing), from the
    config's ``hydra.runtime.choices`` (a callback's config, or
    :func:`harness.api.compose`'s), else from the running Hydra app, else none (a config
    made by hand).
    """
    node = OmegaConf.select(cfg, "hydra.runtime.choices", default=None)
    if node is None:
        from hydra.core.hydra_config import HydraConfig

        if not HydraConfig.initialized():
            return {}
        node = HydraConfig.get().runtime.choices
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, DictConfig) else node
    if not isinstance(raw, dict):
        return {}
    return {
        str(group): "null" if option is None else str(option)
        for group, option in sorted(raw.items())
        if not str(group).startswith("hydra/") and str(group) != "hydra"
    }


def task_overrides(cfg: DictConfig) -> list[str]:
    """The overrides the config was composed with (Hydra's ``hydra.overrides.task``: the
    command line's, a sweep job's, :func:`harness.api.compose`'s), from the config's
    ``hydra`` node, else, for a config without one, from the running Hydra app; none for
    a config made by hand.
    """
    node = OmegaConf.select(cfg, "hydra.overrides.task", default=None)
    if node is None and "hydra" not in cfg:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            node = HydraConfig.get().overrides.task
    raw = OmegaConf.to_container(node, resolve=False) if isinstance(node, ListConfig) else node
    return [str(o) for o in raw] if isinstance(raw, list) else []


def chosen_observers(cfg: DictConfig) -> list[str] | None:
    """The options of the config group ``observers`` as the last override listing them
    wrote them (``observers=[metrics,log,log]``: ``["metrics", "log", "log"]``, a
    duplicate kept, which Hydra merges away and leaves out of :func:`choices`); None
    when no override lists them.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    chosen = None
    for text in task_overrides(cfg):
        key = text.split("=", 1)[0].lstrip("+~").split("@", 1)[0].strip()
        if key != "observers":
            continue
        try:
            (override,) = OverridesParser.create().parse_overrides([text])
            value = override.value()
        except Exception:  # Hydra took it; what it cannot parse here lists nothing
            continue
        if not override.is_delete() and isinstance(value, list):
            chosen = [str(v) for v in value]
    return chosen


def resolved(cfg: DictConfig) -> dict[str, Any]:
    """``cfg`` without ``hydra`` (:func:`run_config`), every interpolation resolved, as
    plain containers.
    """
    data = OmegaConf.to_container(run_config(cfg), resolve=True)
    assert isinstance(data, dict)
    return {str(k): v for k, v in data.items()}


def run_config(cfg: DictConfig) -> DictConfig:
    """``cfg`` without Hydra's own node ``hydra`` (present in a callback's config; its
    run-time values do not resolve before the run starts).
    """
    if "hydra" not in cfg:
        return cfg
    return OmegaConf.masked_copy(cfg, [str(k) for k in cfg.keys() if k != "hydra"])


def config_hash(cfg: DictConfig) -> str:
    """SHA-256 (hex) of the resolved config without ``hydra`` and the presentation keys
    (:data:`harness.runs.checks.PRESENTATION_KEYS`): equal exactly when two runs compute and
    log the same thing. Canonical JSON (sorted keys), so formatting never matters.
    """
    return _hash(resolved(cfg))


def _hash(data: dict) -> str:
    """:func:`config_hash` of a resolved config as plain containers (not modified)."""
    kept = _without(data, [key.split(".") for key in PRESENTATION_KEYS])
    text = json.dumps(kept, sort_keys=True, default=repr, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _without(data: dict, paths: list[list[str]]) -> dict:
    """A copy of ``data`` without the keys at ``paths`` (each a list of nested keys); the
    dicts on those paths are copied, everything else is shared.
    """
    out = dict(data)
    for first in {path[0] for path in paths}:
        rest = [path[1:] for path in paths if path[0] == first]
        if any(not r for r in rest):
            out.pop(first, None)
        elif isinstance(out.get(first), dict):
            out[first] = _without(out[first], rest)
    return out


ROOT = Path(__file__).resolve().parents[2]
"""The project's root: the directory that holds the ``harness`` package (a source
checkout's top level, or ``site-packages`` of an installation)."""


CODE_DIRS = ("harness", "analysis", "experiments", "conf")
"""The folders of :data:`ROOT` that hold the code: the packages and their configs."""

CODE_SUFFIXES = (".py", ".yaml", ".c", ".h", ".toml", ".cfg")
"""Files that are code or configuration; any other file (notes, a floor cache, logs,
compiled caches) is not the code."""

MAX_CODE_FILE = 64 << 20
"""Largest code file read whole for the hash (bytes); a larger one, or one that is not a
regular file, enters the hash by its refusal (:mod:`harness.files`)."""


def _git(*args: str, text: bool = True) -> Any:
    """Output of a git command in :data:`ROOT` (``"unknown"`` when git fails). Git's
    own environment variables (``GIT_DIR``, ``GIT_WORK_TREE``, ...) are left out, so
    the repository is the one that holds :data:`ROOT`, if any.
    """
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    try:
        out = subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=text, timeout=30, env=env
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() if text else out.stdout


def is_code(name: str) -> bool:
    """Whether ``name`` (a path relative to :data:`ROOT`, ``/``-separated) is a code or
    config file of the project: in one of :data:`CODE_DIRS`, with a suffix of
    :data:`CODE_SUFFIXES`.
    """
    parts = name.split("/")
    return len(parts) > 1 and parts[0] in CODE_DIRS and Path(name).suffix in CODE_SUFFIXES


def _file_digest(digest: Any, name: str) -> None:
    """Feed the code file ``name`` (relative to :data:`ROOT`) into ``digest``: its
    name, then its bytes, or the reason it cannot be read (a FIFO or device never
    blocks or fills memory, :func:`harness.files.read_bytes`).
    """
    digest.update(name.encode(errors="surrogateescape") + b"\0")
    try:
        digest.update(read_bytes(ROOT / name, MAX_CODE_FILE))
    except UnreadableFile as err:
        digest.update(f"unreadable: {err}".encode(errors="surrogateescape"))


def _code_names() -> list[str]:
    """The code files (:func:`is_code`) under :data:`CODE_DIRS` in the working tree,
    sorted, as paths relative to :data:`ROOT`: whatever is there (anything but a
    directory; symbolic links to directories are not followed), never what an index or
    a VCS says is there.
    """
    names = []
    for folder in CODE_DIRS:
        base = ROOT / folder
        if not base.is_dir():
            continue
        for path in base.rglob("*"):
            name = path.relative_to(ROOT).as_posix()
            if is_code(name) and not path.is_dir():
                names.append(name)
    return sorted(names)


def _source_sha256() -> str:
    """SHA-256 of the code and config files of :data:`CODE_DIRS` (:func:`_code_names`),
    names and contents: the code's identity when git does not hold the project.
    """
    digest = hashlib.sha256()
    for name in _code_names():
        _file_digest(digest, name)
    return digest.hexdigest()


def _git_holds_project() -> tuple[str, dict[str, tuple[str, str]]] | None:
    """The commit of :data:`ROOT` and its code files (:func:`_committed_code`) when git
    holds the project there: the top level of the repository that contains :data:`ROOT`
    is :data:`ROOT` itself (not a checkout around a copy of the project or around an
    installation) and it tracks the code (files of :data:`CODE_DIRS`) at that commit;
    None otherwise.
    """
    top = _git("rev-parse", "--show-toplevel")
    if top == "unknown":
        return None
    try:
        if Path(top).resolve() != ROOT.resolve():
            return None
    except OSError:
        return None
    commit = _git("rev-parse", "--verify", "HEAD^{commit}")
    if commit == "unknown":
        return None
    committed = _committed_code(str(commit))
    if not committed:
        return None
    return str(commit), committed


def _committed_code(commit: str) -> dict[str, tuple[str, str]] | None:
    """The code files (:func:`is_code`) of ``commit``: name -> (mode, blob id), from
    ``git ls-tree`` (the commit's own tree: replacement objects are ignored, and neither
    the index nor git's diff configuration enters); None when git cannot list them.
    """
    listing = _git(
        "--no-replace-objects", "ls-tree", "-r", "-z", commit, "--", *CODE_DIRS, text=False
    )
    if not isinstance(listing, bytes):
        return None
    files = {}
    for entry in listing.split(b"\0"):
        meta, tab, raw = entry.partition(b"\t")
        fields = meta.split()
        if not tab or len(fields) != 3 or fields[1] != b"blob":
            continue  # a submodule (commit) entry is not a file of this checkout
        name = raw.decode(errors="surrogateescape")
        if is_code(name):
            files[name] = (fields[0].decode(), fields[2].decode())
    return files


def _blob_id(data: bytes, like: str) -> str:
    """Git's id of a blob holding ``data``, in the object format of the id ``like``
    (SHA-1, 40 hex digits, or SHA-256, 64).
    """
    algorithm = hashlib.sha256 if len(like) == 64 else hashlib.sha1
    return algorithm(b"blob %d\0" % len(data) + data).hexdigest()


def _unchanged(name: str, committed: tuple[str, str] | None) -> bool:
    """Whether the working tree's ``name`` holds exactly the bytes of its committed
    blob ``committed`` (mode, blob id): a symbolic link the same target, any other file a
    regular file with the same bytes (read through :mod:`harness.files`; a file that
    cannot be read has changed). The executable bit is not compared.
    """
    if committed is None:
        return False
    mode, blob = committed
    path = ROOT / name
    try:
        if mode == "120000":
            data = os.fsencode(os.readlink(path))
        elif os.path.islink(path):
            return False
        else:
            data = read_bytes(path, MAX_CODE_FILE)
    except OSError:  # UnreadableFile included: missing, not a regular file, too large
        return False
    return _blob_id(data, blob) == blob


def _code_changes(committed: dict[str, tuple[str, str]]) -> str:
    """``clean`` when the code files (:func:`is_code`) of the working tree are the
    commit's ``committed`` files (:func:`_committed_code`), else SHA-256 of the names
    and contents of the code files that differ: modified, deleted (entered as absent),
    or not in the commit (untracked, staged or ignored: ignoring a file does not make it
    less the code).

    Each file's bytes are compared with its committed blob directly (:func:`_unchanged`),
    never through git's index or ``git diff``: index flags (``skip-worktree``,
    ``assume-unchanged``), a stale index, and the user's or the repository's diff
    configuration (``diff.external``, textconv drivers, colour) do not enter, so the
    result is the same for the same bytes and changes whenever a code file's bytes
    change. Any other file, tracked or not (notes, documentation, a floor cache or
    outputs in the checkout), is not the code.
    """
    changed = sorted(
        name
        for name in set(_code_names()) | set(committed)
        if not _unchanged(name, committed.get(name))
    )
    if not changed:
        return "clean"
    digest = hashlib.sha256()
    for name in changed:
        if os.path.lexists(ROOT / name):
            _file_digest(digest, name)
        else:
            digest.update(name.encode(errors="surrogateescape") + b"\0absent\0")
    return digest.hexdigest()


def code_identity() -> dict[str, str]:
    """What identifies the code a run computes with: the git commit, the dirty flag,
    ``git_diff_sha256``, the versions of Python and of :data:`PACKAGES`, and
    ``code_sha256``, the hash of all of these.

    Git says which code only when it holds the project (:func:`_git_holds_project`:
    the repository's top level is :data:`ROOT` and it tracks the code); then
    ``git_diff_sha256`` is ``clean`` or the hash of the changed code files, each
    compared byte for byte with the commit's blob (:func:`_code_changes`: git's index
    and diff configuration never enter), and ``git_dirty`` whether the code changed. Otherwise (an
    installed package, a copy of the project inside another checkout, no git)
    ``git_commit`` and ``git_dirty`` are ``unknown`` and ``git_diff_sha256`` is
    ``source:`` and the hash of the code files themselves (:func:`_source_sha256`).
    """
    held = _git_holds_project()
    if held is None:
        info = {
            "git_commit": "unknown",
            "git_dirty": "unknown",
            "git_diff_sha256": f"source:{_source_sha256()}",
        }
    else:
        commit, committed = held
        changes = _code_changes(committed)
        dirty = str(changes != "clean").lower()
        info = {"git_commit": commit, "git_dirty": dirty, "git_diff_sha256": changes}
    info["python"] = sys.version.split()[0]
    for name in PACKAGES:
        try:
            info[f"version_{name}"] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            info[f"version_{name}"] = "not installed"
    text = json.dumps(info, sort_keys=True, separators=(",", ":"))
    info["code_sha256"] = hashlib.sha256(text.encode()).hexdigest()
    return info


def code_change(logged: dict[str, str], now: dict[str, str]) -> str:
    """What differs between the code identity of a log (its ``provenance`` record) and
    ``now`` (:func:`code_identity`), in words; empty when the code is the same.
    """
    if logged.get("code_sha256") == now["code_sha256"]:
        return ""
    if "code_sha256" not in logged:
        return "the log does not record its code (code_sha256)"
    changed = [
        f"{key} {str(logged.get(key, 'absent'))[:12]} -> {str(value)[:12]}"
        for key, value in now.items()
        if key != "code_sha256" and logged.get(key) != value
    ]
    return "the code changed (" + ("; ".join(changed) or "code_sha256") + ")"


def provenance(seed: int) -> dict[str, str]:
    """The code's identity (:func:`code_identity`: git commit, dirty flag, the diff's
    hash, package versions and their hash ``code_sha256``), Python, seed, host, start
    time.
    """
    return {
        **code_identity(),
        "seed": str(seed),
        "host": platform.node(),
        "start_time_utc": dt_.datetime.now(dt_.UTC).isoformat(timespec="seconds"),
    }
