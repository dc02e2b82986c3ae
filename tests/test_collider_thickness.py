"""A collider is a collider: the same drop onto a plane, a thick box, boxes 0.1 to 1.5 cells
thick (on and between node rows), a zero-thickness mesh and a disk set sampling the same top
surface gives the same pile (issue 14, finding 1: boxes thinner than the stencil used to crush
the material into a sheet of zero thickness).

Scenes: :func:`collider_scenes.drop_spec` (one block per collider, stations 0.8 m apart
along x, with the thick boxes, 8 cells, on and between node rows among them); the plane runs
alone. Each pile is compared with the thick box's at the same placement (on or between node
rows) and, for sand (2D) and the fluid, with the plane's (see ``NO_PLANE_REFERENCE``: the
elastic block bounces on the grid-level plane and is in the air at the end; the 3D sand pile
is one cell thick). Tolerances, in
cells of the drop's grid (dx = 0.02 m in 2D, 0.05 m in 3D):

* thickness (highest minus lowest particle, mean over the last 0.1 s): within 0.5 dx of both
  references (measured: within 0.4 dx; the old code's sheets: 0);
* footprint (extent along x): within 2 dx (before session 45, when a node on a face counted
  outside, sand on a node row spread 1.5 dx wider than on the grid-level plane, which held
  the material half a cell higher; a thick sticky box on a row now gives the plane's pile);
* centre of mass: x within 0.25 dx; height above the top surface within 0.5 dx of the thick
  box's and 1.25 dx of the plane's (whose material rests up to a cell higher);
* no particle crosses: over the whole run none is deeper than 0.5 dx below the top surface;
* volume sum J V0 / sum V0 (mean over the last 0.1 s) within 0.002 of the references', and,
  for the fluid, its compression within a factor 2 of the hydrostatic one ``rho g d /
  (7 kappa)`` (d: half the puddle's thickness; 7 kappa: the fluid's bulk stiffness at J = 1).
"""

from __future__ import annotations

import numpy as np
import pytest
from collider_scenes import DROP_MATERIALS, THICKNESSES, drop_run, drop_spec, drop_substeps, placement_spec
from scenes import slow

from jaxmpm.scene import load_scene
from jaxmpm.step import run_frames

#: The references: thick boxes on and between node rows (stations 0 and 1 of every scene).
THICK_BOXES = [("box", None, True), ("box", None, False)]
#: Default-suite stations: a thin box between node rows, a one-cell box on a node row, a mesh
#: of zero thickness (2D); the thin box alone in 3D.
QUICK = {2: [("box", 0.3, False), ("box", 1.0, True), ("mesh", None, True)], 3: [("box", 0.3, False)]}
FULL = [("mesh", None, True), ("mesh", None, False), ("disks", None, True), ("disks", None, False)] + [
    ("box", t, on) for t in THICKNESSES for on in (True, False)
]


#: Drops not compared with the plane: the elastic block bounces on it; in 3D (dx = 0.05 m) the
#: sand pile is about one cell thick and the plane holds it half a cell higher (measured: 54 mm
#: thick on the plane, 18 mm on a thick box), more than the tolerance.
NO_PLANE_REFERENCE = {("elastic", 2), ("elastic", 3), ("sand", 3)}


def plane_pile(dim: int, material: str, folder) -> dict:
    spec, tops = drop_spec(dim, material, [("plane", None, True)], folder)
    return drop_run(spec, tops)[0][0]


def hydrostatic_compression(thickness: float) -> float:
    """Relative volume loss of the fluid at rest in a puddle ``thickness`` deep (m):
    ``rho g d / (7 kappa)`` with the mean depth ``d`` half the thickness."""
    m = DROP_MATERIALS["newtonian"]
    return 1000.0 * 9.8 * 0.5 * thickness / (7.0 * m["kappa"])


def check_like(p: dict, ref: dict, dx: float, com_height: float, what: str) -> None:
    """``p`` agrees with the reference pile ``ref`` (tolerances in the module docstring)."""
    msg = f"{what}: {p} vs reference {ref}"
    assert abs(p["thickness"] - ref["thickness"]) <= 0.5 * dx, msg
    assert abs(p["footprint"] - ref["footprint"]) <= 2.0 * dx, msg
    assert abs(p["com"][0] - ref["com"][0]) <= 0.25 * dx, msg
    assert abs(p["com"][1] - ref["com"][1]) <= com_height * dx, msg
    assert abs(p["volume"] - ref["volume"]) <= 0.002, msg


