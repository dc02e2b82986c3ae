"""Collider geometry and the CPIC collision grid (affinity, side, distance, normal)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxmpm.colliders import (
    COLLIDER_TYPES,
    Box,
    GaussianDisks,
    MeshCollider,
    Plane,
    asset_path,
    box_from_spec,
    disks_from_spec,
    mesh_from_spec,
    rotation_matrix,
)
from jaxmpm.cpic import build_collision_field, field_to_dense
from jaxmpm.errors import SceneError
from jaxmpm.state import Grid

DX = 1.0 / 32
BAND = 2.0 * DX
GRID3 = Grid((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), DX)
GRID2 = Grid((0.0, 0.0), (1.0, 1.0), 1.0 / 64)


def _arrays(field):
    return (
        np.asarray(field.affinity),
        np.asarray(field.side),
        np.asarray(field.distance),
        np.asarray(field.normal),
    )


def _brute_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact unsigned distance: trimesh's closest point on every triangle, minimum over all."""
    tri = mesh.triangles
    out = np.empty(len(points))
    for i, p in enumerate(points):
        q = trimesh.triangles.closest_point(tri, np.broadcast_to(p, (len(tri), 3)))
        out[i] = np.min(np.linalg.norm(q - p, axis=1))
    return out


def _check_common(field, grid):
    aff, side, dist, nrm = _arrays(field)
    assert aff.shape == (grid.num_nodes,) and nrm.shape == (grid.num_nodes, grid.dim)
    assert side.dtype == np.int8 and set(np.unique(side[aff])) <= {-1, 1}
    assert np.all(side[~aff] == 0) and np.all(nrm[~aff] == 0)
    np.testing.assert_allclose(np.linalg.norm(nrm[aff], axis=1), 1.0, atol=1e-9)
    assert np.all(dist[aff] < BAND if grid.dim == 3 else dist[aff] < 2 * grid.dx)
    return aff, side, dist, nrm


@pytest.mark.x64  # exact comparisons with NumPy float64 geometry
def test_box_matches_analytic_and_mesh():
    box = Box([0.3, 0.3, 0.3], [0.7, 0.6, 0.7], rotate=[10, 20, 30], name="crate")
    x = GRID3.node_positions()
    field = build_collision_field(box, GRID3)
    aff, side, dist, nrm = _check_common(field, GRID3)
    sd, n = map(np.asarray, box.signed_distance(jnp.asarray(x), 0.0))
    np.testing.assert_array_equal(aff, np.abs(sd) < BAND)
    np.testing.assert_array_equal(side[aff], np.where(sd[aff] >= 0, 1, -1))
    np.testing.assert_allclose(dist[aff], np.abs(sd[aff]), atol=1e-12)
    np.testing.assert_allclose(nrm[aff], n[aff], atol=1e-12)
    # The same box as a closed triangle mesh gives the same field.
    tm = trimesh.creation.box(extents=[0.4, 0.3, 0.4])
    verts = tm.vertices @ rotation_matrix([10, 20, 30], 3).T + [0.5, 0.45, 0.5]
    mfield = build_collision_field(MeshCollider(verts, tm.faces, name="crate_mesh"), GRID3)
    m_aff, m_side, m_dist, m_nrm = _arrays(mfield)
    np.testing.assert_array_equal(m_aff, aff)
    np.testing.assert_array_equal(m_side, side)
    np.testing.assert_allclose(m_dist, dist, atol=1e-12)
    np.testing.assert_allclose(m_nrm, nrm, atol=1e-9)
    # Strict (TM) rule: the outer wedges around edges and corners lose affinity.
    strict = np.asarray(build_collision_field(box, GRID3, strict=True).affinity)
    assert np.all(strict <= aff) and strict.sum() < aff.sum()


