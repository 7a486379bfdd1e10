"""Observers (config group ``observers``): what watches a run's steps and never steers it.

* :mod:`~harness.observers.base`: the observer protocol, what observers share during a
  run, and the cadence every periodic observer keeps;
* :mod:`~harness.observers.metrics`: ``metrics``, the paper's errors every step;
* :mod:`~harness.observers.theory`: the theory quantities they log (Poincare constant);
* :mod:`~harness.observers.swarm`: ``swarm``, where the robots are, with
  :mod:`~harness.observers.swarm_metrics` (the metrics and their finite-N floors) and
  :mod:`~harness.observers.floor_cache` (floors computed once per content);
* :mod:`~harness.observers.motion`: ``motion``, how much the robots move;
* :mod:`~harness.observers.estimator`: ``estimator``, the numbers an estimator publishes;
* :mod:`~harness.observers.guard`: ``guard``, the divergence guard;
* :mod:`~harness.observers.live`: ``live``, the run served to Foxglove while it goes;
* :mod:`~harness.observers.log`: ``log``, the MCAP log and its contract;
* :mod:`~harness.observers.progress`: ``progress``, the progress bar.
"""
