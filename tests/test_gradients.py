"""Gradients through rollouts: every fitted parameter of every material against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import MATERIAL_CASES, block_spec

from jaxmpm.constitutive import MATERIALS
from jaxmpm.fit import resolve_name, set_param
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

FLOOR = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "sticky"}


def _scene(material, frames=2, substeps=30):
    spec = block_spec(2, material, dx=0.05, lo=[0.4, 0.1], hi=[0.6, 0.3], frames=frames, substeps=substeps,
                      velocity=[0.3, -2.0], floor=FLOOR)
    return load_scene(spec, dtype=jnp.float64)


def _loss_of(scene, names):
    paths = [resolve_name(scene.model, scene.params, n) for n in names]

    def loss(values):
        params = scene.params
        for path, value in zip(paths, values):
            params = set_param(params, path, value)
        x = simulate(scene.model, params).x[-1]
        return jnp.mean(x[:, 0] ** 3 + 2.0 * x[:, 1] ** 2 + x[:, 0] * x[:, 1])

    return loss


@pytest.mark.x64
@pytest.mark.parametrize("model", list(MATERIAL_CASES))
def test_gradient_matches_central_differences(model):
    """d loss / d p for every fitted parameter p of the material (float64, relative error < 1e-3)."""
    truth, _ = MATERIAL_CASES[model]
    names = MATERIALS[model].required
    scene = _scene(truth)
    loss = _loss_of(scene, names)
    values = jnp.asarray([truth[n] for n in names], jnp.float64)
    steps = 1e-6 * jnp.abs(values)  # small: plastic return maps have kinks a large step may cross

    @jax.jit
    def grad_and_central_differences(v):
        basis = jnp.diag(steps)
        fd = jax.vmap(lambda e, h: (loss(v + e) - loss(v - e)) / (2 * h))(basis, steps)
        return jax.grad(loss)(v), fd

    grad, fd = (np.asarray(a) for a in grad_and_central_differences(values))
    for name, g, f in zip(names, grad, fd):
        assert np.isfinite(g) and g != 0.0, name
        assert abs(g - f) <= 1e-3 * abs(f), (name, g, f)


@pytest.mark.parametrize("model", list(MATERIAL_CASES))
def test_gradient_is_finite_at_the_first_step(model, dtype=jnp.float32):
    """F = I (all singular values equal) at t = 0: the first step's gradient must be finite.

    (float64 first steps are covered by the finite-difference test above.)
    """
    truth, _ = MATERIAL_CASES[model]
    spec = block_spec(2, truth, dx=0.05, frames=2, substeps=1, floor=FLOOR, lo=[0.4, 0.1], hi=[0.6, 0.3])
    scene = load_scene(spec, dtype=dtype)

    def loss(params):
        return jnp.sum(simulate(scene.model, params).x[-1] ** 2)

    grads = jax.grad(loss)(scene.params)
    for leaf in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))
