"""How a component checks its parameters and refuses one: one line naming the key.

A component's constructor checks each of its own parameters with :func:`number`,
:func:`integer`, :func:`flag` or :func:`require` and raises :class:`ParameterError`
naming the parameter; the builder (:func:`harness.runs.build.build`) turns that into a
one-line config error naming the full key (following interpolations such as
``${agents.n}`` to the public key). A component's ``check`` of the others raises
:class:`Incompatible`, naming the config group to change.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np


class ParameterError(ValueError):
    """A component parameter that is not allowed.

    Attributes:
        name: The parameter's name in the component's YAML (the builder prefixes the
            group, or follows an interpolation to the public key).
        value: The value given.
        allowed: What is allowed, as a phrase (``"an integer >= 1"``).
    """

    def __init__(self, name: str, value: Any, allowed: str) -> None:
        self.name, self.value, self.allowed = name, value, allowed
        super().__init__(f"{name}={value!r}: {allowed}")


class Incompatible(ParameterError):
    """A combination of components that cannot run together (raised by a component's
    ``check``); ``name`` is the config group to change (``"control"``, ``"plant"``).
    """


def speed_cap(value: Any) -> float | None:
    """The optional speed cap ``control.v_max``: None, or a number ``> 0`` (length / s)."""
    if value is None:
        return None
    return number("v_max", value, 0.0, strict=True)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def require(ok: bool, name: str, value: Any, allowed: str) -> None:
    """Raise :class:`ParameterError` unless ``ok``."""
    if not ok:
        raise ParameterError(name, value, allowed)


def number(name: str, value: Any, low: float | None = None, strict: bool = False) -> float:
    """A finite number, ``>= low`` (``> low`` when ``strict``); returns it as float."""
    if low is None:
        allowed = "a finite number"
    else:
        allowed = f"a finite number {'>' if strict else '>='} {low:g}"
    ok = _is_number(value) and math.isfinite(float(value))
    if ok and low is not None:
        ok = float(value) > low if strict else float(value) >= low
    require(ok, name, value, allowed)
    return float(value)


def integer(name: str, value: Any, low: int) -> int:
    """An integer ``>= low``; returns it."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, bool) and bool(value >= low)
    require(ok, name, value, f"an integer >= {low}")
    return int(value)


def flag(name: str, value: Any) -> bool:
    """A boolean."""
    require(isinstance(value, bool), name, value, "true or false")
    return value


def pair(name: str, value: object) -> tuple[object, object]:
    """Two coordinates, or :class:`~harness.parameters.ParameterError` naming ``name``."""
    ok = isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2
    require(ok, name, value, "two coordinates [x, y]")
    assert isinstance(value, Sequence)
    return value[0], value[1]