@pytest.mark.x64  # exact comparisons with NumPy float64 geometry
def test_sphere_mesh_side_distance_and_sdf():
    tm = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    tm.vertices += 0.5
    mesh = MeshCollider(tm.vertices, tm.faces, name="ball")
    assert mesh.closed
    x = GRID3.node_positions()
    aff, side, dist, nrm = _check_common(build_collision_field(mesh, GRID3), GRID3)
    r = np.linalg.norm(x - 0.5, axis=1)
    far = np.abs(r - 0.3) > 0.01  # the facets lie up to ~0.004 inside the sphere
    np.testing.assert_array_equal(side[aff & far], np.where(r[aff & far] > 0.3, 1, -1))
    # Exact distances on a sample of band and near-band nodes.
    rng = np.random.default_rng(0)
    near = np.flatnonzero(np.abs(r - 0.3) < 3 * DX)
    pick = rng.choice(near, 150, replace=False)
    ref = _brute_distance(tm, x[pick])
    np.testing.assert_allclose(dist[pick][aff[pick]], ref[aff[pick]], atol=1e-12)
    # Closed mesh, default rule: affine exactly where the distance is below the band.
    np.testing.assert_array_equal(aff[pick], ref < BAND)
    # The jnp brute-force signed distance agrees with the field.
    sd, n = map(np.asarray, mesh.signed_distance(jnp.asarray(x[pick]), 0.0))
    np.testing.assert_allclose(np.abs(sd), ref, atol=1e-12)
    np.testing.assert_array_equal(np.where(sd >= 0, 1, -1)[aff[pick]], side[pick][aff[pick]])
    np.testing.assert_allclose(n[aff[pick]], nrm[pick][aff[pick]], atol=1e-9)
    grad = jax.grad(lambda y: mesh.signed_distance(y, 0.0)[0].sum())(jnp.asarray(x[pick[:20]]))
    assert np.all(np.isfinite(np.asarray(grad)))


def test_bunny_asset():
    bunny = mesh_from_spec({"path": "bunny.obj", "scale": 0.8, "translate": [0.5, 0.5, 0.5]}, "bunny", 3, ".")
    assert bunny.closed and bunny.num_faces == 5000
    x = GRID3.node_positions()
    aff, side, dist, nrm = _check_common(build_collision_field(bunny, GRID3), GRID3)
    tm = bunny.to_trimesh()
    rng = np.random.default_rng(1)
    pick = np.concatenate([rng.choice(np.flatnonzero(aff), 120, replace=False)])
    ref = _brute_distance(tm, x[pick])
    np.testing.assert_allclose(dist[pick], ref, atol=1e-12)
    inside = tm.contains(x[pick])
    clear = ref > 1e-6
    np.testing.assert_array_equal(side[pick][clear], np.where(inside[clear], -1, 1))
    # Nodes in the bunny's bounding box but not affine are farther than the band.
    lo, hi = bunny.bounds()
    box_nodes = np.flatnonzero(np.all((x > lo - BAND) & (x < hi + BAND), axis=1) & ~aff)
    others = rng.choice(box_nodes, 60, replace=False)
    assert np.all(_brute_distance(tm, x[others]) >= BAND - 1e-12)


def test_open_bowl_sides_from_face_normals():
    bowl = mesh_from_spec({"path": "bowl.obj", "scale": 0.8, "translate": [0.5, 0.5, 0.5]}, "bowl", 3, ".")
    assert not bowl.closed
    x = GRID3.node_positions()
    aff, side, dist, nrm = _check_common(build_collision_field(bowl, GRID3), GRID3)
    centre, radius, rim_y = np.array([0.5, 0.7, 0.5]), 0.4, 0.7
    r = np.linalg.norm(x - centre, axis=1)
    clear = aff & (np.abs(r - radius) > 0.01)
    # The shipped bowl's normals point into the bowl: the cavity is the "+" side.
    np.testing.assert_array_equal(side[clear], np.where(r[clear] < radius, 1, -1))
    assert np.any(side[clear] == 1) and np.any(side[clear] == -1)
    # No node beyond the rim is affine (its nearest feature is the open boundary).
    assert not np.any(aff & (x[:, 1] > rim_y + 1e-9))
    rng = np.random.default_rng(2)
    pick = rng.choice(np.flatnonzero(aff), 100, replace=False)
    np.testing.assert_allclose(dist[pick], _brute_distance(bowl.to_trimesh(), x[pick]), atol=1e-12)


