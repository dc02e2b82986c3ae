"""Each parameter declared once: the declarations drive validation, fitting spaces and guesses."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmpm
from jaxmpm.constitutive import MATERIALS
from jaxmpm.errors import JaxmpmError, SceneError
from jaxmpm.fit import FitConfig
from jaxmpm.identify import parameters as P
from jaxmpm.parameters import Linear, Log10, TanhBounded

# PAC-NeRF's initial guesses for its 45-sequence batch (configs, anchors §1.8), written out here.
PACNERF_GUESS = {
    "newtonian": {"mu": 10.0, "kappa": 1e4},
    "viscoplastic": {"mu": 100.0, "kappa": 1e5, "yield_stress": 10.0, "eta": 1.0},
    "elastic": {"E": 10**5.5, "nu": 0.25},
    "plasticine": {"E": 1e4, "nu": 0.25, "yield_stress": 1e3},
    "sand": {"friction_angle": 10.0},
}
# PAC-NeRF's Adam learning rates (anchors §1.5) in its spaces.
PACNERF_LR = {"E": 0.1, "nu": 0.01, "mu": 0.1, "kappa": 0.1, "yield_stress": 0.1, "eta": 0.05, "friction_angle": 1.0}


@pytest.mark.parametrize("model", sorted(PACNERF_GUESS))
def test_declared_guesses_and_rates_are_pacnerfs(model):
    cls = MATERIALS[model]
    assert set(cls.required()) == set(PACNERF_GUESS[model])
    for name, guess in PACNERF_GUESS[model].items():
        p = cls.parameter(name)
        assert p.guess == pytest.approx(guess, rel=1e-12), name
        assert p.learning_rate == PACNERF_LR[name], name


@pytest.mark.x64
def test_fitting_spaces_are_pacnerfs():
    for name in ("E", "mu", "kappa", "yield_stress", "eta", "density"):
        assert isinstance(P.transform_of(name), Log10) and name in P.LOG10_PARAMS
    assert isinstance(P.transform_of("nu"), TanhBounded)
    for name in ("friction_angle", "velocity", "gravity", "floor.friction", "drag.linear"):
        assert isinstance(P.transform_of(name), Linear)
    # round trips, and the tanh map onto (-0.45, 0.495)
    for name, value in (("E", 3e5), ("nu", 0.3), ("friction_angle", 35.0), ("body.mu", 0.02)):
        y = P.to_unconstrained(name, jnp.asarray(value, jnp.float64))
        assert float(P.from_unconstrained(name, y)) == pytest.approx(value, rel=1e-12)
    assert float(P.to_unconstrained("E", jnp.asarray(1e5, jnp.float64))) == pytest.approx(5.0)
    assert float(P.from_unconstrained("nu", jnp.asarray(1e3, jnp.float64))) == pytest.approx(0.495)
    assert float(P.from_unconstrained("nu", jnp.asarray(-1e3, jnp.float64))) == pytest.approx(-0.45)


@pytest.mark.parametrize("model, key, bad, good", [
    ("newtonian", "mu", -1.0, 0.0),          # a viscosity may vanish ...
    ("viscoplastic", "mu", 0.0, 1e3),        # ... a shear modulus may not
    ("elastic", "nu", 0.5, 0.49),
    ("sand", "friction_angle", 90.0, 45.0),
])
def test_scene_validation_reads_the_declared_range(model, key, bad, good):
    cls = MATERIALS[model]
    values = {p: PACNERF_GUESS.get(model, {}).get(p, 1.0) for p in cls.required()}
    assert cls.validate({**values, key: good})[key] == good
    with pytest.raises(SceneError, match=f"{key} = .* is out of range"):
        cls.validate({**values, key: bad})


def test_named_values_are_set_in_the_leaves_dtype():
    spec = {"dim": 2, "dx": 0.1, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 2, "frame_dt": 0.01, "substeps": 10,
            "bodies": [{"shape": "box", "lo": [0.4, 0.4], "hi": [0.6, 0.6], "ppc": 4,
                        "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e3}}],
            "colliders": [{"type": "plane", "name": "floor", "point": [0, 0.1], "normal": [0, 1]}]}
    scene = jaxmpm.load_scene(spec)
    p = P.with_values(scene.model, scene.params, {"mu": 200.0, "velocity": np.array([0.5, -1.0]), "floor.friction": 0.3})
    for name, value in (("mu", 200.0), ("velocity", [0.5, -1.0]), ("floor.friction", 0.3)):
        path = P.resolve_name(scene.model, p, name)
        leaf, old = P.get_param(p, path), P.get_param(scene.params, path)
        np.testing.assert_allclose(np.asarray(leaf), value, rtol=1e-6)
        assert jnp.asarray(leaf).dtype == jnp.asarray(old).dtype
    assert float(P.get_param(p, ("bodies", 0, "kappa"))) == pytest.approx(1e3)  # the others unchanged


def test_parameter_names_are_checked_before_any_work():
    spec = {"dim": 2, "dx": 0.1, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 2, "frame_dt": 0.01, "substeps": 10,
            "bodies": [{"shape": "box", "lo": [0.4, 0.4], "hi": [0.6, 0.6], "ppc": 4,
                        "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e3}}],
            "colliders": [{"type": "plane", "name": "floor", "point": [0, 0.1], "normal": [0, 1]}]}
    scene = jaxmpm.load_scene(spec)
    with pytest.raises(JaxmpmError, match="floor.friction"):  # the error lists the colliders' parameters
        P.resolve_name(scene.model, scene.params, "E")
    assert P.resolve_name(scene.model, scene.params, "floor.friction") == ("colliders", 0, "friction")
    with pytest.raises(JaxmpmError, match="mu given more than once"):
        P.check_names(["mu", "mu"])
    with pytest.raises(JaxmpmError, match="empty parameter name"):
        P.check_names(["mu", ""])
    for bad in ({"max_steps": 0}, {"max_steps": -5}, {"method": "sgd"}, {"grad": "sideways"}, {"stages": "some"}):
        with pytest.raises(JaxmpmError):
            FitConfig(**bad).check()
    obs = jaxmpm.Observation(times=np.array([0.01]), positions=np.zeros((1, 3, 2)))
    with pytest.raises(JaxmpmError, match="max_steps"):
        jaxmpm.fit(scene.model, scene.params, obs, ["mu"], FitConfig(max_steps=0))


@pytest.mark.parametrize("where, key, bad, words", [
    ("material", "density", -1.0, "density = -1.0 is out of range (must be > 0)"),
    ("collider", "friction", -0.1, "friction = -0.1 is out of range (must be >= 0)"),
    ("collider", "restitution", 1.5, "restitution = 1.5 is out of range (must be in [0, 1])"),
])
def test_scene_files_check_body_and_collider_parameters_against_their_declarations(where, key, bad, words):
    spec = {"dim": 2, "dx": 0.1, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 2, "frame_dt": 0.01, "substeps": 10,
            "bodies": [{"shape": "box", "lo": [0.4, 0.4], "hi": [0.6, 0.6], "ppc": 4,
                        "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e3}}],
            "colliders": [{"type": "plane", "point": [0, 0.1], "normal": [0, 1]}]}
    jaxmpm.load_scene(spec)
    target = spec["bodies"][0]["material"] if where == "material" else spec["colliders"][0]
    target[key] = bad
    with pytest.raises(SceneError) as err:
        jaxmpm.load_scene(spec)
    assert words in str(err.value)
