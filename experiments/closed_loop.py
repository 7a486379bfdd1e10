"""The paper's closed-loop experiment as a Hydra app.

    python -m experiments.closed_loop [overrides]        # e.g. agents.n=4096 grid.n=64
    python -m experiments.closed_loop -m agents.n=256,1024,4096

Writes ``run.mcap`` into the Hydra run (or job) directory; see ``harness/mcap_log.py``
for its contract and ``python -m analysis.figures RUN_DIR`` for the figures. A config
value that is not allowed stops the app before anything is written, with one line
naming the key, the value and what is allowed, and exit status 2 (the check runs in
:class:`harness.jobs.CheckCallback`; in a multirun each job checks its own config).
Hydra's own flags (``--cfg job``, ``--info``, ``--help``, ``-cn``, ``-m``) work as usual.
The configs are read from :data:`harness.api.CONFIG_DIR` (``conf/``, shipped inside the
package), so the app runs from any directory, installed or not; ``harness.api`` composes
the same configs from Python.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from harness.api import CONFIG_DIR
from harness.checks import ConfigError, describe
from harness.jobs import checked, finish_sweep, run_job
from harness.run import DiskFull, Terminated, run


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """Run one closed loop (or one job of a multirun) and print where its log is."""
    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    if hc.mode == RunMode.MULTIRUN:
        run_job(cfg, out, hc.job.num, list(hc.overrides.task))  # outcome in job_status.json
        return
    try:
        result = run(checked(cfg), out)
    except ConfigError as err:  # found only when the run starts (a live port in use)
        print(err, file=sys.stderr)
        sys.exit(2)
    except DiskFull as err:
        print(err, file=sys.stderr)
        sys.exit(1)
    except Terminated as err:  # SIGINT, SIGTERM or SIGHUP between steps
        print(f"interrupted: {err}; log (aborted): {out / 'run.mcap'}", file=sys.stderr)
        sys.exit(130)
    m = result.last_metrics
    print(
        f"{result.state} after {result.steps} steps in {result.wall_s:.1f} s wall: "
        f"||p_hat - p*|| = {m.get('phat_target_l2', float('nan')):.4g} 1/length, "
        f"||p - p*|| = {m.get('phi_l2', float('nan')):.4g} 1/length at t = {m.get('t', 0):.2f} s"
    )
    if result.reason:
        print(f"reason: {result.reason}")
    print(f"log: {result.log_path} ({result.log_path.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    # Hydra's errors come back to us (not as Hydra's report) so that a config that does
    # not compose is one line and exit status 2, like every other config error.
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    # A sweep interrupted (SIGINT, SIGTERM, SIGHUP) or whose launcher failed still
    # writes its status table (harness.jobs.finish_sweep) and exits non-zero.
    try:
        main()
    except (HydraException, OmegaConfBaseException) as err:
        finish_sweep(f"{type(err).__name__}")
        print(describe(err, sys.argv[1:]), file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt as err:
        finish_sweep(str(err) or "KeyboardInterrupt")
        print(f"interrupted: {err}".strip(), file=sys.stderr)
        sys.exit(130)
    except Exception as err:  # the launcher failed (a worker process lost)
        if finish_sweep(f"{type(err).__name__}: {err}") is None:
            raise
        first = (str(err).strip().splitlines() or [""])[0]
        print(f"sweep failed: {type(err).__name__}: {first}", file=sys.stderr)
        sys.exit(1)