def test_thin_plate_two_sides():
    # An open sheet (zero thickness, so thinner than dx) between node layers.
    y0 = 0.51
    v = np.array([[0.2, y0, 0.2], [0.8, y0, 0.2], [0.8, y0, 0.8], [0.2, y0, 0.8]])
    sheet = MeshCollider(v, [[0, 2, 1], [0, 3, 2]], name="sheet")
    np.testing.assert_allclose(np.asarray(sheet.face_normals), [[0, 1, 0], [0, 1, 0]])
    x = GRID3.node_positions()
    aff, side, dist, _ = _check_common(build_collision_field(sheet, GRID3), GRID3)
    above, below = aff & (x[:, 1] > y0), aff & (x[:, 1] < y0)
    assert above.sum() > 100 and below.sum() > 100
    assert np.all(side[above] == 1) and np.all(side[below] == -1)
    np.testing.assert_allclose(dist[aff], np.abs(x[aff, 1] - y0), atol=1e-12)
    beyond = (x[:, 0] < 0.2) | (x[:, 0] > 0.8) | (x[:, 2] < 0.2) | (x[:, 2] > 0.8)
    assert not np.any(aff & beyond)
    # A *closed* plate thinner than dx has no inside nodes: both faces are "+" (documented).
    tm = trimesh.creation.box(extents=[0.6, 0.004, 0.6])
    slab = MeshCollider(tm.vertices + [0.5, y0, 0.5], tm.faces, name="slab")
    s_aff, s_side, _, _ = _arrays(build_collision_field(slab, GRID3))
    assert np.all(s_side[s_aff] == 1)


def test_polylines_2d(tmp_path):
    x = GRID2.node_positions()
    th = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    pts = np.stack([0.5 + 0.3 * np.cos(th), 0.5 + 0.3 * np.sin(th)], axis=1)[::-1]  # clockwise
    np.savez(tmp_path / "ring.npz", points=pts, closed=True)
    ring = mesh_from_spec({"path": "ring.npz"}, "ring", 2, tmp_path)
    assert ring.closed  # re-oriented so that "+" is outside
    aff, side, dist, nrm = _check_common(build_collision_field(ring, GRID2), GRID2)
    r = np.linalg.norm(x - 0.5, axis=1)
    clear = aff & (np.abs(r - 0.3) > 0.003)
    np.testing.assert_array_equal(side[clear], np.where(r[clear] > 0.3, 1, -1))
    # Exact distance to the segments (brute force).
    a, b = pts, np.roll(pts, -1, axis=0)
    p = x[aff][:, None, :]
    t = np.clip(np.sum((p - a) * (b - a), -1) / np.sum((b - a) ** 2, -1), 0, 1)
    ref = np.min(np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=-1), axis=1)
    np.testing.assert_allclose(dist[aff], ref, atol=1e-12)
    # Open polyline, inline points: "+" is on the right of the direction of travel.
    line = mesh_from_spec({"points": [[0.2, 0.5], [0.5, 0.45], [0.8, 0.5]]}, "line", 2, ".")
    l_aff, l_side, _, _ = _check_common(build_collision_field(line, GRID2), GRID2)
    assert np.all(l_side[l_aff & (x[:, 1] < 0.44)] == 1) and np.all(l_side[l_aff & (x[:, 1] > 0.51)] == -1)
    assert not np.any(l_aff & ((x[:, 0] < 0.2) | (x[:, 0] > 0.8)))


def _sphere_disks(k=1500, seed=0, radius=0.3):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    flips = rng.choice([-1.0, 1.0], size=k)
    sigma = radius * np.sqrt(4 * np.pi / k) / 2.0
    return d, flips, 0.5 + radius * d, sigma


