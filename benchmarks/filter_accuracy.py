"""Fast filters against the reference filters in one closed loop (slow).

    python -m benchmarks.filter_accuracy [--n 30] [--steps 1000] [--seed 0]

Prints, every 100 steps, the reference's L2 errors against the mean-field truth and
the fast-to-reference distances, and at the end the worst and mean ratios (the
accuracy bar is a ratio below 0.1). At n = 30 the dense reference gradient filter
(1800 states) costs about 0.65 s per step.
"""

from __future__ import annotations

import argparse
import time

from harness.estimators.filters.compare import compare_filters


def main() -> None:
    """Run the comparison and print the ratios."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=30, help="cells per side")
    parser.add_argument("--steps", type=int, default=1000, help="closed-loop steps of 0.01 s")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    t0 = time.perf_counter()
    c = compare_filters(n=args.n, steps=args.steps, seed=args.seed, progress=True)
    worst, mean = c.ratios(skip=1), c.mean_ratios(skip=1)
    print(f"n = {args.n}, {args.steps} steps, {time.perf_counter() - t0:.0f} s wall")
    print(f"density : worst gap/error {worst[0]:.4f}, mean gap / mean error {mean[0]:.4f}")
    print(f"gradient: worst gap/error {worst[1]:.4f}, mean gap / mean error {mean[1]:.4f}")
    print("bar (< 0.1):", "met" if max(worst) < 0.1 else "NOT met")


if __name__ == "__main__":
    main()
