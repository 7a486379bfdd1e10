"""What the robots share each step: their kernels only, or also the law's input.

Dynamic average consensus (:mod:`harness.estimators.distributed.consensus`) shares the robots'
kernels; every robot then filters what it tracks. With ``estimator.share: density``
(:class:`ShareDensity`) that is all, and each robot's law reads its own filtered
estimate; with ``estimator.share: command`` (:class:`ShareCommand`) the robots then
agree on what the law reads (eq. ``AGREE``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.consensus import message_counts
from harness.estimators.distributed.messages import Messages
from harness.estimators.distributed.mixing import Mixer


class Share(Protocol):
    """What the robots share beyond their kernels: the law's input they agree on, and
    what that costs.
    """

    memory_fields: int
    """Per-robot fields of ``M`` float64 values it holds during a step (memory
    estimate)."""

    def agree(
        self, p_hat: np.ndarray, mixer: Callable[[], Mixer], messages: Messages
    ) -> np.ndarray:
        """The law's input ``(N, M)`` from the robots' filtered estimates ``p_hat``
        (``mixer()`` gives the step's ``x -> W x``).
        """
        ...

    def count(self, counts: dict[str, float], adj: sp.csr_matrix, messages: Messages) -> None:
        """Add its ``messages``, ``bytes`` and ``message_bytes`` to consensus' counts
        (:meth:`harness.estimators.distributed.estimator.RobotEstimators.communication`).
        """
        ...


class ShareDensity:
    """The robots share their kernels only (``estimator.share: density``): each law
    reads its robot's own filtered estimate.
    """

    memory_fields = 0

    def agree(
        self, p_hat: np.ndarray, mixer: Callable[[], Mixer], messages: Messages
    ) -> np.ndarray:
        """``p_hat`` itself."""
        return p_hat

    def count(self, counts: dict[str, float], adj: sp.csr_matrix, messages: Messages) -> None:
        """Nothing beyond consensus."""


class ShareCommand:
    """The robots also agree on the law's input (``estimator.share: command``):
    ``command_rounds`` rounds of static average consensus on their filtered estimates,
    started each step from each robot's own,

        p_bar(0) = p_hat,     p_bar(k + 1) = W p_bar(k),     k < m_c,             (AGREE)

    on the band's coefficients with ``messages: band`` (each robot keeps its own part
    outside the band, which the law's smoothing of the KDE barely carries). The filters
    keep their own states; only the law's input is agreed. For a law affine in ``(p_hat,
    q_hat)`` with the grid gradient, such as the paper's (eq. ``modified density
    feedback law using estimates``: ``v = -alpha grad(p_hat / p_*) + sigma grad log
    p_*``), the law of the agreed estimate is the agreed command field: ``W`` has rows
    summing to one, so ``sum_j W_ij law(p_hat_j) = law(sum_j W_ij p_hat_j)``; robots
    thus agree on the law's output without differentiating their disagreement again.
    *Error.* With ``e_i`` the robots' disagreement after the filters, ``Pi e`` the part
    off the mean, the agreed estimates' disagreement is ``W^{m_c} Pi e``, smaller by
    ``rho^{m_c}`` (``rho`` of :class:`~harness.estimators.distributed.consensus.FirstOrder`),
    and the law's ISS gain w.r.t. estimation errors applies to it as to any estimation
    error.

    Args:
        rounds: ``m_c >= 1``, rounds of eq. ``AGREE`` per step.
    """

    memory_fields = 2

    def __init__(self, rounds: int) -> None:
        if rounds < 1:
            raise ValueError(f"command rounds must be >= 1, got {rounds}")
        self.rounds = int(rounds)

    def agree(
        self, p_hat: np.ndarray, mixer: Callable[[], Mixer], messages: Messages
    ) -> np.ndarray:
        """Eq. ``AGREE``: ``rounds`` rounds of ``W`` on the robots' estimates, on
        what the messages carry of them
        (:meth:`~harness.estimators.distributed.messages.Messages.mixed`).
        """
        return messages.mixed(p_hat, mixer(), self.rounds)

    def count(self, counts: dict[str, float], adj: sp.csr_matrix, messages: Messages) -> None:
        """Eq. ``AGREE`` sends ``rounds`` messages of ``C`` values per neighbour."""
        per = messages.size
        agree = message_counts(adj, self.rounds, per)
        counts["messages"] += agree["messages"]
        counts["bytes"] += agree["bytes"]
        counts["message_bytes"] = max(counts["message_bytes"], float(8 * per))
