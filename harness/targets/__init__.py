"""Targets ``p_*`` and initial densities ``p_0`` (config groups ``target`` and ``init``).

* :mod:`~harness.targets.densities`: the density protocol, the densities with closed
  forms (uniform, box, Gaussian mixture) and :class:`~harness.targets.densities.Target`,
  ``p_*`` on the grid with what the laws use;
* :mod:`~harness.targets.raster`: densities constant on the pixels of an image, a
  rasterised annulus (``target=ring``) and a grey PNG (``target=picture``);
* :mod:`~harness.targets.moving`: moving targets ``p_*(t)`` and the path a run follows;
* :mod:`~harness.targets.feedforward`: the velocity that carries a moving ``p_*`` along.
"""
