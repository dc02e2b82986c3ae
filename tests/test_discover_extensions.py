"""The extension library: null values reproduce the base model; each extension acts, with the
formula and sign that extensions.py and docs/discover.md document."""

import equinox as eqx
import jax
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


def test_each_extension_alone_is_bitwise_null():
    """Each extension alone at its null value gives the base model bit for bit: the prepared
    params, the initial state, and each compiled step (x, v, C, F) from the same states.

    Steps, not rollouts: compiling dominates (one program per extension), and a step is the
    unit that is exact. An extension whose step program (jaxpr) is the base one's (those
    applied by ``prepare`` or to the initial state or the observation) needs no compile. In a compiled rollout (``lax.scan``) XLA may fuse the step differently
    around an extension's zero term: rate_dependence then moves the last bit of some
    velocities (seen on CPU: 6e-8 m/s after 6 substeps); the rollout with all extensions at
    their null values is compared to 1e-6 in the test above. The scenes are tiny: the
    collider extensions on a block hitting a floor, the others on two blocks pushing into
    each other, so that stress and the affine field are non-zero."""
    from jaxmpm.step import _start, step

    collider = ("collider_friction", "restitution", "moving_collider")
    material = {"model": "elastic", "E": 3e3, "nu": 0.3}
    floor = load_scene(block_spec(2, material, dx=0.1, lo=[0.3, 0.12], hi=[0.5, 0.27], frames=2, substeps=3,
                                  velocity=[1.0, -3.0], ppc=1, floor=FLOOR))
    spec = block_spec(2, material, dx=0.1, frames=2, substeps=3)
    box = {"shape": "box", "material": material, "ppc": 1}
    spec["bodies"] = [{**box, "lo": [0.3, 0.5], "hi": [0.5, 0.6], "velocity": [1.0, 0.0]},
                      {**box, "lo": [0.5, 0.5], "hi": [0.7, 0.7], "velocity": [-1.0, 0.5]}]
    free = load_scene(spec)
    one = eqx.filter_jit(step)
    fields = ("x", "v", "C", "F", "aux", "tag", "time")
    seen, no_op = set(), set()

    def jaxpr(model, params, state):  # the step's program (params closed over: their values are checked above)
        return str(jax.make_jaxpr(lambda st: step(model, params, st))(state))

    for scene, ids in ((floor, collider), (free, [e for e in X.EXTENSIONS if e not in collider])):
        m, p = scene.model, scene.params
        m0, p0, s0 = _start(m, p, None)
        states = [s0]
        for _ in range(3):
            states.append(one(m0, p0, states[-1]))
        assert float(np.max(np.abs(np.asarray(states[-1].C)))) > 0.1  # something to damp / to stress
        base_jaxpr = jaxpr(m0, p0, s0)
        for e in [e for e in ids if X.applicable(m, e) is None]:
            seen.add(e)
            me, pe, se = _start(m, X.enable(m, p, [e]), None)
            for name in fields:
                np.testing.assert_array_equal(getattr(se, name), getattr(s0, name), err_msg=f"{e}: initial {name}")
            np.testing.assert_array_equal(pe["gravity"], p0["gravity"], err_msg=e)
            for c, c0 in zip(pe["colliders"], p0["colliders"]):
                for key in c0:
                    np.testing.assert_array_equal(c[key], c0[key], err_msg=f"{e}: collider {key}")
            if jaxpr(me, pe, s0) == base_jaxpr:  # adds no operation to the step: the same program
                no_op.add(e)
                continue
            for k, s in enumerate(states[:-1]):
                out = one(me, pe, s)
                for name in fields:
                    a, b = np.asarray(getattr(out, name)), np.asarray(getattr(states[k + 1], name))
                    if e == "moving_collider":  # its rest-frame look-ups round
                        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0, err_msg=f"{e}: step {k} {name}")
                    else:
                        np.testing.assert_array_equal(a, b, err_msg=f"{e}: step {k} {name}")
    assert seen == set(X.EXTENSIONS) - {"cohesion"}  # cohesion: test_cohesion_is_null_at_zero_for_sand
    # applied by prepare (values checked above), to the initial state, or to the observation only
    assert no_op >= {"gravity", "restitution", "initial_velocity", "time_offset"}


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


