"""What docs/colliders.md says of the baseline collision modes and of restitution, checked on
small 2D scenes: the grid-level mode lets material fall through a thin plate that lies between
node rows, boundary particles hold it about 1 dx off without a leak, and the contact law sends
``-e v_n`` back along the normal."""

import json
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from collider_scenes import ELASTIC, FLUID, SAND, rollout

from jaxmpm import FitConfig, JaxmpmError, JaxmpmWarning, Observation, fit, simulate
from jaxmpm.cli import main
from jaxmpm.colliders import project_velocity
from jaxmpm.model import CPIC_RESTITUTION_NOTE
from jaxmpm.sweep import sweep_params
from jaxmpm.scene import load_scene
from jaxmpm import initial_state, step

DX = 0.02


def _thin_plate(collision: str) -> tuple[dict, float]:
    """Fluid, sand and an elastic block dropped at 2 m/s on a full-width segment of zero
    thickness half-way between two node rows (docs/colliders.md, "Penetration and leaks");
    the spec and the plate's height."""
    y0 = (math.floor(0.405 / DX) + 0.5) * DX
    bodies = [
        {"shape": "box", "lo": [x0, 0.55], "hi": [x0 + 0.2, 0.7], "velocity": [0.0, -2.0], "material": m}
        for x0, m in ((0.08, FLUID), (0.4, SAND), (0.72, ELASTIC))
    ]
    spec = {
        "dim": 2, "dx": DX, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 10, "frame_dt": 1 / 24,
        "substeps": 80, "gravity": [0, -9.8], "collision": collision, "bodies": bodies,
        "colliders": [{"type": "mesh", "name": "plate", "points": [[1.1, y0], [-0.1, y0]], "contact": "slip"}],
    }
    return spec, y0


def _deepest_below_the_plate(collision: str) -> tuple[np.ndarray, int]:
    """Per particle, the largest depth (in dx) it ever reached below the plate; and how many
    particles end below it."""
    spec, y0 = _thin_plate(collision)
    scene = load_scene(spec)
    _, x, _ = rollout(scene.model, scene.params)
    return ((y0 - x[..., 1]) / DX).max(axis=0), int((x[-1, :, 1] < y0 - 0.5 * DX).sum())


def test_grid_mode_lets_everything_through_a_plate_between_node_rows():
    """No node lies on or inside a zero-thickness plate between node rows, so the grid-level
    condition never acts (docs: 900 of 900 leaked, +20.5 dx)."""
    depth, below = _deepest_below_the_plate("grid")
    assert (depth > 0.5).all()  # every particle leaked ...
    assert below > 0.8 * len(depth)  # ... and most lie below the plate at the end (measured 792/900)


def test_boundary_particles_hold_material_about_one_dx_off_without_leaking():
    """docs: boundary particles never leak and keep the material 0.8-1.4 dx off the surface
    (measured here: the closest particle stays 0.93 dx above the plate)."""
    depth, below = _deepest_below_the_plate("particles")
    assert below == 0
    assert -1.4 < depth.max() < -0.8


@pytest.mark.parametrize("contact", ["slip", "friction"])
def test_contact_law_sends_back_e_times_the_approach_speed(contact):
    """``project_velocity``: an approaching normal velocity ``v_n`` (relative to a moving
    collider) leaves as ``-e v_n``; slip keeps the tangential part, friction shrinks it by
    ``mu |v_n|``; a separating velocity is unchanged."""
    n = jnp.asarray([[0.6, 0.8]])
    t = jnp.asarray([[0.8, -0.6]])
    v_c = jnp.asarray([[0.1, 0.2]])
    e, mu = 0.7, 0.25
    v_n, v_t = -1.5, 2.0
    v = v_c + v_n * n + v_t * t
    out = project_velocity(v, n, contact, friction=mu, restitution=e, v_collider=v_c)
    tangential = v_t - (mu * abs(v_n) if contact == "friction" else 0.0)
    np.testing.assert_allclose(out, v_c - e * v_n * n + tangential * t, rtol=1e-6)
    away = v_c + 0.5 * n + v_t * t
    np.testing.assert_allclose(project_velocity(away, n, contact, friction=mu, restitution=e, v_collider=v_c), away,
                               rtol=1e-6)


