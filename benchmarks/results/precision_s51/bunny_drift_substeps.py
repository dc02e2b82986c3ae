"""Substep by substep from one shared state: frame F0 of the float64 run of examples/bunny.toml,
rounded to float32, stepped in both precisions; per substep how far apart they are, whose CPIC
incompatible bits or side tags differ, and particle P's signed distance, stencil and velocity.

    python benchmarks/results/precision_s51/bunny_drift_substeps.py 2 566   # (session 51: frame 2, particle 566)
"""
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np, sys, importlib
from jaxmpm.scene import load_scene
sim = importlib.import_module("jaxmpm.step")
from jaxmpm.state import compute_stencil

F0, P = int(sys.argv[1]), int(sys.argv[2])
path = "examples/bunny.toml"
M = {}
for dt in (jnp.float32, jnp.float64):
    sc = load_scene(path, dtype=dt)
    model, params, state = sim._start(sc.model, sc.params, None)
    step = jax.jit(lambda s, model=model, params=params: sim.step(model, params, s))
    def contact(s, model=model):
        st = compute_stencil(model.grid, s.x)
        return sim.gather_contact(model, st, s)
    M[dt] = (model, params, step, jax.jit(contact), state)
model64, params64, step64, contact64, s = M[jnp.float64]
for f in range(F0 * model64.substeps):
    s = step64(s)
cast = lambda t, d: jax.tree_util.tree_map(lambda a: a.astype(d) if jnp.issubdtype(a.dtype, jnp.floating) else a, t)
a = cast(s, jnp.float32); b = cast(a, jnp.float64)
dx = float(model64.grid.dx)
for i in range(model64.substeps):
    ca, cb = M[jnp.float32][3](a), contact64(b)
    diff_inc = np.flatnonzero(np.asarray(ca.any_incompatible) != np.asarray(cb.any_incompatible))
    diff_tag = np.flatnonzero(np.any(np.asarray(ca.tag) != np.asarray(cb.tag), axis=1))
    dxp = np.abs(np.asarray(a.x, np.float64) - np.asarray(b.x)).max(axis=1) / dx
    print(f"substep {i}: max apart {dxp.max():.2e} dx (p {int(dxp.argmax())}), particle {P}: {dxp[P]:.2e}; "
          f"incompatible bits differ for {diff_inc[:8].tolist()}, tags differ for {diff_tag[:8].tolist()}")
    if 14 <= i <= 21:
        sa = compute_stencil(M[jnp.float32][0].grid, a.x); sb = compute_stencil(model64.grid, b.x)
        print(f"    p{P}: phi32 {float(np.asarray(ca.phi[0])[P]) / dx:+.6f} phi64 {float(np.asarray(cb.phi[0])[P]) / dx:+.6f} dx; "
              f"base {np.asarray(sa.base)[P].tolist()} {np.asarray(sb.base)[P].tolist()}; fx {[float(np.asarray(f)[P]) for f in sa.fx]}; "
              f"tag {np.asarray(ca.tag)[P].tolist()} {np.asarray(cb.tag)[P].tolist()}; bits {int(np.asarray(ca.any_incompatible)[P])} {int(np.asarray(cb.any_incompatible)[P])}; "
              f"v {np.asarray(a.v)[P].tolist()}")
    for p in diff_inc[:3].tolist():
        print("    p", p, "phi32", [float(np.asarray(ph)[p]) / dx for ph in ca.phi], "phi64", [float(np.asarray(ph)[p]) / dx for ph in cb.phi],
              "bits", int(np.asarray(ca.any_incompatible)[p]), int(np.asarray(cb.any_incompatible)[p]))
    a, b = M[jnp.float32][2](a), step64(b)