# =========================================================================== formulas and signs
# Each test below computes the documented effect of one extension independently
# (extensions.py's table / docs/discover.md) in a scene where it is exact, so a flipped sign,
# a dropped factor or another formula fails it. Rollouts go through discover's ``_rollout`` where
# possible (compiled once per params structure).

#: a free body high in the domain (no collider): one particle per cell, no stress develops
def _free(material=None, frames=6, velocity=None, bodies=None):
    spec = block_spec(2, material or {"model": "elastic", "E": 3e3, "nu": 0.3}, dx=0.1, lo=[0.4, 0.5], hi=[0.6, 0.7],
                      frames=frames, substeps=20, velocity=velocity, ppc=1)
    if bodies is not None:
        spec["bodies"] = bodies
    return load_scene(spec)


def _v(m, p, frames):
    from jaxmpm.discover import _rollout

    frames_, ok = _rollout(m, p, frames)
    assert bool(ok)
    return np.asarray(frames_.v, float), np.asarray(frames_.x, float)


def _two_colliders():
    spec = block_spec(2, {"model": "elastic", "E": 3e3, "nu": 0.3}, dx=0.05, lo=[0.3, 0.12], hi=[0.5, 0.27])
    spec["colliders"] = [
        {"type": "plane", "name": "floor", "point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "slip",
         "restitution": 0.25},
        {"type": "plane", "name": "wall", "point": [0.9, 0.0], "normal": [-1.0, 0.0], "contact": "friction",
         "friction": 0.375, "restitution": 0.125},
        {"type": "plane", "name": "roof", "point": [0.0, 0.95], "normal": [0.0, -1.0], "contact": "sticky"},
    ]
    return load_scene(spec)


def test_restitution_adds_its_offset_to_each_named_collider():
    scene = _two_colliders()
    m, p = scene.model, scene.params
    specs = {s.key: s for s in X.parameter_specs(m, p, "restitution")}
    assert set(specs) == {"floor", "wall"}  # sticky colliders do not bounce
    # the offset's bounds keep e = base + offset in [0, 1]
    assert (specs["floor"].lower, specs["floor"].upper) == (-0.25, 0.75)
    assert (specs["wall"].lower, specs["wall"].upper) == (-0.125, 0.875)
    m2, p2 = X.prepare(m, X.enable(m, p, ["restitution"], {"restitution": {"floor": 0.5, "wall": -0.0625}}))
    e = [float(c["restitution"]) for c in p2["colliders"]]
    assert e == [0.75, 0.0625, 0.0]
    assert [float(c["friction"]) for c in p2["colliders"]] == [float(c["friction"]) for c in p["colliders"]]
    assert [c.contact for c in m2.colliders] == ["slip", "friction", "sticky"]  # the contact law is kept


def test_collider_friction_adds_coulomb_friction_and_makes_slip_colliders_coulomb():
    scene = _two_colliders()
    m, p = scene.model, scene.params
    specs = {s.key: s for s in X.parameter_specs(m, p, "collider_friction")}
    assert set(specs) == {"floor", "wall"}
    assert specs["floor"].lower == 0.0 and specs["wall"].lower == -0.375  # mu = base + offset >= 0
    m2, p2 = X.prepare(m, X.enable(m, p, ["collider_friction"], {"collider_friction": {"floor": 0.5, "wall": 0.25}}))
    assert [float(c["friction"]) for c in p2["colliders"]] == [0.5, 0.625, float(p["colliders"][2]["friction"])]
    assert [float(c["restitution"]) for c in p2["colliders"]] == [0.25, 0.125, 0.0]
    assert [c.contact for c in m2.colliders] == ["friction", "friction", "sticky"]
    assert [c.contact for c in m.colliders] == ["slip", "friction", "sticky"]  # the input model is not changed


