"""Paired, interleaved timing of two variants of module-level functions of jaxmpm.step, in one
process (session 52): the host is shared, and runs of separate processes drifted by 20-40 %.

    git show BASE:jaxmpm/step.py > jaxmpm/_step_orig.py     # the variant to compare against
    python benchmarks/results/grad_s52/paired.py STEPS ROUNDS KS NAMES [ALSO]
    # e.g. 20 16 1,6 apply_domain_walls; stencil_moments@jaxmpm._state_orig (after
    # git show BASE:jaxmpm/state.py > jaxmpm/_state_orig.py) swaps a name step.py imports; k = 0 times the forward, k = -1 the reverse-mode gradient; delete jaxmpm/_step_orig.py after
    # ALSO (session 53): modules, comma-separated, whose imports of NAMES are swapped as well, e.g. jaxmpm.state

Both variants are compiled before any timing; each round times every program once, the order
reversed every other round; the figure is the median over rounds of new/orig in the same round.
25,000 particles, 64^3 grid (the target-6 cube)."""
import importlib, sys, time, numpy as np, jax, jax.numpy as jnp
import jaxmpm.step; S = sys.modules["jaxmpm.step"]
import jaxmpm._step_orig; O = sys.modules["jaxmpm._step_orig"]
from jaxmpm.bench import grad_problem
steps, rounds = int(sys.argv[1]), int(sys.argv[2]); ks = [int(k) for k in sys.argv[3].split(",")]
names = sys.argv[4].split(",")  # names in jaxmpm.step to swap; NAME@MODULE takes the old one from MODULE
names, sources = [n.split("@")[0] for n in names], [n.split("@")[1] if "@" in n else None for n in names]
also = [importlib.import_module(m) for m in sys.argv[5].split(",")] if len(sys.argv) > 5 else []
new = {n: getattr(S, n) for n in names}
old = {n: getattr(O if m is None else importlib.import_module(m), n) for n, m in zip(names, sources)}
final_x, theta0 = grad_problem(25000, 64, steps)
def put(variant):
    for module in [S, *also]:
        for n in names: setattr(module, n, variant[n])
def build(k, variant):
    put(variant)
    basis = jnp.eye(6, dtype=theta0.dtype)[:k]
    if k == 0:
        f = jax.jit(lambda th: final_x(th))
    elif k < 0:  # reverse mode, as bench_grad: every step checkpointed
        f = jax.jit(jax.grad(lambda th: jnp.mean(final_x(th, checkpoint=True) ** 2)))
    else:
        f = jax.jit(lambda th: jax.vmap(lambda t: jax.jvp(final_x, (th,), (t,))[1])(basis))
    f = f.lower(theta0).compile()
    return f
progs = {(k, v): build(k, var) for k in ks for v, var in (("orig", old), ("new", new))}
put(new)
outs = {key: np.asarray(p(theta0)) for key, p in progs.items()}
for k in ks: print("k", k, "max |new - orig|", float(np.max(np.abs(outs[(k, 'new')] - outs[(k, 'orig')]))))
times = {key: [] for key in progs}
for r in range(rounds):
    for key, p in (progs.items() if r % 2 == 0 else reversed(list(progs.items()))):
        t0 = time.perf_counter(); jax.block_until_ready(p(theta0)); times[key].append(time.perf_counter() - t0)
for k in ks:
    o, n = np.array(times[(k, "orig")]), np.array(times[(k, "new")])
    print(f"k={k}: orig median {1e3*np.median(o):.0f} ms, new median {1e3*np.median(n):.0f} ms, "
          f"new/orig per round median {np.median(n/o):.3f} (min {np.min(n/o):.3f}, max {np.max(n/o):.3f})", flush=True)