def _free_particle_normal_speeds(restitution: float, folder, contact: str = "slip") -> np.ndarray:
    """One free particle thrown at 2 m/s onto a CPIC box with restitution ``e``, without
    gravity: its normal velocity (m/s) and height after every substep, ``(S, 2)``. Its
    material is elastic with E = 1 Pa: stress negligible (with E = 1 kPa the deformation the
    contact gives it pushes it off the box slowly, as it would a real elastic body)."""
    np.save(folder / "one.npy", np.array([[0.5, 0.13]]))
    spec = {
        "dim": 2, "dx": DX, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 30, "frame_dt": 1 / 480,
        "substeps": 8, "gravity": [0.0, 0.0],
        "bodies": [{"shape": "points", "path": "one.npy", "velocity": [0.6, -2.0],
                    "material": {"model": "elastic", "E": 1.0, "nu": 0.3}}],
        "colliders": [{"type": "box", "name": "floor", "lo": [0.0, 0.0], "hi": [1.0, 0.1], "contact": contact,
                       "restitution": restitution}],
    }
    scene = load_scene(spec, base_dir=folder)

    def substeps(state, _):
        state = step(scene.model, scene.params, state)
        return state, jnp.stack([state.v[0, 1], state.x[0, 1]])

    _, out = jax.lax.scan(substeps, initial_state(scene.model, scene.params), None, length=30 * 8)
    return np.asarray(out)


#: Known defect, measured and not fixed (docs/colliders.md, "Restitution in CPIC"): the contact
#: law acts on a particle only through its ghost nodes, whose share W < 1 of its stencil makes
#: a drag that slows an approach (harder with a restitution) and stores nothing to give back;
#: without stress a particle stops before the face and never bounces. Applying the law where
#: the particle is predicted to cross changes nothing now: it never gets there (session 54).
SURFACE_LAW_MISSING = pytest.mark.xfail(strict=True, reason="known defect: CPIC's ghost layer slows an approach "
                                        "and never sends it back (docs/colliders.md)")


@SURFACE_LAW_MISSING
@pytest.mark.parametrize("e", [0.0, 0.3, 1.0])
def test_a_free_particle_leaves_a_box_at_e_times_the_speed_it_arrives_with(e, tmp_path):
    """The contact law's promise (docs/colliders.md): a particle that reaches the surface
    leaves with ``e`` times its normal arrival speed, and with ``e = 0`` it stays on the
    surface. Today (E = 1 Pa; the face lies on a node row) the ghost layer's drag stops it
    before the face, 0.19 cells above it with e = 0 and 0.98 with e = 1: no bounce (with
    E = 1 kPa its own stress sends it off at 0.56 v_in for e = 0 and 0.62 for e = 1;
    ``benchmarks/cpic_restitution.py``, session 54)."""
    vy, y = _free_particle_normal_speeds(e, tmp_path).T
    turn = int(np.argmax(vy >= 0.0))  # the substep at which the particle met the surface
    arrival = -vy[turn - 1]
    assert 0.75 * 2.0 < arrival <= 2.0  # the ghost layer slowed it, but not much
    assert np.all(np.diff(vy[:turn]) > -1e-6)  # ... monotonically, without a bounce before the surface
    # it leaves at e v_a (v_a: the speed of the substep before the hit, which slows it by
    # another 0.5% in the ghost layer before the rebound), and keeps that speed
    np.testing.assert_allclose(vy[turn], e * arrival, rtol=1e-2, atol=1e-5)
    assert np.ptp(vy[turn:]) < 1e-5
    assert y.min() > 0.1 - 0.05 * DX  # it did not enter the box
    if e == 0.0:
        assert np.ptp(y[turn:]) < 1e-3 * DX  # it rests on the surface


@SURFACE_LAW_MISSING
def test_sticky_contact_has_no_rebound_whatever_its_restitution(tmp_path):
    vy, y = _free_particle_normal_speeds(1.0, tmp_path, contact="sticky").T
    turn = int(np.argmax(vy >= 0.0))
    assert vy[turn - 1] < -1.5  # it arrived fast ...
    assert vy[turn:].max() < 1e-3 and abs(vy[-1]) < 1e-3  # ... and never left
    assert y.min() > 0.1 - 0.05 * DX


