"""The closed loop of the paper's block diagram, one step at a time.

    robots --positions--> KDE --(p_KDE, grad p_KDE)--> estimator --(p_hat, q_hat)--> law
      ^                                                                             |
      +--------------------------- velocity field v on the grid <-------------------+
    truth: the Fokker-Planck density p advances under the same v

Step ``n -> n + 1`` (``v_n`` was computed at ``t_n`` and is held over the step):

1. the plant moves under ``v_n``: robots by Euler-Maruyama (``agents`` plant) and the
   mean-field truth ``p`` by the backward-Euler Fokker-Planck step, sharing ``A(v_n)``;
2. measure at ``t_{n+1}``: the KDE of the robots (``agents``), or, for the
   ``meanfield`` plant, the truth plus seeded Gaussian noise with the KDE's own
   variances ``k p`` and ``k_g p`` per cell (no robots);
3. the estimator predicts under ``v_n`` and updates with the measurement;
4. the control law gives ``v_{n+1}`` from ``(p_hat, q_hat)``.

Errors are measured against the mean-field truth ``p`` (notes section 5): ``Phi = p -
p_*``, ``eps = p_hat - p`` and ``eps_g = q_hat - grad p``, the states of the paper's
interconnected system (eqs. ``tracking error equation`` and ``interconnected system``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from harness.agents import Swarm
from harness.control import heat_law, paper_law
from harness.densities import Target
from harness.estimators import Estimate, Estimator, StepInput
from harness.fokker_planck import FokkerPlanck, NumericalError
from harness.grid import Grid
from harness.kde import KDE, noise_constants
from harness.theory import lyapunov
from harness.velocity import VelocityField


@dataclass(frozen=True)
class StepRecord:
    """Everything the trackers may observe after a step (or at ``t = 0``).

    ``positions`` is None for the ``meanfield`` plant; ``p_meas``/``grad_meas`` are
    the measurement the estimator saw (None for ``exact``/``injected``).
    """

    step: int
    t: float
    p_true: np.ndarray
    p_meas: np.ndarray | None
    grad_meas: np.ndarray | None
    estimate: Estimate
    velocity: VelocityField
    positions: np.ndarray | None


class ControlLaw:
    """A configured feedback law: ``(p_hat, q_hat) -> v``."""

    def __init__(self, name: str, target: Target, alpha: float, sigma: float, **options) -> None:
        if name not in ("paper", "heat"):
            raise ValueError(f"controller must be 'paper' or 'heat', got {name!r}")
        self.name, self.target, self.alpha, self.sigma = name, target, alpha, sigma
        self.options = options

    def __call__(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The velocity field for the estimates."""
        if self.name == "paper":
            return paper_law(p_hat, q_hat, self.target, self.alpha, self.sigma)
        return heat_law(p_hat, q_hat, self.target, self.alpha, self.sigma, **self.options)


