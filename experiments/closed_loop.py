"""The paper's closed-loop experiment as a Hydra app.

    python -m experiments.closed_loop [overrides]        # e.g. agents.n=4096 grid.n=64
    python -m experiments.closed_loop -m agents.n=256,1024,4096

Writes ``run.mcap`` into the Hydra run (or job) directory; see ``harness/mcap_log.py``
for its contract and ``python -m analysis.figures RUN_DIR`` for the figures. A config
value that is not allowed stops the app before anything is written, with one line
naming the key, the value and what is allowed, and exit status 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from harness.config import register_configs
from harness.run import Terminated, run
from harness.sweep import log_state, read_status, write_status
from harness.validate import ConfigError, check_overrides, validate

register_configs()


@hydra.main(version_base="1.3", config_path="../conf", config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """Validate, run one closed loop and print where its log is.

    In a multirun the job skips itself when its log is already complete, and a
    failure is recorded rather than raised (see :mod:`harness.sweep`).
    """
    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    if multirun:
        job = {"job": hc.job.num, "overrides": list(hc.overrides.task)}
        if log_state(out / "run.mcap") == "completed":
            write_status(out, state="completed", **job)
            print(f"job {hc.job.num}: already completed, skipped ({out})")
            return
    try:
        validate(cfg)
    except ConfigError as err:
        print(err, file=sys.stderr)
        if multirun:
            write_status(out, state="invalid", reason=str(err), **job)
            return
        sys.exit(2)
    if not multirun:
        result = run(cfg, out)
    else:
        runs = read_status(out).get("runs", 0) + 1
        write_status(out, state="running", runs=runs, reason="", **job)
        try:
            result = run(cfg, out)
        except (KeyboardInterrupt, Terminated):
            write_status(out, state="aborted", reason="interrupted")
            raise
        except Exception as err:  # recorded, not raised: the other jobs go on
            write_status(out, state="aborted", reason=f"{type(err).__name__}: {err}")
            print(f"job {hc.job.num} failed: {type(err).__name__}: {err}", file=sys.stderr)
            return
        write_status(out, state=result.state, reason=result.reason, wall_s=result.wall_s)
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
    error = check_overrides(sys.argv[1:], "closed_loop")
    if error:
        print(error, file=sys.stderr)
        sys.exit(2)
    main()
