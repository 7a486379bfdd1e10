"""Plants (config group ``plant``): what moves under the held command and what it lets
the estimator measure.

One module per option, named as the option:

* :mod:`~harness.plants.agents`: ``plant=agents``, ``N`` ideal integrators (eq.
  ``Langevin equation``) measured by their KDE; the robots' shared constructor, command
  link and localisation error, which the other robots inherit;
* :mod:`~harness.plants.unicycles`: ``plant=unicycles``, robots with a heading;
* :mod:`~harness.plants.double_integrators`: ``plant=double_integrators``,
  acceleration-limited robots;
* :mod:`~harness.plants.meanfield`: ``plant=meanfield``, the Fokker-Planck density itself,
  measured with the KDE's own noise;

and what the robot plants share:

* :mod:`~harness.plants.link`: the command link (period, latency, loss);
* :mod:`~harness.plants.limit`: the loop's deterministic ``N -> infinity`` limit, the
  reference the errors of a robot run are measured against.

The robots' compiled steps are in :mod:`harness.compiled.agents` and
:mod:`harness.compiled.robots`. Every plant implements :class:`harness.protocols.Plant`
and takes the run-time arguments ``grid``, ``model`` and ``init``.
"""
