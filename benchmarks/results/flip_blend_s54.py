import sys, dataclasses, time, numpy as np, jax, jax.numpy as jnp
sys.path.insert(0, "benchmarks")
import transfer_dissipation as T
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate
dx = 0.02
for flip in [float(a) for a in sys.argv[1].split(",")]:
    for substeps in (40, 80, 160, 320):
        whole = load_scene(T.spec(dx, substeps, 30))
        model = dataclasses.replace(whole.model, flip=flip)
        t0 = time.time()
        traj = simulate(model, whole.params, observe=lambda s: s)
        e = [T.mechanical(jax.tree.map(lambda a, i=i: a[i], traj.extra), dx) for i in range(30)]
        x = np.asarray(traj.x)
        front = x[:, :, 0].max(axis=1)
        print(f"flip {flip} substeps {substeps}: lost by 0.2/0.4/0.58 s " + " / ".join(f"{e[0] - e[i]:.2f}" for i in (10, 20, 29))
              + f" J/m; front at 0.2 s {front[10]:.3f} m; nan {bool(np.asarray(traj.nan).any())}; {time.time()-t0:.0f} s", flush=True)
