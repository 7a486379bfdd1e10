"""The mean-field closed loop with exact estimates.

Each step of length ``dt``: the control law reads the exact density ``p`` and its
grid gradient (``p_hat = p``, ``q_hat = grad p``), and the Fokker-Planck equation
advances ``p`` under the velocity held over the step (backward Euler). This is
the loop of the paper's Theorem ``thm:exponential stability`` at the grid level;
the agent-level loop with KDE and filters builds on the same pieces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from harness.control import heat_law, paper_law
from harness.densities import Density, Target
from harness.fokker_planck import FokkerPlanck
from harness.grid import Grid
from harness.theory import lyapunov


@dataclass(frozen=True)
class MeanFieldResult:
    """Time series of a mean-field run.

    Attributes:
        t: Times (s), including 0.
        phi_l2: ``||p - p_*||`` (1 / length).
        lyapunov: ``V = 1/2 int (p - p_*)^2 / p_*`` (1 / length^2).
        mass: ``int p`` (dimensionless).
        p_final: ``p`` at the last time, ``(ny, nx)``.
    """

    t: np.ndarray
    phi_l2: np.ndarray
    lyapunov: np.ndarray
    mass: np.ndarray
    p_final: np.ndarray


def run_meanfield(
    grid: Grid,
    target: Target,
    init: Density,
    *,
    law: str = "paper",
    alpha: float = 0.003,
    sigma: float = 5e-5,
    dt: float = 0.01,
    t_final: float = 100.0,
    law_options: dict | None = None,
    progress: bool | None = None,
) -> MeanFieldResult:
    """Run the mean-field closed loop and record its errors at every step.

    Args:
        grid: The grid.
        target: Target ``p_*`` on the grid.
        init: Initial density ``p_0``.
        law: ``paper`` or ``heat``.
        alpha: Feedback gain (length^4 / s).
        sigma: Noise intensity (length^2 / s).
        dt: Step (s).
        t_final: Horizon (s).
        law_options: Extra keyword arguments of the heat law.
        progress: Show a progress bar (default: only when stderr is a terminal).

    Raises:
        harness.fokker_planck.NumericalError: if the density becomes non-finite,
            negative or loses mass.
    """
    if law not in ("paper", "heat"):
        raise ValueError(f"control.law must be 'paper' or 'heat', got {law!r}")
    if not (dt > 0 and t_final > 0):
        raise ValueError(f"need sim.dt > 0 and sim.t_final > 0, got {dt}, {t_final}")
    steps = round(t_final / dt)
    options = law_options or {}
    op = FokkerPlanck(grid, sigma)
    p = init.on_grid(grid)
    t = np.arange(steps + 1) * dt
    phi, lyap, mass = (np.empty(steps + 1) for _ in range(3))

    def record(k: int) -> None:
        phi[k] = grid.l2(p - target.p)
        lyap[k] = lyapunov(grid, p, target.p)
        mass[k] = grid.integrate(p)

    record(0)
    bar = tqdm(total=steps, disable=None if progress is None else not progress, unit="step")
    for k in range(1, steps + 1):
        q = grid.gradient(p)
        if law == "paper":
            v = paper_law(p, q, target, alpha, sigma)
        else:
            v = heat_law(p, q, target, alpha, sigma, **options)
        p = op.step(p, v, dt)
        record(k)
        if k % 100 == 0 or k == steps:
            bar.set_postfix_str(f"t={t[k]:.1f} s  ||p-p*||={phi[k]:.3e}", refresh=False)
            bar.update(k - bar.n)
    bar.close()
    return MeanFieldResult(t=t, phi_l2=phi, lyapunov=lyap, mass=mass, p_final=p)
