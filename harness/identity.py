"""What identifies a run in its log: the resolved config, its hash and the provenance.

:func:`config_hash` decides whether a sweep's job is done already (:mod:`harness.jobs`);
:func:`provenance` says which code, packages and machine made the log.
"""

from __future__ import annotations

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

from harness.checks import PRESENTATION_KEYS

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
    """What the log's ``config`` and ``provenance`` records hold, made when the log
    opens from the resolved config taken at build.

    Args:
        data: The resolved config without ``hydra``, as plain containers (not modified).
        seed: The run's seed.
    """

    def __init__(self, data: dict[str, Any], seed: int) -> None:
        self.data, self.seed = data, seed

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
    (:data:`harness.checks.PRESENTATION_KEYS`): equal exactly when two runs compute and
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


def provenance(seed: int) -> dict[str, str]:
    """Git commit and dirty flag, package versions, Python, seed, host, start time."""
    root = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        try:
            out = subprocess.run(
                ["git", *args], cwd=root, capture_output=True, text=True, timeout=10
            )
            return out.stdout.strip() if out.returncode == 0 else "unknown"
        except (OSError, subprocess.SubprocessError):
            return "unknown"

    status = git("status", "--porcelain")
    info = {
        "git_commit": git("rev-parse", "HEAD"),
        "git_dirty": "unknown" if status == "unknown" else str(bool(status)).lower(),
        "python": sys.version.split()[0],
        "seed": str(seed),
        "host": platform.node(),
        "start_time_utc": dt_.datetime.now(dt_.UTC).isoformat(timespec="seconds"),
    }
    for name in PACKAGES:
        try:
            info[f"version_{name}"] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            info[f"version_{name}"] = "not installed"
    return info
