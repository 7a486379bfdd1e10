"""A benchmark tier: what it runs and how much it tunes (``conf/benchmark/NAME.yaml``).

A tier file holds:

* ``scenarios``: options of config group ``scenario`` (``conf/scenario/``), or ``all``;
* ``laws``: options of config group ``control``, or ``all`` (every option the config
  search path holds, a law of your own added with ``hydra.searchpath`` included);
* ``trials``: tuning trials per law and scenario, besides the law's default gains;
* ``tuning_seeds``: the seeds each trial runs on (its objectives are their geometric
  means);
* ``verdict_seeds``: fresh seeds, none of them a tuning seed, on which every law's chosen
  points are re-run, the same seeds for every law;
* ``budget_law``: the law whose effort at its default gains, per scenario, is the
  matched effort budget (:mod:`harness.benchmark.tuning`);
* ``values``: config values over every run of the tier (``{agents: {n: 256}}``), on top
  of each scenario's own;
* ``sampler_seed``: the seed of the tuning samplers.

Tiers are read with OmegaConf's YAML loader (no Python objects), checked here, and
refused in one line naming the key.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

TIERS = Path(__file__).resolve().parents[1] / "conf" / "benchmark"
"""The tiers the package ships (``conf/benchmark/``)."""


class PlanError(ValueError):
    """A tier file that cannot be run (names the key)."""


@dataclass(frozen=True)
class Plan:
    """A benchmark tier, checked (see the module docstring for the keys)."""

    name: str
    scenarios: tuple[str, ...]
    laws: tuple[str, ...]
    trials: int
    tuning_seeds: tuple[int, ...]
    verdict_seeds: tuple[int, ...]
    budget_law: str
    values: dict[str, Any] = field(default_factory=dict)
    sampler_seed: int = 0


def _seeds(key: str, value: Any) -> tuple[int, ...]:
    if not isinstance(value, list) or not value:
        raise PlanError(f"{key}={value!r}: a non-empty list of seeds")
    seeds = []
    for s in value:
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise PlanError(f"{key}={value!r}: seeds are integers >= 0")
        seeds.append(s)
    if len(set(seeds)) != len(seeds):
        raise PlanError(f"{key}={value!r}: each seed once")
    return tuple(seeds)


def _names(key: str, value: Any, known: list[str]) -> tuple[str, ...]:
    if value == "all":
        return tuple(known)
    if not isinstance(value, list) or not value:
        raise PlanError(f"{key}={value!r}: 'all' or a non-empty list of options")
    unknown = [v for v in value if v not in known]
    if unknown:
        raise PlanError(f"{key}: {unknown} not among the options {known}")
    return tuple(str(v) for v in value)


def read_plan(tier: str | Path, scenarios: list[str], laws: list[str]) -> Plan:
    """The tier ``tier`` (a name in :data:`TIERS` or a path to a YAML file), checked
    against the known ``scenarios`` and ``laws``.

    Raises:
        PlanError: for a missing file, a key missing or of the wrong kind, an unknown
            scenario or law, a verdict seed that is also a tuning seed.
    """
    path = Path(tier)
    if path.suffix not in (".yaml", ".yml"):
        known = sorted(p.stem for p in TIERS.glob("*.yaml"))
        if str(tier) not in known:
            raise PlanError(f"tier {tier!r}: one of {known}, or a path to a YAML file")
        path = TIERS / f"{tier}.yaml"
    if not path.is_file():
        raise PlanError(f"tier {str(path)!r}: no such file")
    try:
        node = OmegaConf.load(path)
    except Exception as err:  # a YAML error: one line
        raise PlanError(f"tier {str(path)!r}: not YAML ({type(err).__name__})") from None
    if not isinstance(node, DictConfig):
        raise PlanError(f"tier {str(path)!r}: a mapping of keys")
    raw = OmegaConf.to_container(node, resolve=True)
    assert isinstance(raw, dict)
    expected = {
        "scenarios",
        "laws",
        "trials",
        "tuning_seeds",
        "verdict_seeds",
        "budget_law",
        "values",
        "sampler_seed",
    }
    extra = sorted(set(raw) - expected)
    if extra:
        raise PlanError(f"{extra}: not keys of a tier (keys: {sorted(expected)})")
    missing = sorted(expected - {"values", "sampler_seed"} - set(raw))
    if missing:
        raise PlanError(f"{missing}: missing from the tier {str(path)!r}")
    trials = raw["trials"]
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise PlanError(f"trials={trials!r}: an integer >= 1")
    tuning, verdict = (
        _seeds("tuning_seeds", raw["tuning_seeds"]),
        _seeds("verdict_seeds", raw["verdict_seeds"]),
    )
    shared = sorted(set(tuning) & set(verdict))
    if shared:
        raise PlanError(f"verdict_seeds: {shared} also tuning seeds (verdicts need fresh seeds)")
    chosen_laws = _names("laws", raw["laws"], laws)
    if raw["budget_law"] not in chosen_laws:
        raise PlanError(f"budget_law={raw['budget_law']!r}: one of the tier's laws")
    values = raw.get("values") or {}
    if not isinstance(values, Mapping):
        raise PlanError(f"values={values!r}: a mapping of config values")
    seed = raw.get("sampler_seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise PlanError(f"sampler_seed={seed!r}: an integer >= 0")
    return Plan(
        name=path.stem,
        scenarios=_names("scenarios", raw["scenarios"], scenarios),
        laws=chosen_laws,
        trials=trials,
        tuning_seeds=tuning,
        verdict_seeds=verdict,
        budget_law=str(raw["budget_law"]),
        values=dict(values),
        sampler_seed=seed,
    )