def test_disks_orientation_and_field():
    d, flips, centres, sigma = _sphere_disks()
    assert np.any(flips < 0) and np.any(flips > 0)
    disks = GaussianDisks(centres, normals=d * flips[:, None], scales=np.full(len(d), sigma), name="shell")
    n = np.asarray(disks.normals)
    assert np.all(np.sum(n * d, axis=1) > 0.99)  # consistent, and outward for a closed shape
    x = GRID3.node_positions()
    aff, side, dist, nrm = _check_common(build_collision_field(disks, GRID3), GRID3)
    r = np.linalg.norm(x - 0.5, axis=1)
    clear = aff & (np.abs(r - 0.3) > 0.01)
    np.testing.assert_array_equal(side[clear], np.where(r[clear] > 0.3, 1, -1))
    assert np.mean(aff[np.abs(r - 0.3) < DX]) > 0.95  # few holes at cutoff 3 sigma
    # distance = |offset along the chosen disk's normal|; normal = that disk's normal
    assert np.all(np.abs(np.sum(nrm[aff] * (x[aff] - 0.5), axis=1)) > 0.9 * r[aff] - 0.05)
    # orient="none" keeps the given (inconsistent) signs
    raw = GaussianDisks(centres, normals=d * flips[:, None], scales=np.full(len(d), sigma), orient="none")
    assert np.any(np.sum(np.asarray(raw.normals) * d, axis=1) < 0)


def _write_ply(path, props: dict):
    names = list(props)
    count = len(props[names[0]])
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % count
    header += "".join(f"property float {k}\n" for k in names) + "end_header\n"
    data = np.stack([np.asarray(props[k], np.float32) for k in names], axis=1)
    with open(path, "wb") as fh:
        fh.write(header.encode())
        fh.write(data.astype("<f4").tobytes())


def test_disks_from_2dgs_ply(tmp_path):
    d, flips, centres, sigma = _sphere_disks(k=800, seed=3)
    # quaternion (w, x, y, z) rotating +z onto the (randomly flipped) normal
    nz = d * flips[:, None]
    axis = np.cross([0, 0, 1.0], nz)
    s = np.linalg.norm(axis, axis=1)
    ang = np.arctan2(s, nz[:, 2])
    axis = axis / np.maximum(s, 1e-12)[:, None]
    quat = np.concatenate([np.cos(ang / 2)[:, None], np.sin(ang / 2)[:, None] * axis], axis=1)
    opacity = np.full(len(d), 0.9)
    opacity[:5] = 0.01  # pruned
    props = {"x": centres[:, 0], "y": centres[:, 1], "z": centres[:, 2]}
    props.update({k: np.zeros(len(d)) for k in ("nx", "ny", "nz")})  # 2DGS writes zeros here
    props.update({f"rot_{i}": quat[:, i] for i in range(4)})
    props.update(scale_0=np.full(len(d), np.log(sigma)), scale_1=np.full(len(d), np.log(sigma)))
    props["opacity"] = np.log(opacity / (1 - opacity))
    _write_ply(tmp_path / "surfels.ply", props)
    disks = disks_from_spec({"path": "surfels.ply"}, "gs", 3, tmp_path)
    assert disks.num_disks == len(d) - 5
    np.testing.assert_allclose(np.asarray(disks.scales), sigma, rtol=1e-5)
    assert np.all(np.sum(np.asarray(disks.normals) * d[5:], axis=1) > 0.99)
    field = build_collision_field(disks, GRID3)
    assert field.num_affine > 1000


