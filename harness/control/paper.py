"""``control=paper``: the paper's law, eq. ``modified density feedback law using
estimates``,

    v = -alpha (p_* q_hat - p_hat grad p_*) / p_*^2 + sigma grad p_* / p_*,

as a field law (:mod:`harness.control.field`): :func:`paper_law` holds the equation on
the grid's faces, :func:`paper_law_reference` states it plainly, and
:class:`PaperControl` is the component, with the debiased comparison (``kde.debias``)
and the feedforward of a moving target.
"""

from __future__ import annotations

import numpy as np

from harness.compiled.control import paper_velocity
from harness.control.field import (
    FieldLaw,
    check_gains,
    no_flux_into_obstacles,
    positive_on_blocked,
)
from harness.estimators.smoothing import smoothed_target
from harness.parameters import flag, number, speed_cap
from harness.targets.densities import Target
from harness.targets.feedforward import NeumannPoisson, feedforward
from harness.velocity import VelocityField, centres_to_face_x, centres_to_face_y


def paper_law(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    alpha: float,
    sigma: float,
    feedback_target: Target | None = None,
) -> VelocityField:
    """The paper's law with estimates (eq. ``modified density feedback law using
    estimates``):

        v = -alpha (p_* q_hat - p_hat grad p_*) / p_*^2 + sigma grad p_* / p_*.

    With exact estimates it equals eq. ``modified density feedback law 1``,
    ``v = -alpha grad(p / p_*) + sigma grad p_* / p_*``, and the closed loop is
    ``d_t p = div((alpha p + sigma p_*) grad(p / p_*))``. ``p_hat`` never appears in
    a denominator. Compiled (:func:`harness.compiled.control.paper_velocity`, one pass, the same
    bits as the numpy statement :func:`paper_law_reference`).

    Discretisation. Cell centres take the formula above. On the faces, the
    feedback term is the mean of its two neighbouring centre values, and the
    drift ``sigma grad p_* / p_* = sigma grad log p_*`` is the face difference
    ``sigma (log p*_R - log p*_L) / h``. With the Scharfetter-Gummel fluxes of
    :mod:`harness.fokker_planck` this makes ``p_*`` an exact discrete steady state
    for ``alpha = 0``, and for every ``alpha`` when ``p_hat = p_*`` and ``q_hat``
    is the grid gradient of ``p_*``.

    ``feedback_target`` (default ``target``) replaces ``p_*`` in the feedback term only;
    the debiased law passes the smoothed target ``K_h * p_*`` there (see
    :class:`PaperControl`).

    Free space (``target.free``, a domain with obstacles). The same statements on the
    free cells and open faces; centre values are 0 on blocked cells and face values 0
    on closed faces (:func:`harness.control.field.no_flux_into_obstacles`), where the
    Fokker-Planck operator carries no flux either. ``target.grad`` is
    :meth:`harness.domains.base.FreeSpace.gradient` (a closed face reflects as a
    wall does), so with ``p_hat = p_*`` and ``q_hat = free.gradient(p_*)`` the
    feedback term is 0 on every free cell (the two products are the same numbers),
    and the face drift makes every open face's flux of ``p_*`` vanish: ``p_*`` is the
    exact discrete steady state on the masked grid, as on the rectangle.
    """
    check_gains(alpha, sigma)
    g = target.grid
    f = target if feedback_target is None else feedback_target
    p_hat, q_hat = np.asarray(p_hat), np.asarray(q_hat)
    if p_hat.shape != g.shape or q_hat.shape != (2, *g.shape):
        raise ValueError(
            f"estimates of shapes {p_hat.shape} and {q_hat.shape} do not fit the grid "
            f"{g.shape} (p_hat (ny, nx), q_hat (2, ny, nx))"
        )
    free = target.free
    centres, face_x, face_y = paper_velocity(
        np.ascontiguousarray(p_hat, dtype=float), np.ascontiguousarray(q_hat, dtype=float),
        positive_on_blocked(f.p, free), f.grad, positive_on_blocked(target.p, free),
        target.grad, target.log_p, float(alpha), float(sigma), g.dx, g.dy,
    )  # fmt: skip
    return no_flux_into_obstacles(VelocityField(centres, face_x, face_y), free)


