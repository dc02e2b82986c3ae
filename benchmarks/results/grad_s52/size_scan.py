"""Per-direction cost of forward-mode Jacobians (k = 6) against particle count, one grid."""
import time, sys, numpy as np, jax, jax.numpy as jnp
from jaxmpm.bench import grad_problem
steps = int(sys.argv[1]); k = int(sys.argv[2])
for n in [int(s) for s in sys.argv[3].split(",")]:
    final_x, theta0 = grad_problem(n, 64, steps)
    basis = jnp.eye(6, dtype=theta0.dtype)[:k]
    fwd = jax.jit(lambda th: final_x(th))
    jac = jax.jit(lambda th: jax.vmap(lambda t: jax.jvp(final_x, (th,), (t,))[1])(basis))
    jax.block_until_ready(fwd(theta0)); jax.block_until_ready(jac(theta0))
    tf, tj = [], []
    for _ in range(3):
        t0 = time.perf_counter(); jax.block_until_ready(fwd(theta0)); tf.append(time.perf_counter() - t0)
        t0 = time.perf_counter(); jax.block_until_ready(jac(theta0)); tj.append(time.perf_counter() - t0)
    f, j = np.median(tf), np.median(tj)
    print(f"{n:7d} forward {1e3*f:8.1f} ms ({1e9*f/steps/n:6.1f} ns/particle/step)  jac k={k} {1e3*j:8.1f} ms  ratio {j/f:5.2f}"
          f"  per direction {(j/f-1)/k:5.2f} x forward, {1e9*(j-f)/k/steps/n:6.1f} ns/particle/step", flush=True)
