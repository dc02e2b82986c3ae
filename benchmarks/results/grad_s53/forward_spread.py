"""Forward rollout of the target-6 cube (200 steps), four timed calls after the compiling one; run it in several fresh processes to see the spread (session 53)."""
import time, sys, numpy as np, jax
from jaxmpm.bench import grad_problem
final_x, theta0 = grad_problem(25000, 64, 200)
f = jax.jit(final_x)
jax.block_until_ready(f(theta0)); ts = []
for _ in range(4):
    t0 = time.perf_counter(); jax.block_until_ready(f(theta0)); ts.append(time.perf_counter() - t0)
print("forward ms", [round(1e3 * t) for t in ts], flush=True)
