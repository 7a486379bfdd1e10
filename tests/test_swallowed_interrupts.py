"""A second signal stops a run at once even when its interrupt lands in code that swallows
it (docs/reliability.md, signals): a ctypes callback, which prints and drops what it
raises (llvmlite's, while numba compiles the first step), or a library that catches it
and raises an error of its own (numba's ``RuntimeError: no compiled object yet``). The
run ends ``aborted`` with the interrupt as its reason, the program exits with status 130
and one line, and nothing prints a traceback.

Each case makes the swallowing happen deterministically inside a step: the step sends
itself the signals (``signal.raise_signal`` runs the handler before it returns).
"""

import ctypes
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest

from analysis.load import LogWarning, load_run
from harness.loop import ClosedLoop
from harness.runs.run import run

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "grid.n=8",
    "agents.n=40",
    "log.floor_draws=2",
    "log.progress=off",
    "sim.dt=0.02",
    "sim.t_final=0.08",
]
"""A run of 4 steps on an 8 x 8 grid."""

DROPS = ctypes.CFUNCTYPE(None)
"""A C function pointer that calls back into Python: ctypes prints what the callback
raises (through ``sys.unraisablehook``) and drops it, as llvmlite's callbacks do."""

INTERRUPT = "interrupted at step 1: KeyboardInterrupt second signal SIGINT"
"""The log's reason when the second SIGINT comes in step 2."""


def two_signals() -> None:
    """SIGINT twice: the first asks to stop, the second raises KeyboardInterrupt here."""
    signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGINT)


def in_step(monkeypatch, at: int, body) -> None:
    """Call ``body`` at the start of step ``at`` (inside the run's stop window)."""
    step = ClosedLoop.step

    def with_body(self):
        if self.n + 1 == at:
            body()
        return step(self)

    monkeypatch.setattr(ClosedLoop, "step", with_body)


@pytest.fixture
def unraisable(monkeypatch) -> list[object]:
    """What reaches the ``sys.unraisablehook`` in place before the run (the hook that
    prints ``Exception ignored ...`` and a traceback)."""
    seen: list[object] = []
    monkeypatch.setattr(sys, "unraisablehook", seen.append)
    return seen


def aborted(directory: Path) -> str:
    """The reason of the log in ``directory``, which must read back whole, ``aborted``."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", LogWarning)
        log = load_run(directory)
    assert log.state == "aborted", log.state
    return str(log.metadata["status"]["reason"])


def test_an_interrupt_a_callback_drops_is_raised_again_at_once(
    tmp_path, compose, monkeypatch, unraisable
):
    went_on: list[str] = []

    def body():
        DROPS(two_signals)()
        went_on.append("the step went on after the callback")

    in_step(monkeypatch, 2, body)
    with pytest.raises(KeyboardInterrupt, match=r"^second signal SIGINT$"):
        run(compose(TINY), tmp_path)
    assert went_on == []
    assert unraisable == [], "the dropped interrupt was printed"
    assert aborted(tmp_path) == INTERRUPT
    assert sys.getprofile() is None and sys.unraisablehook == unraisable.append


def test_an_error_in_place_of_a_swallowed_interrupt_ends_the_run_as_the_interrupt(
    tmp_path, compose, monkeypatch
):
    def body():
        signal.raise_signal(signal.SIGINT)
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:  # as numba's compiler, its state left half-built
            raise RuntimeError("no compiled object yet") from None

    in_step(monkeypatch, 2, body)
    with pytest.raises(KeyboardInterrupt, match=r"^second signal SIGINT$") as caught:
        run(compose(TINY), tmp_path)
    assert isinstance(caught.value.__cause__, RuntimeError)
    assert aborted(tmp_path) == INTERRUPT


def test_every_further_signal_raises_a_swallowed_interrupt_again(tmp_path, compose, monkeypatch):
    went_on: list[str] = []

    def body():
        signal.raise_signal(signal.SIGINT)
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pass
        went_on.append("swallowed")
        signal.raise_signal(signal.SIGINT)
        went_on.append("the third signal was only recorded")

    in_step(monkeypatch, 2, body)
    with pytest.raises(KeyboardInterrupt):
        run(compose(TINY), tmp_path)
    assert went_on == ["swallowed"]
    assert aborted(tmp_path) == INTERRUPT


def test_a_swallowed_interrupt_in_the_last_step_still_aborts_the_run(
    tmp_path, compose, monkeypatch
):
    """The window raises the interrupt again at its end: there is no next step to stop
    before."""

    def body():
        signal.raise_signal(signal.SIGINT)
        try:
            signal.raise_signal(signal.SIGINT)
        except KeyboardInterrupt:
            pass

    in_step(monkeypatch, 4, body)
    with pytest.raises(KeyboardInterrupt, match=r"^second signal SIGINT$"):
        run(compose(TINY), tmp_path)
    assert aborted(tmp_path) == "interrupted at step 3: KeyboardInterrupt second signal SIGINT"


SCRIPT = """
import ctypes, runpy, signal, sys
from harness.loop import ClosedLoop

step = ClosedLoop.step

def two_signals():
    signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGINT)

def swallowed():
    signal.raise_signal(signal.SIGINT)
    try:
        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        raise RuntimeError("no compiled object yet") from None

def with_signals(self):
    if self.n == 1:
        {body}
    return step(self)

ClosedLoop.step = with_signals
sys.argv = ["closed_loop", *sys.argv[1:]]
runpy.run_module("experiments.closed_loop", run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(
    "body",
    ["ctypes.CFUNCTYPE(None)(two_signals)()", "swallowed()"],
    ids=["dropped-by-a-callback", "turned-into-a-RuntimeError"],
)
def test_a_swallowed_interrupt_exits_130_in_one_line(tmp_path, body):
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable, "-c", textwrap.dedent(SCRIPT).format(body=body), *TINY,
            f"hydra.run.dir={out}",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )  # fmt: skip
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines() == ["interrupted: second signal SIGINT"], proc.stderr
    assert aborted(out) == INTERRUPT