def test_invalid_inputs_name_the_collider(tmp_path):
    bad_obj = tmp_path / "garbage.obj"
    bad_obj.write_text("this is not a mesh\n")
    verts_only = tmp_path / "verts.obj"
    verts_only.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    bowl = trimesh.load(asset_path("bowl.obj"), force="mesh")
    faces = bowl.faces.copy()
    faces[7] = faces[7][::-1]
    trimesh.Trimesh(bowl.vertices, faces, process=False).export(tmp_path / "flipped.obj")
    with pytest.raises(SceneError, match="'ghost'"):
        mesh_from_spec({"path": "nope.obj"}, "ghost", 3, tmp_path)
    with pytest.raises(SceneError, match="'junk'.*no faces"):
        mesh_from_spec({"path": "garbage.obj"}, "junk", 3, tmp_path)
    with pytest.raises(SceneError, match="'cloud'.*no faces"):
        mesh_from_spec({"path": "verts.obj"}, "cloud", 3, tmp_path)
    with pytest.raises(SceneError, match="'flip'.*winding"):
        mesh_from_spec({"path": "flipped.obj"}, "flip", 3, tmp_path)
    ball = trimesh.creation.icosphere(subdivisions=1)
    f2 = ball.faces.copy()
    f2[0] = f2[0][::-1]
    with pytest.raises(SceneError, match="'ball'.*winding"):
        MeshCollider(ball.vertices, f2, name="ball")
    with pytest.raises(SceneError, match="'zig'.*winding"):
        mesh_from_spec({"points": [[0, 0], [1, 0], [2, 0]], "segments": [[0, 1], [2, 1]]}, "zig", 2, ".")
    with pytest.raises(SceneError, match="'flat'.*normals"):
        GaussianDisks(np.zeros((3, 3)), normals=[[0, 0, 1], [0, 0, 0], [0, 1, 0]], scales=np.ones(3), name="flat")
    with pytest.raises(SceneError, match="'thin'.*scales"):
        GaussianDisks(np.zeros((2, 3)), normals=np.ones((2, 3)), scales=[1.0, 0.0], name="thin")
    with pytest.raises(SceneError, match="'faraway'.*outside the domain"):
        build_collision_field(Box([2, 2, 2], [3, 3, 3], name="faraway"), GRID3)
    far_mesh = mesh_from_spec({"path": "bunny.obj", "translate": [5, 0, 0]}, "far_bunny", 3, ".")
    with pytest.raises(SceneError, match="'far_bunny'.*outside the domain"):
        build_collision_field(far_mesh, GRID3)
    with pytest.raises(SceneError, match="'sky'"):
        build_collision_field(Plane([0, 5, 0], [0, 1, 0], name="sky"), GRID3)
    with pytest.raises(SceneError, match="'crate'.*lo < hi"):
        box_from_spec({"lo": [0, 0, 0], "hi": [1, 0, 1]}, "crate", 3, ".")


def test_registry_and_assets():
    assert {"plane", "box", "mesh", "disks"} <= set(COLLIDER_TYPES)
    for kind in ("box", "mesh", "disks"):
        ctor, required, optional = COLLIDER_TYPES[kind]
        assert callable(ctor) and "velocity" in optional and "angular_velocity" in optional
    assert COLLIDER_TYPES["box"][1] == ("lo", "hi") and COLLIDER_TYPES["disks"][1] == ("path",)
    for name in ("bunny.obj", "armadillo.obj", "bowl.obj", "meshes/bowl.obj"):
        assert trimesh.load(asset_path(name), force="mesh").faces.shape[0] > 0
    with pytest.raises(FileNotFoundError):
        asset_path("teapot.obj")


