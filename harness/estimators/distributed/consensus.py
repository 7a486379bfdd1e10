"""Dynamic average consensus: every robot tracks the swarm's KDE from its own kernel.

The KDE is the mean of the robots' kernels ``phi_i``
(:mod:`harness.estimators.distributed.robot_kde`), so each robot can track it from its own
kernel and messages from its neighbours in the communication graph
(:mod:`harness.estimators.distributed.graph`: adjacency ``A``, Laplacian ``L``, eigenvalues
``0 = lambda_1 <= lambda_2 <= ... <= lambda_N``); Zheng and Lin, arXiv 2009.05366 /
2106.05318.

Each robot keeps ``z_i`` (a field of ``M`` cells, its estimate of the KDE), adds its own
kernel's change every step and runs ``m`` rounds of ``W_t = I - eps_t L_t`` with its
neighbours, in one of two forms (``estimator.consensus``, one interface,
:class:`ConsensusForm`): :class:`FirstOrder` (eq. ``DAC``, the first-order form) or
:class:`ProportionalIntegral` (eq. ``PI``, a second state per robot that integrates the
disagreement). Their equations, error dynamics and stability are in their docstrings;
what they share is here.

*Invariant.* ``L`` is symmetric with zero row and column sums, so ``1^T W = 1^T`` for
every graph and gain: under eq. ``DAC``, ``1^T z(t + 1) = 1^T z(t) + 1^T phi(t + 1) -
1^T phi(t)``, and by induction from ``1^T z(0) = 1^T phi(0)``,

    (1/N) sum_i z_i(t) = (1/N) sum_i phi_i(t) = p_KDE(t)     at every step, exactly,

whatever the graph does (it may change, disconnect, reconnect). The robots' mean
observation is the centralised one; consensus only distributes it. The PI form keeps
it too (:class:`ProportionalIntegral`).

*Gain* and the product ``W z``: :mod:`harness.estimators.distributed.mixing`.

Messages. A *message* is what one robot sends one neighbour in one exchange: ``C``
float64 values per field, ``C = M`` grid values or ``C = K`` band coefficients
(``estimator.messages``, :mod:`harness.estimators.distributed.messages`,
:mod:`harness.estimators.distributed.band`). Per robot per step the first-order form sends
``m deg_i`` messages of ``C`` values, the PI form ``2 m deg_i`` messages (``(v, w)`` of
``2 C`` values, then ``z'`` of ``C``); :func:`message_counts` reports the means over
robots (with a broadcast medium one transmission per exchange would do).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from harness.estimators.distributed.messages import GridMessages, KernelFactors, Messages
from harness.estimators.distributed.mixing import Mixer, mixer
from harness.estimators.distributed.robot_kde import kernel_factors
from harness.grid import Grid


class RobotKernels(Protocol):
    """The robots' kernels other than the square's separable ones (on free space,
    :class:`harness.estimators.distributed.free_space.FreeRobotKernels`).
    """

    def __call__(self, positions: np.ndarray) -> KernelFactors:
        """What the messages need of the robots' kernels at ``positions`` ``(2, N)``."""
        ...

    def kde(self, factors: KernelFactors) -> tuple[np.ndarray, np.ndarray]:
        """The centralised KDE the kernels average to, ``(p, grad p)``."""
        ...


