"""Density feedback laws (config group ``control``): estimates in, commands out.

:class:`PaperControl` (``control=paper``) and :class:`HeatControl` (``control=heat``)
are field laws (:class:`FieldLaw`): a velocity field of the estimates, which robots
follow by interpolation or, when each robot holds its own estimate, evaluate on their
own (:mod:`harness.robot_law`). They implement :class:`harness.components.Control`; the
functions :func:`paper_law` and :func:`heat_law` hold the equations. Both laws take the
density estimate ``p_hat`` (``(ny, nx)``, 1 / length^2), the gradient estimate
``q_hat`` (``(2, ny, nx)``, 1 / length^3), the target (``p_*``, ``grad p_*`` and
``log p_*`` on the grid, see :class:`harness.densities.Target`), the gain
``alpha >= 0`` (length^4 / time, so that ``alpha grad(p / p_*)`` is a velocity) and the
noise intensity ``sigma >= 0`` (length^2 / time), and return a
:class:`~harness.velocity.VelocityField` (length / time).

Moving targets (``target=moving``, :mod:`harness.moving`). Every field law follows
``p_*(t)``: given the target at the step's time (:attr:`ControlInput.target
<harness.records.ControlInput.target>`) it evaluates its equation with that target in
place of its own (:meth:`FieldLaw.at_target`). The paper's law can add the feedforward
``w`` with ``div(p_* w) = -d_t p_*`` (``control.feedforward``,
:meth:`PaperControl.feedforward_field`, derived there).
"""

from __future__ import annotations

import copy
from typing import ClassVar, Self

import numpy as np

from harness.agents import interpolate
from harness.compiled.control import paper_velocity
from harness.components import flag, number, speed_cap
from harness.densities import Target
from harness.feedforward import NeumannPoisson, feedforward
from harness.grid import Grid
from harness.moving import TargetPath
from harness.records import Command, ControlInput
from harness.robot_law import own_velocities
from harness.smoothing import smoothed_target, transfer
from harness.velocity import VelocityField, centres_to_face_x, centres_to_face_y


