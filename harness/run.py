"""Run a closed loop built from a config to a finished ``run.mcap``.

:func:`harness.build.build` builds the components; the loop (:mod:`harness.loop`)
advances the plant, the estimator and the control; the observers (metrics, the
divergence guard and the MCAP logger) see each step and never steer. Whatever happens,
the log is finalised with a ``status`` record: ``completed``; ``diverged`` (non-finite
values, negative density, lost mass or a numerical exception such as a singular
factorisation, with the reason); or ``aborted`` (an exception, Ctrl-C, SIGTERM or
SIGHUP, re-raised after the log is closed; a full disk, raised as :class:`DiskFull`).
"""

from __future__ import annotations

import datetime as dt_
import errno
import hashlib
import importlib.metadata
import json
import math
import platform
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse.linalg as spla
from omegaconf import DictConfig, OmegaConf
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from harness.build import Experiment, build
from harness.checks import PRESENTATION_KEYS, ConfigError, check_disk
from harness.fokker_planck import NumericalError
from harness.live import LiveServer, LiveServerError
from harness.loop import ClosedLoop
from harness.mcap_log import McapLogger
from harness.metrics import ALWAYS_NUMBERS, SwarmTruth, metrics
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
    """Raised in the run loop, between steps, after SIGINT, SIGTERM or SIGHUP."""


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