def paper_law_reference(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    alpha: float,
    sigma: float,
    feedback_target: Target | None = None,
) -> VelocityField:
    """Numpy statement of :func:`paper_law` (which is compiled,
    :func:`harness.compiled.control.paper_velocity`; the same bits).
    """
    check_gains(alpha, sigma)
    g = target.grid
    f = target if feedback_target is None else feedback_target
    free = target.free
    fp, tp = positive_on_blocked(f.p, free), positive_on_blocked(target.p, free)
    feedback = -alpha * (fp * q_hat - p_hat * f.grad) / fp**2
    drift = sigma * target.grad / tp
    centres = feedback + drift
    face_x = centres_to_face_x(feedback[0]) + sigma * np.diff(target.log_p, axis=1) / g.dx
    face_y = centres_to_face_y(feedback[1]) + sigma * np.diff(target.log_p, axis=0) / g.dy
    return no_flux_into_obstacles(VelocityField(centres, face_x, face_y), free)


class PaperControl(FieldLaw):
    """The paper's law (``control=paper``), :func:`paper_law` with fixed gains.

    Source: Zheng, Han, Lin, "Feedback interconnected mean-field density estimation and
    control" (arXiv 2106.00899), eq. ``modified density feedback law using
    estimates``. Inputs: the density and gradient estimates and the target;
    no estimate in a denominator (only ``p_*``). Globally ISS in L2 with respect to
    the estimation errors (Theorem ``thm:ISS``); fixed point ``p_*`` with the noise
    (the drift ``sigma grad log p_*`` is the compensation).

    Debiased law (``kde.debias=true``). The KDE measures ``p~ = K_h * p``, the density
    smoothed by its kernel, and the filters (measurement operator ``H = I``) estimate
    that; with ``p_hat = p~`` the paper's law drives the swarm until ``p~ = p_*``, i.e.
    to the sharpened ``p = K_h^{-1} p_*``. The debiased law compares the estimates with
    what they estimate, the smoothed target ``p~_* = K_h * p_*``
    (:func:`harness.estimators.smoothing.smoothed_target`), in the feedback term only:

        v = -alpha (p~_* q_hat - p_hat grad p~_*) / p~_*^2 + sigma grad p_* / p_*.

    Fixed point: with ``p_hat = p~`` and ``q_hat = grad p~`` the zero-flux condition is
    ``alpha p grad(p~ / p~_*) + sigma p_* grad(p / p_*) = 0``; at ``p = p_*`` both
    terms vanish, so the robots' distribution at the fixed point is ``p_*`` itself; and
    a fixed point with ``p~ = p~_*`` has ``p = p_*`` because ``K_h`` is injective (it
    multiplies each Neumann cosine mode by ``exp(-k^2 h^2 / 2) > 0``). On the grid,
    ``p_hat = p~_*``, ``q_hat = G p~_*`` make the feedback term vanish exactly and the
    face drift keeps ``p_*`` the exact steady state.

    ISS (Theorem ``thm:ISS``). With ``eps~ = p_hat - p~`` and ``eps~_g = q_hat - grad
    p~``, ``dV/dt`` for ``V = 1/2 int (p - p_*)^2 / p_*`` keeps the paper's error term
    with ``p~_*`` in place of ``p_*`` (weights bounded since ``p~_* >= min p_*``), but
    the alpha dissipation becomes the cross form ``-alpha int p grad(p / p_*) .
    grad(p~ / p~_*)``, which is not a square. If it is at least ``-(1 - c) sigma int
    p_* |grad(p / p_*)|^2`` for some ``c in (0, 1]`` (condition (C)), the paper's proof
    goes through with ``alpha_1 + alpha_2`` replaced by ``c alpha_2``: ISS w.r.t.
    ``||eps~||``, ``||eps~_g||`` with a larger gain and a guaranteed rate ``c sigma
    lambda`` instead of ``(alpha + sigma) lambda``. (C) holds with ``c = 1`` near a
    uniform target; for the default target the linearised certificate gives ``c =
    0.063`` at the paper's gains (``docs/debias.md``, ``python -m
    benchmarks.debias_check --certificate``). What the debiased law gives up is the
    guarantee on modes below the kernel's scale, which the KDE cannot see anyway.

    Moving target (``target=moving``): the law at ``p_*(t)``, plus with ``feedforward``
    the velocity ``w`` of :meth:`feedforward_field` (its docstring derives what it does
    to the closed loop and to the ISS argument).

    Args:
        target: The target on the grid (run-time argument).
        alpha: Feedback gain ``>= 0`` (length^4 / s).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s), for the drift term.
        debias: Compare the estimates with ``K_h * p_*`` in the feedback term.
        bandwidth: The KDE's bandwidth ``h`` (length), for ``debias``.
        mirror: The KDE's wall images, for ``debias``.
        v_max: Speed cap (length / s), or None.
        feedforward: Add the feedforward ``w`` for a moving target (no effect on a
            static one).
    """

    free_space = True  # no flux through closed faces, p_* kept (tests/test_field_laws_domains.py)

    def __init__(
        self,
        target: Target,
        alpha: float,
        sigma: float,
        debias: bool = False,
        bandwidth: float | None = None,
        mirror: bool = True,
        v_max: float | None = None,
        feedforward: bool = False,
    ) -> None:
        self.target = target
        self.alpha = number("alpha", alpha, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self._debias = (debias, bandwidth, mirror)
        self.feedback_target = feedback_target(target, debias, bandwidth, mirror)
        self.v_max = speed_cap(v_max)
        self.feedforward = flag("feedforward", feedforward)
        self._poisson: NeumannPoisson | None = None

    def retarget(self, target: Target) -> None:
        """``target`` and its feedback target (smoothed again when debiased)."""
        self.target = target
        self.feedback_target = feedback_target(target, *self._debias)

    def feedforward_field(self, target: Target, rate: np.ndarray) -> VelocityField | None:
        """The feedforward ``w`` for ``p_*(t) = target`` moving at ``d_t p_* = rate``
        (length / s), None unless ``feedforward``:

            div(p_* w) = -d_t p_*,   (p_* w) . n = 0 on the walls,

        solved as ``p_* w = grad phi``, ``Laplacian phi = -d_t p_*`` with Neumann walls
        and zero mean (compatible because ``int d_t p_* = 0``), on the grid with the
        Fokker-Planck step's own divergence (:func:`harness.targets.feedforward.feedforward`).

        Closed loop. With ``v = -alpha grad(p / p_*) + sigma grad log p_* + w`` and
        exact estimates, the computation in the proof of Theorem ``thm:exponential
        stability`` (eq. ``modified density feedback law 1`` in eq. ``FP equation``)
        gains the transport by ``w``:

            d_t p = div((alpha p + sigma p_*) grad(p / p_*)) - div(p w),

        so the tracking error ``Phi = p - p_*(t)`` obeys

            d_t Phi = div((alpha p + sigma p_*) grad(p / p_*))
                      - [div(p_* w) + d_t p_*] - div(Phi w),

        where the bracket is zero with the feedforward and is ``d_t p_*`` without it (a
        forcing of eq. ``tracking error equation``). With the feedforward what is left
        beyond the static loop is ``-div(Phi w)``, and it is not a further input: for
        ``V = 1/2 int Phi^2 / p_*`` (whose weight now moves) and ``f = Phi / p_* = p /
        p_* - 1``,

            dV/dt = int f d_t Phi - 1/2 int f^2 d_t p_*,

        and the transport term is ``-int f div(Phi w) = int p_* f w . grad f = 1/2 int
        p_* w . grad(f^2) = -1/2 int f^2 div(p_* w) = 1/2 int f^2 d_t p_*`` (the wall
        term vanishes since ``p_* w . n = 0``): it cancels the moving weight's term
        exactly, and

            dV/dt = -int (alpha p + sigma p_*) |grad(p / p_*)|^2,

        the static loop's identity, with no smallness condition on ``|w|`` (in the
        continuum; on the grid the cancellation holds up to the discretisation, whose
        residual is estimated below). The Poincare inequality (eq. ``poincare
        inequality`` with ``g = p_*(t)``, constant ``lambda(t)``) gives ``dV/dt <= -2
        (sigma + alpha min_x p / p_*) lambda(t) V``, about ``-2 (alpha + sigma) lambda
        V`` near the target: with exact estimates the tracking error decays to zero at
        the static rate. The feedforward reads no
        estimate, so with estimates the proof of Theorem ``thm:ISS`` goes through at
        every ``t`` unchanged (the same estimation-error terms), its constants taken
        uniformly in ``t``: ``inf_t lambda(t)`` and the bounds of ``p_*(t)`` and
        ``|grad p_*(t)|``, which for the rotating mixture are the static target's up
        to the walls (:mod:`harness.targets.moving`).

        Without the feedforward, ``dV/dt = -int (alpha p + sigma p_*) |grad f|^2 - int
        f d_t p_* - 1/2 int f^2 d_t p_*``; with the decay rate ``r`` of the first term
        (``dissipation >= 2 r V``), ``m = max |d_t p_* / p_*|`` and ``y = sqrt(2 V) =
        ||Phi||_{L2(1/p_*)}``,

            dy/dt <= -(r - m / 2) y + ||d_t p_*||_{L2(1/p_*)},

        ISS with respect to ``d_t p_*`` provided ``m < 2 r`` (the target may not change
        faster, relatively, than twice the decay rate), with the residual lag ``y <=
        sup_t ||d_t p_*||_{L2(1/p_*)} / (r - m / 2)``.

        Residual with the feedforward on the grid. The feedforward makes ``p =
        p_*(t)`` an exact solution of the semi-discrete loop (``A(v + w) p_* = d_t
        p_*``, :mod:`harness.targets.feedforward`); what remains is the sampled data: the
        command is computed at ``t_n`` and held, and the step is backward Euler. Per
        step the target's own path misses the step by ``tau_n = p_*(t_n) -
        p_*(t_{n+1}) + dt A_n p_*(t_{n+1}) = dt^2 (A_n d_t p_* - d_t^2 p_* / 2) +
        O(dt^3)``, an input of size ``rho = dt ||A_n d_t p_* - d_t^2 p_* / 2||_{L2(1/p_*)}``
        per unit time, so by the same bound the residual is ``y <= rho / r``: first
        order in ``dt``, of the order of ``dt omega`` times the lag without the
        feedforward for a target turning at ``omega`` (``A d_t p_*`` and ``d_t^2 p_*``
        are both about ``omega |d_t p_*|``). The bounds use the slowest rate ``r`` and
        overestimate (by about 13 times in the test's setting, where ``d_t p_*`` lies
        in faster modes); ``tests/test_moving_target.py`` predicts both errors sharply from
        the loop's linearisation about ``p_*(t)``, ``L Phi = -s`` with the input ``s =
        -d_t p_*`` or ``s = dt (A d_t p_* - d_t^2 p_* / 2)``, and compares them with the
        loop.
        """
        if not self.feedforward:
            return None
        if self._poisson is None or self._poisson.grid != target.grid:
            self._poisson = NeumannPoisson(target.grid)
        # div(p_* w) = -d_t p_*, (p_* w) . n = 0
        return feedforward(target, rate, self.sigma, self._poisson)

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The velocity by eq. ``modified density feedback law using estimates``."""
        return paper_law(p_hat, q_hat, self.target, self.alpha, self.sigma, self.feedback_target)

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cell-centre values of :meth:`field` at flat cell indices ``cells``,
        from estimates ``p``, ``qx``, ``qy`` given at those cells (any common shape):
        the law each robot evaluates from its own estimate
        (:func:`harness.control.own_estimates.own_velocities`). Returns ``(vx, vy)`` (length / s).
        """
        f, t = self.feedback_target, self.target
        fp, fgx, fgy = f.p.ravel()[cells], f.grad[0].ravel()[cells], f.grad[1].ravel()[cells]
        tp, tgx, tgy = t.p.ravel()[cells], t.grad[0].ravel()[cells], t.grad[1].ravel()[cells]
        # v = -alpha (p~_* q_hat - p_hat grad p~_*) / p~_*^2 + sigma grad p_* / p_*
        vx = -self.alpha * (fp * qx - p * fgx) / fp**2 + self.sigma * tgx / tp
        vy = -self.alpha * (fp * qy - p * fgy) / fp**2 + self.sigma * tgy / tp
        return vx, vy

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``alpha max(p0 / p~_*)``: the feedback term is the nonlinear diffusion
        ``div(alpha p grad(p / p~_*))`` of local diffusivity ``alpha p / p~_*``
        (``p~_* = p_*`` without debiasing).
        """
        f = self.feedback_target
        if self.target.free is None:
            return self.alpha * float(np.max(p0 / f.p))
        cells = self.target.free.cells  # the feedback acts on free cells only
        return self.alpha * float(np.max(p0[cells] / f.p[cells]))


def feedback_target(target: Target, debias: bool, bandwidth: float | None, mirror: bool) -> Target:
    """``target``, or with ``debias`` the smoothed target ``K_h * p_*``."""
    if not flag("debias", debias):
        return target
    h = number("bandwidth", bandwidth, 0.0, strict=True)
    return smoothed_target(target, h, flag("mirror", mirror))
