"""Forward and k=4 forward-mode step cost on a 3D block over a floor plane (with and without
discover's extensions)."""
import sys, time, importlib
sys.path.insert(0, "tests")
import jax, jax.numpy as jnp, numpy as np
from scenes import block_spec
from jaxmpm.scene import load_scene
from jaxmpm import extensions as X
D = importlib.import_module("jaxmpm.discover")
dx = float(sys.argv[1]) if len(sys.argv) > 1 else 0.02
spec = block_spec(3, {"model": "elastic", "E": 3e4, "nu": 0.3}, dx=dx, frames=3, substeps=100,
                  floor={"point": [0.0, 0.1, 0.0], "normal": [0.0, 1.0, 0.0], "contact": "slip"}, velocity=[1.0, 0.5, 0.0])
scene = load_scene(spec); m, p = scene.model, scene.params
def t(f):
    f(); a = []
    for _ in range(3):
        t0 = time.perf_counter(); f(); a.append(time.perf_counter() - t0)
    return min(a)
for label, params in (("plain", p), ("extensions", X.enable(m, p, [e for e in X.EXTENSIONS if X.applicable(m, e) is None]))):
    fwd = t(lambda: jax.block_until_ready(D._rollout(m, params, 3)))
    leaves, tree = jax.tree_util.tree_flatten(params)
    tans = tree.unflatten([jnp.ones((4, *jnp.shape(a)), jnp.result_type(a)) * 1e-3 if jnp.issubdtype(jnp.result_type(a), jnp.floating) else jnp.zeros((4, *jnp.shape(a)), jax.dtypes.float0) for a in leaves])
    jvp = t(lambda: jax.block_until_ready(D._rollout_jvps(m, params, tans, 3)))
    print(f"{m.num_particles} particles 3D, grid {m.grid.shape}, {label}: forward {fwd:.3f} s, jvp k=4 {jvp:.3f} s ({jvp / fwd:.2f}x)", flush=True)