def _run(dim, material, stations, folder):
    dx = drop_substeps(dim)[0]
    spec, tops = drop_spec(dim, material, THICK_BOXES + stations, folder)
    piles, _ = drop_run(spec, tops)
    plane = plane_pile(dim, material, folder) if (material, dim) not in NO_PLANE_REFERENCE else None
    for st, p in zip(THICK_BOXES + stations, piles):
        what = f"{dim}D {material} on {st}"
        assert p["lowest"] >= -0.5 * dx, what + f": a particle crossed the surface ({p['lowest']} m)"
        check_like(p, piles[0 if st[2] else 1], dx, 0.5, what + " (thick box reference)")
        if plane is not None:
            check_like(p, plane, dx, 1.25, what + " (plane reference)")
        if material == "newtonian":
            predicted = hydrostatic_compression(p["thickness"])
            assert 0.5 * predicted <= 1.0 - p["volume"] <= 2.0 * predicted, what + f": {p}, predicted {predicted}"


@pytest.mark.parametrize(
    "dim, material", [(2, "sand"), slow(2, "newtonian"), slow(2, "elastic"), (3, "newtonian")],
    ids=["2d-sand", "2d-newtonian", "2d-elastic", "3d-newtonian"],
)
def test_thin_and_zero_thickness_colliders_hold_the_same_pile_as_thick_ones_and_planes(dim, material, tmp_path):
    _run(dim, material, QUICK[dim], tmp_path)


def test_a_flip_blend_lands_sand_on_cpic_boxes_as_apic_does(tmp_path):
    """``flip`` (``Model.flip``) counts a CPIC particle's ghost nodes as its own affine
    velocity: the 2D sand drop on thick boxes (face on and between node rows) with
    ``flip = 0.99`` forms the pile APIC forms, within the module's tolerances (centre of mass
    0.5 dx), and no particle crosses the face."""
    dx = drop_substeps(2)[0]
    runs = []
    for flip in (0.0, 0.99):
        spec, tops = drop_spec(2, "sand", THICK_BOXES, tmp_path)
        runs.append(drop_run({**spec, "flip": flip}, tops)[0])
    for st, apic, flip in zip(THICK_BOXES, *runs):
        what = f"sand on {st} with flip = 0.99"
        assert flip["lowest"] >= -0.5 * dx, what + f": a particle crossed the surface ({flip['lowest']} m)"
        check_like(flip, apic, dx, 0.5, what + " (APIC reference)")


@pytest.mark.slow
@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("material", sorted(DROP_MATERIALS))
def test_every_collider_kind_and_thickness_holds_the_same_pile(dim, material, tmp_path):
    _run(dim, material, FULL, tmp_path)


def test_a_face_on_a_node_row_holds_a_resting_block_as_a_plane_on_that_row_does():
    """2D elastic blocks (0.2 x 0.1 m, 2 x 2 particles a cell, dx = 0.05 m) dropped at 1 m/s onto
    slip boxes whose tops lie on a node row and 1 um above it, and onto a slip plane on that
    row, after 2 s at rest. A node on the face belongs to the collider, as a grid-level plane
    counts it. So each block keeps its particles' height within 5 %, and rests where the others
    do: its lowest particle within 0.02 dx of the raised box's and 0.04 dx of the plane's.
    Measured: 53.5 / 53.5 / 54.3 mm above the face, 1.033 / 1.033 / 1.008 of the unloaded height.
    When CPIC counted the face's nodes outside, the block on the row rested 8.1 mm above it,
    squashed to 0.73 of its height while J stayed 0.99."""
    dx = 0.05
    rests = []
    for kind, offsets in (("box", [0.0, 1e-6]), ("plane", [0.0])):
        spec, tops = placement_spec(offsets, kind=kind, dx=dx)
        scene = load_scene(spec)
        x = np.asarray(run_frames(scene.model, scene.params).x)
        for body, top in zip(scene.model.body_slices(), tops):
            y0, y = x[0, body, 1], x[-1, body, 1]
            assert abs(np.ptp(y) / np.ptp(y0) - 1.0) < 0.05, (kind, top, np.ptp(y), np.ptp(y0))
            rests.append(y.min() - top)
    on_row, raised, plane = rests
    assert abs(on_row - raised) < 0.02 * dx, rests
    assert abs(on_row - plane) < 0.04 * dx, rests


