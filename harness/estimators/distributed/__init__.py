"""The decentralised loop: every robot estimates the swarm's density and moves on its own.

The centralised loop forms one KDE of every position. But the KDE is a mean over robots,
``p_KDE = (1/N) sum_i phi_i`` with ``phi_i`` robot ``i``'s own kernel, so each robot can
*track* it from its own kernel and messages from its neighbours (Zheng and Lin, arXiv
2009.05366 / 2106.05318), run the project's fast density filter on what it tracks, and
move by the paper's law evaluated on its own estimate (a field law's cell values at its
own position, :func:`harness.control.own_estimates.own_velocities`; the robots' step is
:meth:`harness.plants.agents.Swarm.step_robots`). One idea per module:

* :mod:`~harness.estimators.distributed.graph`: the communication graph, its Laplacian and
  algebraic connectivity;
* :mod:`~harness.estimators.distributed.robot_kde`: each robot's KDE kernel on the grid;
* :mod:`~harness.estimators.distributed.mixing`: the consensus weights ``W = I - eps L``
  (gain) and the product ``W z``;
* :mod:`~harness.estimators.distributed.consensus`: dynamic average consensus in its two
  forms (derivations, invariant, error bounds) and the messages it costs;
* :mod:`~harness.estimators.distributed.messages` and
  :mod:`~harness.estimators.distributed.band`: what a message carries, grid fields or the
  band's coefficients;
* :mod:`~harness.estimators.distributed.share`: what the robots share beyond their
  kernels (the agreement on the law's input);
* :mod:`~harness.estimators.distributed.design`: the design's parameters, and the tables
  that map its config values to the classes above;
* :mod:`~harness.estimators.distributed.filters`: the per-robot fast density filters, built from
  :mod:`~harness.estimators.distributed.density` (the density step, compiled over robots) and
  :mod:`~harness.estimators.distributed.row_solver` (one sparse LU over robots);
* :mod:`~harness.estimators.distributed.metrics`: the estimates' spread and the network figures;
* :mod:`~harness.estimators.distributed.free_space`: on a domain with obstacles, each robot's
  kernel (the free-space heat kernel's column at its position), the messages of free cells
  or of the masked Laplacian's band, and each robot's free-space gradient;
* :mod:`~harness.estimators.distributed.walls`: radio links through obstacles, or only with a
  line of sight;
* :mod:`~harness.estimators.distributed.estimator`: the assembly, and ``estimator=distributed``
  (:class:`DistributedEstimator`).
"""
