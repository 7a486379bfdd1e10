"""A decentralised design: the consensus form, what the robots share, what a message
carries, and their parameters (``estimator.consensus``, ``integral_gain``, ``share``,
``command_rounds``, ``messages``, ``band_limit``; ``conf/design/*.yaml`` set the three
choices together).

Each choice is a config value that one table here maps to its class, once, when the
estimator is built: :data:`FORMS` (:mod:`harness.estimators.distributed.consensus`),
:data:`SHARES` (:mod:`harness.estimators.distributed.share`) and :data:`MESSAGES`
(:mod:`harness.estimators.distributed.messages`, :mod:`harness.estimators.distributed.band`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from harness.estimators.distributed.band import BandMessages
from harness.estimators.distributed.consensus import (
    ConsensusForm,
    FirstOrder,
    ProportionalIntegral,
)
from harness.estimators.distributed.messages import GridMessages, Messages
from harness.estimators.distributed.share import Share, ShareCommand, ShareDensity
from harness.grid import Grid
from harness.parameters import integer, number, require

FORMS: dict[str, Callable[[Design], ConsensusForm]] = {
    "first_order": lambda design: FirstOrder(),
    "pi": lambda design: ProportionalIntegral(design.integral_gain),
}
"""``estimator.consensus``: eq. ``DAC``
(:class:`~harness.estimators.distributed.consensus.FirstOrder`) or eq. ``PI``
(:class:`~harness.estimators.distributed.consensus.ProportionalIntegral`, gain
``integral_gain``); the first is the default.

:meta hide-value:
"""

SHARES: dict[str, Callable[[Design], Share]] = {
    "density": lambda design: ShareDensity(),
    "command": lambda design: ShareCommand(design.command_rounds),
}
"""``estimator.share``: the robots' kernels only
(:class:`~harness.estimators.distributed.share.ShareDensity`), or also the law's input
(:class:`~harness.estimators.distributed.share.ShareCommand`, ``command_rounds`` rounds of eq.
``AGREE``); the first is the default.

:meta hide-value:
"""

MESSAGES: dict[str, Callable[[Design, Grid, float], Messages]] = {
    "grid": lambda design, grid, bandwidth: GridMessages(grid),
    "band": lambda design, grid, bandwidth: BandMessages(grid, design.band_limit / bandwidth),
}
"""``estimator.messages``: grid fields
(:class:`~harness.estimators.distributed.messages.GridMessages`) or the band's coefficients
(:class:`~harness.estimators.distributed.band.BandMessages`, ``kappa_c = band_limit / h``), from
the design, the grid and the bandwidth ``h``; the first is the default.

:meta hide-value:
"""


def _default(table: Mapping[str, object]) -> str:
    """A table's default value: its first."""
    return next(iter(table))


def _choice(key: str, value: object, table: Mapping[str, object]) -> None:
    """Refuse a value that is not one of ``table``'s (:class:`ParameterError` naming
    ``key``).
    """
    known = isinstance(value, str) and value in table
    require(known, key, value, f"one of {', '.join(table)}")


@dataclass(frozen=True)
class Design:
    """The six parameters of a decentralised design, as the YAML keys of
    ``estimator=distributed`` name them; validated when made (a value that is not
    allowed raises :class:`~harness.parameters.ParameterError` naming its key).

    Attributes:
        consensus: The consensus form, a key of :data:`FORMS`: ``first_order`` (eq.
            ``DAC``) or ``pi`` (eq. ``PI``).
        integral_gain: ``k_I`` of ``pi`` in ``(0, 1)`` (``k_P = 1 - k_I^2``).
        share: What the robots agree on, a key of :data:`SHARES`: ``density`` or
            ``command`` (eq. ``AGREE``).
        command_rounds: Rounds of eq. ``AGREE`` per step (``>= 1``).
        messages: What a message carries, a key of :data:`MESSAGES`: ``grid`` or
            ``band``.
        band_limit: ``kappa_c h`` of ``band`` messages (finite, ``> 0``).
    """

    consensus: str = _default(FORMS)
    integral_gain: float = 0.5
    share: str = _default(SHARES)
    command_rounds: int = 1
    messages: str = _default(MESSAGES)
    band_limit: float = 2.5

    def __post_init__(self) -> None:
        _choice("consensus", self.consensus, FORMS)
        _choice("share", self.share, SHARES)
        _choice("messages", self.messages, MESSAGES)
        integral_gain = number("integral_gain", self.integral_gain, 0.0, strict=True)
        require(integral_gain < 1.0, "integral_gain", integral_gain, "a number in (0, 1)")
        band_limit = number("band_limit", self.band_limit, 0.0, strict=True)
        require(bool(np.isfinite(band_limit)), "band_limit", band_limit, "a finite number > 0")
        command_rounds = integer("command_rounds", self.command_rounds, 1)
        object.__setattr__(self, "integral_gain", integral_gain)
        object.__setattr__(self, "band_limit", band_limit)
        object.__setattr__(self, "command_rounds", command_rounds)

    @classmethod
    def of(cls, params: Mapping[str, Any]) -> Design:
        """The design of a component's parameters (the six keys; the others ignored,
        a missing one at its default).
        """
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in params.items() if k in names})

    def form(self) -> ConsensusForm:
        """The consensus form (:data:`FORMS`)."""
        return FORMS[self.consensus](self)

    def sharing(self) -> Share:
        """What the robots share (:data:`SHARES`)."""
        return SHARES[self.share](self)

    def carrier(self, grid: Grid, bandwidth: float) -> Messages:
        """What a message carries, for kernels of bandwidth ``h`` (length) on ``grid``
        (:data:`MESSAGES`).
        """
        return MESSAGES[self.messages](self, grid, bandwidth)
