"""What identifies a run in its log: the resolved config, its hash, Hydra's choices and
the provenance.

:func:`config_hash` and :func:`code_identity` decide together whether a sweep's job is
done already (:mod:`harness.runs.resume`): a log counts only for the same config computed by
the same code; :func:`provenance` says which code, packages and machine made the log.
"""

from __future__ import annotations

import contextlib
import datetime as dt_
import hashlib
import importlib.metadata
import json
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

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


ROOT = Path(__file__).resolve().parents[1]
"""The source tree (or installation) of the ``harness`` package."""


CODE_SUFFIXES = (".py", ".yaml", ".c", ".h", ".toml", ".cfg")
"""Files that are code or configuration: untracked ones count in the diff's hash."""


def _git(*args: str, text: bool = True) -> Any:
    """Output of a git command in :data:`ROOT` (``"unknown"`` when git fails)."""
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=text, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() if text else out.stdout


def _source_sha256() -> str:
    """SHA-256 of the code and config files of the installed packages (``harness``,
    ``analysis``, ``experiments``, ``conf``): the code's identity when git cannot say.
    """
    digest = hashlib.sha256()
    for folder in ("harness", "analysis", "experiments", "conf"):
        base = ROOT / folder
        if not base.is_dir():
            continue
        for path in sorted(base.rglob("*")):
            if path.suffix in CODE_SUFFIXES and path.is_file():
                digest.update(str(path.relative_to(ROOT)).encode() + b"\0")
                digest.update(path.read_bytes())
    return digest.hexdigest()


def code_identity() -> dict[str, str]:
    """What identifies the code a run computes with: the git commit, the dirty flag,
    ``git_diff_sha256`` (SHA-256 of ``git diff HEAD`` and of the untracked code and
    config files; ``clean`` when there are none), the versions of Python and of
    :data:`PACKAGES`, and ``code_sha256``, the hash of all of these. Without git (an
    installed package) the diff's hash is the hash of the package's own source files.
    """
    info = {"git_commit": _git("rev-parse", "HEAD")}
    status = _git("status", "--porcelain")
    info["git_dirty"] = "unknown" if status == "unknown" else str(bool(status)).lower()
    if info["git_commit"] == "unknown":
        info["git_diff_sha256"] = f"source:{_source_sha256()}"
    elif info["git_dirty"] == "false":
        info["git_diff_sha256"] = "clean"
    else:
        digest = hashlib.sha256()
        diff = _git("diff", "HEAD", "--binary", text=False)
        digest.update(diff if isinstance(diff, bytes) else str(diff).encode())
        others = _git("ls-files", "--others", "--exclude-standard", "-z", text=False)
        names = others.split(b"\0") if isinstance(others, bytes) else []
        for entry in sorted(n for n in names if n):
            path = ROOT / entry.decode(errors="surrogateescape")
            if path.suffix in CODE_SUFFIXES and path.is_file():
                digest.update(entry + b"\0")
                with contextlib.suppress(OSError):
                    digest.update(path.read_bytes())
        info["git_diff_sha256"] = digest.hexdigest()
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
