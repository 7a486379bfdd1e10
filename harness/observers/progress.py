"""``progress``: a progress bar on standard error."""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm

from harness.observers.base import Cadence, RunContext, Status
from harness.parameters import ParameterError, integer
from harness.records import StepRecord

PROGRESS = {"auto": None, "on": True, "off": False}
"""Values of the progress bar's ``show`` (``log.progress``): ``auto`` shows it on a
terminal."""


def automatic(show: object) -> bool:
    """Whether a ``show`` value (:data:`PROGRESS`) leaves the bar to the terminal."""
    return isinstance(show, str) and show in PROGRESS and PROGRESS[show] is None


class ProgressBar:
    """A progress bar on standard error (tqdm) with the time and ``||p_hat - p_*||``.

    Args:
        steps: The run's last step (run-time argument).
        show: ``auto`` (on a terminal) | ``on`` | ``off``.
        every: Steps between updates.
    """

    def __init__(self, steps: int, show: str = "auto", every: int = 50) -> None:
        if show not in PROGRESS:
            raise ParameterError("show", show, f"one of {', '.join(PROGRESS)}")
        self.steps, self.show = steps, PROGRESS[show]
        self.every = integer("every", every, 1)
        self.cadence = Cadence(self.every, steps)
        self.bar: Any = None

    def initialize(self, run: RunContext) -> None:
        """Open the bar."""
        disable = (not sys.stderr.isatty()) if self.show is None else not self.show
        self.bar = tqdm(total=self.steps, unit="step", disable=disable)

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Update every ``every`` steps and at the last."""
        if rec.step == 0 or not self.cadence.due(rec.step):
            return
        err = values.get("phat_target_l2")
        text = f"t={rec.t:.2f} s" + ("" if err is None else f" |p_hat-p*|={err:.3e}")
        self.bar.set_postfix_str(text, refresh=False)
        self.bar.update(rec.step - self.bar.n)

    def finalize(self, status: Status) -> None:
        """Close the bar."""
        if self.bar is not None:
            self.bar.close()
