"""Values a component receives as its constructor declares them: ints given where it
declares floats made floats (:func:`as_declared`), at the config boundary.
"""

from __future__ import annotations

import collections.abc
import inspect
import types
import typing
from typing import Any


def _floats(hint: Any) -> Any:
    """What of a value annotated ``hint`` is a float: ``True`` for ``float`` (or an
    optional float), the element's answer for a list, tuple or sequence of them, else
    ``False`` (an annotation that also allows ints or anything else is left alone).
    """
    if hint is float:
        return True
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return _floats(args[0]) if len(args) == 1 else False
    if origin in (list, tuple, collections.abc.Sequence) and args:
        if origin is tuple and len(args) > 1 and args[-1] is not Ellipsis:
            return False
        return ("each", _floats(args[0]))
    return False


def _as_float(value: Any, kind: Any) -> Any:
    """``value`` with the ints that ``kind`` (:func:`_floats`) declares floats made floats
    (``bool`` and anything not an int left as they are, for the class's own check).
    """
    if kind is True:
        return float(value) if type(value) is int else value
    if isinstance(kind, tuple) and isinstance(value, list):
        return [_as_float(v, kind[1]) for v in value]
    return value


def as_declared(target: Any, params: dict[str, Any]) -> dict[str, Any]:
    """``params`` with every int given for a parameter that ``target`` declares a float
    (``float``, ``float | None``, ``list[float]``, ...) made a float.

    The config boundary: YAML and the command line write ``1`` for ``1.0``, and a value
    that reaches compiled code keeps its type there (numba types a function by its
    arguments, and an int where a float was compiled fails or recompiles). Each
    component thus receives the types it declares; a target whose annotations cannot be
    read gets the values as they are.
    """
    try:
        hints = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception:  # annotations naming what cannot be imported here
        return params
    return {k: _as_float(v, _floats(hints.get(k))) for k, v in params.items()}
