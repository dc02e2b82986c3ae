"""Per-direction cost of forward-mode Jacobians against k (session 53): the forward (k = 0) and
k = 1..K tangent directions, all compiled in one process and timed in alternation.

    python benchmarks/results/grad_s53/kscan.py STEPS ROUNDS KS   # e.g. 20 8 0,1,2,3,4,5,6

25,000 particles, 64^3 grid (the target-6 cube). Prints, per k, the median time, its ratio to
the forward in the same round, and (ratio - 1) / k, the per-direction cost in forwards."""
import sys, time, numpy as np, jax, jax.numpy as jnp
from jaxmpm.bench import grad_problem
steps, rounds = int(sys.argv[1]), int(sys.argv[2]); ks = [int(k) for k in sys.argv[3].split(",")]
final_x, theta0 = grad_problem(25000, 64, steps)
def build(k):
    basis = jnp.eye(6, dtype=theta0.dtype)[:k]
    if k == 0:
        f = jax.jit(lambda th: final_x(th))
    else:
        f = jax.jit(lambda th: jax.vmap(lambda t: jax.jvp(final_x, (th,), (t,))[1])(basis))
    return f.lower(theta0).compile()
progs = {k: build(k) for k in sorted(set(ks) | {0})}
for p in progs.values(): jax.block_until_ready(p(theta0))
times = {k: [] for k in progs}
for r in range(rounds):
    for k, p in (progs.items() if r % 2 == 0 else reversed(list(progs.items()))):
        t0 = time.perf_counter(); jax.block_until_ready(p(theta0)); times[k].append(time.perf_counter() - t0)
f = np.array(times[0])
for k in progs:
    t = np.array(times[k]); ratio = np.median(t / f)
    print(f"k={k}: median {1e3*np.median(t):.0f} ms, / forward {ratio:.2f} (target {1 + 0.6*k:.1f}), "
          f"per direction {(ratio - 1)/max(k, 1):.2f}", flush=True)
