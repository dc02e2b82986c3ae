"""Gradients through rollouts: every fitted parameter of every material against finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scenes import MATERIAL_CASES, block_spec, final_position_loss, slow

from jaxmpm.constitutive import MATERIALS
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate

FLOOR = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "sticky"}


def _scene(material, frames=2, substeps=30):
    spec = block_spec(2, material, dx=0.05, lo=[0.4, 0.1], hi=[0.6, 0.3], frames=frames, substeps=substeps,
                      velocity=[0.3, -2.0], floor=FLOOR)
    return load_scene(spec, dtype=jnp.float64)


@pytest.mark.x64
@pytest.mark.parametrize("model", list(MATERIAL_CASES))
def test_gradient_matches_central_differences(model):
    """d loss / d p for every fitted parameter p of the material (float64, relative error < 1e-3)."""
    truth, _ = MATERIAL_CASES[model]
    names = MATERIALS[model].required()
    scene = _scene(truth)
    loss = final_position_loss(scene, names)
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


def _first_steps_loss(model_name: str, dtype):
    """``sum |x|^2`` after two substeps from rest on a sticky floor (F = I, all singular values
    equal, at the first; F ~ I at the second, where the SVD's derivative acts), as a function
    of the scene's whole parameter pytree."""
    truth, _ = MATERIAL_CASES[model_name]
    spec = block_spec(2, truth, dx=0.05, frames=2, substeps=2, floor=FLOOR, lo=[0.4, 0.1], hi=[0.6, 0.3])
    scene = load_scene(spec, dtype=dtype)
    return scene.params, lambda params: jnp.sum(simulate(scene.model, params).x[-1] ** 2)


@pytest.mark.parametrize("model", [m if m in ("viscoplastic", "plasticine", "sand") else slow(m) for m in MATERIAL_CASES])
def test_first_step_gradient_in_float32_matches_float64_central_differences(model):
    """F = I at t = 0 (repeated singular values): the float32 gradient of every parameter
    (material, density, velocity, gravity) is finite and, along a random relative direction,
    equals float64 central differences (measured agreement ~1e-5 relative).

    The default run takes the materials that differentiate an SVD at F = I (viscoplastic,
    plasticine, sand); the fluid and the neo-Hookean solid take none (they run with ``-m slow``;
    every material's rollout gradient is checked above in the default run)."""
    params32, loss32 = _first_steps_loss(model, jnp.float32)
    grads = jax.jit(jax.grad(loss32))(params32)
    leaves32 = [np.asarray(g) for g in jax.tree_util.tree_leaves(grads)]
    assert all(np.all(np.isfinite(g)) for g in leaves32)
    with jax.enable_x64(True):
        params64, loss64 = _first_steps_loss(model, jnp.float64)
        leaves, tree = jax.tree_util.tree_flatten(params64)
        rng = np.random.default_rng(0)
        direction = [np.asarray(v) * rng.uniform(0.5, 1.5, np.shape(v)) for v in leaves]  # relative steps
        h = 1e-6

        def shifted_loss(sign):
            return loss64(jax.tree_util.tree_unflatten(tree, [v + sign * h * d for v, d in zip(leaves, direction)]))

        plus, minus = np.asarray(jax.jit(jax.vmap(shifted_loss))(jnp.asarray([1.0, -1.0])))
        fd = float(plus - minus) / (2 * h)
    along = sum(float(np.sum(g * d)) for g, d in zip(leaves32, direction))
    assert along == pytest.approx(fd, rel=1e-3)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_offset_translates_the_body_rigidly_in_free_flight(dim):
    """A body's ``offset`` (m) moves its reference positions: with no collider in reach every
    frame of the rollout is the offset-free one translated by it (to rounding), and the mean
    position's forward-mode derivative with respect to it is the identity."""
    from jaxmpm.identify.parameters import with_values

    spec = block_spec(dim, dx=0.05, lo=[0.4, 0.5, 0.4][:dim], hi=[0.6, 0.7, 0.6][:dim], frames=3, substeps=10,
                      velocity=[0.3, -1.0, 0.2][:dim])
    scene = load_scene(spec)
    np.testing.assert_array_equal(scene.params["bodies"][0]["offset"], np.zeros(dim))
    delta = np.array([0.013, -0.021, 0.008][:dim])
    run = jax.jit(lambda p: simulate(scene.model, p).x)
    x, shifted = (np.asarray(run(with_values(scene.model, scene.params, {"offset": d})))
                  for d in (np.zeros(dim), delta))
    np.testing.assert_allclose(shifted - x, np.broadcast_to(delta, x.shape), atol=2e-6)

    def mean_position(d):
        return jnp.mean(simulate(scene.model, with_values(scene.model, scene.params, {"offset": d})).x[-1], axis=0)

    np.testing.assert_allclose(jax.jit(jax.jacfwd(mean_position))(jnp.asarray(delta, jnp.float32)), np.eye(dim),
                               atol=1e-4)


@pytest.mark.x64
def test_the_offsets_gradient_matches_central_differences_against_a_floor():
    """Against a sticky floor the final positions depend on the offset nonlinearly (where and
    when the body lands); reverse and forward mode agree with central differences (float64)."""
    from jaxmpm.identify.parameters import with_values

    scene = _scene({"model": "newtonian", "mu": 10.0, "kappa": 1e4}, frames=3)

    def loss(d):
        x = simulate(scene.model, with_values(scene.model, scene.params, {"offset": d})).x[-1]
        return jnp.mean(jnp.sum((x - jnp.asarray([0.55, 0.12])) ** 2, axis=-1) * (1.0 + x[:, 0]))

    d0 = jnp.asarray([0.004, 0.01], jnp.float64)
    h = 1e-6
    grad = np.asarray(jax.jit(jax.grad(loss))(d0))
    tangents = np.asarray(jax.jit(jax.jacfwd(loss))(d0))
    fd = np.array([(loss(d0 + h * e) - loss(d0 - h * e)) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(grad, fd, rtol=1e-4)
    np.testing.assert_allclose(tangents, fd, rtol=1e-4)