def test_moving_collider_translates_the_plane_by_v_t():
    scene = _two_colliders()
    m, p = scene.model, scene.params
    assert [s.key for s in X.parameter_specs(m, p, "moving_collider")] == ["floor", "wall", "roof"]
    vc = np.array([0.2, 0.3])
    m2, _ = X.prepare(m, X.enable(m, p, ["moving_collider"], {"moving_collider": {"floor": vc}}))
    pts = jnp.asarray([[0.3, 0.2], [0.7, 0.05], [0.5, 0.5]], jnp.float32)
    for t in (0.0, 0.25, 1.0):
        sd, n = m2.colliders[0].signed_distance(pts, jnp.asarray(t, jnp.float32))
        # the floor y = 0.1 moves up by 0.3 t (its x motion does not change a horizontal plane's distance)
        np.testing.assert_allclose(np.asarray(sd), np.asarray(pts)[:, 1] - (0.1 + 0.3 * t), atol=1e-6)
        np.testing.assert_allclose(np.asarray(n), [[0.0, 1.0]] * 3, atol=1e-6)
        v = m2.colliders[0].velocity_at(pts, jnp.asarray(t, jnp.float32))
        np.testing.assert_allclose(np.asarray(v), np.broadcast_to(vc, (3, 2)), atol=1e-6)
        c, _ = m2.colliders[0].rigid_transform(jnp.asarray(t, jnp.float32))
        np.testing.assert_allclose(np.asarray(c), np.array([0.0, 0.1]) + vc * t, atol=1e-6)
    # the wall (no offset given: null) stays where it is
    sd, _ = m2.colliders[1].signed_distance(pts, jnp.asarray(1.0, jnp.float32))
    np.testing.assert_allclose(np.asarray(sd), 0.9 - np.asarray(pts)[:, 0], atol=1e-6)


def test_gravity_delta_adds_to_the_free_fall_acceleration():
    scene = _free(frames=4)
    m, p = scene.model, scene.params
    dg = np.array([0.5, -1.5])
    v, _ = _v(m, X.enable(m, p, ["gravity"], {"gravity": {"delta": dg}}), 4)
    t = np.arange(4) * m.frame_dt
    expected = t[:, None] * (np.array([0.0, -9.8]) + dg)  # a free body: v = (g + dg) t, every particle
    np.testing.assert_allclose(v, np.broadcast_to(expected[:, None, :], v.shape), rtol=1e-4, atol=1e-5)


def test_initial_velocity_adds_delta_and_a_rigid_spin_about_the_body_centre():
    from jaxmpm.step import _start

    bodies = [
        {"shape": "box", "lo": [0.2, 0.5], "hi": [0.4, 0.7], "velocity": [0.1, 0.0],
         "material": {"model": "elastic", "E": 3e3, "nu": 0.3}, "ppc": 1},
        {"shape": "box", "lo": [0.6, 0.3], "hi": [0.8, 0.6], "velocity": [0.0, -0.2],
         "material": {"model": "elastic", "E": 3e3, "nu": 0.3}, "ppc": 1},
    ]
    scene = _free(bodies=bodies)
    m, p = scene.model, scene.params
    dv, w = np.array([0.3, -0.4]), 2.0
    pe = X.enable(m, p, ["initial_velocity"], {"initial_velocity": {"delta": dv, "spin": [w]}})
    _, _, state = _start(m, pe, None)
    x, v = np.asarray(state.x, float), np.asarray(state.v, float)
    for sl, v0 in zip(m.body_slices(), ([0.1, 0.0], [0.0, -0.2])):
        r = x[sl] - x[sl].mean(axis=0)  # about each body's own centre
        expected = np.array(v0) + dv + w * np.stack([-r[:, 1], r[:, 0]], axis=1)  # w e_z x r, counter-clockwise
        np.testing.assert_allclose(v[sl], expected, rtol=1e-5, atol=1e-6)
        assert np.allclose(v[sl].mean(axis=0), np.array(v0) + dv, atol=1e-6)  # spin adds no momentum