def _one_collider_scene(collision: str, kind: str, contact: str, friction: float, restitution: float) -> dict:
    """A 2D block above one collider of ``kind`` (``"box"`` or ``"plane"``) with the given contact."""
    shape = ({"lo": [0.0, 0.0], "hi": [1.0, 0.1]} if kind == "box" else {"point": [0.0, 0.1], "normal": [0.0, 1.0]})
    return {
        "dim": 2, "dx": 0.05, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 2, "frame_dt": 0.01, "substeps": 4,
        "collision": collision,
        "bodies": [{"shape": "box", "lo": [0.4, 0.3], "hi": [0.6, 0.4], "material": ELASTIC}],
        "colliders": [{"type": kind, "name": "floor", "contact": contact, "friction": friction,
                       "restitution": restitution, **shape}],
    }


@pytest.mark.parametrize("dim, substeps", [(2, 80), pytest.param(3, 20, marks=pytest.mark.slow)])  # 3D: the same code
def test_a_flip_blend_rests_an_elastic_block_on_a_cpic_box_as_apic_does(dim, substeps):
    """``flip`` (``Model.flip``) with a CPIC collider: an elastic block (E = 100 kPa, dx = 5 cm)
    dropped 4 cells onto a slip box comes to rest on it as with APIC alone, over 0.6 s: no NaN,
    no energy gained, the CFL number small, no particle near the face, its area or volume
    kept, its top and centre of mass within a quarter cell of APIC's. Measured: lowest
    particle 1.2 cells above the face in both, top 2.7 cells, mean det F 0.995. (A first
    version counted the ghost nodes' unforced velocity as ``v_p`` without ``C_p M``: this
    block went NaN by frame 22-42 in 2D.)"""
    lo, hi = [0.4, 0.3, 0.4][:dim], [0.6, 0.4, 0.6][:dim]
    box_hi = [1.0, 0.1, 1.0][:dim]
    runs = []
    for flip in (0.0, 0.99):
        scene = load_scene({
            "dim": dim, "dx": 0.05, "domain": {"lo": [0] * dim, "hi": [1] * dim}, "frames": 60, "frame_dt": 0.01,
            "substeps": substeps, "flip": flip,
            "bodies": [{"shape": "box", "lo": lo, "hi": hi, "material": ELASTIC}],
            "colliders": [{"type": "box", "name": "floor", "lo": [0.0] * dim, "hi": box_hi, "contact": "slip"}],
        })
        traj = simulate(scene.model, scene.params)
        assert not np.asarray(traj.nan).any(), f"flip = {flip}: NaN"
        assert np.asarray(traj.energy_gain).max() <= 1e-3, f"flip = {flip}: energy grew"
        assert np.asarray(traj.cfl).max() < 0.1, f"flip = {flip}: CFL {np.asarray(traj.cfl).max()}"
        height = (np.asarray(traj.x)[-1, :, 1] - 0.1) / 0.05  # cells above the face
        runs.append({"lowest": height.min(), "top": height.max(), "centre": height.mean(),
                     "J": float(np.linalg.det(np.asarray(traj.final.F)).mean())})
    apic, flip = runs
    assert flip["lowest"] > 0.75, flip  # resting on the box, not pressed into its face
    assert abs(flip["J"] - apic["J"]) < 2e-3, (flip, apic)
    for key in ("top", "centre"):
        assert abs(flip[key] - apic[key]) < 0.25, (key, flip, apic)


@pytest.mark.parametrize("collision, kind, contact, friction, restitution, words", [
    ("cpic", "box", "slip", 0.0, 0.5, "restitution = 0.5: in CPIC contact a restitution barely changes a rebound"),
    ("cpic", "box", "sticky", 0.0, 0.5, "restitution = 0.5 has no effect: its contact is 'sticky'"),
    ("cpic", "box", "slip", 0.3, 0.0, "friction = 0.3 has no effect: its contact is 'slip'"),
    ("particles", "box", "friction", 0.3, 0.0, "friction = 0.3 has no effect: boundary particles"),
    ("cpic", "box", "friction", 0.3, 0.0, None),
    ("cpic", "plane", "slip", 0.0, 0.5, None),  # planes act on the grid in every mode
    ("grid", "box", "slip", 0.0, 0.5, None),
    ("particles", "plane", "friction", 0.3, 0.5, None),
])
def test_load_scene_warns_of_contact_parameters_that_do_nothing_or_little(
        collision, kind, contact, friction, restitution, words):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_scene(_one_collider_scene(collision, kind, contact, friction, restitution))
    said = [str(w.message) for w in caught if issubclass(w.category, JaxmpmWarning)]
    if words is None:
        assert said == []
    else:
        assert len(said) == 1 and said[0].startswith("collider 'floor': ") and words in said[0], said


