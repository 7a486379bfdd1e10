"""What a benchmark may tune: the gains a law's YAML declares under ``tunable``.

Each entry of a law's ``tunable`` node names one of its parameters and its range::

    tunable:
      alpha: {low: 3.0e-4, high: 3.0e-2, log: true}   # a number in [low, high]
      period: {values: [0.2, 0.5, 1.0, 2.0, 5.0]}     # one of a list

``log: true`` samples the range uniformly in ``log x`` (a gain whose effect scales with
its size). The node is logged with the config and never passed to the law
(:data:`harness.runs.build.TUNABLE`). An empty node declares a law with nothing to tune.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np


class TunableError(ValueError):
    """A ``tunable`` declaration that is not one (names the key)."""


@dataclass(frozen=True)
class Gain:
    """One tunable parameter of a law.

    Attributes:
        name: The law's parameter (a key of its config node).
        low: Least value (None for a list of values).
        high: Greatest value (None for a list of values).
        log: Whether the range is sampled uniformly in ``log x``.
        values: The allowed values, or None for a range.
    """

    name: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    values: tuple[Any, ...] | None = None

    def grid(self, points: int) -> list[Any]:
        """``points`` values spread over the range (geometrically when ``log``), or the
        declared values (all of them, whatever ``points``).
        """
        if self.values is not None:
            return list(self.values)
        assert self.low is not None and self.high is not None
        if points == 1:
            mid = np.sqrt(self.low * self.high) if self.log else 0.5 * (self.low + self.high)
            return [float(mid)]
        if self.log:
            return [float(v) for v in np.geomspace(self.low, self.high, points)]
        return [float(v) for v in np.linspace(self.low, self.high, points)]


def _number(key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise TunableError(f"{key}={value!r}: a finite number")
    return float(value)


def gains(control: Mapping[str, Any], key: str = "control") -> list[Gain]:
    """The gains a law's config node ``control`` declares tunable, in declared order.

    Args:
        control: The law's config node (resolved), with its ``tunable`` node.
        key: The node's config key, for the messages.

    Raises:
        TunableError: for a missing ``tunable`` node, an entry that names no parameter of
            the law, a range with ``low >= high`` (or ``low <= 0`` on a log scale), or an
            empty list of values.
    """
    node = control.get("tunable")
    if node is None:
        raise TunableError(
            f"{key}.tunable: missing (declare the law's gains, or tunable: {{}} for none)"
        )
    if not isinstance(node, Mapping):
        raise TunableError(f"{key}.tunable={node!r}: a mapping of parameter to range")
    out = []
    for name, spec in node.items():
        where = f"{key}.tunable.{name}"
        if name not in control or name == "tunable":
            raise TunableError(f"{where}: not a parameter of the law")
        if not isinstance(spec, Mapping):
            raise TunableError(f"{where}={spec!r}: {{low, high, log}} or {{values}}")
        if "values" in spec:
            values = spec["values"]
            if not isinstance(values, Sequence) or isinstance(values, str) or not values:
                raise TunableError(f"{where}.values={values!r}: a non-empty list")
            out.append(Gain(str(name), values=tuple(values)))
            continue
        low = _number(f"{where}.low", spec.get("low"))
        high = _number(f"{where}.high", spec.get("high"))
        log = bool(spec.get("log", False))
        if not low < high:
            raise TunableError(f"{where}: low < high (low {low:g}, high {high:g})")
        if log and low <= 0:
            raise TunableError(f"{where}.low={low:g}: > 0 on a log scale")
        out.append(Gain(str(name), low, high, log))
    return out


def distributions(declared: Sequence[Gain]) -> dict[str, Any]:
    """Optuna's distribution of every gain (a float range, log or not, or a categorical
    list).
    """
    from optuna.distributions import CategoricalDistribution, FloatDistribution

    out: dict[str, Any] = {}
    for g in declared:
        if g.values is not None:
            out[g.name] = CategoricalDistribution(list(g.values))
        else:
            assert g.low is not None and g.high is not None
            out[g.name] = FloatDistribution(g.low, g.high, log=g.log)
    return out
