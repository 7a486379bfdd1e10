# %% [markdown]
# # Exploring the closed loop in memory
#
# `harness.api.simulate` steps the closed loop without writing a log and yields each
# step's record and metrics. Here: the paper's experiment (N = 1024 robots, dt = 0.01 s,
# the KDE, both filters, the paper's law), shortened to 20 s on a 20 x 20 grid; its
# estimation error `||p_hat - p_*||` (metric `phat_target_l2`, 1/length) against t; then
# the same with the heat-equation law (`control=heat`), compared.
#
# Run it as a script (`python examples/explore.py`, from any directory: the figure goes
# to `$EXPLORE_FIGURE`, its folder created when missing, else to a temporary directory)
# or cell by cell in an editor that reads `# %%` cells (VS Code, Spyder, Jupytext).

# %%
import os
import sys
import tempfile
from pathlib import Path

import matplotlib
import numpy as np

if "ipykernel" not in sys.modules:
    matplotlib.use("Agg")  # no display: the figure is written to a file
import matplotlib.pyplot as plt

from harness import api


def refuse(why: str) -> None:
    """Stop before the simulations: one line, exit status 2 (as a config the harness refuses)."""
    print(f"error: EXPLORE_FIGURE={figure}: {why}", file=sys.stderr)
    sys.exit(2)


# where the figure goes, decided before the simulations: a missing folder is created, and
# one that cannot be stops here, not after them
figure = Path(os.environ.get("EXPLORE_FIGURE") or Path(tempfile.mkdtemp()) / "explore.png")
formats = plt.gcf().canvas.get_supported_filetypes()
plt.close("all")
if figure.suffix.lstrip(".").lower() not in formats:
    refuse(f"a file name ending in one of .{', .'.join(formats)}")
if figure.exists() and not figure.is_file():
    refuse("not a regular file")
try:
    figure.parent.mkdir(parents=True, exist_ok=True)
except OSError as err:
    refuse(f"no folder for it ({err.strerror or err})")

SHORT = ["sim.t_final=20", "grid.n=20"]  # the paper's defaults otherwise (conf/closed_loop.yaml)
cfg = api.compose(SHORT)
print(f"N = {cfg.agents.n}, {cfg.grid.n} x {cfg.grid.n} grid, dt = {cfg.sim.dt} s")


# %%
def error_curve(cfg):
    """``(t, ||p_hat - p_*||)`` at every step of the loop of ``cfg``."""
    t, err = [], []
    for rec, m in api.simulate(cfg, copy=False):  # only numbers are kept: no copy needed
        t.append(rec.t)
        err.append(m["phat_target_l2"])
    return np.array(t), np.array(err)


curves = {"paper": error_curve(cfg)}

# %%
curves["heat"] = error_curve(api.compose([*SHORT, "control=heat"]))

# %%
final = {law: float(err[-1]) for law, (t, err) in curves.items()}
for law, value in final.items():
    print(f"{law:>5}: ||p_hat - p_*|| = {value:.4g} 1/length at t = {curves[law][0][-1]:g} s")

fig, ax = plt.subplots(figsize=(6, 3.5), layout="constrained")
for law, (t, err) in curves.items():
    ax.plot(t, err, label=f"control={law}")
ax.set(xlabel="t (s)", ylabel=r"$\|\hat p - p_*\|$ (1/length)", yscale="log")
ax.legend()
fig.savefig(figure, dpi=120)
print(f"figure: {figure}")