def _check_gains(alpha: float, sigma: float) -> None:
    if not (np.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"control.alpha must be finite and >= 0, got {alpha}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"dynamics.sigma must be finite and >= 0, got {sigma}")


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
    """
    _check_gains(alpha, sigma)
    g = target.grid
    f = target if feedback_target is None else feedback_target
    p_hat, q_hat = np.asarray(p_hat), np.asarray(q_hat)
    if p_hat.shape != g.shape or q_hat.shape != (2, *g.shape):
        raise ValueError(
            f"estimates of shapes {p_hat.shape} and {q_hat.shape} do not fit the grid "
            f"{g.shape} (p_hat (ny, nx), q_hat (2, ny, nx))"
        )
    centres, face_x, face_y = paper_velocity(
        np.ascontiguousarray(p_hat, dtype=float), np.ascontiguousarray(q_hat, dtype=float),
        f.p, f.grad, target.p, target.grad, target.log_p,
        float(alpha), float(sigma), g.dx, g.dy,
    )  # fmt: skip
    return VelocityField(centres, face_x, face_y)


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
    _check_gains(alpha, sigma)
    g = target.grid
    f = target if feedback_target is None else feedback_target
    feedback = -alpha * (f.p * q_hat - p_hat * f.grad) / f.p**2
    drift = sigma * target.grad / target.p
    centres = feedback + drift
    face_x = centres_to_face_x(feedback[0]) + sigma * np.diff(target.log_p, axis=1) / g.dx
    face_y = centres_to_face_y(feedback[1]) + sigma * np.diff(target.log_p, axis=0) / g.dy
    return VelocityField(centres, face_x, face_y)


def heat_law(
    p_hat: np.ndarray,
    q_hat: np.ndarray,
    target: Target,
    alpha: float,
    sigma: float,
    density_floor: float = 0.1,
    noise_compensation: bool = True,
    feedback_target: Target | None = None,
) -> VelocityField:
    """The prior heat-equation law, estimate in the denominator (the paper's
    remark after eq. ``modified density feedback law 1`` contrasts it):

        v = -alpha (q_hat - grad p_*) / max(p_hat, c)  +  sigma q_hat / max(p_hat, c).

    With exact estimates and ``p >= c`` the closed loop is the heat equation
    ``d_t p = alpha Laplacian(p - p_*)``: the second term's transport
    ``-div(sigma grad p)`` cancels the robots' diffusion ``sigma Laplacian(p)``.
    Without it (``noise_compensation=False``, the law as usually written for
    noise-free robots) the loop settles at ``(alpha p_* + sigma c') / (alpha +
    sigma)`` rather than at ``p_*``.

    Args:
        density_floor: ``c > 0`` (1 / length^2), the floor that keeps the
            denominator away from zero where ``p_hat`` is small or negative. The
            default 0.1 is a tenth of the uniform density on the unit square.
        noise_compensation: Include the ``+sigma q_hat / p_hat`` term.
        feedback_target: Replaces ``p_*`` in the feedback term (the debiased law).
    """
    _check_gains(alpha, sigma)
    if not density_floor > 0:
        raise ValueError(f"heat law density_floor must be > 0, got {density_floor}")
    denom = np.maximum(p_hat, density_floor)
    f = target if feedback_target is None else feedback_target
    centres = -alpha * (q_hat - f.grad) / denom
    if noise_compensation:
        centres = centres + sigma * q_hat / denom
    return VelocityField.from_centres(centres)


def grid_modes(grid: Grid, resolution: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per cosine mode: the eigenvalue of the held feedback's discrete operator and of
    the robots' implicit diffusion (both 1 / length^2, arrays of shape ``(ny, nx)``).

    The Neumann cosine modes ``cos(k_i (x - x0)) cos(k_j (y - y0))``, ``k_i = i pi /
    Lx`` (``0 <= i < nx``), ``k_j = j pi / Ly``, are eigenvectors of every operator here.
    With ``theta_i = k_i dx``:

    * diffusion (the 5-point Laplacian of eq. ``FP equation``'s backward-Euler step):
      ``(4 / dx^2) sin^2(theta_i / 2)`` per axis, summed;
    * feedback: the laws put the centre values of their velocity on the faces by
      averaging, and the flux's divergence then acts on a cosine mode of the gradient
      estimate as ``-cos(k x) sin(theta) / dx`` times the mode's gradient amplitude.
      With grid gradients ``G p`` (exact estimates; ``resolution = None``) that
      amplitude is ``sin(theta) / dx``, giving ``sin^2(theta_i) / dx^2`` per axis; with
      analytic gradients of estimates smoothed at scale ``h`` (the KDE, the noise-free
      KDE) it is ``k T(k)``, giving ``k_i sin(theta_i) / dx`` per axis, the sum times
      ``T = exp(-|k|^2 h^2 / 2)`` (:func:`harness.smoothing.transfer`).
    """
    i = np.arange(grid.nx)
    j = np.arange(grid.ny)
    kx, ky = i * np.pi / (grid.x1 - grid.x0), j * np.pi / (grid.y1 - grid.y0)
    tx, ty = kx * grid.dx, ky * grid.dy
    diff_x = (4 / grid.dx**2) * np.sin(tx / 2) ** 2
    diff_y = (4 / grid.dy**2) * np.sin(ty / 2) ** 2
    if resolution is None:
        fb_x, fb_y = np.sin(tx) ** 2 / grid.dx**2, np.sin(ty) ** 2 / grid.dy**2
    else:
        fb_x, fb_y = kx * np.sin(tx) / grid.dx, ky * np.sin(ty) / grid.dy
    damping = transfer(np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2), resolution)
    feedback = (fb_y[:, None] + fb_x[None, :]) * damping
    return feedback, diff_y[:, None] + diff_x[None, :]


