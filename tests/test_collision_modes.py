"""What docs/colliders.md says of the baseline collision modes and of restitution, checked on
small 2D scenes: the grid-level mode lets material fall through a thin plate that lies between
node rows, boundary particles hold it about 1 dx off without a leak, and the contact law sends
``-e v_n`` back along the normal."""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from collider_scenes import ELASTIC, FLUID, SAND, rollout

from jaxmpm.colliders import project_velocity
from jaxmpm.scene import load_scene

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


def _rebound_speed(restitution: float, folder) -> float:
    """One free particle (no stress) falls at 2 m/s onto a CPIC box with slip contact and
    restitution ``e``, without gravity; its normal speed once it has left the box, / 2 m/s."""
    np.save(folder / "one.npy", np.array([[0.5, 0.13]]))
    spec = {
        "dim": 2, "dx": DX, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 60, "frame_dt": 1 / 480,
        "substeps": 8, "gravity": [0.0, 0.0],
        "bodies": [{"shape": "points", "path": "one.npy", "velocity": [0.0, -2.0],
                    "material": {"model": "elastic", "E": 1e3, "nu": 0.3}}],
        "colliders": [{"type": "box", "name": "floor", "lo": [0.0, 0.0], "hi": [1.0, 0.1], "contact": "slip",
                       "restitution": restitution}],
    }
    scene = load_scene(spec, base_dir=folder)
    _, x, v = rollout(scene.model, scene.params)
    assert x[-1, 0, 1] > 0.12  # it has bounced off and left the box's band
    return float(v[-1, 0, 1]) / 2.0


@pytest.mark.xfail(strict=True, reason="known gap (reported): a free particle leaves a CPIC box at 0.40 v_in "
                   "with e = 0 (the penetration correction pushes it out) and 0.60 v_in with e = 1")
def test_a_free_particle_bounces_off_a_box_at_e_times_its_speed(tmp_path):
    """What docs/colliders.md's contact law promises a user: rebound speed e v_in."""
    for e in (0.0, 1.0):
        assert _rebound_speed(e, tmp_path) == pytest.approx(e, abs=0.1)


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
