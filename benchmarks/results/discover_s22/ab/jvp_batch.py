"""Per-tangent cost of discover's forward-mode rollouts vs the number of tangents per primal."""
import importlib, sys, time, json
from pathlib import Path
import numpy as np
sys.path.insert(0, "benchmarks"); sys.path.insert(0, "tests")
import argparse
from discover_time import scene_arguments, block_scene
from jaxmpm import extensions as X
from jaxmpm.observe import Observation
D = importlib.import_module("jaxmpm.discover")
ap = argparse.ArgumentParser(); scene_arguments(ap); ap.add_argument("--ks", default="1,2,4,8,16")
args = ap.parse_args()
scene = block_scene(args); m, p = scene.model, scene.params
ids = [e for e in X.EXTENSIONS if X.applicable(m, e) is None]
x = np.asarray(D._rollout(m, X.enable(m, p, ids), args.frames)[0].x, float)
obs = Observation(times=np.arange(args.frames) * m.frame_dt, positions=x, point_ids="particles")
prob = D._Problem([D.Sequence(m, p, obs)], ["E", "nu"], [e for e in D.DEFAULT_EXTENSIONS if e in ids], 64, x.dtype)
theta = prob.initial()
def t(f):
    f(); t0 = time.perf_counter(); f(); a = time.perf_counter() - t0; t0 = time.perf_counter(); f(); return min(a, time.perf_counter() - t0)
fwd = t(lambda: (prob._remembered.clear(), prob.residuals(theta)))
print(f"{m.num_particles} particles, {args.frames * args.substeps} steps: forward {fwd:.3f} s", flush=True)
rows = {"forward_s": fwd}
for k in [int(v) for v in args.ks.split(",")]:
    D.JVP_BATCH = k
    cols = np.arange(k) % prob.size
    cols = np.arange(min(k, prob.size))
    s = t(lambda: prob.jacobian(theta, cols))
    rows[k] = s
    print(f"k={k:2d} ({len(cols)} live): {s:.3f} s = {s / fwd:.2f} forwards; per tangent {(s - fwd) / k / fwd:.2f} forwards beyond the primal", flush=True)