def test_a_box_edge_on_node_rows_acts_as_the_same_edge_bevelled_by_two_millimetres(tmp_path):
    """The 3D elastic drop of the identification case studies (a 0.2 m block thrown down at
    1 m/s; dx = 0.05 m) lands half on the edge of a box whose top and side lie on node rows.
    The same box as a mesh with that edge bevelled by 2 mm, as a reconstruction leaves it,
    must give nearly the same motion: the mean particle moves less than the bevel, 2 mm,
    apart in 0.21 s. A node on a convex edge is outside the collider and the bevel's corner
    nodes lie outside too. Measured: 0.7 mm at the last frame. Counted inside, as a face's
    nodes are, the edge held the body up a cell higher than the bevel did: 98 mm apart. Before
    session 45 (the face's nodes outside too): 7.3 mm."""
    import trimesh

    from jaxmpm.reconstruct.synthetic import drop_scene
    from jaxmpm.step import simulate

    bevel = 0.002
    section = [(0.3, 0.0), (0.5, 0.0), (0.5, 0.2), (0.3 + bevel, 0.2), (0.3, 0.2 - bevel)]
    prism = trimesh.convex.convex_hull([(x, y, z) for x, y in section for z in (0.15, 0.45)])
    prism.export(tmp_path / "bevelled.obj")
    runs = []
    for collider in (None, {"type": "mesh", "name": "box", "path": str(tmp_path / "bevelled.obj")}):
        spec = drop_scene("edge", material="elastic")
        if collider is not None:
            spec["colliders"][-1] = collider
        scene = load_scene(spec)
        runs.append(np.asarray(simulate(scene.model, scene.params, checkpoint=None, frames=6).x))
    apart = np.linalg.norm(runs[0] - runs[1], axis=-1).mean(axis=1)
    assert apart[-1] < bevel, apart


#: Known defect, measured and not fixed (docs/colliders.md, "Where a face lies between node
#: rows"): a block at rest on a CPIC box rests up to a cell above the face, depending on where
#: the face lies between node rows, and within 0.2 cells below a node row it is squashed.
PLACEMENT_DEPENDENT_REST = pytest.mark.xfail(
    strict=True, reason="known defect: CPIC's rest height and shape depend on where a face lies between node rows "
    "(docs/colliders.md)")


@PLACEMENT_DEPENDENT_REST
def test_a_resting_elastic_block_keeps_its_shape_and_height_wherever_the_face_lies_between_node_rows():
    """Three 2D elastic blocks (0.2 x 0.1 m, 2 x 2 particles a cell, dx = 0.05 m) dropped at
    1 m/s onto slip boxes whose tops lie 0.5 mm, half a cell and 0.9 cells above a node row,
    after 2 s at rest. Each should keep its particles' height within 5 %. A J-based volume
    misses the squash, because J stays 0.99. Each lowest particle should rest half a particle
    spacing (dx / 4: the material's edge on the face) above the top, within dx / 4. Measured:
    heights 77.4 / 77.4 / 68.6 mm of 75; lowest particle 53.0 / 28.5 / 8.5 mm above the top."""
    dx = 0.05
    spec, tops = placement_spec([0.0005, 0.025, 0.045], dx=dx)
    scene = load_scene(spec)
    x = np.asarray(run_frames(scene.model, scene.params).x)
    for body, top in zip(scene.model.body_slices(), tops):
        y0, y = x[0, body, 1], x[-1, body, 1]
        assert abs(np.ptp(y) / np.ptp(y0) - 1.0) < 0.05, (top, np.ptp(y), np.ptp(y0))
        assert abs((y.min() - top) - dx / 4) < dx / 4, (top, y.min() - top)
