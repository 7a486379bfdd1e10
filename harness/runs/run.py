"""Run a closed loop built from a config to a finished ``run.mcap``.

A straight line: :func:`harness.runs.build.build` builds everything from the config; the
observers are initialised (:mod:`harness.observers`); the loop (:mod:`harness.loop`)
advances the plant, the estimator and the control, and every observer sees each step
(metrics, the divergence guard, the MCAP logger, the live view, the progress bar) and
never steers; the observers are finalised. Whatever happens, the log is finalised with
a ``status`` record: ``completed``; ``diverged`` (non-finite
values, negative density, lost mass or a numerical exception such as a singular
factorisation, with the reason); or ``aborted`` (an exception, Ctrl-C, SIGTERM or
SIGHUP, re-raised after the log is closed; a full disk, raised as :class:`DiskFull`).
"""

from __future__ import annotations

import errno
import signal
import sys
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import numpy as np
import scipy.sparse.linalg as spla
from omegaconf import DictConfig

from harness.fokker_planck import NumericalError
from harness.loop import Experiment, computing, trajectory
from harness.observers.base import Observer, RunContext, Status, seconds, writes_log
from harness.observers.log import LOG_FILE
from harness.parameters import ParameterError
from harness.runs.build import build
from harness.runs.checks import ConfigError
from harness.runs.resources import check_disk, disk_need


class Terminated(Exception):
    """Raised in the run loop, between steps, after SIGINT, SIGTERM or SIGHUP."""


@dataclass(frozen=True)
class RunResult:
    """Outcome of :func:`run`: final state and reason, steps done, wall time (s),
    the log's path, the last metrics and the wall time spent logging steps (s: the sum
    of the observers' ``seconds``, which the logger keeps).
    """

    state: str
    reason: str
    steps: int
    wall_s: float
    log_path: Path
    last_metrics: dict[str, Any]
    log_s: float = 0.0


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
"""Signals that stop a run with status ``aborted``: between steps, and between the draws
of the finite-N floors (:class:`StopRequest`)."""


class DiskFull(RuntimeError):
    """The log could not be written for want of space; ``str()`` is one line."""


def is_numerical(err: BaseException) -> bool:
    """Whether ``err`` raised inside the loop means the numbers broke down."""
    if isinstance(err, NUMERICAL):
        return True
    return isinstance(err, RuntimeError) and "singular" in str(err).lower()


