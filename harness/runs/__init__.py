"""From a config to a finished log, one run or a sweep of them.

* :mod:`~harness.runs.build`: every component and observer from its YAML, checked; the
  only reader of the config;
* :mod:`~harness.runs.checks`: the checks no single component can make;
* :mod:`~harness.runs.resources`: the memory and disk a run needs, against what the
  machine has;
* :mod:`~harness.runs.identity`: what identifies a run (config hash, Hydra's choices,
  code provenance);
* :mod:`~harness.runs.run`: one run to its ``run.mcap``, whatever happens;
* :mod:`~harness.runs.app`: what the Hydra app calls: the callbacks, a single run's
  check, a sweep's job and the end of a sweep;
* :mod:`~harness.runs.resume`: whether a job's log counts as the job done;
* :mod:`~harness.runs.supervision`: directories claimed, a job in a process of its own,
  the running jobs stopped;
* :mod:`~harness.runs.status`: each job's ``job_status.json`` and the sweep's status
  table;
* :mod:`~harness.runs.sweep_progress`: a sweep's progress while it runs.
"""