@pytest.mark.x64  # exact comparisons with NumPy float64 geometry
def test_rigid_motion_3d_and_2d():
    box = Box([0.4, 0.4, 0.4], [0.6, 0.5, 0.6], velocity=[0.3, 0.0, -0.1], angular_velocity=[0.5, 1.0, -2.0], name="m")
    assert box.moving
    t = 0.7
    c, R = map(np.asarray, box.rigid_transform(t))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(c, np.asarray(box.pivot) + t * np.asarray(box.velocity))
    X = np.random.default_rng(0).uniform(0.2, 0.8, size=(40, 3))
    xw = c + (X - np.asarray(box.pivot)) @ R.T  # where rest point X is at time t
    np.testing.assert_allclose(np.asarray(box.to_local(jnp.asarray(xw), t)), X, atol=1e-12)
    sd0, n0 = map(np.asarray, box.signed_distance(jnp.asarray(X), 0.0))
    sdt, nt = map(np.asarray, box.signed_distance(jnp.asarray(xw), t))
    np.testing.assert_allclose(sdt, sd0, atol=1e-12)
    np.testing.assert_allclose(nt, n0 @ R.T, atol=1e-12)
    # The surface velocity is the time derivative of the rigid placement.
    eps = 1e-6
    c2, R2 = map(np.asarray, box.rigid_transform(t + eps))
    fd = ((c2 + (X - np.asarray(box.pivot)) @ R2.T) - xw) / eps
    np.testing.assert_allclose(np.asarray(box.velocity_at(jnp.asarray(xw), t)), fd, atol=1e-5)
    # A plane is placed at t directly (its point and normal moved): the same as the rest frame.
    plane = Plane([0.5, 0.3, 0.4], [0.2, 1.0, -0.3], velocity=box.velocity, angular_velocity=box.angular_velocity,
                  pivot=box.pivot)
    sd0, n0 = map(np.asarray, plane.signed_distance(jnp.asarray(X), 0.0))
    sdt, nt = map(np.asarray, plane.signed_distance(jnp.asarray(xw), t))
    np.testing.assert_allclose(sdt, sd0, atol=1e-12)
    np.testing.assert_allclose(nt, n0 @ R.T, atol=1e-12)
    np.testing.assert_allclose(sd0, (X - plane.point) @ np.asarray(plane.normal), atol=1e-12)
    # 2D: scalar angular velocity
    sq = Box([0.4, 0.4], [0.6, 0.5], angular_velocity=[2.0], name="sq")
    v = np.asarray(sq.velocity_at(jnp.asarray([[0.7, 0.45]]), 0.0))
    np.testing.assert_allclose(v, [[0.0, 0.4]], atol=1e-12)
    # Static colliders: zero surface velocity, identity transform.
    assert not Box([0.4, 0.4], [0.6, 0.5]).moving
    np.testing.assert_array_equal(np.asarray(Box([0.4, 0.4], [0.6, 0.5]).velocity_at(jnp.ones((2, 2)), 1.0)), 0.0)


def test_collider_is_a_jit_argument_and_dense_view():
    tm = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    a = MeshCollider(tm.vertices + 0.5, tm.faces, name="s")
    b = MeshCollider(tm.vertices + 0.5, tm.faces, name="s")
    assert hash(a) == hash(b) and a == b  # static geometry compares by value
    calls = []

    @jax.jit
    def sdf(col, x):
        calls.append(1)
        return col.signed_distance(x, jnp.asarray(0.0))[0]

    x = jnp.asarray(GRID3.node_positions()[:5])
    np.testing.assert_allclose(sdf(a, x), sdf(b, x))
    assert len(calls) == 1
    field = build_collision_field(a, GRID3, dtype=jnp.float32)
    assert field.distance.dtype == jnp.float32
    dense = field_to_dense(field, GRID3)
    assert dense["affinity"].shape == GRID3.shape and dense["normal"].shape == GRID3.shape + (3,)
    assert dense["affinity"].sum() == field.num_affine


def test_with_contact_swaps_the_contact_law_or_motion_and_keeps_the_shape():
    box = Box([0.1, 0.2], [0.4, 0.3], contact="slip", name="b")
    rough = box.with_contact("friction")
    assert (rough.contact, box.contact) == ("friction", "slip")  # a copy; the original is unchanged
    x = jnp.asarray([[0.2, 0.25], [0.5, 0.5]])
    for a, b in zip(rough.signed_distance(x, jnp.asarray(0.0)), box.signed_distance(x, jnp.asarray(0.0))):
        np.testing.assert_array_equal(a, b)
    moved = box.with_contact(motion=lambda t: (jnp.asarray([0.25, 0.25]) + t, jnp.eye(2)))
    assert moved.moving and moved.contact == "slip" and not box.moving
    with pytest.raises(SceneError, match="'contact' must be one of"):
        box.with_contact("glue")
    with pytest.raises(SceneError, match="'motion' must be a callable"):
        box.with_contact(motion=3.0)


