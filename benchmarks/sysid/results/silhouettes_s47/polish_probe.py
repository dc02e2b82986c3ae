"""Probe: LM on all frames from the viscoplastic bunny's silhouette fit end, with one velocity
component moved to the value a coordinate move finds lower (vx -> 0)."""
import json, sys, time
import numpy as np
import jax.numpy as jnp
from jaxmpm.bench_sysid import FIT_NAMES, find_case, fit_config, observe_case, start_scene, errors
from jaxmpm.fit import fit
from jaxmpm.identify.parameters import apply_unconstrained, to_unconstrained

key = "viscoplastic-bunny-0-silhouettes-cpic"
row = [json.loads(l) for l in open("/work/main/benchmarks/sysid/results/silhouettes_s47/results.jsonl") if key in l][0]
e = row["estimate"]
vx = float(sys.argv[1])
preset, case = find_case(key, "reduced")
obs, truth, v0, _ = observe_case(case, preset)
names = FIT_NAMES[case.material]
start = start_scene(case, preset, {n: e[n] for n in names})
vel = list(e["velocity"]); vel[0] = vx
params = apply_unconstrained(start.model, start.params, ["velocity"], {"velocity": jnp.asarray(vel, jnp.float32)})
model = start.model.with_substeps(row["substeps"])
cfg = fit_config(case, preset, scan=(), stages=None, refine_velocity=True)
t0 = time.perf_counter()
res = fit(model, params, obs, names + ["velocity"], cfg, progress=lambda *a: None)
print("start vx", vx, "seconds", round(time.perf_counter() - t0), res.message[:120])
print("errors", errors(names, res.values, truth), "v", np.asarray(res.values["velocity"]).tolist(),
      "loss", res.stages[-1]["loss"])
