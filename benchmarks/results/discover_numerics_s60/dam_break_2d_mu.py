"""discover --numerics on measured data (session 60): the 2D dam break's fronts (Martin & Moyce,
Koshizuka & Oka; examples/dam_break_2d.py's sequences, 8 cells across), the water's viscosity
``mu`` fitted as the base model's one parameter from a start of 1 Pa s (an apparent viscosity:
the model lacks the floor's friction and the release), no extension offered. Prints the base
fit, the numerics check's moves, and where full refits (25 iterations) at dt/2 and with the FLIP
blend end, for comparison with the check's short refits.

    python benchmarks/results/discover_numerics_s60/dam_break_2d_mu.py [CELLS]
"""

import importlib
import json
import sys
import time

import jax.numpy as jnp

sys.path.insert(0, "examples")
import dam_break_2d as db  # noqa: E402

from jaxmpm.identify.parameters import set_param  # noqa: E402

D = importlib.import_module("jaxmpm.discover")

cells = int(sys.argv[1]) if len(sys.argv) > 1 else 8
seqs = db.sequences(cells)
for s in seqs:
    s.params = set_param(s.params, ("bodies", 0, "mu"), jnp.asarray(1.0))
clock = time.perf_counter()
r = D.discover(seqs, names=["mu"], extensions=[], holdout=0.0, holdout_sequences=["mm_small"], numerics=True,
               progress=lambda line: print(f"[{time.perf_counter() - clock:6.1f}s] {line}", file=sys.stderr))
total = time.perf_counter() - clock
print(json.dumps({"mu": float(r.base_values["mu"]), "std": float(r.base_std["mu"]), "moves": r.numerics,
                  "check": r.numerics_check, "notes": r.notes, "seconds": total,
                  "phases": {p["phase"]: round(p["wall_s"], 1) for p in r.timing["phases"]}}, indent=1))
_, _, entry_train = D._holdout_masks(r.problem, 0.0, ["mm_small"], None)
for numerics in (D.Numerics(substeps_factor=2), D.Numerics(other_transfer=True)):
    full = D._lm(r.problem, r.base_theta, ["mu"], entry_train, max_iter=25, numerics=numerics)
    mu = float(r.problem.values(full.theta)["mu"])
    print(f"full refit {numerics}: mu {mu:.4g} (move {mu - float(r.base_values['mu']):+.4g}), "
          f"{full.iterations} iterations, converged {full.converged}")
