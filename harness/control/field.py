"""Field laws: a velocity field of the estimates, and what every such law shares.

:class:`~harness.control.paper.PaperControl` (``control=paper``),
:class:`~harness.control.heat.HeatControl` (``control=heat``) and
:class:`~harness.control.heat.LangevinControl` (``control=langevin``) are field laws
(:class:`FieldLaw`): a velocity field of the estimates, which robots follow by
interpolation or, when each robot holds its own estimate, evaluate on their own
(:mod:`harness.control.own_estimates`). They implement
:class:`harness.protocols.Control`; the functions
:func:`~harness.control.paper.paper_law` and :func:`~harness.control.heat.heat_law` hold
the equations. The laws take the density estimate ``p_hat`` (``(ny, nx)``, 1 /
length^2), the gradient estimate ``q_hat`` (``(2, ny, nx)``, 1 / length^3), the target
(``p_*``, ``grad p_*`` and ``log p_*`` on the grid, see
:class:`harness.targets.densities.Target`), the gain ``alpha >= 0`` (length^4 / time, so
that ``alpha grad(p / p_*)`` is a velocity) and the noise intensity ``sigma >= 0``
(length^2 / time), and return a :class:`~harness.velocity.VelocityField` (length /
time).

Moving targets (``target=moving``, :mod:`harness.targets.moving`). Every field law follows
``p_*(t)``: given the target at the step's time (:attr:`ControlInput.target
<harness.records.ControlInput.target>`) it evaluates its equation with that target in
place of its own (:meth:`FieldLaw.at_target`). The paper's law can add the feedforward
``w`` with ``div(p_* w) = -d_t p_*`` (``control.feedforward``,
:meth:`harness.control.paper.PaperControl.feedforward_field`, derived there).


The sampled-data step bound of a field law's feedback (:func:`sampled_data_dt_bound`)
is checked by the builder before a run starts.
"""

from __future__ import annotations

import copy
from typing import ClassVar, Self

import numpy as np

from harness.control.own_estimates import CellLaw, own_velocities
from harness.domains.base import FreeSpace
from harness.estimators.smoothing import transfer
from harness.grid import Grid
from harness.records import Command, ControlInput
from harness.targets.densities import Target
from harness.targets.moving import TargetPath
from harness.velocity import VelocityField, interpolate


def check_gains(alpha: float, sigma: float) -> None:
    """Refuse a gain ``alpha`` or noise intensity ``sigma`` that is negative or not
    finite (a ``ValueError`` naming the key), for the field laws' equations.
    """
    if not (np.isfinite(alpha) and alpha >= 0):
        raise ValueError(f"control.alpha must be finite and >= 0, got {alpha}")
    if not (np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"dynamics.sigma must be finite and >= 0, got {sigma}")


def no_flux_into_obstacles(v: VelocityField, free: FreeSpace | None) -> VelocityField:
    """``v`` with no flux through an obstacle: centre values 0 on blocked cells and
    face-normal values 0 on closed faces (``free.face_x``, ``free.face_y``); ``v``
    itself when ``free`` is None (the plain rectangle).

    The Fokker-Planck operator already carries no flux through a closed face
    (:mod:`harness.fokker_planck`); this makes the command say so too, so that what is
    logged and what robots interpolate near an obstacle carry no velocity inside it.
    """
    if free is None:
        return v
    return VelocityField(
        np.where(free.cells, v.centres, 0.0),
        np.where(free.face_x, v.face_x, 0.0),
        np.where(free.face_y, v.face_y, 0.0),
    )


