"""Control laws (config group ``control``): what a law uses in, a command out.

One module per family of laws (``docs/laws.md`` gives each law's equation and source):

* :mod:`~harness.control.field`: the base of the field laws, which give a velocity
  field of the estimates, and the sampled-data step bound;
* :mod:`~harness.control.paper`: ``control=paper``, the paper's law;
* :mod:`~harness.control.heat`: ``control=heat`` and ``control=langevin``;
* :mod:`~harness.control.kernels`, :mod:`~harness.control.mmd`,
  :mod:`~harness.control.svgd`: the laws of the robots' positions through a Gaussian
  kernel, ``control=mmd`` and ``control=svgd``;
* :mod:`~harness.control.guidance`: ``control=psg`` and ``control=psg_feedback``,
  Markov chains on the grid's cells;
* :mod:`~harness.control.continuification`: ``control=continuification``, the density
  error asked to decay at a rate, the flux from a Neumann Poisson solve;
* :mod:`~harness.control.dsmc`: ``control=dsmc``, a state-dependent chain on the cells
  whose expected distribution is a consensus of ``m / v``;
* :mod:`~harness.control.assignment`: ``control=ot``, optimal-transport deployment;
* :mod:`~harness.control.waypoints`: robots that head for goal points, shared by the
  last two;
* :mod:`~harness.control.own_estimates`: a field law evaluated by each robot on its own
  estimate (the decentralised loop).

Every law implements :class:`harness.protocols.Control` and takes the run-time argument
``target`` (:class:`harness.targets.densities.Target`).
"""
