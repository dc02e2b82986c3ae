"""Matrix products at full precision (jaxmpm/precision.py).

On a GPU the default float32 matrix product is TF32, which made a silhouette fit stall
(docs/benchmarks.md, "On a GPU"); the CPU computes both the same way, so these tests check
the traced programs: every ``dot_general`` of the step, ``simulate`` (and its gradient) and the
renderers carries ``Precision.HIGHEST``, and a plain product traced beside them does not (the
check can fail).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import block_spec

from jaxmpm.render import SurfelRenderer, VolumeRenderer, look_at
from jaxmpm.model import initial_state
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate, step

HIGHEST = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)


def dot_precisions(fn, *args) -> list:
    """The ``precision`` of every ``dot_general`` in ``fn``'s jaxpr, sub-jaxprs (scan, cond,
    custom derivatives) included."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                found.append(eqn.params["precision"])
            for value in eqn.params.values():
                for sub in value if isinstance(value, (list, tuple)) else [value]:
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        walk(inner)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return found


def test_a_plain_product_keeps_the_default_precision():
    assert dot_precisions(lambda a: a @ a, jnp.ones((3, 3))) == [None]


@pytest.mark.parametrize("dim", [2, 3])
def test_the_step_and_the_rollout_trace_their_products_at_full_precision(dim):
    scene = load_scene(block_spec(dim, {"model": "elastic", "E": 1e4, "nu": 0.3}, frames=2, substeps=2))
    m, p = scene.model, scene.params
    state = initial_state(m, p)
    # The step's own small matrix products are elementwise (exact at any precision setting);
    # the dots are those of their forward-mode rule, which the gradient traces.
    traced = 0
    for fn, args in ((lambda q, s: step(m, q, s), (p, state)), (lambda q: simulate(m, q), (p,)),
                     (lambda q: jax.grad(lambda r: simulate(m, r).x[-1].sum())(q), (p,))):
        found = dot_precisions(fn, *args)
        assert all(prec == HIGHEST for prec in found), set(map(str, found))
        traced += len(found)
    assert traced


@pytest.mark.parametrize("kind", ["surfels", "volume"])
def test_the_renderers_trace_their_products_at_full_precision(kind):
    cam = look_at((0.0, 0.0, -2.0), (0.0, 0.0, 0.0), fov_deg=40.0, width=8, dtype=jnp.float32)
    x = np.random.default_rng(0).uniform(-0.2, 0.2, (20, 3))
    renderer = SurfelRenderer(scale=0.05) if kind == "surfels" else VolumeRenderer.for_particles(x, spacing=0.05)
    x = jnp.asarray(x, jnp.float32)
    for fn in (lambda y: renderer.render(y, cam).alpha, lambda y: renderer.silhouette(y, cam)):
        found = dot_precisions(fn, x)
        assert found and all(prec == HIGHEST for prec in found), set(map(str, found))
