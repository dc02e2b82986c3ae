"""Each execution of the named XLA ops in a forward-mode program (k tangents of the parameters
and the state, 10-step rollout of the 25,000-particle cube), as the profiler records it: start
offset, duration (us) and thread (session 53). Every op is one event per execution, so the
durations are the op's wall time.

    python benchmarks/results/grad_s53/op_events.py 3,4 multiply_add_fusion.47,copy_pad_fusion
"""
import sys, collections, tempfile, json, numpy as np, jax
from tangent_program import P, push, arguments
ops = sys.argv[2].split(",")
for k in [int(a) for a in sys.argv[1].split(",")]:
    params, dynamic, tangents = arguments(k)
    f = jax.jit(push).lower(params, dynamic, tangents).compile()
    jax.block_until_ready(f(params, dynamic, tangents))
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            for _ in range(2): jax.block_until_ready(f(params, dynamic, tangents))
        ev = P._trace_events(d)
    for op in ops:
        es = sorted((e["ts"], e["dur"], e["tid"]) for e in ev if e.get("ph") == "X" and e.get("args", {}).get("hlo_op") == op)
        print(f"k={k} {op}: {len(es)} events; first 8 (ts offset us, dur us, tid):",
              [(round(t - es[0][0]), round(du), tid) for t, du, tid in es[:8]])