class ClosedLoop:
    """Plant, measurement, estimator and law, advanced by :meth:`step`.

    Args:
        grid: The grid.
        target: Target ``p_*``.
        p0: Initial mean-field density on the grid.
        estimator: The estimator.
        law: The control law.
        sigma: Noise intensity (length^2 / s).
        dt: Step (s).
        rng: The run's random generator (robots, synthetic noise).
        swarm: Robots (``agents`` plant) or None (``meanfield`` plant).
        kde: KDE (``agents`` plant).
        n_robots, bandwidth: Used for the synthetic noise of the ``meanfield`` plant.
    """

    def __init__(
        self,
        grid: Grid,
        target: Target,
        p0: np.ndarray,
        estimator: Estimator,
        law: ControlLaw,
        sigma: float,
        dt: float,
        rng: np.random.Generator,
        swarm: Swarm | None = None,
        kde: KDE | None = None,
        n_robots: int = 1024,
        bandwidth: float = 0.04,
    ) -> None:
        if swarm is not None and kde is None:
            raise ValueError("the agents plant needs a KDE")
        self.grid, self.target, self.estimator, self.law = grid, target, estimator, law
        self.sigma, self.dt, self.rng = sigma, dt, rng
        self.swarm, self.kde = swarm, kde
        self.noise_k = noise_constants(n_robots, bandwidth)
        self.truth = FokkerPlanck(grid, sigma)
        self.p = np.array(p0, dtype=float)
        self.mass0 = self.grid.integrate(self.p)
        self.mass_drift = 1e-6
        self.n = 0
        self.v: VelocityField | None = None

    @property
    def t(self) -> float:
        """Current time ``n dt`` (s)."""
        return self.n * self.dt

    def _measure(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        if not self.estimator.uses_kde:
            return None, None
        if self.swarm is not None:
            assert self.kde is not None
            return self.kde(self.swarm.positions)
        k, k_g = self.noise_k
        sd = np.sqrt(np.maximum(self.p, 0.0))
        p_meas = self.p + np.sqrt(k) * sd * self.rng.standard_normal(self.grid.shape)
        grad = self.grid.gradient(self.p)
        grad_meas = grad + np.sqrt(k_g) * sd * self.rng.standard_normal((2, *self.grid.shape))
        return p_meas, grad_meas

    def _control(self, est: Estimate) -> VelocityField:
        if not (np.isfinite(est.p_hat).all() and np.isfinite(est.q_hat).all()):
            raise NumericalError("the estimate became non-finite")
        v = self.law(est.p_hat, est.q_hat)
        if not v.is_finite():
            raise NumericalError("the velocity field became non-finite")
        return v

    def start(self) -> StepRecord:
        """Measure and estimate at ``t = 0`` and compute ``v_0``."""
        p_meas, grad_meas = self._measure()
        est = self.estimator.initialize(
            StepInput(0.0, p_meas, grad_meas, None, None, self.p)  # type: ignore[arg-type]
        )
        self.v = self._control(est)
        return self._record(p_meas, grad_meas, est)

    def step(self) -> StepRecord:
        """Advance by one step (see the module docstring)."""
        assert self.v is not None, "call start first"
        v = self.v
        a = self.truth.matrix(v)
        if self.swarm is not None:
            self.swarm.step(v, self.dt, self.rng)
        self.p = self.truth.step(self.p, v, self.dt, a)
        mass = self.grid.integrate(self.p)
        if abs(mass - self.mass0) > self.mass_drift * self.mass0:
            raise NumericalError(f"mass drifted from {self.mass0:.15g} to {mass:.15g}")
        self.n += 1
        p_meas, grad_meas = self._measure()
        est = self.estimator.step(
            StepInput(self.t, p_meas, grad_meas, v, a, self.p)  # type: ignore[arg-type]
        )
        self.v = self._control(est)
        return self._record(p_meas, grad_meas, est)

    def _record(self, p_meas, grad_meas, est: Estimate) -> StepRecord:
        assert self.v is not None
        return StepRecord(
            step=self.n,
            t=self.t,
            p_true=self.p,
            p_meas=p_meas,
            grad_meas=grad_meas,
            estimate=est,
            velocity=self.v,
            positions=None if self.swarm is None else self.swarm.positions,
        )


def metrics(grid: Grid, target: Target, rec: StepRecord) -> dict[str, float | None]:
    """The per-step metrics (all L2 norms are :meth:`Grid.l2`):

    ``t`` (s); ``phi_l2`` = ``||p - p_*||`` and ``phat_target_l2`` = ``||p_hat - p_*||``
    (1 / length); ``eps_l2`` = ``||p_hat - p||`` (1 / length); ``eps_g_l2`` =
    ``||q_hat - G p||`` (1 / length^2); ``kde_l2`` = ``||p_KDE - p||`` (1 / length, None
    without a measurement); ``lyapunov`` = ``1/2 int (p - p_*)^2 / p_*`` (1 /
    length^2); ``mass`` = ``int p`` (1); ``trace_P``, ``trace_Q`` (density filter, 1 /
    length^2) and ``trace_P_grad``, ``trace_Q_grad`` (gradient filter, 1 / length^4),
    None without filters.
    """
    est = rec.estimate
    p = rec.p_true
    return {
        "t": rec.t,
        "phi_l2": grid.l2(p - target.p),
        "phat_target_l2": grid.l2(est.p_hat - target.p),
        "eps_l2": grid.l2(est.p_hat - p),
        "eps_g_l2": grid.l2(est.q_hat - grid.gradient(p)),
        "kde_l2": None if rec.p_meas is None else grid.l2(rec.p_meas - p),
        "lyapunov": lyapunov(grid, p, target.p),
        "mass": grid.integrate(p),
        "trace_P": est.trace_P,
        "trace_Q": est.trace_Q,
        "trace_P_grad": est.trace_P_grad,
        "trace_Q_grad": est.trace_Q_grad,
    }
