"""3D (coarse): nothing leaks into closed meshes, and an open bowl holds what is poured into it."""

import numpy as np
import pytest
from collider_scenes import ELASTIC, FLUID, SAND, depth_inside, rollout
from scenes import slow

from jaxmpm.scene import load_scene


def _side_by_side(dx, collision="cpic", shift=0.0):
    """A box, the bunny and the armadillo side by side on a sticky floor; three bars of fluid,
    sand and elastic material (one behind the other) fall across all three (moved by ``shift``
    metres along x and z)."""
    z = (0.17, 0.29, 0.41)
    bodies = [
        {"shape": "box", "lo": [0.1 + shift, 0.55, zk - 0.04 + shift], "hi": [1.7 + shift, 0.63, zk + 0.04 + shift],
         "velocity": [0.0, -2.0, 0.0], "material": m, "name": name}
        for zk, m, name in zip(z, (FLUID, SAND, ELASTIC), ("fluid", "sand", "elastic"))
    ]
    placed = {"scale": 0.42, "contact": "slip"}
    return {
        "dim": 3, "dx": dx, "domain": {"lo": [0.0, 0.0, 0.0], "hi": [1.8, 0.8, 0.6]}, "frames": 8,
        "frame_dt": 1 / 24, "substeps": int(round(2.0 / dx)), "gravity": [0.0, -9.8, 0.0],
        "collision": collision, "bodies": bodies,
        "colliders": [
            {"type": "plane", "name": "floor", "point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]},
            {"type": "box", "name": "box", "lo": [0.15, 0.0, 0.12], "hi": [0.45, 0.3, 0.48], "rotate": [0.0, 20.0, 0.0],
             "contact": "slip"},
            {"type": "mesh", "name": "bunny", "path": "bunny.obj", "translate": [0.9, 0.21, 0.3], **placed},
            {"type": "mesh", "name": "armadillo", "path": "armadillo.obj", "translate": [1.5, 0.21, 0.3], **placed},
        ],
    }


#: Known defect, measured and not fixed (docs/colliders.md, "Penetration where the field
#: cannot resolve the shape"): with the bars moved 13 mm, a particle creeps 0.27 dx into the
#: bunny over ~15 substeps (0.02-0.03 dx each) while its surface estimate, from a cell whose
#: corners see several different faces of a part smaller than a cell, has a normal 75-115
#: degrees off the true one. Before session 40 the same placement stayed within 0.083 dx; 2 of
#: 24 placements and resolutions measured exceeded 0.2 dx before and after it.
UNRESOLVED_CREEP = pytest.mark.xfail(strict=True, reason="known defect: a particle creeps 0.27 dx into the bunny "
                                     "where the field cannot resolve its shape (docs/colliders.md)")


@pytest.mark.parametrize("dx, shift", [(0.05, 0.0), pytest.param(0.04, 0.0, marks=pytest.mark.slow),
                                       pytest.param(0.05, 0.013, marks=[pytest.mark.slow, UNRESOLVED_CREEP])])
def test_fluid_sand_and_elastic_never_enter_box_bunny_or_armadillo(dx, shift):
    scene = load_scene(_side_by_side(dx, shift=shift))
    n = scene.model.num_particles
    assert 500 < n < 4000
    times, x, _ = rollout(scene.model, scene.params)
    for collider in scene.model.colliders[1:]:
        depth = depth_inside(collider, times, x)
        # every material touched this collider ...
        for sl in scene.model.body_slices():
            assert depth[:, sl].max() > -dx, (collider.name, sl)
        # ... and no particle ever got deeper than 0.2 dx inside it. Measured (float32, session
        # 40): bunny 0.138 / 0.127 dx, armadillo 0.066 / 0.112 dx at dx = 0.05 / 0.04 (before
        # session 40 a particle in a crease was measured from the facing wall and pushed 0.4 dx
        # into the bunny at dx = 0.04; earlier, 0.293 dx in the bunny when its surface came
        # from the *farthest* face of a crease)
        assert depth.max() < 0.2 * dx, (collider.name, depth.max() / dx)


def _bowl_spec(dx=0.05):
    return {
        "dim": 3, "dx": dx, "domain": {"lo": [0.0, 0.0, 0.0], "hi": [1.2, 0.9, 0.8]}, "frames": 14,
        "frame_dt": 1 / 24, "substeps": int(round(2.0 / dx)), "gravity": [0.0, -9.8, 0.0],
        "bodies": [
            {"shape": "sphere", "center": [0.4, 0.5, 0.4], "radius": 0.1,
             "material": {**FLUID, "mu": 20.0}, "name": "poured"},
            {"shape": "box", "lo": [0.8, 0.55, 0.3], "hi": [0.95, 0.7, 0.5], "velocity": [0.0, -1.0, 0.0],
             "material": SAND, "name": "outside"},
        ],
        "colliders": [
            {"type": "plane", "name": "floor", "point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]},
            # the shipped bowl: open hemisphere, rim radius 0.5 * scale, normals into the bowl
            {"type": "mesh", "name": "bowl", "path": "bowl.obj", "scale": 0.6, "translate": [0.4, 0.25, 0.4],
             "contact": "slip"},
        ],
    }


def test_open_bowl_holds_what_is_poured_in_and_outside_material_falls_past():
    scene = load_scene(_bowl_spec())
    bowl = scene.model.colliders[1]
    assert not bowl.closed
    times, x, _ = rollout(scene.model, scene.params)
    dx = scene.model.grid.dx
    centre, radius, rim = np.array([0.4, 0.4, 0.4]), 0.3, 0.4  # sphere centre, radius, rim height
    inside, outside = scene.model.body_slices()
    r = np.linalg.norm(x[:, inside] - centre, axis=-1)
    assert x[-1, inside, 1].max() < rim  # it stays in the bowl (below the rim) ...
    assert x[:, inside, 1].min() < 0.1 + 2 * dx  # ... after reaching its bottom
    assert r.max() < radius + 0.15 * dx  # and never went through the shell (measured 0.07 dx)
    # the sand dropped beyond the rim falls past it to the floor without touching the shell
    # (its closest approach, measured: 2.3 dx outside)
    assert x[-1, outside, 1].max() < 0.25
    rr = np.linalg.norm(x[:, outside] - centre, axis=-1)
    assert rr.min() > radius + dx


def _bunny_drop(collision, dx=0.05):
    """docs/colliders.md's leak table scene: fluid, sand and an elastic ball (r = 0.1 m) dropped
    at 2 m/s on the bunny, 10 frames of 1/24 s."""
    bodies = [
        {"shape": "sphere", "center": [0.3 + 0.2 * k, 0.72, 0.5], "radius": 0.1, "velocity": [0.0, -2.0, 0.0],
         "material": m, "name": name}
        for k, (m, name) in enumerate(((FLUID, "fluid"), (SAND, "sand"), (ELASTIC, "elastic")))
    ]
    return {
        "dim": 3, "dx": dx, "domain": {"lo": [0, 0, 0], "hi": [1, 1, 1]}, "frames": 10, "frame_dt": 1 / 24,
        "substeps": int(round(2.0 / dx)), "gravity": [0, -9.8, 0], "collision": collision, "bodies": bodies,
        "colliders": [
            {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 1, 0]},
            {"type": "mesh", "name": "bunny", "path": "bunny.obj", "scale": 0.6, "translate": [0.5, 0.3, 0.5],
             "contact": "slip"},
        ],
    }


# the grid-level and boundary-particle rows run with -m slow (35 s): the default run keeps
# CPIC's row and test_collision_modes.py's plate cases of the other two modes
@pytest.mark.parametrize("collision", ["cpic", slow("grid"), slow("particles")])
def test_each_collision_mode_on_a_closed_mesh_does_what_the_leak_table_says(collision):
    """docs/colliders.md's leak table on the bunny (dx = 0.05): CPIC keeps every particle
    within 0.15 dx of the surface (measured +0.09 dx); the grid-level condition lets material about 1 dx into the closed mesh (measured +0.88 dx, 36
    particles deeper than dx/2); boundary particles let nothing in but hold the material
    0.8-1.4 dx off the surface (measured: closest approach 0.85 dx)."""
    scene = load_scene(_bunny_drop(collision))
    dx = scene.model.grid.dx
    times, x, _ = rollout(scene.model, scene.params)
    depth = depth_inside(scene.model.colliders[1], times, x)  # (T, N), > 0 inside the bunny
    deepest = depth.max(axis=0)
    for sl in scene.model.body_slices():
        assert deepest[sl].max() > -2.0 * dx  # every material came down onto the bunny
    if collision == "cpic":
        assert depth.max() < 0.15 * dx
    elif collision == "grid":
        assert 0.5 * dx < depth.max() < 1.5 * dx  # about one cell in ...
        assert 10 <= (deepest > 0.5 * dx).sum() <= 0.1 * deepest.size  # ... a few percent of the particles
    else:
        assert -1.4 * dx < depth.max() < -0.8 * dx  # nothing gets in: a visible gap