def sampled_data_dt_bound(
    grid: Grid, diffusivity: float, resolution: float | None = None, sigma: float = 0.0
) -> float:
    """Largest ``dt`` for which the held feedback is stable on every grid mode.

    The control is computed once per step and held for ``dt`` (sampled data). With
    exact estimates the feedback term of the paper's law acts as the nonlinear
    diffusion ``div(alpha p grad(p / p_*))``, of local diffusivity ``D = alpha p /
    p_*`` (:meth:`PaperControl.feedback_diffusivity`). Linearised about a state, a
    cosine mode is fed back with the eigenvalue ``mu`` of the held feedback's discrete
    operator (which includes the estimates' smoothing, :func:`grid_modes`) explicitly,
    because the velocity is held, while the robots' own diffusion ``sigma`` acts on it
    implicitly with eigenvalue ``lambda`` (the backward-Euler step of eq. ``FP
    equation``). Per step the mode is multiplied by

        (1 - dt D mu) / (1 + dt sigma lambda),

    which leaves ``[-1, 1]`` (a grid-scale overshoot that grows) when ``dt (D mu -
    sigma lambda) > 2``. So the bound is

        dt_max = 2 / max_k (D mu_k - sigma lambda_k)

    (``inf`` when no mode has a positive denominator). With exact estimates ``mu``
    peaks at ``1 / dx^2 + 1 / dy^2``. At the agent level the law sees the robots only
    through the KDE, so the maximum is set by the bandwidth ``h`` and not by ``dx``:
    ``k^2 exp(-k^2 h^2 / 2)`` peaks at ``|k| = sqrt(2) / h`` at ``2 / (e h^2)`` (460 /
    length^2 for ``h = 0.04`` on every fine grid, against ``2 / dx^2`` = 32800 at
    ``n = 128`` with exact estimates).

    The bound concerns the physical sampled-data loop, not the Fokker-Planck stepper
    (which is implicit and stable for every ``dt``): the robots receive the same held
    velocity.

    Args:
        grid: The grid.
        diffusivity: ``D``, the largest feedback diffusivity (length^2 / s).
        resolution: The estimates' smallest resolved scale ``h`` (length), or None for
            grid resolution.
        sigma: The robots' noise intensity (length^2 / s).

    Returns:
        The bound in seconds.
    """
    feedback, diffusion = grid_modes(grid, resolution)
    denominator = float(np.max(diffusivity * feedback - sigma * diffusion))
    if denominator <= 0:
        return float("inf")
    return 2.0 / denominator