def test_drag_relaxes_free_fall_to_the_implicit_update_and_terminal_speed():
    scene = _free(frames=7)
    m, p = scene.model, scene.params
    k1, k2 = 20.0, 2.0
    n = 6 * m.substeps
    for lin, quad in ((k1, 0.0), (0.0, k2), (k1, k2)):
        v, _ = _v(m, X.enable(m, p, ["drag"], {"drag": {"linear": lin, "quadratic": quad}}), 7)
        vy = v[:, :, 1]
        # the documented update on the grid, after gravity: v <- (v + g dt) / (1 + dt (k1 + k2 |v + g dt|))
        u, expected = 0.0, [0.0]
        for i in range(n):
            u = u - 9.8 * m.dt
            u = u / (1.0 + m.dt * (lin + quad * abs(u)))
            if (i + 1) % m.substeps == 0:
                expected.append(u)
        np.testing.assert_allclose(vy, np.broadcast_to(np.array(expected)[:, None], vy.shape), rtol=2e-4, atol=1e-6)
        np.testing.assert_allclose(v[:, :, 0], 0.0, atol=1e-6)
        # it slows the fall: below free fall, towards the terminal speed from below
        terminal = 9.8 / lin if quad == 0 else (np.sqrt(9.8 / quad) if lin == 0 else
                                                (-lin + np.sqrt(lin * lin + 4 * quad * 9.8)) / (2 * quad))
        assert np.all(np.abs(vy[1:]) < 9.8 * np.arange(1, 7)[:, None] * m.frame_dt)
        assert np.all(np.abs(vy) < terminal) and np.all(np.diff(np.abs(vy[:, 0])) > 0)
    # linear drag over 6 frames (k t = 5): within 1 % of the terminal speed g / k
    v, _ = _v(m, X.enable(m, p, ["drag"], {"drag": {"linear": k1, "quadratic": 0.0}}), 7)
    np.testing.assert_allclose(v[-1, :, 1], -9.8 / k1, rtol=1e-2)


def _random_state(m, p, seed):
    """The initial state with random F (det > 0), C and aux, and a random Kirchhoff stress."""
    from jaxmpm.model import initial_state

    rng = np.random.default_rng(seed)
    n = m.num_particles
    F = np.eye(2) + 0.2 * rng.standard_normal((n, 2, 2))
    C = 3.0 * rng.standard_normal((n, 2, 2))
    aux = rng.uniform(0.7, 1.3, n)
    tau = 100.0 * rng.standard_normal((n, 2, 2))
    state = initial_state(m, p)
    state = eqx.tree_at(lambda s: (s.C, s.F, s.aux), state, (jnp.asarray(C, jnp.float32), jnp.asarray(F, jnp.float32),
                                                          jnp.asarray(aux, jnp.float32)))
    return state, F, C, aux, tau


_TWO_BODIES = [
    {"shape": "box", "lo": [0.2, 0.5], "hi": [0.4, 0.7], "material": {"model": "elastic", "E": 3e3, "nu": 0.3},
     "ppc": 1},
    {"shape": "box", "lo": [0.6, 0.3], "hi": [0.8, 0.6], "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e3},
     "ppc": 1},
]


def test_rate_dependence_adds_eta_J_sym_C_to_the_kirchhoff_stress():
    scene = _free(bodies=_TWO_BODIES)
    m, p = scene.model, scene.params
    state, F, C, aux, tau = _random_state(m, p, 0)
    eta = 7.0
    pe = X.enable(m, p, ["rate_dependence"], {"rate_dependence": {"viscosity": eta}})
    out = np.asarray(X.stress(m, pe, state, state.F, state.aux, jnp.asarray(tau, jnp.float32)), float)
    # J: det F for solids, the evolved volume ratio (aux) for the J-only Newtonian fluid
    J = np.concatenate([np.linalg.det(F[m.body_slices()[0]]), aux[m.body_slices()[1]]])
    expected = tau + eta * J[:, None, None] * 0.5 * (C + np.swapaxes(C, 1, 2))
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-3)


