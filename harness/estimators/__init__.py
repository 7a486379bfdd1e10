"""Estimators (config group ``estimator``): measurements in, ``(p_hat, q_hat)`` out.

One module per option, named as the option, and the kernel they share:

* :mod:`~harness.estimators.kde`: the kernel density estimate of the swarm (the plants'
  measurement) and ``estimator=kde``, the raw KDE as the estimate;
* :mod:`~harness.estimators.smoothing`: the KDE's kernel applied to a density (the
  noise-free KDE ``K_h * p``, cell masses) and ``estimator=smoothed``;
* :mod:`~harness.estimators.exact`: ``estimator=exact``, the mean-field density itself;
* :mod:`~harness.estimators.injected`: ``estimator=injected``, the density plus a known
  error of one of two shapes (ISS gain curves);
* :mod:`harness.estimators.filters`: ``estimator=filters``, the paper's two filters
  (config group ``filter`` for their settings);
* :mod:`harness.estimators.distributed`: ``estimator=distributed``, one estimator per
  robot (the decentralised loop).

Every estimator implements :class:`harness.protocols.Estimator` and takes the run-time
arguments ``grid`` and ``model`` (the run's :class:`~harness.fokker_planck.FokkerPlanck`).
Only ``exact``, ``smoothed`` and ``injected`` read the plant's mean-field density.
"""