class FieldLaw:
    """A law whose command is a velocity field of the estimates ``(p_hat, q_hat)``.

    A subclass defines :meth:`field` (the law on the grid) and, so that each robot can
    move by the law of its own estimate, :meth:`at_cells` (the same law's cell-centre
    values at given cells). :meth:`__call__` gives the field of the estimate and, when
    the estimate carries each robot's own (``estimate.robots``), each robot's velocity
    from its own estimate at its own position (:func:`harness.robot_law.own_velocities`).

    Attributes:
        target: The target on the grid.
        gives_field: True: every command has the field.
        needs_robots: False: a field law acts on estimates, with or without robots.
        uses: What the law reads, as a phrase (logged in the ``theory`` record).
        divides_by_density: Whether a density estimate sits in a denominator.
        v_max: The speed cap (length / s) of every command, or None
            (:meth:`harness.records.Command.capped`).
        own_estimates: Whether the law evaluates each robot's own estimate: true for a
            class that defines :meth:`at_cells` itself, or inherits both :meth:`field`
            and :meth:`at_cells` (a subclass that redefines :meth:`field` without
            :meth:`at_cells` would move each robot by its parent's law, so it is false
            there). Set when the class is created, unless the class body sets it.
        follows_moving_target: True: the law follows a moving target ``p_*(t)``
            (:meth:`__call__`); the builder refuses ``target=moving`` for a law without
            this attribute set (:func:`harness.build.build`).
    """

    follows_moving_target: ClassVar[bool] = True
    gives_field: ClassVar[bool] = True
    own_estimates: ClassVar[bool] = False
    needs_robots: ClassVar[bool] = False
    uses: ClassVar[str] = "estimate, gradient estimate"
    divides_by_density: ClassVar[bool] = False
    target: Target
    v_max: float | None = None

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        defines = vars(cls)
        if "own_estimates" in defines:  # the class says so itself
            return
        if "at_cells" in defines:
            cls.own_estimates = True
        elif "field" in defines:
            cls.own_estimates = False

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The velocity field (length / s) of ``p_hat`` (1 / length^2) and ``q_hat``
        (1 / length^3).
        """
        raise NotImplementedError

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cell-centre values of :meth:`field` at flat cell indices ``cells``, from
        estimates ``p``, ``qx``, ``qy`` given at those cells (any common shape); returns
        ``(vx, vy)`` (length / s).
        """
        raise NotImplementedError

    def at_target(self, target: Target) -> Self:
        """This law for the target ``target`` (``p_*(t)`` of a moving target): a
        shallow copy whose target, and whatever the law derives from it, is that one.
        """
        law = copy.copy(self)
        law.retarget(target)
        return law

    def retarget(self, target: Target) -> None:
        """Put ``target`` in place of the law's target (a subclass that derives
        quantities from the target derives them again).
        """
        self.target = target

    def feedforward_field(self, target: Target, rate: np.ndarray) -> VelocityField | None:
        """The feedforward added to the field for a target moving at ``d_t p_* =
        rate``, or None (a law without one).
        """
        return None

    def moving_target(self, inp: ControlInput) -> tuple[Target | None, np.ndarray | None]:
        """``(p_*(t), d_t p_*)`` at ``inp.t``: the input's when it carries them, else
        the law's own target's path when that moves (a caller that does not fill them,
        such as the agents plant's ``N -> infinity`` limit); ``(None, None)`` for a
        static target.
        """
        if inp.target is not None:
            return inp.target, inp.target_rate
        path = self.__dict__.get("_path")
        if path is None:
            path = TargetPath(self.target)
            self.__dict__["_path"] = path
        if not path.moves:
            return None, None
        return path.at(inp.t), path.rate(inp.t)

    def __call__(self, inp: ControlInput) -> Command:
        """The field of the estimate; with each robot's own estimate, each robot's own
        velocity too (the class docstring). For a moving target, the law at ``p_*(t)``
        (:meth:`at_target`) plus its feedforward (:meth:`feedforward_field`), which
        robots interpolate bilinearly; the speed cap applies to the sum.

        Raises:
            ValueError: for robots' own estimates given to a law without
                ``own_estimates``, or without the robots' positions.
        """
        target, rate = self.moving_target(inp)
        law = self if target is None else self.at_target(target)
        ff = None if target is None or rate is None else law.feedforward_field(target, rate)
        est = inp.estimate
        v = law.field(est.p_hat, est.q_hat)
        if ff is not None:
            v = VelocityField(v.centres + ff.centres, v.face_x + ff.face_x, v.face_y + ff.face_y)
        own = est.robots
        if own is None:
            return Command(v).capped(self.v_max)
        if not self.own_estimates or inp.positions is None:
            raise ValueError(
                f"{type(self).__name__} cannot move robots by their own estimates "
                "(it has no at_cells of its own, or the plant has no robots)"
            )
        grid = self.target.grid
        robots = own_velocities(grid, law.at_cells, own.p_hat, inp.positions, own.q_hat, own.order)
        reference = None
        if own.reference is not None:  # every robot holding the reference's estimate
            shared = np.broadcast_to(own.reference, own.p_hat.shape)
            reference = own_velocities(grid, law.at_cells, shared, inp.positions, order=own.order)
        if ff is not None:
            drift = interpolate(grid, ff.centres, inp.positions)
            robots = robots + drift
            reference = None if reference is None else reference + drift
        return Command(v, robots, reference).capped(self.v_max)


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
    (:func:`harness.smoothing.smoothed_target`), in the feedback term only:

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
        self.feedback_target = _feedback_target(target, debias, bandwidth, mirror)
        self.v_max = speed_cap(v_max)
        self.feedforward = flag("feedforward", feedforward)
        self._poisson: NeumannPoisson | None = None

    def retarget(self, target: Target) -> None:
        """``target`` and its feedback target (smoothed again when debiased)."""
        self.target = target
        self.feedback_target = _feedback_target(target, *self._debias)

    def feedforward_field(self, target: Target, rate: np.ndarray) -> VelocityField | None:
        """The feedforward ``w`` for ``p_*(t) = target`` moving at ``d_t p_* = rate``
        (length / s), None unless ``feedforward``:

            div(p_* w) = -d_t p_*,   (p_* w) . n = 0 on the walls,

        solved as ``p_* w = grad phi``, ``Laplacian phi = -d_t p_*`` with Neumann walls
        and zero mean (compatible because ``int d_t p_* = 0``), on the grid with the
        Fokker-Planck step's own divergence (:func:`harness.feedforward.feedforward`).

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
        to the walls (:mod:`harness.moving`).

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
        p_*``, :mod:`harness.feedforward`); what remains is the sampled data: the
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
        (:func:`harness.robot_law.own_velocities`). Returns ``(vx, vy)`` (length / s).
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
        return self.alpha * float(np.max(p0 / self.feedback_target.p))


def _feedback_target(target: Target, debias: bool, bandwidth: float | None, mirror: bool) -> Target:
    """``target``, or with ``debias`` the smoothed target ``K_h * p_*``."""
    if not flag("debias", debias):
        return target
    h = number("bandwidth", bandwidth, 0.0, strict=True)
    return smoothed_target(target, h, flag("mirror", mirror))


class HeatControl(FieldLaw):
    """The prior heat-equation law (``control=heat``), :func:`heat_law` with fixed gains.

    Source: Eren and Açıkmeşe, "Velocity field generation for density control of
    swarms using heat equation and smoothing kernels", IFAC-PapersOnLine 50(1), 2017:
    ``v = -D (grad p_hat - grad p_*) / p_hat`` (``D`` is ``alpha`` here), with the floor
    ``max(p_hat, c)`` and the noise compensation ``sigma q_hat / max(p_hat, c)``. Inputs:
    the density and gradient estimates, ``grad p_*``. The density estimate sits in the
    denominator: locally robust at best (the seed paper), and the floor ``c`` bounds the
    gain ``1 / c`` that an estimate near zero multiplies the error with. Fixed point:
    with exact estimates and ``p >= c`` the loop is ``d_t p = alpha Laplacian(p -
    p_*)`` (the compensation cancels the noise), whose steady state is ``p_*``; without
    the compensation, ``(alpha p_* + sigma c') / (alpha + sigma)`` (:func:`heat_law`).

    Args:
        target: The target on the grid (run-time argument).
        alpha: Feedback gain ``>= 0`` (length^2 / s times density, as in :func:`heat_law`).
        sigma: Noise intensity ``>= 0`` (length^2 / s).
        density_floor: ``c > 0`` (1 / length^2).
        noise_compensation: Include the ``sigma q_hat / p_hat`` term.
        debias, bandwidth, mirror: As :class:`PaperControl` (``grad p~_*`` replaces
            ``grad p_*`` in the feedback term).
        v_max: Speed cap (length / s), or None.
    """

    divides_by_density = True

    def __init__(
        self,
        target: Target,
        alpha: float,
        sigma: float,
        density_floor: float = 0.1,
        noise_compensation: bool = True,
        debias: bool = False,
        bandwidth: float | None = None,
        mirror: bool = True,
        v_max: float | None = None,
    ) -> None:
        self.v_max = speed_cap(v_max)
        self.target = target
        self.alpha = number("alpha", alpha, 0.0)
        self.sigma = number("sigma", sigma, 0.0)
        self.density_floor = number("density_floor", density_floor, 0.0, strict=True)
        self.noise_compensation = flag("noise_compensation", noise_compensation)
        self._debias = (debias, bandwidth, mirror)
        self.feedback_target = _feedback_target(target, debias, bandwidth, mirror)

    def retarget(self, target: Target) -> None:
        """``target`` and its feedback target (smoothed again when debiased)."""
        self.target = target
        self.feedback_target = _feedback_target(target, *self._debias)

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """The heat-equation law of :func:`heat_law`."""
        return heat_law(
            p_hat,
            q_hat,
            self.target,
            self.alpha,
            self.sigma,
            density_floor=self.density_floor,
            noise_compensation=self.noise_compensation,
            feedback_target=self.feedback_target,
        )

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The cell-centre values of :meth:`field` at flat cell indices ``cells``,
        from estimates given at those cells (see :meth:`PaperControl.at_cells`).
        """
        f = self.feedback_target
        denom = np.maximum(p, self.density_floor)
        # v = -alpha (q_hat - grad p~_*) / max(p_hat, c) [+ sigma q_hat / max(p_hat, c)]
        vx = -self.alpha * (qx - f.grad[0].ravel()[cells]) / denom
        vy = -self.alpha * (qy - f.grad[1].ravel()[cells]) / denom
        if self.noise_compensation:
            vx, vy = vx + self.sigma * qx / denom, vy + self.sigma * qy / denom
        return vx, vy

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """``alpha max(p0 / max(p0, c))``: with exact estimates the feedback flux is
        ``-alpha p / max(p, c) grad(p - p_*)``.
        """
        return self.alpha * float(np.max(p0 / np.maximum(p0, self.density_floor)))


class LangevinControl(FieldLaw):
    """Open-loop Langevin drift (``control=langevin``): the baseline without feedback.

        v = sigma grad log p_* = sigma grad p_* / p_*,

    the paper's law (eq. ``modified density feedback law 1``) at ``alpha = 0``, given its
    own name so that studies group it. Inputs: the target's score ``grad log p_*`` only
    (no estimate, no position); no density in a denominator other than the target's.

    Fixed point and stability. The closed loop is the Fokker-Planck equation ``d_t p =
    div(sigma p_* grad(p / p_*))`` (the paper's ``d_t p = div((alpha p + sigma p_*)
    grad(p / p_*))`` at ``alpha = 0``): ``p_*`` is its stationary density (the drift is
    exactly the compensation ``sigma grad log p_*``), and ``V = 1/2 int (p - p_*)^2 /
    p_*`` decays at the rate ``sigma lambda`` of the ``p_*``-weighted Poincare constant
    ``lambda`` (the paper's rate ``(alpha + sigma) lambda`` at ``alpha = 0``). It needs
    no estimate, so estimation errors do not reach it: its ISS gain is zero, and its
    convergence is as slow as the noise (``1 / (sigma lambda)``; about 2100 s for the
    paper's target and ``sigma = 5e-5``). Discretised as :func:`paper_law` at ``alpha =
    0`` (the face drift makes ``p_*`` the exact discrete steady state).

    Args:
        target: The target on the grid (run-time argument).
        sigma: The robots' noise intensity ``>= 0`` (length^2 / s).
        v_max: Speed cap (length / s), or None.
    """

    uses = "target score"

    def __init__(self, target: Target, sigma: float, v_max: float | None = None) -> None:
        self.alpha = 0.0
        self.sigma = number("sigma", sigma, 0.0)
        self.v_max = speed_cap(v_max)
        self.retarget(target)

    def retarget(self, target: Target) -> None:
        """``target`` and its drift ``sigma grad log p_*``."""
        self.target = target
        zero = np.zeros(target.grid.shape)
        self._field = paper_law(zero, np.zeros((2, *zero.shape)), target, 0.0, self.sigma)

    def field(self, p_hat: np.ndarray, q_hat: np.ndarray) -> VelocityField:
        """``sigma grad log p_*`` (the estimates are not used)."""
        return self._field

    def at_cells(
        self, p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``sigma grad p_* / p_*`` at flat ``cells`` (the estimates are not used)."""
        t = self.target
        tp = t.p.ravel()[cells]
        return self.sigma * t.grad[0].ravel()[cells] / tp, self.sigma * t.grad[1].ravel()[
            cells
        ] / tp

    def feedback_diffusivity(self, p0: np.ndarray) -> float:
        """0: no feedback."""
        return 0.0
