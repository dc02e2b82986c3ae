"""discover --numerics on measured data (session 60): the 2D dam break case study as committed
(examples/dam_break_2d.py: 8 cells across, nothing fitted in the base model, `mm_small` held out,
the six physical extensions), whose extended fit is floor friction + a release delay. Prints the
extended fit's moves at dt/2 and with the FLIP blend (the check's 4-iteration refits) and where
full refits (25 iterations) from the same point end.

    python benchmarks/results/discover_numerics_s60/dam_break_2d_extended.py
"""

import importlib
import json
import sys
import time

sys.path.insert(0, "examples")
import dam_break_2d as db  # noqa: E402

D = importlib.import_module("jaxmpm.discover")

clock = time.perf_counter()
r = D.discover(db.sequences(8), names=[], extensions=list(db.PHYSICAL), holdout=0.0, holdout_sequences=["mm_small"],
               top=3, max_extensions=2, numerics=True,
               progress=lambda line: print(f"[{time.perf_counter() - clock:6.1f}s] {line}", file=sys.stderr))
print(json.dumps({"causes": r.causes, "parameters": {k: float(v) for k, v in r.parameters.items()},
                  "std": r.std, "moves": r.extended_numerics, "check": r.numerics_check["extended"], "notes": r.notes,
                  "seconds": time.perf_counter() - clock,
                  "phases": {p["phase"]: round(p["wall_s"], 1) for p in r.timing["phases"]}}, indent=1))
_, _, entry_train = D._holdout_masks(r.problem, 0.0, ["mm_small"], None)
free = [n for e in r.causes for n in r.problem.ext_names(e)]
for numerics in (D.Numerics(substeps_factor=2), D.Numerics(other_transfer=True)):
    full = D._lm(r.problem, r.extended_theta, free, entry_train, max_iter=25, numerics=numerics)
    values = r.problem.values(full.theta)
    print(f"full refit {numerics}: " + ", ".join(f"{n} {float(values[n]):.4g} (move {float(values[n] - r.parameters[n]):+.4g})"
                                                 for n in free) + f"; {full.iterations} iterations, converged {full.converged}")
