# Session 23: one rollout (6 frames) of the 3D discover case with each candidate extension on at null. Run from the repository root:
#   [PYTHONPATH=<checkout>] python benchmarks/results/discover_s23/hooks.py [--only moving_collider,ALL] --dim 3 --dx 0.01 --frames 24 --substeps 22 --frame-dt 0.016666667 --velocity 1,1.5 --height 0.3 --E 3e4
import sys, time, argparse
from pathlib import Path; ROOT = Path(__file__).resolve().parents[3]; sys.path[:0] = [str(ROOT / 'benchmarks'), str(ROOT / 'tests')]
from discover_time import block_scene, scene_arguments
import jax, numpy as np
from jaxmpm import extensions as X
from jaxmpm.discover import _rollout
ap=argparse.ArgumentParser(); scene_arguments(ap)
ap.add_argument('--only', default=None, help='comma-separated extensions (and ALL) to time; default every one and ALL')
args=ap.parse_args()
sc=block_scene(args); m,p=sc.model,sc.params
base=X.strip(p)
ids=[e for e in X.EXTENSIONS if X.applicable(m, e) is None]
fr=6
def tm(q):
    jax.block_until_ready(_rollout(m,q,fr)[0].x)
    ts=[]
    for _ in range(2):
        t0=time.perf_counter(); x=_rollout(m,q,fr)[0].x; jax.block_until_ready(x); ts.append(time.perf_counter()-t0)
    return min(ts), np.asarray(x)
t0,x0=tm(base); print(f"none: {t0:.2f} s", flush=True)
for e in (args.only.split(',') if args.only else ids+['ALL']):
    q=X.enable(m, base, ids if e=='ALL' else [e])
    t,x=tm(q); print(f"{e}: {t:.2f} s ({t/t0:.2f}x), max |dx| vs none {np.max(np.abs(x-x0)):.3g}", flush=True)
