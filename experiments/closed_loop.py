"""The paper's closed-loop experiment as a Hydra app.

    python -m experiments.closed_loop [overrides]        # e.g. agents.n=4096 grid.n=64
    python -m experiments.closed_loop -m agents.n=256,1024,4096

Writes ``run.mcap`` into the Hydra run (or job) directory; see ``harness/observers/log.py``
for its contract and ``python -m analysis.figures RUN_DIR`` for the figures. A config
value that is not allowed stops the app before anything is written, with one line
naming the key, the value and what is allowed, and exit status 2 (the check runs in
:class:`harness.runs.app.CheckCallback`; in a multirun each job checks its own config).
Hydra's own flags (``--cfg job``, ``--info``, ``--help``, ``-cn``, ``-m``) work as usual.
The configs are read from :data:`harness.api.CONFIG_DIR` (``conf/``, shipped inside the
package), so the app runs from any directory, installed or not; ``harness.api`` composes
the same configs from Python.
"""

from __future__ import annotations

import os
import signal
import sys


def stop_before_run(signum: int, frame: object) -> None:
    """SIGINT, SIGTERM or SIGHUP before the run installs its own handlers (while the config is
    composed and built) stop the program as Ctrl-C does: one line, exit status 130,
    nothing written.
    """
    raise KeyboardInterrupt(f"received {signal.Signals(signum).name} before the run started")


def stop_while_loading(signum: int, frame: object) -> None:
    """SIGINT, SIGTERM or SIGHUP while the modules load: one line, exit status 130 (at
    once: nothing has been written, and an exception here would print a traceback).
    """
    os.write(2, f"interrupted: received {signal.Signals(signum).name} while starting\n".encode())
    os._exit(130)


STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}
"""The signals that stop the program (one line, exit status 130)."""


def settled() -> None:
    """Ignore the stop signals from here on: the outcome is decided and its status chosen.

    The interpreter's shutdown puts the default handlers back for the signals that have
    Python handlers, so a signal arriving then would end the program by the signal
    (128 + its number) instead of with the status chosen; an ignored one stays ignored.
    """
    for sig in STOP_SIGNALS - IGNORED:
        signal.signal(sig, signal.SIG_IGN)


IGNORED = {s for s in STOP_SIGNALS if signal.getsignal(s) is signal.SIG_IGN}
"""Signals ignored when the program started (SIGINT in a background job): left so."""

if __name__ == "__main__":
    for _sig in STOP_SIGNALS - IGNORED:
        signal.signal(_sig, stop_while_loading)
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from hydra.types import RunMode
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from harness.api import CONFIG_DIR
from harness.runs.app import checked, finish_sweep, run_job
from harness.runs.checks import ConfigError, describe
from harness.runs.run import DiskFull, Terminated, run


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="closed_loop")
def main(cfg: DictConfig) -> None:
    """Run one closed loop (or one job of a multirun) and print where its log is."""
    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    if hc.mode == RunMode.MULTIRUN:
        sweep_dir = Path(hc.sweep.dir)
        run_job(cfg, out, hc.job.num, list(hc.overrides.task), sweep_dir)  # in job_status.json
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
        settled()
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


def culprit(argv: list[str], err: BaseException) -> str | None:
    """The command-line override that ``err`` comes from, when one can be told: the
    first that does not parse on its own, or one whose key is longer than a file name
    may be (for a ``File name too long`` error); None otherwise.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    overrides = [a for a in argv if not a.startswith("-")]
    for arg in overrides:
        try:
            parser.parse_overrides([arg])
        except Exception:  # this one does not parse
            return arg
    if isinstance(err, OSError):
        for arg in overrides:
            if len(arg.split("=", 1)[0].encode()) > 255:
                return arg
    return None


def config_error(err: BaseException, argv: list[str]) -> str:
    """One line for a command line that does not compose, naming the override."""
    arg = culprit(argv, err)
    if arg is None:
        return describe(err, argv)
    key, _, value = arg.partition("=")
    cause = err.__cause__ or err
    text = str(cause).strip().splitlines() or [type(cause).__name__]
    reason = next((t for t in text if not t.startswith("Error parsing override")), text[0])
    if isinstance(cause, OSError) and cause.strerror:
        reason = cause.strerror  # not the long name again
    shown = value if len(value) <= 60 else f"{value[:40]}... ({len(value)} characters)"
    if len(key) > 60:
        key = f"{key[:40]}... ({len(key)} characters)"
    return f"invalid config: {key}={shown!r}: {reason.strip()[:300]}"


if __name__ == "__main__":
    # Hydra's errors come back to us (not as Hydra's report) so that a config that does
    # not compose is one line and exit status 2, like every other config error; set
    # whatever the environment says, so the output never depends on it.
    os.environ["HYDRA_FULL_ERROR"] = "1"
    for sig in STOP_SIGNALS - IGNORED:
        signal.signal(sig, stop_before_run)
    # A sweep interrupted (SIGINT, SIGTERM, SIGHUP) or whose launcher failed still
    # writes its status table (harness.runs.app.finish_sweep) and exits non-zero.
    try:
        main()
    except (HydraException, OmegaConfBaseException) as err:
        finish_sweep(f"{type(err).__name__}")
        print(config_error(err, sys.argv[1:]), file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt as err:
        settled()
        finish_sweep(str(err) or "KeyboardInterrupt")
        print(f"interrupted: {err or 'received SIGINT'}", file=sys.stderr)
        sys.exit(130)
    except Exception as err:  # the launcher failed (a worker process lost), or the parser
        status = finish_sweep(f"{type(err).__name__}: {err}")
        first = (str(err).strip().splitlines() or [""])[0]
        if status is not None:
            print(f"sweep failed: {type(err).__name__}: {first}", file=sys.stderr)
            sys.exit(1)
        if culprit(sys.argv[1:], err) is not None:  # an override Hydra could not take
            print(config_error(err, sys.argv[1:]), file=sys.stderr)
            sys.exit(2)
        print(f"failed: {type(err).__name__}: {first}", file=sys.stderr)
        sys.exit(1)
    finally:
        settled()
