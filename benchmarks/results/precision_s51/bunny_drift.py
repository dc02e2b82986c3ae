"""f32 vs f64 drift of examples/bunny.toml: where it appears and whether a single frame from
one shared (rounded) state already splits (a branch decided by rounding) or only amplifies."""
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np, sys
from jaxmpm.scene import load_scene
import importlib
sim = importlib.import_module("jaxmpm.step")

path = sys.argv[1] if len(sys.argv) > 1 else "examples/bunny.toml"
runs = {}
for dt in (jnp.float32, jnp.float64):
    sc = load_scene(path, dtype=dt)
    model, params, state = sim._start(sc.model, sc.params, None)
    n = model.substeps

    @jax.jit
    def frame(s, model=model, params=params):
        return jax.lax.fori_loop(0, n, lambda i, s: sim.step(model, params, s), s)
    states = [state]
    for f in range(model.frames - 1):
        states.append(frame(states[-1]))
    runs[dt] = (model, params, frame, states)
dx = float(runs[jnp.float32][0].grid.dx)
x32 = np.stack([np.asarray(s.x, np.float64) for s in runs[jnp.float32][3]])
x64 = np.stack([np.asarray(s.x) for s in runs[jnp.float64][3]])
d = np.abs(x32 - x64).max(axis=(1, 2)) / dx
print("max |x32 - x64| / dx per frame:", np.array2string(d, precision=2, separator=", "))
# one frame from the same state: the f64 state at frame f, rounded to f32, stepped in both
frame32, frame64 = runs[jnp.float32][2], runs[jnp.float64][2]
for f in range(len(d) - 1):
    s64 = runs[jnp.float64][3][f]
    s32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, s64)
    s64r = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a, s32)
    a, b = frame32(s32), frame64(s64r)
    one = np.abs(np.asarray(a.x, np.float64) - np.asarray(b.x)).max() / dx
    i = int(np.argmax(np.abs(np.asarray(a.x, np.float64) - np.asarray(b.x)).max(axis=1)))
    print(f"frame {f} -> {f + 1}: one frame from the same state apart by {one:.2e} dx (particle {i})", flush=True)
