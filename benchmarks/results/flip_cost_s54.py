"""Forward cost of Model.flip on the target-6 cube (25,000 particles, 64^3 grid, fixed
corotated), 50 steps: flip = 0 against 0.99 compiled in one process and timed in alternation;
the median over rounds of each round's ratio."""
import dataclasses, sys, time, numpy as np, jax, jax.numpy as jnp
import jaxmpm.bench as B
from jaxmpm.model import initial_state
from jaxmpm.step import step
steps, rounds = int(sys.argv[1]), int(sys.argv[2])
model, params = B._scene_model(25000, 64, "corotated", jnp.float32)
def prog(flip):
    m = dataclasses.replace(model, flip=flip)
    f = jax.jit(lambda p: jax.lax.scan(lambda s, _: (step(m, p, s), None), initial_state(m, p), None, length=steps)[0].x)
    return f.lower(params).compile()
progs = {0.0: prog(0.0), 0.99: prog(0.99)}
for p in progs.values(): jax.block_until_ready(p(params))
t = {k: [] for k in progs}
for r in range(rounds):
    for k, p in (progs.items() if r % 2 == 0 else reversed(list(progs.items()))):
        t0 = time.perf_counter(); jax.block_until_ready(p(params)); t[k].append(time.perf_counter() - t0)
a, b = np.array(t[0.0]), np.array(t[0.99])
print(f"{steps} steps: APIC median {1e3*np.median(a):.0f} ms, flip 0.99 median {1e3*np.median(b):.0f} ms, "
      f"ratio (median of rounds) {np.median(b/a):.3f}")
