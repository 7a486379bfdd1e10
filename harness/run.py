"""Run a closed loop built from a config to a finished ``run.mcap``.

:func:`harness.build.build` builds the components; the loop (:mod:`harness.loop`)
advances the plant, the estimator and the control; the observers (metrics, the
divergence guard and the MCAP logger) see each step and never steer. Whatever happens,
the log is finalised with a ``status`` record: ``completed``; ``diverged`` (non-finite
values, negative density or lost mass, with the reason); or ``aborted`` (an exception,
Ctrl-C or SIGTERM, re-raised after the log is closed).
"""

from __future__ import annotations

import datetime as dt_
import importlib.metadata
import platform
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from harness.build import Experiment, build
from harness.checks import ConfigError
from harness.fokker_planck import NumericalError
from harness.live import LiveServer, LiveServerError
from harness.loop import ClosedLoop
from harness.mcap_log import McapLogger
from harness.metrics import SwarmTruth, metrics
from harness.records import StepRecord
from harness.theory import poincare_constant

PACKAGES = (
    "numpy",
    "scipy",
    "numba",
    "filterpy",
    "mcap",
    "mcap-protobuf-support",
    "foxglove-schemas-protobuf",
    "hydra-core",
    "omegaconf",
    "densityloop",
)


class Terminated(Exception):
    """Raised in the run loop, between steps, after SIGINT or SIGTERM."""


@dataclass(frozen=True)
class RunResult:
    """Outcome of :func:`run`: final state and reason, steps done, wall time (s),
    the log's path, the last metrics and the wall time spent logging steps (s).
    """

    state: str
    reason: str
    steps: int
    wall_s: float
    log_path: Path
    last_metrics: dict[str, Any]
    log_s: float = 0.0


def provenance(seed: int) -> dict[str, str]:
    """Git commit and dirty flag, package versions, Python, seed, host, start time."""
    root = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        try:
            out = subprocess.run(
                ["git", *args], cwd=root, capture_output=True, text=True, timeout=10
            )
            return out.stdout.strip() if out.returncode == 0 else "unknown"
        except (OSError, subprocess.SubprocessError):
            return "unknown"

    status = git("status", "--porcelain")
    info = {
        "git_commit": git("rev-parse", "HEAD"),
        "git_dirty": "unknown" if status == "unknown" else str(bool(status)).lower(),
        "python": sys.version.split()[0],
        "seed": str(seed),
        "host": platform.node(),
        "start_time_utc": dt_.datetime.now(dt_.UTC).isoformat(timespec="seconds"),
    }
    for name in PACKAGES:
        try:
            info[f"version_{name}"] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            info[f"version_{name}"] = "not installed"
    return info


def run(cfg: DictConfig, out_dir: Path) -> RunResult:
    """Run the closed loop of ``cfg`` and write ``out_dir / 'run.mcap'``.

    Raises:
        ConfigError: before anything is written, for a value that is not allowed.
        KeyboardInterrupt, Terminated, Exception: re-raised after the log is
            finalised with status ``aborted``.
    """
    parts = build(cfg)
    live = start_live(cfg)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    steps = round(cfg.sim.t_final / cfg.sim.dt)
    target = parts.target
    swarm = SwarmTruth(
        parts.grid,
        target,
        cfg.kde.bandwidth,
        cfg.kde.mirror,
        cfg.kde.method,
        cfg.log.positions_every,
        cfg.log.w2_every,
        steps,
    )
    loop = ClosedLoop(parts.plant, parts.estimator, parts.control, parts.model, cfg.sim.dt, rng)
    logger = McapLogger(
        out_dir / "run.mcap",
        parts.grid,
        OmegaConf.to_yaml(cfg, resolve=True),
        provenance(cfg.seed),
        cfg.log.field_every,
        cfg.log.positions_every,
        steps,
        live=live,
    )
    progress = {"auto": None, "on": True, "off": False}.get(cfg.log.progress, None)
    bar = tqdm(
        total=steps,
        unit="step",
        disable=(not sys.stderr.isatty()) if progress is None else not progress,
    )
    state, reason, done, last = "aborted", "", 0, {}
    # SIGINT and SIGTERM request a stop that the loop honours between steps, so a
    # signal never lands inside the MCAP writer; a second signal stops at once.
    requested: list[int] = []

    def request_stop(signum: int, frame: Any) -> None:
        if requested:
            raise KeyboardInterrupt
        requested.append(signum)

    previous = {}
    if threading_is_main():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, request_stop)
    t0 = time.perf_counter()
    try:
        with threadpool_limits(1):
            logger.write_target(target.p)
            rec = loop.start()
            logger.add_metadata("theory", theory(cfg, parts, swarm, rec))
            last = metrics(loop.grid, target, rec) | swarm(rec)
            logger.handle(rec, last)
            for _ in range(steps):
                if requested:
                    raise Terminated(f"received {signal.Signals(requested[0]).name}")
                rec = loop.step()
                done = rec.step
                last = metrics(loop.grid, target, rec) | swarm(rec)
                logger.handle(rec, last)
                if done % 50 == 0 or done == steps:
                    bar.set_postfix_str(
                        f"t={rec.t:.2f} s |p_hat-p*|={last['phat_target_l2']:.3e}", refresh=False
                    )
                    bar.update(done - bar.n)
        state = "completed"
    except NumericalError as err:
        state, reason = "diverged", f"step {done + 1}: {err}"
    except (KeyboardInterrupt, Terminated) as err:
        reason = f"interrupted at step {done}: {type(err).__name__} {err}".strip()
        raise
    except Exception as err:
        reason = f"step {done}: {type(err).__name__}: {err}"
        raise
    finally:
        bar.close()
        logger.finalize(state, reason, time.perf_counter() - t0)
        if live is not None:
            live.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return RunResult(
        state, reason, done, time.perf_counter() - t0, logger.path, last, logger.seconds
    )


def theory(cfg: DictConfig, parts: Experiment, swarm: SwarmTruth, start: StepRecord) -> dict:
    """The ``theory`` record: the ``p_*``-weighted Poincare constant ``lambda`` (1 /
    length^2); for laws with a gain ``alpha``, the exact-estimate decay rate ``(alpha +
    sigma) lambda`` (1 / s); with robots, the finite-N floors of the swarm metrics
    (:meth:`harness.metrics.SwarmTruth.floors`, drawn from the stream ``[seed, 2]``,
    apart from the run's own).
    """
    lam = poincare_constant(parts.grid, parts.target.p)
    out = {"poincare_lambda": repr(lam)}
    alpha = getattr(parts.control, "alpha", None)
    if isinstance(alpha, float):
        out["rate_exact"] = repr((alpha + cfg.dynamics.sigma) * lam)
    if start.positions is not None:
        rng = np.random.default_rng([cfg.seed, 2])
        out |= swarm.floors(start.positions.shape[1], rng, cfg.log.floor_draws)
    return out


def start_live(cfg: DictConfig) -> LiveServer | None:
    """The live server of ``log.live`` (None when off).

    Raises:
        ConfigError: naming ``log.live_port`` when the server cannot start there.
    """
    if not cfg.log.live:
        return None
    try:
        server = LiveServer(cfg.log.live_host, cfg.log.live_port)
    except LiveServerError as err:
        raise ConfigError("log.live_port", cfg.log.live_port, str(err)) from None
    print(f"live view: {server.url} (Foxglove: Open connection)", file=sys.stderr)
    return server


def threading_is_main() -> bool:
    """Signal handlers can only be installed from the main thread."""
    import threading

    return threading.current_thread() is threading.main_thread()
