"""The extension library: null values reproduce the base model; each extension acts."""

import jax.numpy as jnp
import numpy as np
import pytest
from scenes import block_spec

from jaxmpm import extensions as X
from jaxmpm.errors import JaxmpmError
from jaxmpm.scene import load_scene

FLOOR = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "slip"}


def _scene(material=None, frames=6):
    material = material or {"model": "elastic", "E": 3e3, "nu": 0.3}
    return load_scene(block_spec(2, material, dx=0.05, lo=[0.3, 0.12], hi=[0.5, 0.27], frames=frames, substeps=20,
                                 velocity=[1.0, -1.0], floor=FLOOR))


#: a non-null value of every extension
VALUES = {
    "collider_friction": {"floor": 0.4},
    "restitution": {"floor": 0.5},
    "drag": {"linear": 1.0, "quadratic": 0.5},
    "gravity": {"delta": [0.5, -1.0]},
    "initial_velocity": {"delta": [0.3, 0.2], "spin": [2.0]},
    "moving_collider": {"floor": [0.0, 0.3]},
    "rate_dependence": {"viscosity": 20.0},
    "heterogeneity": {"gradient": [0.5, 0.0]},
    "damping": {"rate": 20.0},
}


def _x(m, p, frames=6):
    from jaxmpm.discover import _rollout  # cached on the scene's structure: one compile per structure

    return np.asarray(_rollout(m, p, frames)[0].x)


def test_null_values_reproduce_the_base_model_and_each_extension_acts():
    scene = _scene()
    m, p = scene.model, scene.params
    base = _x(m, p)
    ids = [e for e in X.EXTENSIONS if X.applicable(m, e) is None]
    assert set(ids) == set(VALUES) | {"time_offset"}
    # all at once (the structure discover uses): moving_collider's rest-frame look-up rounds
    np.testing.assert_allclose(_x(m, X.enable(m, p, ids)), base, atol=1e-6, rtol=0)
    for e, value in VALUES.items():
        on = _x(m, X.enable(m, p, ids, {e: value}))
        assert np.max(np.abs(on - base)) > 1e-3, e


@pytest.mark.slow
def test_each_extension_alone_is_bitwise_null():
    scene = _scene()
    m, p = scene.model, scene.params
    base = _x(m, p)
    for e in [e for e in X.EXTENSIONS if X.applicable(m, e) is None]:
        null = _x(m, X.enable(m, p, [e]))
        if e == "moving_collider":
            np.testing.assert_allclose(null, base, atol=1e-6, rtol=0)
        else:
            np.testing.assert_array_equal(null, base, err_msg=e)


def test_cohesion_is_null_at_zero_for_sand():
    scene = _scene({"model": "sand", "friction_angle": 30.0}, frames=3)
    m, p = scene.model, scene.params
    assert X.applicable(m, "cohesion") is None
    assert X.applicable(_scene().model, "cohesion") is not None  # elastic body: not applicable
    np.testing.assert_array_equal(_x(m, X.enable(m, p, ["cohesion"]), 3), _x(m, p, 3))


def test_extension_parameters_and_errors():
    scene = _scene()
    m, p = scene.model, scene.params
    specs = {s.name: s for e in X.EXTENSIONS if X.applicable(m, e) is None for s in X.parameter_specs(m, p, e)}
    assert specs["drag.linear"].lower == 0.0 and specs["drag.linear"].bounded
    assert specs["gravity.delta"].shape == (2,) and not specs["gravity.delta"].bounded
    assert specs["moving_collider.floor"].shape == (2,)
    assert specs["initial_velocity.spin"].shape == (1,)
    with pytest.raises(JaxmpmError, match="unknown extension"):
        X.enable(m, p, ["wind"])
    with pytest.raises(JaxmpmError, match="has no parameter"):
        X.enable(m, p, ["drag"], {"drag": {"cubic": 1.0}})
    with pytest.raises(JaxmpmError, match="does not apply"):
        X.enable(m, p, ["cohesion"])
    # prepare() consumes what it applies, so nested calls do not apply it twice
    pe = X.enable(m, p, ["gravity"], {"gravity": {"delta": [0.0, -1.0]}})
    m2, p2 = X.prepare(m, pe)
    m3, p3 = X.prepare(m2, p2)
    np.testing.assert_allclose(np.asarray(p3["gravity"]), np.asarray(p["gravity"]) + np.array([0.0, -1.0]))
    assert "gravity" not in p3["extensions"]
    assert jnp.asarray(p3["gravity"]).dtype == jnp.asarray(p["gravity"]).dtype
