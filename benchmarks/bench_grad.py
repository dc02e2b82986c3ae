"""Gradient benchmark (the same as `jaxmpm bench grad`): run from the repository root.

    python benchmarks/bench_grad.py [--particles 25000] [--grid 64] [--steps 200] [--json out.json]

Issue 15, target 6: one reverse-mode gradient of the rollout loss mean(x_final^2) with respect to
(E, nu, density, initial velocity) against Taichi's autodiff of the same step
(benchmarks/peers/taichi_grad.py, ti.ad.Tape; skipped when Taichi is not installed), and
forward-mode Jacobians of the final positions for k = 1..6 parameters against one forward
rollout. Each code runs in its own process.
"""

import sys

from jaxmpm.bench import bench_grad

if __name__ == "__main__":
    sys.exit(bench_grad(sys.argv[1:]))
