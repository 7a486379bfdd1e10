"""The benchmark of the field's laws: scenarios, each law tuned to its best, verdicts on
fresh seeds (``make benchmark``, ``docs/benchmark.md``).

* :mod:`~harness.benchmark.space`: the gains a law's YAML declares tunable
  (``control.tunable``) as Optuna distributions, and a trial's values as config values;
* :mod:`~harness.benchmark.plan`: a benchmark tier (``conf/benchmark/*.yaml``): the
  scenarios, the laws, the tuning budget and the seeds;
* :mod:`~harness.benchmark.points`: the config of every run the benchmark makes, written
  as an option of config group ``point`` that a Hydra multirun sweeps, so every run goes
  through any Hydra launcher and a re-run skips the runs that finished;
* :mod:`~harness.benchmark.tuning`: the tuning loop (Optuna's ask and tell over a
  SQLite storage, so a killed benchmark resumes) and the choice of each law's points;
* :mod:`~harness.benchmark.driver`: the whole benchmark in order, with its progress.

The leaderboard is written by :mod:`analysis.leaderboard` from the runs' logs alone.
"""
