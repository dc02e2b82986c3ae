"""moment_sums alone under jax.vmap over k tangent directions (25,000 particles, 27 offsets,
gathered 4-wide rows), median ms per call for k = 1..6, two passes (session 53). Run it once as
is and once under ``taskset -c 0`` to compare 2 threads with 1."""
import time, numpy as np, jax, jax.numpy as jnp
from jaxmpm.state import moment_sums, stencil_offsets
N = 25000; offs = stencil_offsets(3)
key = jax.random.PRNGKey(0)
w = [jax.random.uniform(jax.random.fold_in(key, i), (N,)) for i in range(27)]
def bench(k, n=60):
    rows = jax.random.normal(key, (k, 27 * N, 4))
    def one(r1):
        vals = [r[:, :3] for r in jnp.split(r1, 27, axis=0)]
        return moment_sums(offs, w, vals)
    f = jax.vmap(one)
    g = jax.jit(f).lower(rows).compile()
    jax.block_until_ready(g(rows)); ts = []
    for _ in range(n):
        t0 = time.perf_counter(); jax.block_until_ready(g(rows)); ts.append(time.perf_counter() - t0)
    return 1e3 * np.median(ts)
for r in range(2):
    for k in (1, 2, 3, 4, 5, 6):
        ms = bench(k); print(k, f"{ms:.2f} ms, per direction {ms/k:.2f}")
