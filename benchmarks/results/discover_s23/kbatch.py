# Session 23. Run from the repository root:
#   python benchmarks/results/discover_s23/kbatch.py --dim 3 --dx 0.01 --frames 2 --substeps 22 --frame-dt 0.016666667 --velocity 1,1.5 --height 0.3 --E 3e4
# the discover scene's Jacobian rollouts at k tangents per batch: seconds per tangent (3D 48k or 2D)
import sys, time, argparse
from pathlib import Path; ROOT = Path(__file__).resolve().parents[3]; sys.path[:0] = [str(ROOT / 'benchmarks'), str(ROOT / 'tests')]
from discover_time import block_scene, scene_arguments
import jax, jax.numpy as jnp, numpy as np
from jaxmpm.discover import _rollout, _rollout_jvps
ap=argparse.ArgumentParser(); scene_arguments(ap); ap.add_argument('--ks', default='1,2,4,8')
args=ap.parse_args()
sc=block_scene(args); m,p=sc.model,sc.params
fr=args.frames
def tm(fn, reps=2):
    jax.block_until_ready(fn()); ts=[]
    for _ in range(reps):
        t0=time.perf_counter(); jax.block_until_ready(fn()); ts.append(time.perf_counter()-t0)
    return min(ts)
f=tm(lambda: _rollout(m,p,fr)[0].x)
print(f"{m.num_particles} particles, {fr} frames x {m.substeps}: forward {f:.2f} s", flush=True)
leaves, td = jax.tree_util.tree_flatten(p)
for k in [int(a) for a in args.ks.split(',')]:
    rng=np.random.default_rng(k)
    tang=td.unflatten([jnp.asarray(rng.standard_normal((k,)+np.shape(a)), jnp.asarray(a).dtype) for a in leaves])
    t=tm(lambda: _rollout_jvps(m,p,tang,fr)[1].x)
    print(f"  k={k}: {t:.2f} s = {t/f:.2f} forwards; {(t-f)/k/f:.2f} forwards per tangent beyond the primal", flush=True)
