"""A memory-bound elementwise fusion a*b+c on (k, 25000, 12) against (75000, 12), median ms per slab (session 53): does XLA CPU split a leading axis of 3 unevenly between 2 threads? (It does not: per slab the times are equal.) Run once as is, once under taskset -c 0."""
import time, numpy as np, jax, jax.numpy as jnp
def f(a, b, c):
    return a * b + c
for shape in [(2, 25000, 12), (3, 25000, 12), (4, 25000, 12), (75000, 12), (5, 25000, 12), (6, 25000, 12)]:
    args = [jnp.full(shape, 1.0 + i) for i in range(3)]
    g = jax.jit(f).lower(*args).compile()
    jax.block_until_ready(g(*args)); ts = []
    for _ in range(400):
        t0 = time.perf_counter(); jax.block_until_ready(g(*args)); ts.append(time.perf_counter() - t0)
    slabs = np.prod(shape) / 300000
    print(shape, f"{1e3*np.median(ts):.3f} ms, per slab {1e3*np.median(ts)/slabs:.3f}")
