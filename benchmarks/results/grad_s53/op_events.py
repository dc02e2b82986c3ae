"""Each execution of the named XLA ops in a forward-mode program (k tangents of the parameters
and the state, 10-step rollout of the 25,000-particle cube), as the profiler records it: start
offset, duration (us) and thread (session 53). Every op is one event per execution, so the
durations are the op's wall time.

    python benchmarks/results/grad_s53/op_events.py 3,4 multiply_add_fusion.47,copy_pad_fusion
"""
import sys, collections, tempfile, numpy as np, jax, jax.numpy as jnp, equinox as eqx
sys.path.insert(0, "benchmarks")
import profile_step as P
from jaxmpm.bench import _scene_model
from jaxmpm.model import initial_state
from jaxmpm.step import step
model, params = _scene_model(25000, 64, "corotated", jnp.float32)
state = initial_state(model, params)
adv = jax.jit(lambda s: step(model, params, s))
for _ in range(5): state = adv(state)
dynamic, static = eqx.partition(state, eqx.is_inexact_array)
leaves, treedef = jax.tree_util.tree_flatten((params, dynamic))
def push(params, dynamic, tangents):
    def out(p, d):
        return eqx.partition(P.rollout(model, p, eqx.combine(d, static), 10), eqx.is_inexact_array)[0]
    return jax.vmap(lambda t: jax.jvp(out, (params, dynamic), t)[1])(tangents)
ops = sys.argv[2].split(",")
for k in [int(a) for a in sys.argv[1].split(",")]:
    keys = jax.random.split(jax.random.PRNGKey(0), len(leaves))
    tangents = treedef.unflatten([1e-3 * jax.random.normal(kk, (k, *jnp.shape(a)), jnp.result_type(a)) for kk, a in zip(keys, leaves)])
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