def test_a_fit_of_a_cpic_restitution_says_in_its_notes_that_it_barely_acts():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", JaxmpmWarning)
        scene = load_scene(_one_collider_scene("cpic", "box", "slip", 0.0, 0.2))
    traj = simulate(scene.model, scene.params)
    obs = Observation(times=np.asarray(traj.times), positions=np.asarray(traj.x), point_ids="particles")
    result = fit(scene.model, scene.params, obs, ["floor.restitution"], FitConfig(max_steps=1, stages=None))
    assert [n for n in result.notes if "barely changes a rebound" in n] == [
        f"floor.restitution: {CPIC_RESTITUTION_NOTE}"]


def test_the_command_prints_a_contact_warning_as_one_line_before_its_work(tmp_path, capsys):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(_one_collider_scene("cpic", "box", "sticky", 0.0, 0.5)))
    # the observation file does not exist: the warning comes with the scene, before it is read
    code = main(["fit", str(path), str(tmp_path / "none.npz"), "--out", str(tmp_path / "fit.json")])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and "Traceback" not in "\n".join(lines)
    assert lines[0] == ("warning: collider 'floor': restitution = 0.5 has no effect: its contact is 'sticky', "
                        "which stops all sliding and bouncing")
    assert lines[-1].startswith("jaxmpm fit: error: ") and "none.npz" in lines[-1], lines


@pytest.mark.parametrize("contact, name", [("slip", "floor.friction"), ("sticky", "floor.restitution")])
def test_fitting_or_sweeping_a_contact_parameter_that_does_nothing_is_refused(contact, name):
    """Its derivative is exactly zero: refused with the reason, before any rollout."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", JaxmpmWarning)
        scene = load_scene(_one_collider_scene("cpic", "box", contact, 0.0, 0.0))
    obs = Observation(times=np.asarray(scene.model.frame_times()), positions=np.zeros((2, scene.model.num_particles, 2)),
                      point_ids="particles")
    with pytest.raises(JaxmpmError, match=f"parameter '{name}' cannot be fitted: it has no effect on collider "
                                          f"'floor': its contact is '{contact}'"):
        fit(scene.model, scene.params, obs, [name])
    with pytest.raises(JaxmpmError, match=f"parameter '{name}' cannot be swept"):
        sweep_params(scene.model, scene.params, {name: [0.1, 0.2]})


def test_fluid_on_a_3d_shell_of_gaussian_disks_stays_outside(tmp_path):
    """A sphere of 1,500 2D Gaussian disks (random normal signs, oriented by the loader) loaded
    from a scene file: a fluid ball dropped on it flows over it and never enters (docs: CPIC
    deepest penetration +0.01 dx; measured here -0.005 dx, i.e. it never touched the shell's
    exact sphere from inside)."""
    rng = np.random.default_rng(0)
    k, radius, centre, dx = 1500, 0.15, np.array([0.3, 0.2, 0.3]), 0.05
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.savez(tmp_path / "shell.npz", centers=centre + radius * d, normals=d * rng.choice([-1.0, 1.0], size=(k, 1)),
             scales=np.full(k, radius * math.sqrt(4 * math.pi / k) / 2.0))
    spec = {
        "dim": 3, "dx": dx, "domain": {"lo": [0, 0, 0], "hi": [0.6, 0.6, 0.6]}, "frames": 5, "frame_dt": 1 / 24,
        "substeps": 40, "gravity": [0, -9.8, 0],
        "bodies": [{"shape": "sphere", "center": [0.3, 0.45, 0.3], "radius": 0.08, "velocity": [0, -1.0, 0],
                    "material": FLUID}],
        "colliders": [{"type": "disks", "name": "shell", "path": "shell.npz", "contact": "slip"}],
    }
    scene = load_scene(spec, base_dir=tmp_path)
    _, x, _ = rollout(scene.model, scene.params)
    depth = (radius - np.linalg.norm(x - centre, axis=-1)) / dx  # > 0: inside the shell
    assert depth.max() > -0.5  # the fluid reached the shell ...
    assert depth.max() < 0.2  # ... and never entered it
    assert np.ptp(x[-1, :, 0]) > 2 * np.ptp(x[0, :, 0])  # it spread over the shell's top
