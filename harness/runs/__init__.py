"""From a config to a finished log, one run or a sweep of them.

* :mod:`~harness.runs.build`: every component and observer from its YAML, checked; the
  only reader of the config;
* :mod:`~harness.runs.checks`: the checks no single component can make;
* :mod:`~harness.runs.identity`: what identifies a run (config hash, Hydra's choices,
  code provenance);
* :mod:`~harness.runs.run`: one run to its ``run.mcap``, whatever happens;
* :mod:`~harness.runs.jobs`: a sweep's jobs;
* :mod:`~harness.runs.sweep_progress`: a sweep's progress while it runs.
"""
