"""The forward-mode program that profile_pair.py and op_events.py time (session 53), as
profile_step.py --tangents K builds it: k random tangents of the parameters and the state of the
25,000-particle cube (after 5 steps, so that C and F are not trivial), pushed through a 10-step
rollout by ``jax.vmap`` of ``jax.jvp``.

    from tangent_program import push, arguments
    jax.jit(push)(*arguments(k))
"""
import sys

import equinox as eqx
import jax
import jax.numpy as jnp

sys.path.insert(0, "benchmarks")
import profile_step as P  # noqa: E402
from jaxmpm.bench import _scene_model  # noqa: E402
from jaxmpm.model import initial_state  # noqa: E402
from jaxmpm.step import step  # noqa: E402

model, params = _scene_model(25000, 64, "corotated", jnp.float32)
_state = initial_state(model, params)
_advance = jax.jit(lambda s: step(model, params, s))
for _ in range(5):
    _state = _advance(_state)
dynamic, static = eqx.partition(_state, eqx.is_inexact_array)
leaves, treedef = jax.tree_util.tree_flatten((params, dynamic))


def push(params, dynamic, tangents):
    def out(p, d):
        return eqx.partition(P.rollout(model, p, eqx.combine(d, static), 10), eqx.is_inexact_array)[0]

    return jax.vmap(lambda t: jax.jvp(out, (params, dynamic), t)[1])(tangents)


def arguments(k: int):
    """``(params, dynamic, tangents)`` with ``k`` random tangent directions of every float input."""
    keys = jax.random.split(jax.random.PRNGKey(0), len(leaves))
    tangents = treedef.unflatten([1e-3 * jax.random.normal(kk, (k, *jnp.shape(a)), jnp.result_type(a))
                                  for kk, a in zip(keys, leaves)])
    return params, dynamic, tangents
