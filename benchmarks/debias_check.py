"""Paper loop against the debiased loop, measured where the robots are (slow).

    python -m benchmarks.debias_check [--n 16384] [--t-final 60] [--law both] [--seed 0]
                                      [--draws 200] [--out result.json]
    python -m benchmarks.debias_check --certificate [--grid 30]
    python -m benchmarks.debias_check --costs

Runs the paper's closed loop (agents, KDE, both filters, paper's law; the composed
``closed_loop`` config with ``agents.n`` and ``sim.t_final`` overridden) through
:func:`harness.runs.run.run`, and for ``--law debiased`` the same with ``kde.debias=true``
(docs/debias.md): the feedback term compares the estimates with the smoothed target
``K_h * p_*``, the sigma drift keeps ``p_*``. From the log, every 10 s it prints
``swarm_l2`` and ``swarm_w2`` with their ratios to the finite-N floor (mean of the
Monte-Carlo band of N robots drawn independently from ``p_*``), and ``||p_hat - p_*||``
and ``||p_hat - K_h * p_*||``.

The bar: the debiased loop within 1.3 times its ``swarm_l2`` floor by
t = 60 s, the paper's loop above 2 times (N = 16384).

``--certificate`` prints the linearised stability facts of docs/debias.md for the
default target and the paper's gains: the range of the generalised eigenvalues of
the symmetric part of the cross form ``Q`` against ``S = int p_* |grad u|^2``
(condition (C) holds near ``p_*`` when the minimum exceeds ``-sigma / alpha``), and
the slowest decay rates of the linearised debiased and paper loops.

``--costs`` times the swarm metrics per call (median of 5, BLAS on one thread as in
the run) at N = 1024 to 65536 on the 30 x 30 grid, and one floor draw at N = 65536.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

from analysis.load import load_run
from harness.api import compose
from harness.estimators.kde import KDE, kernel_1d
from harness.estimators.smoothing import smoothed_density
from harness.grid import Grid
from harness.observers.swarm_metrics import TargetMeasure, swarm_l2, swarm_w2
from harness.runs.run import run
from harness.targets.densities import DEFAULT_TARGET


def run_one(
    law: str, n: int, t_final: float, seed: int, draws: int, every: float, out: Path
) -> dict[str, object]:
    """One run of the paper's loop (``law = paper``) or the debiased loop
    (``kde.debias=true``) through the harness; the swarm metrics every ``every`` s."""
    stride = max(1, round(every / 0.01))
    cfg = compose(
        [
            f"agents.n={n}",
            f"sim.t_final={t_final}",
            f"seed={seed}",
            f"kde.debias={str(law == 'debiased').lower()}",
            f"log.positions_every={stride}",
            f"log.w2_every={stride}",
            "log.field_every=100000",
            f"log.floor_draws={draws}",
            "log.progress=off",
        ]
    )
    t0 = time.perf_counter()
    result = run(cfg, out)
    log = load_run(out)
    theory = log.metadata["theory"]
    fl2, fw2 = (float(theory[f"swarm_{k}_floor_mean"]) for k in ("l2", "w2"))
    m = log.metrics
    rows = []
    for i in np.flatnonzero(np.isfinite(m["swarm_l2"])):
        rows.append(
            {
                "t": float(m["t"][i]),
                "swarm_l2": float(m["swarm_l2"][i]),
                "swarm_l2_ratio": float(m["swarm_l2"][i]) / fl2,
                "swarm_w2": float(m["swarm_w2"][i]),
                "swarm_w2_ratio": float(m["swarm_w2"][i]) / fw2,
                "phat_target_l2": float(m["phat_target_l2"][i]),
                "phat_smoothed_l2": float(m["phat_smoothed_target_l2"][i]),
            }
        )
        r = rows[-1]
        print(
            f"[{law} N={n}] t={r['t']:5.1f} s swarm_l2={r['swarm_l2']:.4f} "
            f"({r['swarm_l2_ratio']:.2f} x floor) swarm_w2={r['swarm_w2']:.5f} "
            f"({r['swarm_w2_ratio']:.2f} x floor) |p_hat-p*|={r['phat_target_l2']:.4f} "
            f"|p_hat-K_h p*|={r['phat_smoothed_l2']:.4f}"
        )
    print(f"[{law} N={n}] {result.state} in {time.perf_counter() - t0:.0f} s wall")
    return {
        "law": law,
        "n": n,
        "seed": seed,
        "t_final": t_final,
        "w2_method": theory["swarm_w2_method"],
        "floor_swarm_l2": {k: theory[f"swarm_l2_floor_{k}"] for k in ("mean", "lo", "hi")},
        "floor_swarm_w2": {k: theory[f"swarm_w2_floor_{k}"] for k in ("mean", "lo", "hi")},
        "rows": rows,
    }


def certificate(n: int = 30, h: float = 0.04, alpha: float = 0.003, sigma: float = 5e-5) -> None:
    """Linearised dissipation and spectrum at ``p_*`` (see the module docstring).

    In ``u = Phi / p_*`` on the grid: ``S = G^T P G`` (``P = diag p_*`` on both gradient
    components) and the cross form ``B = S K diag(p_*) / p~_*`` with ``K`` the KDE's
    kernel on the cells; both restricted to mass-zero perturbations. The linearised
    loops on ``Phi``: debiased ``-alpha S K / p~_* - sigma L_c / p_*``, paper ``-(alpha
    S + sigma L_c) / p_*``, with ``L_c`` the compact face-difference operator of the
    Fokker-Planck step (face values of ``p_*`` by averaging).
    """
    g = Grid.square(n)
    ps = DEFAULT_TARGET.on_grid(g).ravel()
    pt = smoothed_density(DEFAULT_TARGET, g, h).ravel()
    kx, _ = kernel_1d(g.x, g.x, h, g.x0, g.x1, True)
    ky, _ = kernel_1d(g.y, g.y, h, g.y0, g.y1, True)
    k = np.kron(ky * g.dy, kx * g.dx)
    gm = g.gradient_matrix.toarray()
    s_form = gm.T @ (np.concatenate([ps, ps])[:, None] * gm)

    def diff(m: int, d: float) -> sp.spmatrix:
        return sp.diags([-np.ones(m - 1), np.ones(m - 1)], [0, 1], shape=(m - 1, m)) / d

    dm = sp.vstack(
        [sp.kron(sp.identity(n), diff(n, g.dx)), sp.kron(diff(n, g.dy), sp.identity(n))]
    ).toarray()
    p_face = 0.5 * (np.abs(dm) * g.dx) @ ps
    l_c = dm.T @ (p_face[:, None] * dm)
    basis, _ = np.linalg.qr(np.column_stack([ps, np.eye(n * n)[:, : n * n - 1]]))
    z = basis[:, 1:]
    b = s_form @ ((k * ps[None, :]) / pt[:, None])
    b = 0.5 * (b + b.T)
    w = sl.eigh(z.T @ b @ z, z.T @ s_form @ z, eigvals_only=True)
    print(
        f"n = {n}: Q / S in [{w.min():.4f}, {w.max():.4f}]; -sigma / alpha = {-sigma / alpha:.4f}"
    )
    loops = {
        "debiased": -alpha * s_form @ (k / pt[:, None]) - sigma * l_c / ps[None, :],
        "paper": -(alpha * s_form + sigma * l_c) / ps[None, :],
    }
    for name, a in loops.items():
        ev = np.linalg.eigvals(a)
        ev = ev[np.argsort(-ev.real)]
        rates = ", ".join(f"{-e.real:.4f}" for e in ev[1:4])
        print(
            f"  {name:9s} mass mode {ev[0].real:.1e}, slowest rates (1/s) {rates}, "
            f"max |imag| {np.abs(ev.imag).max():.3f}"
        )


def costs(repeats: int = 5) -> None:
    """Median wall time per call of the swarm metrics (see the module docstring)."""
    g = Grid.square(30)
    kde = KDE(g, 0.04)
    smooth = smoothed_density(DEFAULT_TARGET, g, 0.04)
    measures = {r: TargetMeasure.from_density(DEFAULT_TARGET, g, r) for r in (1, 4)}
    rng = np.random.default_rng(0)

    def timed(fn, *args) -> float:
        out = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn(*args)
            out.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(out))

    with threadpool_limits(1):
        t0 = time.perf_counter()
        smoothed_density(DEFAULT_TARGET, g, 0.04)
        print(f"smoothed_density (once per run): {1e3 * (time.perf_counter() - t0):.2f} ms")
        for n in (1024, 4096, 16384, 65536):
            x = DEFAULT_TARGET.sample(n, g, rng)
            swarm_l2(x, kde, smooth, g)
            line = [f"N = {n:6d}: swarm_l2 {timed(swarm_l2, x, kde, smooth, g):7.2f} ms"]
            for r, m in measures.items():
                line.append(f"sliced(refine {r}) {timed(swarm_w2, x, m, 'sliced'):7.1f} ms")
            if n <= 4096:
                line.append(f"emd(refine 1) {timed(swarm_w2, x, measures[1], 'emd'):7.1f} ms")
            line.append(f"sample p_* {timed(DEFAULT_TARGET.sample, n, g, rng):6.1f} ms")
            print(", ".join(line), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=16384, help="robots")
    parser.add_argument("--t-final", type=float, default=60.0, help="horizon (s)")
    parser.add_argument("--law", choices=["paper", "debiased", "both"], default="both")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--draws", type=int, default=200, help="Monte-Carlo draws of the floor")
    parser.add_argument("--every", type=float, default=10.0, help="print interval (s)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON")
    parser.add_argument("--certificate", action="store_true", help="linearised facts only")
    parser.add_argument("--grid", type=int, default=30, help="cells per side (certificate)")
    parser.add_argument("--costs", action="store_true", help="time the swarm metrics only")
    args = parser.parse_args()
    if args.costs:
        costs()
        return
    if args.certificate:
        certificate(args.grid)
        return
    laws = ["paper", "debiased"] if args.law == "both" else [args.law]
    with tempfile.TemporaryDirectory() as tmp:
        results = [
            run_one(law, args.n, args.t_final, args.seed, args.draws, args.every, Path(tmp) / law)
            for law in laws
        ]
    print(f"\nN = {args.n}, t = {args.t_final:g} s, seed {args.seed}:")
    for r in results:
        last = r["rows"][-1]
        print(
            f"  {r['law']:9s} swarm_l2 / floor = {last['swarm_l2_ratio']:.2f}   "
            f"swarm_w2 / floor = {last['swarm_w2_ratio']:.2f} ({r['w2_method']})   "
            f"|p_hat - p*| = {last['phat_target_l2']:.4f}"
        )
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