def test_rate_dependence_dissipates_an_expansion():
    """The viscous stress resists the deformation rate: a soft body expanding from rest shape
    loses kinetic energy faster with eta > 0 (a flipped sign would feed it)."""
    from jaxmpm.model import initial_state
    from jaxmpm.step import simulate

    scene = load_scene(block_spec(2, {"model": "elastic", "E": 10.0, "nu": 0.3}, dx=0.05, lo=[0.4, 0.4], hi=[0.6, 0.6],
                                  frames=2, substeps=20, gravity=[0.0, 0.0]))
    m, p = scene.model, scene.params
    s0 = initial_state(m, p)
    s0 = eqx.tree_at(lambda s: s.v, s0, 2.0 * (s0.x - jnp.mean(s0.x, axis=0)))
    final = eqx.filter_jit(lambda pp: simulate(m, pp, state=s0, frames=2, checkpoint=None).final)  # one compile

    def kinetic(pp):
        f = final(pp)
        return float(jnp.sum(0.5 * f.mass * jnp.sum(f.v ** 2, axis=-1)))

    k_base = kinetic(X.enable(m, p, ["rate_dependence"]))
    k_visc = kinetic(X.enable(m, p, ["rate_dependence"], {"rate_dependence": {"viscosity": 50.0}}))
    assert k_visc < 0.6 * k_base, (k_visc, k_base)


def test_heterogeneity_scales_the_stress_by_ten_to_the_g_dot_xi():
    scene = _free(bodies=_TWO_BODIES)
    m, p = scene.model, scene.params
    state, F, C, aux, tau = _random_state(m, p, 1)
    g, eta = np.array([0.5, -0.25]), 3.0
    pe = X.enable(m, p, ["heterogeneity", "rate_dependence"],
                  {"heterogeneity": {"gradient": g}, "rate_dependence": {"viscosity": eta}})
    out = np.asarray(X.stress(m, pe, state, state.F, state.aux, jnp.asarray(tau, jnp.float32)), float)
    J = np.concatenate([np.linalg.det(F[m.body_slices()[0]]), aux[m.body_slices()[1]]])
    visc = tau + eta * J[:, None, None] * 0.5 * (C + np.swapaxes(C, 1, 2))  # eta is scaled too
    x0 = np.asarray(state.x, float)
    for sl in m.body_slices():
        lo, hi = x0[sl].min(axis=0), x0[sl].max(axis=0)
        xi = (x0[sl] - (lo + hi) / 2) / ((hi - lo) / 2)  # [-1, 1] over each body's own box
        assert np.isclose(xi.min(), -1) and np.isclose(xi.max(), 1)
        np.testing.assert_allclose(out[sl], visc[sl] * 10.0 ** (xi @ g)[:, None, None], rtol=1e-5, atol=1e-3)
    # the corner with xi = (1, -1) is 10^0.75 times stiffer
    i = np.argmax(x0[:, 0] - x0[:, 1])
    assert np.allclose(out[i], visc[i] * 10**0.75, rtol=1e-5)


