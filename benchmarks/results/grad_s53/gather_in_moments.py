"""G2P tangent sums with the gather fused into them, against the stored gather + moment_sums (session 53): 25,000 particles on a 67^3 grid, k = 1, 3, 6 (not landed: slower)."""
import time, numpy as np, jax, jax.numpy as jnp
from jaxmpm.state import moment_sums, stencil_offsets, _gather, gather_rows
from jaxmpm.fusion import compute_once, always_true, materialize
shape = (67, 67, 67); G = int(np.prod(shape)); N = 25000
key = jax.random.PRNGKey(0)
base = jnp.sort(jax.random.randint(key, (N,), 67*67*20, 67*67*44))
offs = stencil_offsets(3)
strides = (67*67, 67, 1)
idx = [base + int(np.dot(o, strides)) for o in offs]
w = [jax.random.uniform(jax.random.fold_in(key, i), (N,)) for i in range(27)]
def current(table):  # table (G, 3), tangent
    rows = compute_once(_gather, table, jnp.concatenate(idx), token=always_true(base))
    vals = [b[:, :3] for b in jnp.split(rows, 27)]
    return materialize(moment_sums(offs, w, vals), always_true(base))
def fused(table):
    tp = jnp.pad(table, ((0, 0), (0, 1)))
    acc = None
    for o, wo, io in zip(offs, w, idx):
        coeff = jnp.asarray((1.0,) + tuple(float(x) for x in o), table.dtype)
        term = (wo[:, None] * tp.at[io].get(mode="promise_in_bounds")[:, :3])[..., None] * coeff
        acc = term if acc is None else acc + term
    acc = materialize(acc, always_true(base))
    return acc[..., 0], acc[..., 1:]
def fused3(table):  # unpadded table
    acc = None
    for o, wo, io in zip(offs, w, idx):
        coeff = jnp.asarray((1.0,) + tuple(float(x) for x in o), table.dtype)
        term = (wo[:, None] * table.at[io].get(mode="promise_in_bounds"))[..., None] * coeff
        acc = term if acc is None else acc + term
    acc = materialize(acc, always_true(base))
    return acc[..., 0], acc[..., 1:]
for k in (1, 3, 6):
    tab = jax.random.normal(key, (k, G, 3))
    res = {}; outs = {}
    for name, fn in (("current", current), ("fused", fused), ("fused3", fused3)):
        f = jax.jit(jax.vmap(fn)).lower(tab).compile()
        outs[name] = f(tab)
        jax.block_until_ready(outs[name]); ts = []
        for _ in range(40):
            t0 = time.perf_counter(); jax.block_until_ready(f(tab)); ts.append(time.perf_counter() - t0)
        res[name] = 1e3 * np.median(ts)
    err = max(float(jnp.max(jnp.abs(a - b))) for n in ("fused", "fused3") for a, b in zip(outs[n], outs["current"]))
    print(k, {n: f"{v:.2f} ms" for n, v in res.items()}, "max diff", err)
