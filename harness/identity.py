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
from dataclasses import dataclass
from pathlib import Path

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


@dataclass(frozen=True)
class RunIdentity:
    """The log's ``config`` and ``provenance`` records.

    Attributes:
        config_yaml: The resolved config (YAML).
        provenance: Git commit and dirty flag, package versions, Python, seed, host,
            start time and the config's hash ``config_sha256`` (strings).
    """

    config_yaml: str
    provenance: dict[str, str]


def run_config(cfg: DictConfig) -> DictConfig:
    """``cfg`` without Hydra's own node ``hydra`` (present in a callback's config; its
    run-time values do not resolve before the run starts).
    """
    if "hydra" not in cfg:
        return cfg
    return OmegaConf.masked_copy(cfg, [str(k) for k in cfg.keys() if k != "hydra"])


def identify(cfg: DictConfig) -> RunIdentity:
    """The identity of a run of ``cfg`` (its ``hydra`` node, when present, is Hydra's,
    not the run's: left out).
    """
    return RunIdentity(
        OmegaConf.to_yaml(run_config(cfg), resolve=True),
        {**provenance(cfg.seed), "config_sha256": config_hash(cfg)},
    )


def config_hash(cfg: DictConfig) -> str:
    """SHA-256 (hex) of the resolved config without ``hydra`` and the presentation keys
    (:data:`harness.checks.PRESENTATION_KEYS`): equal exactly when two runs compute and
    log the same thing. Canonical JSON (sorted keys), so formatting never matters.
    """
    data = OmegaConf.to_container(run_config(cfg), resolve=True)
    assert isinstance(data, dict)
    for key in PRESENTATION_KEYS:
        block, _, leaf = key.partition(".")
        if isinstance(data.get(block), dict):
            data[block].pop(leaf, None)
    text = json.dumps(data, sort_keys=True, default=repr, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


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
