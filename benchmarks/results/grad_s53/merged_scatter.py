"""P2G: the primal and k tangent rows scattered as one (1+k)C-wide row per node, against a primal scatter plus the batched tangent scatter into a k G table (session 53; not landed: no consistent gain)."""
import time, numpy as np, jax, jax.numpy as jnp
from jaxmpm.state import _BLOCK_SCATTER, _IN_BOUNDS
G = 67 ** 3; N = 25000
key = jax.random.PRNGKey(0)
base = jnp.sort(jax.random.randint(key, (N,), 67*67*20, 67*67*44))
idx = [base + a * 67 * 67 + b * 67 for a in range(3) for b in range(3)]  # 9 runs of 3 consecutive nodes
def scat(num, index, blocks):
    c = blocks[0].shape[-1]
    out = jnp.zeros((num, c), blocks[0].dtype)
    for i, b in zip(index, blocks):
        out = jax.lax.scatter_add(out, i[:, None], b, _BLOCK_SCATTER, mode=_IN_BOUNDS)
    return out
def current(k, rows):  # rows (1+k, 9, N, 3, 4): primal scatter + batched tangent scatter into a k G table
    p = scat(G, idx, [rows[0, j] for j in range(9)])
    sh = [(i[None] + G * jnp.arange(k)[:, None]).reshape(-1) for i in idx]
    t = scat(k * G, sh, [rows[1:, j].reshape(-1, 3, 4) for j in range(9)])
    return p, t
def merged(k, rows):  # one scatter of (1+k) 4-wide rows side by side, width padded to a power of two
    w = 4 * (1 + k); wp = 1 << (w - 1).bit_length()
    r = jnp.moveaxis(rows, 0, -2).reshape(9, N, 3, w)
    r = jnp.pad(r, ((0, 0), (0, 0), (0, 0), (0, wp - w)))
    return scat(G, idx, [r[j] for j in range(9)])
def merged_nopad(k, rows):
    w = 4 * (1 + k)
    r = jnp.moveaxis(rows, 0, -2).reshape(9, N, 3, w)
    return scat(G, idx, [r[j] for j in range(9)])
for k in (1, 3, 6):
    rows = jax.random.normal(key, (1 + k, 9, N, 3, 4))
    res = {}
    for name, fn in (("current", current), ("merged", merged), ("merged_nopad", merged_nopad)):
        f = jax.jit(lambda r, fn=fn: fn(k, r)).lower(rows).compile()
        jax.block_until_ready(f(rows)); ts = []
        for _ in range(30):
            t0 = time.perf_counter(); jax.block_until_ready(f(rows)); ts.append(time.perf_counter() - t0)
        res[name] = 1e3 * np.median(ts)
    print(k, {n: f"{v:.2f} ms" for n, v in res.items()})
