"""fit --numerics on measured data: the water's apparent viscosity from the Martin-Moyce large column's fronts.

    python benchmarks/results/flip_fit_s59/martin_moyce_numerics.py mm_large 8   (from the repository root)

Fits mu with numerics=True, then refits it fully at dt/2 and with the FLIP blend 0.99 from the
result, to compare with the check's moves (docs/fitting.md, "Numerical error of the parameters").
"""
import json, sys, time
sys.path.insert(0, "examples")
import numpy as np
import dam_break_2d as E
from jaxmpm import load_scene
from jaxmpm.fit import FitConfig, fit
name, cells = sys.argv[1], int(sys.argv[2])
sc = load_scene(E.scene_spec(name, cells))
obs = E.observation(name)
print(name, sc.model.num_particles, sc.model.substeps, sc.model.frames, file=sys.stderr)
t0 = time.perf_counter()
res = fit(sc.model, sc.params, obs, ["mu"], FitConfig(stages=None, numerics=True), log=lambda m: print(m, file=sys.stderr))
row = {"case": name, "cells": cells, "mu": float(res.values["mu"]), "std": float(res.std["mu"]), "converged": res.converged,
       "numerics": res.to_json()["numerics"], "check": res.stages[-1]["numerics"], "seconds": time.perf_counter() - t0,
       "timing": res.timing, "notes": res.notes}
print(json.dumps(row), flush=True)
for label, m in (("dt/2", sc.model.with_substeps(2 * sc.model.substeps)), ("blend", sc.model.with_flip(0.99))):
    t0 = time.perf_counter()
    r2 = fit(m, res.params, obs, ["mu"], FitConfig(stages=None))
    print(json.dumps({"refit": label, "mu": float(r2.values["mu"]), "std": float(r2.std["mu"]), "converged": r2.converged,
                      "moved": float(r2.values["mu"] - res.values["mu"]),
                      "moved_decades": float(np.log10(r2.values["mu"] / res.values["mu"])) if r2.values["mu"] > 0 else None,
                      "seconds": time.perf_counter() - t0}), flush=True)
