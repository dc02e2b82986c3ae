import time, sys, numpy as np, jax, jax.numpy as jnp
from jaxmpm.bench import grad_problem
final_x, theta0 = grad_problem(25000, 64, int(sys.argv[1]))
e = jnp.eye(6, dtype=theta0.dtype)
fns = {
 "forward": jax.jit(lambda th: final_x(th)),
 "vmap k1": jax.jit(lambda th: jax.vmap(lambda t: jax.jvp(final_x, (th,), (t,))[1])(e[:1])),
 "plain k1": jax.jit(lambda th: jax.jvp(final_x, (th,), (e[0],))[1][None]),
}
for f in fns.values(): jax.block_until_ready(f(theta0))
print(float(jnp.max(jnp.abs(fns["vmap k1"](theta0) - fns["plain k1"](theta0)))))
res = {k: [] for k in fns}
for r in range(4):
    for k, f in fns.items():
        t0 = time.perf_counter(); jax.block_until_ready(f(theta0)); res[k].append(time.perf_counter() - t0)
for k, v in res.items(): print(k, [round(1e3*x) for x in v], "median", round(1e3*np.median(v)), "ratio", round(np.median(v)/np.median(res["forward"]), 2))