def config_hash(cfg: DictConfig) -> str:
    """SHA-256 (hex) of the resolved config without ``hydra`` and the presentation keys
    (:data:`harness.checks.PRESENTATION_KEYS`): equal exactly when two runs compute and
    log the same thing. Canonical JSON (sorted keys), so formatting never matters.
    """
    data = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(data, dict)
    data.pop("hydra", None)
    for key in PRESENTATION_KEYS:
        block, _, leaf = key.partition(".")
        if isinstance(data.get(block), dict):
            data[block].pop(leaf, None)
    text = json.dumps(data, sort_keys=True, default=repr, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


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


NUMERICAL = (
    NumericalError,
    FloatingPointError,
    ZeroDivisionError,
    OverflowError,
    np.linalg.LinAlgError,
    spla.MatrixRankWarning,
    RuntimeWarning,
)
"""Exceptions inside the loop that mean the numbers broke down: the run ends
``diverged`` with the reason (so does a ``RuntimeError`` saying a factorisation is
singular, as SuperLU's ``splu`` raises). Inside the loop numpy's floating-point
warnings from the harness (overflow, division by zero, invalid value) are errors, as in
the test suite."""

DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""``errno`` values of a write that failed for want of space."""

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""Signals that stop a run between steps with status ``aborted``."""


class DiskFull(RuntimeError):
    """The log could not be written for want of space; ``str()`` is one line."""


def is_numerical(err: BaseException) -> bool:
    """Whether ``err`` raised inside the loop means the numbers broke down."""
    if isinstance(err, NUMERICAL):
        return True
    return isinstance(err, RuntimeError) and "singular" in str(err).lower()


def check_finite(values: dict[str, Any]) -> None:
    """Raise :class:`NumericalError` when a metric is NaN or infinite (None is allowed
    only for keys that may be null).
    """
    for key, value in values.items():
        if value is None:
            if key in ALWAYS_NUMBERS:
                raise NumericalError(f"metric {key} is missing")
            continue
        if not math.isfinite(float(value)):
            raise NumericalError(f"metric {key} became non-finite ({value})")


class StopRequest:
    """Signal handler of a run: SIGINT, SIGTERM and SIGHUP ask the loop to stop between
    steps. A second signal stops at once, but only while a step is computing
    (``interruptible``): never inside the logger or the log's finalisation, so a burst
    of signals cannot leave the log unfinalised.
    """

    def __init__(self) -> None:
        self.signals: list[int] = []
        self.interruptible = False
        self._previous: dict[int, Any] = {}

    def __call__(self, signum: int, frame: Any) -> None:
        """Record the signal; raise KeyboardInterrupt on a repeat during a step."""
        self.signals.append(signum)
        if len(self.signals) > 1 and self.interruptible:
            self.interruptible = False
            raise KeyboardInterrupt(f"second signal {signal.Signals(signum).name}")

    @property
    def reason(self) -> str:
        """``received SIGTERM`` (the first signal)."""
        return f"received {signal.Signals(self.signals[0]).name}" if self.signals else ""

    def install(self) -> None:
        """Install the handler (main thread only; elsewhere signals stay as they are)."""
        if threading_is_main():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self)

    def restore(self) -> None:
        """Put the previous handlers back."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()


def _disk_full(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in DISK_FULL


def run(cfg: DictConfig, out_dir: Path, overwrite: bool = False) -> RunResult:
    """Run the closed loop of ``cfg`` and write ``out_dir / 'run.mcap'``.

    Args:
        cfg: The config.
        out_dir: The run directory.
        overwrite: Replace an existing ``run.mcap`` (a sweep's resume decides this);
            by default an existing log is refused.

    Raises:
        ConfigError: before anything is written, for a value that is not allowed, an
            existing log in ``out_dir``, or a log larger than the free disk space.
        DiskFull: when the disk fills during the run (the log holds every chunk
            written before; status ``aborted`` when it could still be finalised).
        KeyboardInterrupt, Terminated, Exception: re-raised after the log is
            finalised with status ``aborted``.
    """
    parts = build(cfg)
    log_path = Path(out_dir) / "run.mcap"
    if not overwrite and (log_path.exists() or log_path.is_symlink()):
        raise ConfigError(
            "hydra.run.dir",
            str(out_dir),
            "a directory without a run.mcap (it holds one already: not overwritten)",
        )
    check_disk(cfg, parts.grid, int(getattr(parts.plant, "n", 0) or 0), Path(out_dir))
    stop = StopRequest()
    stop.install()  # before the log exists: a signal from here on finalises it
    live = None
    try:
        live = start_live(cfg)
        out_dir.mkdir(parents=True, exist_ok=True)
        return _run(cfg, parts, out_dir, stop, live)
    finally:
        stop.interruptible = False
        if live is not None:
            live.close()
        stop.restore()


def _run(cfg: DictConfig, parts: Any, out_dir: Path, stop: StopRequest, live: Any) -> RunResult:
    """The loop of :func:`run`, with the log always finalised."""
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
        {**provenance(cfg.seed), "config_sha256": config_hash(cfg)},
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
    disk_error: OSError | None = None
    t0 = time.perf_counter()
    try:
        with threadpool_limits(1), warnings.catch_warnings():
            warnings.simplefilter("error", spla.MatrixRankWarning)
            warnings.filterwarnings("error", category=RuntimeWarning, module="harness")
            logger.write_target(target.p)
            stop.interruptible = True
            rec = loop.start()
            stop.interruptible = False
            logger.add_metadata("theory", theory(cfg, parts, swarm, rec))
            last = metrics(loop.grid, target, rec) | swarm(rec)
            check_finite(last)
            logger.handle(rec, last)
            for _ in range(steps):
                if stop.signals:
                    raise Terminated(stop.reason)
                stop.interruptible = True
                rec = loop.step()
                stop.interruptible = False
                done = rec.step
                last = metrics(loop.grid, target, rec) | swarm(rec)
                check_finite(last)
                logger.handle(rec, last)
                if done % 50 == 0 or done == steps:
                    bar.set_postfix_str(
                        f"t={rec.t:.2f} s |p_hat-p*|={last['phat_target_l2']:.3e}", refresh=False
                    )
                    bar.update(done - bar.n)
        state = "completed"
    except (KeyboardInterrupt, Terminated) as err:
        stop.interruptible = False
        reason = f"interrupted at step {done}: {type(err).__name__} {err}".strip()
        raise
    except Exception as err:
        stop.interruptible = False
        if is_numerical(err):
            state, reason = "diverged", f"step {done + 1}: {type(err).__name__}: {err}"
        elif _disk_full(err):
            disk_error = err  # type: ignore[assignment]
            reason = f"disk full at step {done}: {err}"
        else:
            reason = f"step {done}: {type(err).__name__}: {err}"
            raise
    finally:
        stop.interruptible = False
        bar.close()
        try:
            logger.finalize(state, reason, time.perf_counter() - t0)
        except OSError as err:
            if not _disk_full(err):
                raise
            disk_error = disk_error or err
    if disk_error is not None:
        raise DiskFull(
            f"disk full while writing {logger.path} at step {done} (t = {done * cfg.sim.dt:g} s): "
            f"{disk_error.strerror}; the log keeps what was written before "
            "(analysis.load.load_run recovers it)"
        )
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