class ConsensusForm(ABC):
    """How a step's rounds move the robots' states: the interface of :class:`FirstOrder`
    and :class:`ProportionalIntegral`, which :class:`DynamicAverageConsensus` runs.
    """

    exchanges = 1
    """Messages per neighbour per round."""

    fields_per_round = 1
    """Fields of ``C`` values a robot sends one neighbour per round."""

    largest_message = 1
    """Fields of ``C`` values in the largest message."""

    memory_fields = 0
    """Per-robot fields of ``M`` float64 values beyond the first-order form's (the
    integral state and a round's temporaries; memory estimate)."""

    def integral(self, z: np.ndarray) -> np.ndarray | None:
        """The second state's start ``w(0)`` for states ``z`` (None: there is none)."""
        return None

    @abstractmethod
    def add_input(
        self, z: np.ndarray, messages: Messages, factors: KernelFactors, old: KernelFactors
    ) -> np.ndarray | None:
        """The step's input change ``phi(t + 1) - phi(t)`` (in what ``messages``
        carry): added to ``z`` in place (None returned), or returned to be spread over
        the rounds.
        """

    @abstractmethod
    def run(
        self, c: DynamicAverageConsensus, mix: Mixer, rounds: int, delta: np.ndarray | None
    ) -> None:
        """Add the input's change ``delta`` to ``c``'s states and run ``rounds`` rounds
        (``delta`` None: :meth:`add_input` added it already).
        """

    @abstractmethod
    def reference(
        self,
        w: sp.csr_matrix,
        z: np.ndarray,
        delta: np.ndarray,
        rounds: int,
        integral: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Plain statement (scipy) of a step from ``(z, integral)`` with the input's
        change ``delta``: the new ``(z, w)``.
        """


class FirstOrder(ConsensusForm):
    """Dynamic average consensus, first-order form (``estimator.consensus:
    first_order``). Each robot keeps ``z_i`` (a field of ``M`` cells, its estimate of
    the KDE). With ``W_t = I - eps_t L_t`` and ``m`` rounds per step,

        z_i(0)     = [W_0^{m_0} phi(0)]_i,
        z(t + 1)   = W_{t+1}^m ( z(t) + phi(t + 1) - phi(t) )                          (DAC)

    (rows are robots; ``phi(t)`` the ``N x M`` matrix of the robots' kernels at ``X(t)``;
    ``m_0`` the ``initial_rounds``, by default ``m``: with ``m_0 >> 1`` the robots agree
    before they start moving). Robot ``i`` needs ``z_j`` of its neighbours once per round:
    one message of ``M`` floats per neighbour per round.

    *Error dynamics.* Let ``Pi = I - 1 1^T / N`` and ``e = Pi z`` the disagreement
    (``z_i - p_KDE``). ``Pi`` commutes with ``W`` (both are polynomials in symmetric,
    constant-preserving operators), so

        e(t + 1) = W^m ( e(t) + Pi (phi(t + 1) - phi(t)) ),
        ||e(t + 1)|| <= rho^m ( ||e(t)|| + ||Pi Delta phi|| ),
        rho = max(|1 - eps lambda_2|, |1 - eps lambda_N|)            (spectral radius on 1^perp).

    On a fixed connected graph with a static swarm the error decays geometrically at the
    rate ``rho^m`` per step, which is ``(1 - eps lambda_2)^m`` whenever ``eps (lambda_2 +
    lambda_N) <= 2`` (always true for the default gain, *Gain* of
    :mod:`~harness.estimators.distributed.mixing`, when the graph is not bipartite-like;
    the test uses a ring and checks both). With
    moving robots the error is input-to-state stable with respect to the kernels'
    per-step change: asymptotically ``||e|| <= rho^m / (1 - rho^m) sup ||Pi Delta
    phi||``. Robots move ``~ 1e-3`` per step against a bandwidth ``h = 0.04``, so ``Delta
    phi`` is small and one round per step already tracks; the disconnected case
    (``lambda_2 = 0``) keeps the component averages instead (each component tracks the
    mean over its members).
    """

    def add_input(
        self, z: np.ndarray, messages: Messages, factors: KernelFactors, old: KernelFactors
    ) -> None:
        """Straight into ``z`` (on grid fields without an ``N M`` temporary)."""
        messages.add_increment(z, factors, old)

    def run(
        self, c: DynamicAverageConsensus, mix: Mixer, rounds: int, delta: np.ndarray | None
    ) -> None:
        """Eq. ``DAC``: ``z <- W^m (z + delta)``."""
        assert c.z is not None and c.buffer is not None
        if delta is not None:
            c.z += delta
        for _ in range(rounds):
            mix(c.z, c.buffer)
            c.z, c.buffer = c.buffer, c.z

    def reference(
        self,
        w: sp.csr_matrix,
        z: np.ndarray,
        delta: np.ndarray,
        rounds: int,
        integral: np.ndarray | None,
    ) -> tuple[np.ndarray, None]:
        """``W^m (z + delta)``, and no second state."""
        out = z + delta
        for _ in range(rounds):
            out = w @ out
        return out, None


class ProportionalIntegral(ConsensusForm):
    """Dynamic average consensus, proportional-integral form (``estimator.consensus:
    pi``; Freeman, Yang and Lynch, "Stability and convergence properties of dynamic
    average consensus estimators", CDC 2006, in the input-difference form of Kia et al.,
    "Tutorial on dynamic average consensus", IEEE Control Systems 39(3), 2019). A second
    state ``w`` per robot (same shape as ``z``, ``w(0) = 0``) integrates the
    disagreement. With ``L_eps = eps L = I - W`` and gains ``k_P``, ``k_I``, each step
    adds the input's change and runs ``m`` rounds of

        v       = z + (phi(t + 1) - phi(t)) / m      (the input's change, split over the rounds)
        z'      = v - k_P L_eps v - k_I L_eps w                                          (PI)
        w'      = w + k_I L_eps z'

    ``1^T L_eps = 0``, so ``1^T z`` changes only by the input's change: the invariant of
    the module docstring holds as for the first-order form (with one round per step, the
    PI form with ``k_I = 0``, ``k_P = 1`` is it). *Ramps.* For a constant input change
    ``phi(t + 1) - phi(t) = c`` (robots moving at constant velocity, to first order) the
    first-order form settles at the lag ``e_* = (I - W^m)^+ W^m Pi c``, which the smallest
    eigenvalues of ``L`` amplify as ``1 / (m eps lambda_2)``. In the PI form every round
    of a step is then the same affine map (each adds ``c / m``), and its fixed point needs
    ``w' = w``, i.e. ``L_eps z' = 0``: the robots agree after every round (``e = 0``), and
    ``k_I L_eps w = (I - k_P L_eps) Pi c / m`` absorbs the ramp. So the PI form tracks a
    ramp with zero steady error (tested against the first-order lag formula). *Stability.*
    On the eigenvector of ``L_eps`` with eigenvalue ``mu`` in ``(0, 2)`` one round maps
    ``(e, w)`` by ``[[1 - a, -b], [b (1 - a), 1 - b^2]]`` with ``a = k_P mu``, ``b = k_I
    mu``: determinant ``1 - a``, trace ``2 - a - b^2``. Both eigenvalues lie inside the
    unit circle (Jury) iff ``|1 - a| < 1`` and ``b^2 < 4 - 2 a``, true for every ``mu <
    2`` when ``0 < k_P <= 1`` and ``k_I^2 <= 1 - k_P``. The harness sets ``k_P = 1 -
    k_I^2`` with ``k_I = estimator.integral_gain`` in ``(0, 1)`` (default 0.5, ``k_P =
    0.75``): stable on every *fixed* graph the gain rule (*Gain* of
    :mod:`~harness.estimators.distributed.mixing`) admits. The graph of the loop changes
    every step, and the round map is not a contraction (its largest singular value is 1.14
    at ``k_I = 0.5``), so stability under switching is not proved by this; random
    switching radius graphs stayed stable in simulation. For small ``mu`` the two rates
    per round are about ``k_P mu`` and ``k_I^2 mu / k_P``. *ISS* (fixed graph). The error
    ``(e, w)`` obeys a stable linear recursion driven by ``Pi Delta phi``, so it is
    bounded by a constant times ``sup ||Pi (Delta phi - Delta phi_prev)||`` (the input's
    change of change) plus a decaying transient: a constant drift costs nothing, but white
    increments (the robots' noise) cost more than in the first-order form, about 1.3 to 2
    times its variance per mode at ``k_I = 0.5`` (from ``mu -> 0`` to ``mu = 0.5``),
    because the slow mode keeps them longer. *Cost.* A round needs two exchanges: ``(v,
    w)`` to compute ``z'``, then ``z'`` to update ``w``; three fields per neighbour per
    round against one.

    Args:
        integral_gain: ``k_I`` in ``(0, 1)`` (``k_P = 1 - k_I^2``).
    """

    exchanges = 2
    fields_per_round = 3
    largest_message = 2
    memory_fields = 6

    def __init__(self, integral_gain: float = 0.5) -> None:
        if not 0 < integral_gain < 1:
            raise ValueError(f"integral gain must be in (0, 1), got {integral_gain}")
        self.k_i = float(integral_gain)
        self.k_p = 1.0 - self.k_i**2

    def integral(self, z: np.ndarray) -> np.ndarray:
        """``w(0) = 0``."""
        return np.zeros_like(z)

    def add_input(
        self, z: np.ndarray, messages: Messages, factors: KernelFactors, old: KernelFactors
    ) -> np.ndarray:
        """The input's change, spread over the rounds by :meth:`run`."""
        return messages.increment(factors, old)

    def run(
        self, c: DynamicAverageConsensus, mix: Mixer, rounds: int, delta: np.ndarray | None
    ) -> None:
        """Eq. ``PI`` with ``delta / m`` added before each round (so that every round of
        a step is the same map under a ramp, and its fixed point agrees after every
        round; the whole change is in ``z`` by the step's end).
        """
        assert c.z is not None and c.w is not None and delta is not None
        if rounds == 0:
            c.z += delta
            return
        cols = c.columns
        for _ in range(rounds):
            v = c.z + delta / rounds
            both = mix(np.concatenate([v, c.w], axis=1))  # exchange (v, w)
            # z' = v - k_P L_eps v - k_I L_eps w,  with L_eps x = x - W x
            z_new = v - self.k_p * (v - both[:, :cols]) - self.k_i * (c.w - both[:, cols:])
            # w' = w + k_I L_eps z'  (exchange z')
            c.w = c.w + self.k_i * (z_new - mix(z_new))
            c.z = z_new

    def reference(
        self,
        w: sp.csr_matrix,
        z: np.ndarray,
        delta: np.ndarray,
        rounds: int,
        integral: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``m`` rounds of eq. ``PI`` from ``(z, integral)`` (``integral`` None: zero)
        with ``delta / m`` added before each.
        """
        out, acc = z, (np.zeros_like(z) if integral is None else integral)

        def lap(x: np.ndarray) -> np.ndarray:
            return x - w @ x

        for _ in range(rounds):
            v = out + delta / rounds
            out_new = v - self.k_p * lap(v) - self.k_i * lap(acc)
            acc = acc + self.k_i * lap(out_new)
            out = out_new
        return out, acc


class DynamicAverageConsensus:
    """Dynamic average consensus on the robots' kernels in a form (:class:`FirstOrder`,
    eq. ``DAC``, or :class:`ProportionalIntegral`, eq. ``PI``), on what the messages
    carry (:mod:`harness.estimators.distributed.messages`: grid fields or the band's
    coefficients).

    State ``z`` of shape ``(N, C)``: ``C = M`` grid values, or ``C = K`` band
    coefficients; the PI form keeps ``w`` of the same shape (None otherwise). The form
    (:meth:`ConsensusForm.run`) moves ``z`` and ``w``, and may swap ``z`` with
    ``buffer``, a spare array of ``z``'s shape.

    Args:
        grid: The grid.
        bandwidth: Kernel bandwidth ``h`` (length).
        rounds: Consensus rounds per step ``m >= 1``.
        gain: ``eps = gain / (1 + d_max)``, ``0 < gain <= 1``.
        initial_rounds: Rounds ``m_0 >= 0`` at ``t = 0``, before the first estimate:
            ``z(0) = W_0^{m_0} phi(0)`` (default ``m``). With one round per step each
            robot's first estimate is nearly its own kernel; ``m_0`` rounds bring the
            disagreement down by ``rho^{m_0}`` before the robots start moving.
        chunk: Robots per chunk of the neighbour-sum product
            (:func:`~harness.estimators.distributed.mixing.mixer`).
        form: The form (default :class:`FirstOrder`).
        messages: What a message carries (default grid fields,
            :class:`~harness.estimators.distributed.messages.GridMessages`).
        kernels: The robots' kernels (default the square's Gaussian with wall images,
            :func:`~harness.estimators.distributed.robot_kde.kernel_factors`; on free
            space :class:`~harness.estimators.distributed.free_space.FreeRobotKernels`).
    """

    def __init__(
        self,
        grid: Grid,
        bandwidth: float,
        rounds: int = 1,
        gain: float = 1.0,
        initial_rounds: int | None = None,
        chunk: int = 64,
        form: ConsensusForm | None = None,
        messages: Messages | None = None,
        kernels: RobotKernels | None = None,
    ) -> None:
        if rounds < 1:
            raise ValueError(f"consensus rounds must be >= 1, got {rounds}")
        initial_rounds = rounds if initial_rounds is None else int(initial_rounds)
        if initial_rounds < 0:
            raise ValueError(f"initial rounds must be >= 0, got {initial_rounds}")
        self.grid, self.bandwidth = grid, bandwidth
        self.rounds, self.gain = int(rounds), gain
        self.initial_rounds, self.chunk = initial_rounds, int(chunk)
        self.form = FirstOrder() if form is None else form
        self.messages = GridMessages(grid) if messages is None else messages
        self.kernels = kernels
        self.columns = self.messages.size
        self.z: np.ndarray | None = None
        self.w: np.ndarray | None = None
        self.buffer: np.ndarray | None = None
        self._factors: KernelFactors | None = None
        self.eps = 0.0

    @property
    def exchanges(self) -> int:
        """Exchanges per round: 1 (first order) or 2 (PI: ``(v, w)``, then ``z'``)."""
        return self.form.exchanges

    @property
    def floats_per_round(self) -> int:
        """Float64 values a robot sends one neighbour per round: ``C`` or ``3 C``."""
        return self.form.fields_per_round * self.columns

    @property
    def message_bytes(self) -> int:
        """Bytes of the largest message: ``8 C`` (first order) or ``16 C`` (PI)."""
        return 8 * self.columns * self.form.largest_message

    def mixer(self, w: sp.csr_matrix, positions: np.ndarray) -> Mixer:
        """``x -> W x`` for the robots at ``positions``
        (:func:`harness.estimators.distributed.mixing.mixer`).
        """
        return mixer(w, positions, self.chunk)

    def _mix(
        self, w: sp.csr_matrix, rounds: int, positions: np.ndarray, delta: np.ndarray | None
    ) -> None:
        """Add the input's change ``delta`` and run ``rounds`` rounds of the form
        (:meth:`ConsensusForm.run`).
        """
        self.form.run(self, self.mixer(w, positions), rounds, delta)

    def _kernel_factors(self, positions: np.ndarray) -> KernelFactors:
        """The robots' kernels at ``positions`` as the messages take them."""
        if self.kernels is not None:
            return self.kernels(positions)
        return kernel_factors(self.grid, positions, self.bandwidth)

    def kde(self) -> tuple[np.ndarray, np.ndarray]:
        """The exact KDE of the current positions, ``(p, grad p)`` of shapes ``(ny, nx)``
        and ``(2, ny, nx)``: the mean of the robots' kernels, from the factors the last
        step computed (:meth:`harness.estimators.kde.KDE.exact` without evaluating them again).
        """
        assert self._factors is not None, "call initialize first"
        if self.kernels is not None:
            return self.kernels.kde(self._factors)
        kx, dkx, ky, dky = self._factors
        n = kx.shape[0]
        return ky.T @ kx / n, np.stack([ky.T @ dkx / n, dky.T @ kx / n])

    def observation(self) -> np.ndarray:
        """What each robot's filter observes, ``(N, M)`` grid fields: ``z`` itself, or
        the band-limited fields ``Pi F_i`` its coefficients stand for.
        """
        assert self.z is not None, "call initialize first"
        return self.messages.fields(self.z)

    def initialize(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """``z(0) = W^{m_0} phi(0)`` (``m_0`` initial rounds of the form; ``w(0) = 0``);
        returns the robots' observations (:meth:`observation`).
        """
        n = positions.shape[1]
        self.z = np.zeros((n, self.columns))
        self.w = self.form.integral(self.z)
        self.buffer = np.empty_like(self.z)
        self._factors = self._kernel_factors(positions)
        self._mix(w, self.initial_rounds, positions, self.messages.increment(self._factors, None))
        return self.observation()

    def step(self, positions: np.ndarray, w: sp.csr_matrix) -> np.ndarray:
        """Add the kernels' change, then ``m`` rounds; returns the observations."""
        assert self.z is not None and self._factors is not None, "call initialize first"
        factors = self._kernel_factors(positions)
        delta = self.form.add_input(self.z, self.messages, factors, self._factors)
        self._factors = factors
        self._mix(w, self.rounds, positions, delta)
        return self.observation()

    def reference_step(
        self,
        z: np.ndarray,
        phi_new: np.ndarray,
        phi_old: np.ndarray,
        w: sp.csr_matrix,
        integral: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Plain statement of :meth:`step` (scipy): ``W^m (z + phi_new - phi_old)``, or
        ``m`` rounds of eq. ``PI`` from ``(z, integral)`` with ``(phi_new - phi_old) / m``
        added before each; returns ``(z, w)`` (``w`` None for the first-order form).
        """
        return self.form.reference(w, z, phi_new - phi_old, self.rounds, integral)


def message_counts(
    adj: sp.csr_matrix, rounds: int, floats_per_round: int, exchanges: int = 1
) -> dict[str, float]:
    """Communication per robot per step (means over robots; see the module docstring).

    Args:
        adj: The step's communication graph.
        rounds: Rounds per step.
        floats_per_round: Float64 values a robot sends one neighbour in one round.
        exchanges: Messages per neighbour per round.

    Returns:
        ``messages`` (messages / robot / step), ``floats`` (float64 values / robot /
        step), ``bytes`` (bytes / robot / step) and ``mean_degree``.
    """
    deg = float(adj.nnz) / adj.shape[0]
    return {
        "messages": rounds * exchanges * deg,
        "floats": rounds * deg * floats_per_round,
        "bytes": 8.0 * rounds * deg * floats_per_round,
        "mean_degree": deg,
    }