def test_damping_divides_C_by_1_plus_dt_zeta_each_step_and_keeps_momentum():
    from jaxmpm.model import initial_state
    from jaxmpm.step import step

    scene = load_scene(block_spec(2, {"model": "elastic", "E": 3e3, "nu": 0.3}, dx=0.05, lo=[0.4, 0.4], hi=[0.6, 0.6],
                                  frames=3, substeps=20))
    m, p = scene.model, scene.params
    zeta = 0.5 / m.dt  # dt zeta = 1/2: 1/(1 + 1/2) = 0.667, exp(-1/2) = 0.607
    base = X.enable(m, p, ["damping", "initial_velocity"], {"initial_velocity": {"spin": [3.0]}})
    damped = X.enable(m, p, ["damping", "initial_velocity"], {"initial_velocity": {"spin": [3.0]},
                                                               "damping": {"rate": zeta}})
    s0 = X.initial_velocity(m, base, initial_state(m, base))
    one = eqx.filter_jit(step)  # one compile: base and damped share the params structure
    a, b = one(m, base, s0), one(m, damped, s0)
    Ca, Cb = np.asarray(a.C, float), np.asarray(b.C, float)
    assert np.max(np.abs(Ca)) > 1.0  # the spin gives an affine field to damp
    np.testing.assert_allclose(Cb, Ca / (1.0 + m.dt * zeta), rtol=1e-5, atol=1e-6)
    assert not np.allclose(Cb, Ca * np.exp(-m.dt * zeta), rtol=1e-2, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(b.v), np.asarray(a.v))  # G2P velocities: untouched
    np.testing.assert_array_equal(np.asarray(b.x), np.asarray(a.x))
    # over a rollout: the spin dies out faster, the centre of mass moves as without damping
    va, xa = _v(m, base, 3)
    vb, xb = _v(m, X.enable(m, p, ["damping", "initial_velocity"],
                            {"initial_velocity": {"spin": [3.0]}, "damping": {"rate": 20.0}}), 3)
    mass = np.asarray(s0.mass, float)
    np.testing.assert_allclose(mass @ vb[-1] / mass.sum(), mass @ va[-1] / mass.sum(), atol=1e-5)

    def spin(v, x):  # angular momentum of the particle velocities about the centre of mass
        r = x - mass @ x / mass.sum()
        return np.sum(mass * (r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]))

    assert 0.0 < spin(vb[-1], xb[-1]) < 0.9 * spin(va[-1], xa[-1])


def test_time_offset_compares_the_model_at_t_minus_t0():
    """Data that are the simulation delayed by two frames (observed at t = simulated at
    t - 2 frame_dt) are matched exactly by t0 = +2 frame_dt, through discover's residuals."""
    from jaxmpm.discover import Sequence, _Problem
    from jaxmpm.observe import Observation

    scene = _free(frames=6, velocity=[0.5, 1.0])
    m, p = scene.model, scene.params
    fdt = m.frame_dt
    times = (np.arange(6) + 2.0) * fdt  # every problem below has these times: one rollout compile

    def problem(positions):
        obs = Observation(times=times, positions=positions, point_ids="particles")
        return _Problem([Sequence(m, p, obs)], [], ["time_offset"], 64, jnp.float32)

    prob = problem(np.zeros((6, m.num_particles, 2)))
    x = np.asarray(prob.trajectories(prob.initial())[0][0].x, float)  # the model's frames (null t0)
    col = prob.slices["time_offset.t0"]

    def rms(t0):
        theta = prob.initial()
        theta[col] = t0
        return float(np.sqrt(np.mean(prob.residuals(theta) ** 2)))

    prob = problem(x[:6])  # observed at (k + 2) frame_dt: simulated frame k
    assert rms(2 * fdt) < 1e-5
    assert rms(0.0) > 1e-3 and rms(-2 * fdt) > rms(0.0)
    # between frames (cubic Hermite): data delayed by 1.5 frames, observed at the frame times
    # (k + 2) frame_dt = simulated mid-frames (k + 1/2) frame_dt, on the free-fall parabola
    prob = problem((x[:6] + x[1:7]) / 2 - np.array([0.0, -9.8]) * fdt**2 / 8)
    assert rms(1.5 * fdt) < 1e-5
    assert rms(1.0 * fdt) > 2e-3 and rms(2.0 * fdt) > 2e-3 and rms(-1.5 * fdt) > 2e-2


