"""What a study declares about its analysis, and what its figure draws from.

A study preset (``conf/experiment/*.yaml``) declares its analysis in a top-level
``analysis`` block, which every job logs with its config::

    analysis:
      figure: iss_gain                    # a figure of analysis.sweep.FIGURES
      primary: [law, estimator.delta]     # the keys the study varies (besides seed)
      tail: 0.25                          # tail fraction of each run

:func:`declaration` reads one job's block (checking the figure's name against the
figures it is given), :func:`study_declaration` the one block of a sweep's jobs. A
figure (:class:`Figure`) draws from a :class:`Study`: the sweep's rows and metrics.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

GENERIC_FIGURE = "convergence"
"""The figure of a sweep without a declaration."""

DEFAULT_TAIL = 0.25
"""The tail fraction when neither ``--tail`` nor the declaration gives one."""

DECLARATION_BLOCK = "analysis"
"""The config block of the declaration (accepted by the harness, which logs it:
:data:`harness.runs.checks.LOGGED_BLOCKS`)."""

DECLARATION_KEYS = ("figure", "primary", "tail")
"""The keys of a declaration."""


class DeclarationError(ValueError):
    """A declaration the analysis cannot follow; ``str()`` is the one-line message."""


@dataclass(frozen=True)
class Declaration:
    """A study's declared analysis (see the module docstring).

    Attributes:
        figure: The figure's name.
        primary: The keys that make the study's points, or None for every varied key
            but ``seed``.
        tail: The tail fraction in ``(0, 1]``.
    """

    figure: str = GENERIC_FIGURE
    primary: tuple[str, ...] | None = None
    tail: float = DEFAULT_TAIL


def declaration(flat: Mapping[str, Any], figures: Collection[str] | None = None) -> Declaration:
    """The declaration in a job's flattened config (the generic one without a block).

    Args:
        flat: The job's config, flattened (``{"analysis.figure": "laws_n", ...}``).
        figures: The figure names to accept; None accepts any name (the name is then
            checked where the figure is drawn).

    Raises:
        DeclarationError: for a key that is not one of :data:`DECLARATION_KEYS`, a figure
            that is not one of ``figures``, a ``primary`` that is not a list of keys, or a
            tail outside ``(0, 1]``.
    """
    prefix = DECLARATION_BLOCK + "."
    if DECLARATION_BLOCK in flat:
        raise DeclarationError(
            f"{DECLARATION_BLOCK}={flat[DECLARATION_BLOCK]!r}: a block with "
            f"{', '.join(DECLARATION_KEYS)}"
        )
    block = {k[len(prefix) :]: v for k, v in flat.items() if k.startswith(prefix)}
    if not block:
        return Declaration()
    for key, v in block.items():
        if key not in DECLARATION_KEYS:
            raise DeclarationError(
                f"{prefix}{key}={v!r}: not a key of the analysis declaration "
                f"(one of {', '.join(DECLARATION_KEYS)})"
            )
    figure = block.get("figure")
    if not isinstance(figure, str) or (figures is not None and figure not in figures):
        known = f" (one of {', '.join(figures)})" if figures is not None else ""
        raise DeclarationError(f"{prefix}figure={figure!r}: no such figure{known}")
    primary = block.get("primary")
    if primary is not None and not (
        isinstance(primary, list) and all(isinstance(k, str) for k in primary)
    ):
        raise DeclarationError(f"{prefix}primary={primary!r}: a list of config keys")
    tail = block.get("tail", DEFAULT_TAIL)
    if isinstance(tail, bool) or not isinstance(tail, (int, float)) or not 0 < tail <= 1:
        raise DeclarationError(f"{prefix}tail={tail!r}: a fraction in (0, 1]")
    return Declaration(figure, None if primary is None else tuple(primary), float(tail))


def study_declaration(
    configs: Iterable[tuple[str, Mapping[str, Any]]], figures: Collection[str]
) -> Declaration:
    """The one declaration of a sweep's jobs.

    Args:
        configs: ``(job, flattened config)`` of every job whose config was read (an
            empty config is left out).
        figures: The figure names to accept.

    Raises:
        DeclarationError: for a declaration :func:`declaration` refuses, or jobs that
            declare different analyses.
    """
    found: dict[Declaration, str] = {}
    for job, flat in configs:
        if flat:
            found.setdefault(declaration(flat, figures), job)
    if len(found) > 1:
        jobs = ", ".join(f"{d.figure} ({job})" for d, job in found.items())
        raise DeclarationError(
            f"the jobs declare different analyses: {jobs} "
            "(analyse each sweep from a directory of its own)"
        )
    return next(iter(found), Declaration())


@dataclass(frozen=True)
class Study:
    """What a figure draws from: the completed jobs' rows (``usable``, with
    statistics, :mod:`analysis.rows`), their metrics by job directory, the varied config
    keys (``seed`` included), the output directory, the sweep directory and the tail
    fraction.
    """

    usable: list[dict[str, Any]]
    series: dict[str, Any]
    varied: list[str]
    out: Path
    sweep_dir: Path | None = None
    tail: float = DEFAULT_TAIL


@dataclass(frozen=True)
class Figure:
    """A figure of a study: how to draw it (the paths it wrote), the primary keys it
    draws against, and keys it tells points apart by beside them (``also``: a point may
    set them off their defaults, e.g. a graph of the ``k`` nearest in a study of radii).
    """

    draw: Callable[[Study], list[Path]]
    needs: tuple[str, ...] = ()
    also: tuple[str, ...] = ()