def _square_mesh(lo: float, hi: float, dim: int) -> MeshCollider:
    """The box ``[lo, hi]^dim`` as a mesh with vertices at the middle of its edges and faces (a
    subdivided cube; in 2D a closed 8-segment polyline, counter-clockwise): features that lie
    on the box's flat faces, not on its edges."""
    if dim == 3:
        tm = trimesh.creation.box(extents=[hi - lo] * 3).subdivide()
        return MeshCollider(tm.vertices + (lo + hi) / 2, tm.faces, name="cube")
    mid = (lo + hi) / 2
    ring = [(lo, lo), (mid, lo), (hi, lo), (hi, mid), (hi, hi), (mid, hi), (lo, hi), (lo, mid)]
    return MeshCollider(np.asarray(ring), [(k, (k + 1) % 8) for k in range(8)], name="square")


@pytest.mark.x64  # exact node positions
@pytest.mark.parametrize("dim", [2, 3])
def test_a_node_on_a_face_is_inside_and_a_node_on_a_convex_edge_outside_for_every_kind(dim):
    """Nodes lying exactly on a collider's surface (faces on node rows, as round coordinates
    put them) get one side whatever the collider's kind: box, mesh, surfels, plane. On a face
    they are inside, as a grid-level plane counts them: outside, a node on a face supports
    nothing and a body resting on it is squashed (test_collider_thickness.py). On a convex
    edge or corner they are outside: inside, the edge catches material that flows over it
    (docs/colliders.md, "Where a face lies between node rows"). A mesh's vertices and edges
    inside a flat face, and coplanar surfels, count as the face."""
    dx = 1.0 / 16
    grid = Grid((0.0,) * dim, (1.0,) * dim, dx)
    lo, hi = 4 * dx, 12 * dx
    x = grid.node_positions()
    on_bound = np.isclose(x, lo) | np.isclose(x, hi)
    within = (x > lo - 1e-9) & (x < hi + 1e-9)
    on_surface = np.all(within, axis=1) & on_bound.any(axis=1)
    on_edge = on_surface & (on_bound.sum(axis=1) >= 2)
    on_face = on_surface & ~on_edge
    assert on_face.any() and on_edge.any()
    box = Box([lo] * dim, [hi] * dim, name="box")
    sd = np.asarray(box.signed_distance(jnp.asarray(x), 0.0)[0])
    for collider in (box, _square_mesh(lo, hi, dim)):
        field = build_collision_field(collider, grid)
        side, off = np.asarray(field.side), np.asarray(field.affinity) & ~on_surface
        assert np.all(side[on_face] == -1), type(collider).__name__
        assert np.all(side[on_edge] == 1), type(collider).__name__
        np.testing.assert_array_equal(side[off], np.where(sd[off] > 0, 1, -1))
    if dim == 3:  # surfels covering the cube, as a reconstruction places them on a box's faces
        tm = trimesh.creation.box(extents=[hi - lo] * 3).subdivide().subdivide()
        disks = GaussianDisks(tm.triangles_center + (lo + hi) / 2, normals=tm.face_normals,
                              scales=np.full(len(tm.faces), np.sqrt(tm.area_faces.mean())), orient="none", name="cover")
        field = build_collision_field(disks, grid)
        side, aff = np.asarray(field.side), np.asarray(field.affinity)
        assert aff[on_surface].all()
        assert np.all(side[on_face] == -1) and np.all(side[on_edge] == 1)
    normal = np.eye(dim)[1]
    side = np.asarray(build_collision_field(Plane(normal * hi, normal, name="plane"), grid).side)
    assert np.all(side[np.isclose(x[:, 1], hi)] == -1)