def _rotation(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def test_cohesion_moves_the_drucker_prager_apex_to_mean_stress_c():
    """The documented yield surface with cohesion c (2D, alpha = tan(phi)/sqrt 2):
    ||dev tau|| <= alpha (D c - tr tau); tension beyond it returns to the apex tau = c I."""
    scene = _scene({"model": "sand", "friction_angle": 30.0}, frames=3)
    m, p = scene.model, scene.params
    sand, bp = m.bodies[0].material, p["bodies"][0]
    E, nu, D = 1e6, 0.3, 2
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    alpha = np.tan(np.radians(30.0)) / np.sqrt(2.0)
    c = 1e4
    rng = np.random.default_rng(3)
    # principal Hencky strains: hydrostatic tension (beyond the apex), mild tension (inside the
    # cohesive cone, outside the cohesionless one), compression with large shear (on the cone)
    eps = np.concatenate([np.full((4, 2), 0.02) + rng.uniform(0, 1e-4, (4, 2)),
                          0.001 + rng.uniform(0, 1e-3, (4, 2)),
                          -0.01 + np.array([1.0, -1.0]) * rng.uniform(0.03, 0.05, (8, 1))])
    F = np.stack([_rotation(a) @ np.diag(np.exp(e)) @ _rotation(b).T
                  for e, a, b in zip(eps, rng.uniform(0, 6, len(eps)), rng.uniform(0, 6, len(eps)))])
    n = len(F)
    args = (jnp.asarray(F, jnp.float32), jnp.zeros((n, 2, 2), jnp.float32), jnp.ones(n, jnp.float32), bp, m.dt)

    update = eqx.filter_jit(X.material_update)

    def tau(cohesion):
        pp = X.enable(m, p, ["cohesion"], {"cohesion": {"strength": cohesion}})
        return np.asarray(update(sand, *args, pp)[2], float)

    t0, tc = tau(0.0), tau(c)
    tr = lambda t: np.trace(t, axis1=1, axis2=2)  # noqa: E731
    dev = lambda t: np.linalg.norm(t - tr(t)[:, None, None] / D * np.eye(D), axis=(1, 2))  # noqa: E731
    elastic = np.stack([np.diag(2 * mu * e + lam * e.sum()) for e in eps])  # the trial stress (its invariants)
    tension, mild, shear = slice(0, 4), slice(4, 8), slice(8, None)
    # beyond the apex: tau = c I with cohesion, 0 without
    np.testing.assert_allclose(tc[tension], np.broadcast_to(c * np.eye(2), (4, 2, 2)), rtol=0, atol=1e-3 * c)
    np.testing.assert_allclose(t0[tension], 0.0, atol=1e-3)
    # mild tension: elastic (untouched) with cohesion, at the apex without
    np.testing.assert_allclose(tr(tc[mild]), tr(elastic[mild]), rtol=1e-4)
    np.testing.assert_allclose(dev(tc[mild]), dev(elastic[mild]), rtol=1e-3, atol=1.0)  # float32 strains: ~0.1 Pa
    assert np.all(tr(tc[mild]) > 0) and np.all(dev(tc[mild]) < alpha * (D * c - tr(tc[mild])))
    np.testing.assert_allclose(t0[mild], 0.0, atol=1e-3)
    # large shear under compression: on the cone, pressure kept (the return is purely deviatoric)
    for t, cc in ((t0, 0.0), (tc, c)):
        np.testing.assert_allclose(tr(t[shear]), tr(elastic[shear]), rtol=1e-4)
        np.testing.assert_allclose(dev(t[shear]), alpha * (D * cc - tr(t[shear])), rtol=1e-3)
    assert np.all(dev(tc[shear]) > dev(t0[shear]) + 0.9 * alpha * D * c)


def test_cohesive_sand_column_stands_taller():
    """A sand column on a floor slumps without cohesion and stands with it (sign of c)."""
    floor = {"point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "friction", "friction": 0.5}
    scene = load_scene(block_spec(2, {"model": "sand", "friction_angle": 30.0, "E": 1e5}, dx=0.05, lo=[0.4, 0.1],
                                  hi=[0.55, 0.4], frames=6, substeps=20, floor=floor))
    m, p = scene.model, scene.params

    def shape(c):
        _, x = _v(m, X.enable(m, p, ["cohesion"], {"cohesion": {"strength": c}}), 6)
        return np.ptp(x[:, :, 1], axis=1), np.ptp(x[:, :, 0], axis=1)  # height, width per frame

    h0, w0 = shape(0.0)
    hc, wc = shape(5e3)  # c >= 0.37 rho g h is needed at the base (rho g h = 2.9 kPa)
    assert h0[-1] < 0.7 * h0[0] and w0[-1] > 1.5 * w0[0]  # cohesionless: slumps
    assert hc[-1] > 0.97 * hc[0] and wc[-1] < 1.05 * wc[0]  # cohesive: stands