class StopRequest:
    """Signal handler of a run: SIGINT, SIGTERM and SIGHUP ask the run to stop at the
    next entry of its :meth:`window` (between steps, and between the draws of the
    finite-N floors). A second signal stops at once, but only inside the window (while
    the harness computes): never inside the logger or the log's finalisation, so a burst
    of signals cannot leave the log unfinalised.

    The stop at once is a ``KeyboardInterrupt`` raised from whatever Python code runs
    when the signal is handled, and code can swallow it: a ctypes callback (llvmlite's,
    while numba compiles) prints it and drops it, and a library may turn it into an
    error of its own (numba's ``RuntimeError: no compiled object yet``). The request
    remembers that it raised, and until the interrupt leaves the window:

    - every further signal raises it again;
    - one dropped by a callback (seen by the hook for exceptions Python cannot raise,
      ``sys.unraisablehook``, which then stays silent about it) is raised again at the
      next Python call or return in the main thread outside this module
      (``sys.setprofile``; not while another profiler is set), and so is a signal that
      comes while the window itself enters or exits (never raised in this module's
      code, so the window always restores its state);
    - an exception that leaves the window in its place becomes the interrupt (chained
      to it), and a window that ends without it raises it at its end;
    - entering a window raises it.

    So the run ends ``aborted`` with the interrupt as its reason, never with the error a
    swallowed interrupt left behind.
    """

    def __init__(self) -> None:
        self.signals: list[int] = []
        self.interruptible = False
        self.interrupted = False
        self._raised: BaseException | None = None
        self._profile = self._again  # one bound method, to recognise it in sys.getprofile()
        self._previous: dict[int, Any] = {}
        self._previous_hook: Callable[[Any], Any] | None = None

    def __call__(self, signum: int, frame: Any) -> None:
        """Record the signal; raise KeyboardInterrupt on a repeat inside the window
        (again on every repeat until the interrupt leaves the window).
        """
        self.signals.append(signum)
        if len(self.signals) < 2 or not self.interruptible:
            return
        self.interrupted = True
        if frame is not None and frame.f_globals is _MODULE:
            self._arm()  # the window's own entry or exit: raised just outside it
            return
        self._interrupt()

    def _interrupt(self, cause: BaseException | None = None) -> NoReturn:
        """Raise the interrupt (``second signal SIGINT``: the second signal's name)."""
        err = KeyboardInterrupt(f"second signal {signal.Signals(self.signals[1]).name}")
        self._raised = err
        raise err from cause

    def window(self) -> AbstractContextManager[None]:
        """Around a piece of computation (a step and the observers that compute,
        :func:`harness.loop.trajectory`; a draw of the floors,
        :attr:`harness.observers.base.RunContext.window`): stop before it when a signal
        came (:class:`Terminated`, or the interrupt when one was raised); while it
        computes, a second signal stops at once. Windows nest: leaving an inner one
        keeps the outer one open.
        """
        return _Window(self)

    @property
    def reason(self) -> str:
        """``received SIGTERM`` (the first signal)."""
        return f"received {signal.Signals(self.signals[0]).name}" if self.signals else ""

    def _unraisable(self, info: Any) -> None:
        """``sys.unraisablehook`` while the run is on: the interrupt dropped by a ctypes
        callback is raised again at the next call or return outside this module, and
        not printed; anything else goes to the hook that was there before.
        """
        if info.exc_value is not None and info.exc_value is self._raised:
            self._raised = None  # dropped: the next one raised is the live one
            if self.interruptible:
                self._arm()
            return
        if self._previous_hook is not None:
            self._previous_hook(info)

    def _arm(self) -> None:
        """Raise the interrupt at the next call or return outside this module in the main
        thread (:meth:`_again`), unless another profile function is set.
        """
        if sys.getprofile() is None and threading_is_main():
            sys.setprofile(self._profile)

    def _again(self, frame: FrameType, event: str, arg: Any) -> None:
        """The profile function :meth:`_arm` sets: raise the interrupt (Python then
        unsets it); off, without raising, once the window is left.
        """
        if frame.f_globals is _MODULE:  # the window's own exit, the handler and hooks
            return
        if not (self.interruptible and self.interrupted):
            sys.setprofile(None)
            return
        self._interrupt()

    def _disarm(self) -> None:
        """Unset the profile function of :meth:`_again` when it is set."""
        if sys.getprofile() is self._profile:
            sys.setprofile(None)

    def install(self) -> None:
        """Install the handler and the hook of dropped interrupts (main thread only;
        elsewhere signals stay as they are).
        """
        if threading_is_main():
            for sig in STOP_SIGNALS:
                self._previous[sig] = signal.signal(sig, self)
            self._previous_hook = sys.unraisablehook
            sys.unraisablehook = self._unraisable

    def restore(self) -> None:
        """Put the previous handlers and hook back."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()
        if self._previous_hook is not None:
            sys.unraisablehook = self._previous_hook
            self._previous_hook = None
        self._disarm()


class _Window(AbstractContextManager[None]):
    """The context manager of :meth:`StopRequest.window` (a class, not a generator, so
    that its exit runs in this module, where the re-raising profile function stays
    quiet, and always sets the request's state before anything can raise).
    """

    def __init__(self, stop: StopRequest) -> None:
        self.stop = stop
        self.outer = False

    def __enter__(self) -> None:
        stop = self.stop
        if stop.interrupted:
            stop._interrupt()
        if stop.signals:
            raise Terminated(stop.reason)
        self.outer = stop.interruptible
        stop.interruptible = True

    def __exit__(self, kind: Any, err: BaseException | None, tb: Any) -> None:
        stop = self.stop
        stop.interruptible = self.outer and not stop.interrupted
        if not stop.interruptible:
            stop._disarm()
        if stop.interrupted and (err is None or isinstance(err, Exception)):
            stop._interrupt(err)  # swallowed, or turned into another error


_MODULE = globals()
"""This module's namespace: :meth:`StopRequest._again` never raises in its frames."""


def check_writes_log(exp: Experiment) -> None:
    """A run writes its log: one of its observers must
    (:func:`harness.observers.base.writes_log`, the observer ``log``).

    Raises:
        ConfigError: naming ``observers`` for a run whose observers write no log
            (``observers=[metrics]``, ``~observers.log``), before anything is written.
    """
    if not any(writes_log(o) for o in exp.observers.values()):
        raise ConfigError(
            "observers",
            list(exp.observers),
            "observers that include log, which writes the run's run.mcap "
            "(observers=[default], or a list with log; harness.api.simulate runs without one)",
        )


def _disk_full(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in DISK_FULL


def run(cfg: DictConfig | Experiment, out_dir: Path, overwrite: bool = False) -> RunResult:
    """Run the closed loop of ``cfg`` (a config, or its :func:`~harness.runs.build.build`)
    and write ``out_dir / 'run.mcap'``.

    Args:
        cfg: The config, or the experiment built from it (built once: a caller that
            built to check hands its build on). An experiment runs once.
        out_dir: The run directory.
        overwrite: Replace an existing ``run.mcap``; by default an existing log is
            refused, and the log is created exclusively, so of two runs started into
            one directory at the same moment exactly one writes it.

    Raises:
        ConfigError: before anything is written, for a value that is not allowed,
            observers that write no log (:func:`check_writes_log`), an existing log in
            ``out_dir`` (also one another process creates while this
            run starts), a log larger than the free disk space, or an observer that
            cannot start (a live port in use).
        ValueError: for an experiment that has run already.
        DiskFull: when the disk fills during the run (the log holds every chunk
            written before; status ``aborted`` when it could still be finalised).
        KeyboardInterrupt, Terminated, Exception: re-raised after the log is
            finalised with status ``aborted``.
    """
    exp = cfg if isinstance(cfg, Experiment) else build(cfg)
    if exp.spent:
        raise ValueError(
            "this Experiment has run already (its components keep their state): build it again"
        )
    check_writes_log(exp)
    out_dir = Path(out_dir)
    log_path = out_dir / LOG_FILE
    if not overwrite and (log_path.exists() or log_path.is_symlink()):
        raise ConfigError(
            "hydra.run.dir",
            str(out_dir),
            "a directory without a run.mcap (it holds one already: not overwritten)",
        )
    check_disk(disk_need(exp), out_dir)
    stop = StopRequest()
    stop.install()  # before the log exists: a signal from here on finalises it
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        return _run(exp, out_dir, stop, exclusive=not overwrite)
    finally:
        stop.interruptible = False
        stop.restore()


def _initialize(exp: Experiment, context: RunContext) -> list[Observer]:
    """Initialise the observers in order; the ones started, for :func:`_finalize`.

    An observer whose ``initialize`` fails is finalised with the ones before it (so a
    logger that could open its file but not write to it still closes it): ``finalize``
    must be safe after a partial ``initialize``.

    Raises:
        ConfigError: for an observer that refuses to start (a live port in use), after
            finalising the ones already started (nothing is logged when it comes before
            the logger, as the live view does).
    """
    started: list[Observer] = []
    for name, observer in exp.observers.items():
        started.append(observer)
        try:
            observer.initialize(context)
        except ParameterError as err:
            _finalize(started, Status("aborted", f"observer {name} could not start: {err}", 0.0))
            key = exp.keys.get(f"observers.{name}.{err.name}", f"observers.{name}.{err.name}")
            raise ConfigError(key, err.value, err.allowed) from None
        except FileExistsError as err:  # another run created the log first
            _finalize(started, Status("aborted", f"observer {name} could not start", 0.0))
            raise ConfigError(
                "hydra.run.dir",
                str(context.out_dir),
                f"a directory without a run.mcap ({err.filename} was created by another "
                "run: not overwritten)",
            ) from None
        except BaseException as err:
            why = f"observer {name} could not start: {type(err).__name__}: {err}"
            try:
                _finalize(started, Status("aborted", why, 0.0))
            except BaseException:  # the first error is the one to report
                pass
            raise
    return started


def _finalize(observers: list[Observer], status: Status) -> None:
    """Finalise the observers in reverse order, each whatever the others do; the first
    error is raised after all ran.
    """
    first: BaseException | None = None
    for observer in reversed(observers):
        try:
            observer.finalize(status)
        except BaseException as err:  # re-raised below, after the others
            first = first or err
    if first is not None:
        raise first


def _run(exp: Experiment, out_dir: Path, stop: StopRequest, exclusive: bool) -> RunResult:
    """The run of :func:`run`: observers initialised, the trajectory stepped
    (:func:`harness.loop.trajectory`), the observers finalised whatever happens (so the
    log always is); the log created exclusively when ``exclusive``.
    """
    context = RunContext(out_dir, exclusive=exclusive, window=stop.window)
    state, reason, done = "aborted", "", 0
    last: dict[str, float | None] = {}
    disk_error: OSError | None = None
    t0 = time.perf_counter()
    started: list[Observer] = []
    watching = list(exp.observers.values())
    try:
        with computing():
            started = _initialize(exp, context)
        for rec, values in trajectory(exp, watching, stop.window, hold=True):
            done, last = rec.step, values
        state = "completed"
    except ConfigError:
        raise  # an observer refused to start: nothing was logged
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
        try:
            _finalize(started, Status(state, reason, time.perf_counter() - t0))
        except OSError as err:
            if not _disk_full(err):
                raise
            disk_error = disk_error or err
    log_s = sum(seconds(o) for o in watching)
    if disk_error is not None:
        raise DiskFull(
            f"disk full while writing {out_dir / 'run.mcap'} at step {done} "
            f"(t = {done * exp.dt:g} s): {disk_error.strerror}; the log keeps what was "
            "written before (analysis.load.load_run recovers it)"
        )
    return RunResult(state, reason, done, time.perf_counter() - t0, out_dir / LOG_FILE, last, log_s)


def threading_is_main() -> bool:
    """Signal handlers can only be installed from the main thread."""
    import threading

    return threading.current_thread() is threading.main_thread()