def _free_cells_only(at_cells: CellLaw, free: FreeSpace) -> CellLaw:
    """A law's cell values (``at_cells``) with 0 on blocked cells, as
    :func:`no_flux_into_obstacles` sets the centres of its field: what a robot's own
    velocity interpolates near an obstacle.
    """
    on = free.cells.ravel()

    def values(
        p: np.ndarray, qx: np.ndarray, qy: np.ndarray, cells: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(divide="ignore", invalid="ignore"):  # p_* = 0 on blocked cells
            vx, vy = at_cells(p, qx, qy, cells)
        inside = on[cells]
        return np.where(inside, vx, 0.0), np.where(inside, vy, 0.0)

    return values


def positive_on_blocked(p: np.ndarray, free: FreeSpace | None) -> np.ndarray:
    """``p`` with its blocked cells set to 1 (``p`` itself when ``free`` is None): a
    target's cell values, 0 on blocked cells, made safe to divide by; the values there
    are discarded by :func:`no_flux_into_obstacles`.
    """
    if free is None:
        return p
    return np.where(free.cells, p, 1.0)


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
      ``T = exp(-|k|^2 h^2 / 2)`` (:func:`harness.estimators.smoothing.transfer`).
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
    grid: Grid,
    diffusivity: float,
    resolution: float | None = None,
    sigma: float = 0.0,
    free: FreeSpace | None = None,
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

    On free space (``free``, a domain with obstacles) the cosine modes are not
    eigenvectors and the bound is :func:`free_space_dt_bound`'s.

    Args:
        grid: The grid.
        diffusivity: ``D``, the largest feedback diffusivity (length^2 / s).
        resolution: The estimates' smallest resolved scale ``h`` (length), or None for
            grid resolution.
        sigma: The robots' noise intensity (length^2 / s).
        free: Free space of a domain with obstacles; None for the rectangle.

    Returns:
        The bound in seconds.
    """
    if free is not None:
        return free_space_dt_bound(free, diffusivity, resolution, sigma)
    feedback, diffusion = grid_modes(grid, resolution)
    denominator = float(np.max(diffusivity * feedback - sigma * diffusion))
    if denominator <= 0:
        return float("inf")
    return 2.0 / denominator


def free_space_dt_bound(
    free: FreeSpace, diffusivity: float, resolution: float | None = None, sigma: float = 0.0
) -> float:
    """:func:`sampled_data_dt_bound` on free space: ``2 / m`` with ``m`` a proven upper
    bound of the held feedback's eigenvalues less the robots' diffusion (``inf`` when
    ``m <= 0``).

    The linearised step on the free cells is ``(I + dt sigma L)^-1 (I - dt D F)``, with
    ``L`` the diffusion (the five-point operator with no flux through closed faces) and
    ``F`` the held feedback's operator. With exact estimates (``resolution`` None) the
    command's face values are the means of its centre values, 0 on closed faces, and
    the flux's divergence of those means is ``-G^T`` for the free-space gradient ``G``
    (central differences, the cell itself behind a closed face): ``F = G^T G``. Both
    ``F`` and ``L`` are symmetric positive semi-definite, so every eigenvalue of the
    step is a Rayleigh quotient ``(1 - dt D f) / (1 + dt sigma l)`` of one vector, which
    stays in ``[-1, 1]`` for every vector exactly when ``dt lambda_max(D F - sigma L) <=
    2``. Along an axis the free cells fall into runs joined through open faces, and on a
    run of ``k`` cells ``G`` is the rectangle's one-dimensional gradient, whose ``G^T
    G`` has eigenvalues ``sin^2(pi a / k) / dx^2`` below the run's Laplacian's ``4
    sin^2(pi a / (2 k)) / dx^2`` (``a < k``). So ``F <= L`` and ``lambda_max(F) <=
    s_x / dx^2 + s_y / dy^2`` with ``s`` the largest ``sin^2(pi a / k)`` over the
    axis's run lengths (1 when a run has an even length), and

        lambda_max(D F - sigma L) <= max(D - sigma, 0) (s_x / dx^2 + s_y / dy^2).

    With estimates smoothed at scale ``h`` the feedback acts through the gradient of
    the kernel's diffusion for ``h^2 / 2`` (:mod:`harness.estimators.diffusion`): in the
    continuum ``-Delta exp(h^2 Delta / 2)`` with the Neumann Laplacian of free space,
    whose eigenvalues ``kappa^2 exp(-kappa^2 h^2 / 2)`` are at most ``2 / (e h^2)``
    on every domain; the bound takes that, and no credit for the robots' diffusion
    (``F`` need not commute with ``L`` there). Tests compare both with dense
    eigen-solves of the discrete operators on masked grids.
    """
    g = free.grid
    d = float(diffusivity)
    if resolution is not None:
        top = d * 2.0 / (np.e * float(resolution) ** 2)
    else:
        s_x = _largest_run_mode(_run_lengths(free.cells, free.face_x))
        s_y = _largest_run_mode(_run_lengths(free.cells.T, free.face_y.T))
        top = max(d - float(sigma), 0.0) * (s_x / g.dx**2 + s_y / g.dy**2)
    if top <= 0.0:
        return float("inf")
    return 2.0 / top


def _run_lengths(cells: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Lengths of the runs of free cells joined through open faces along each row of
    ``cells`` (``(rows, n)``; ``faces`` ``(rows, n - 1)`` open faces between them, an
    open face joining two free cells).
    """
    joined = np.zeros(cells.shape, dtype=bool)  # joined[r, i]: face (i - 1 | i) open
    joined[:, 1:] = faces
    start = cells & ~joined
    run = np.cumsum(start.ravel())  # the run of each free cell, numbered from 1
    return np.bincount(run[cells.ravel()])[1:]


def _largest_run_mode(lengths: np.ndarray) -> float:
    """``max sin^2(pi a / k)`` over ``0 <= a < k`` and the run lengths ``k`` given."""
    best = 0.0
    for k in np.unique(lengths):
        a = np.arange(int(k))
        best = max(best, float(np.max(np.sin(np.pi * a / k) ** 2)))
    return best


class FieldLaw:
    """A law whose command is a velocity field of the estimates ``(p_hat, q_hat)``.

    A subclass defines :meth:`field` (the law on the grid) and, so that each robot can
    move by the law of its own estimate, :meth:`at_cells` (the same law's cell-centre
    values at given cells). :meth:`__call__` gives the field of the estimate and, when
    the estimate carries each robot's own (``estimate.robots``), each robot's velocity
    from its own estimate at its own position
    (:func:`harness.control.own_estimates.own_velocities`).

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
            this attribute set (:func:`harness.runs.build.build`).
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
        such as the loop's ``N -> infinity`` limit); ``(None, None)`` for a
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
                ``own_estimates``, without the robots' positions, or on a domain with
                obstacles without their own gradient estimates.
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
        free = self.target.free
        if free is not None and own.q_hat is None:
            raise ValueError(
                f"{type(self).__name__} moves robots by their own estimates on a domain with "
                "obstacles only with their own gradients (central differences reflect at "
                "the rectangle's walls, not at obstacles)"
            )
        if not self.own_estimates or inp.positions is None:
            raise ValueError(
                f"{type(self).__name__} cannot move robots by their own estimates "
                "(it has no at_cells of its own, or the plant has no robots)"
            )
        grid = self.target.grid
        cell_law = law.at_cells if free is None else _free_cells_only(law.at_cells, free)
        robots = own_velocities(grid, cell_law, own.p_hat, inp.positions, own.q_hat, own.order)
        reference = None
        if own.reference is not None:  # every robot holding the reference's estimate
            shared = np.broadcast_to(own.reference, own.p_hat.shape)
            q_shared = None
            if free is not None:  # the reference's free-space gradient, for every robot
                q_ref = free.gradient(np.reshape(own.reference, grid.shape)).ravel()
                q_shared = np.broadcast_to(q_ref, (own.p_hat.shape[0], q_ref.size))
            reference = own_velocities(
                grid, cell_law, shared, inp.positions, q_shared, order=own.order
            )
        if ff is not None:
            drift = interpolate(grid, ff.centres, inp.positions)
            robots = robots + drift
            reference = None if reference is None else reference + drift
        return Command(v, robots, reference).capped(self.v_max)
