"""YAML from a log read within bounds of size, depth and alias expansion, so a foreign
``config`` record cannot exhaust memory or recursion (:func:`safe_config`).
"""

from __future__ import annotations

from typing import Any

import yaml

MAX_CONFIG_CHARS = 1_000_000
"""Longest ``config`` record read (characters; a run's own is a few kB)."""

MAX_CONFIG_NODES = 100_000
"""Most YAML nodes a config record may hold once its aliases are expanded."""

MAX_CONFIG_DEPTH = 50
"""Deepest nesting of a config record (a run's own is 3 or 4 levels deep)."""


class ConfigRecordError(ValueError):
    """A ``config`` record that is not read: too large, too deep, an alias that refers
    to itself, or more nodes than :data:`MAX_CONFIG_NODES` once expanded.
    """


def safe_config(text: str) -> Any:
    """``text`` read as YAML (safe loader) within bounds of size, depth and alias
    expansion, so a foreign record cannot exhaust memory or recursion.

    Raises:
        ConfigRecordError: for a record beyond the bounds.
        yaml.YAMLError: for text that is not YAML.
    """
    if len(text) > MAX_CONFIG_CHARS:
        raise ConfigRecordError(f"{len(text)} characters, more than {MAX_CONFIG_CHARS}")
    if _flow_depth(text) > MAX_CONFIG_DEPTH:  # the YAML scanner takes depth^2 steps
        raise ConfigRecordError(f"nested more than {MAX_CONFIG_DEPTH} levels deep")
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except RecursionError:
        raise ConfigRecordError("nested too deeply to read") from None
    if root is None:
        return None
    _measure(root)
    return yaml.safe_load(text)


def _flow_depth(text: str) -> int:
    """Deepest nesting of ``[`` and ``{`` in ``text`` (quotes not considered: an upper
    bound of the flow collections' depth), in one pass.
    """
    depth = deepest = 0
    for char in text:
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(depth - 1, 0)
    return deepest


def _measure(root: yaml.Node) -> None:
    """Expanded node count and depth of a composed document (each node measured once;
    an alias shares its anchor's node object), refusing cycles and excess.
    """
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        elif isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        if done:
            active.discard(key)
            size[key] = 1 + sum(size[id(c)] for c in children)
            depth[key] = 1 + max((depth[id(c)] for c in children), default=0)
            if size[key] > MAX_CONFIG_NODES:
                raise ConfigRecordError(f"more than {MAX_CONFIG_NODES} nodes once expanded")
            if depth[key] > MAX_CONFIG_DEPTH:
                raise ConfigRecordError(f"nested more than {MAX_CONFIG_DEPTH} levels deep")
            continue
        if key in size:
            continue
        if key in active:
            raise ConfigRecordError("an alias that refers to itself")
        active.add(key)
        stack.append((node, True))
        for child in children:
            if id(child) in active:
                raise ConfigRecordError("an alias that refers to itself")
            if id(child) not in size:
                stack.append((child, False))
