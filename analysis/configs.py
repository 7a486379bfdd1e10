"""A run's config as the log records it (the ``config`` metadata record).

Analysis takes every config value from the log itself, never from Hydra's files beside
it, so a log moved elsewhere, or a sweep whose jobs were started with different command
lines, is still described correctly.
"""

from __future__ import annotations

import warnings
from typing import Any

import yaml

from analysis.load import LogWarning, RunLog
from analysis.safe_yaml import ConfigRecordError, safe_config


def logged_config(run: RunLog) -> dict[str, Any]:
    """The resolved config of ``run`` (safe YAML, :func:`safe_config`); empty when
    absent or unreadable, with a :class:`~analysis.load.LogWarning` when refused.
    """
    text = run.metadata.get("config", {}).get("yaml", "")
    try:
        cfg = safe_config(text) if text else {}
    except yaml.YAMLError:
        return {}
    except ConfigRecordError as err:
        warnings.warn(f"{run.path}: config record not read: {err}", LogWarning, stacklevel=2)
        return {}
    return cfg if isinstance(cfg, dict) else {}


def flatten(cfg: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Dotted keys to leaf values (lists stay whole): ``{"grid.n": 30, ...}``."""
    out: dict[str, Any] = {}
    for key, value in cfg.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def component(flat: dict[str, Any], group: str) -> str:
    """Short name of a group's component: the class name of its ``_target_``
    (``control._target_ = harness.control.heat.HeatControl`` gives ``HeatControl``).
    """
    target = flat.get(f"{group}._target_", "")
    return str(target).rsplit(".", 1)[-1] if target else ""
