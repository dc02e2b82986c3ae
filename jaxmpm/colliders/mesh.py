"""Triangle meshes (3D) and segment sets (2D) as colliders: topology, pseudo-normals, exact signed distance."""

from __future__ import annotations

import functools
from typing import Callable, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import SceneError
from .base import RigidCollider, StaticArray, init_motion, safe_normalize_np

def closest_on_simplices(p, a, b, c=None, xp=np):
    """Closest points on triangles ``(a, b, c)`` (3D) or segments ``(a, b)`` (2D), row-wise.

    Works with ``xp = numpy`` or ``xp = jax.numpy`` (only elementwise ops and ``where``).

    Returns:
        ``q`` the closest points, ``region`` (int: 0 inside the face, 1..3 vertex a/b/c,
        4..6 edge ab/bc/ca; 2D: 0 inside, 1 vertex a, 2 vertex b) and ``inside`` — whether
        the orthogonal projection of ``p`` onto the face's plane/line lies in the closed
        face (tolerance 1e-7 in barycentric units).
    """
    dot = lambda u, v: xp.sum(u * v, axis=-1)  # noqa: E731
    tol = 1e-7
    if c is None:
        ab = b - a
        den = dot(ab, ab)
        t = dot(p - a, ab) / xp.where(den > 0, den, 1.0)
        tc = xp.clip(t, 0.0, 1.0)
        q = a + tc[..., None] * ab
        region = xp.where(t <= 0, 1, xp.where(t >= 1, 2, 0))
        inside = (t >= -tol) & (t <= 1 + tol)
        return q, region, inside
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    def safe_div(num, den):
        return num / xp.where(den != 0, den, 1.0)

    # Barycentric coordinates of the plane projection (interior formula).
    s = va + vb + vc
    bv, bw = safe_div(vb, s), safe_div(vc, s)
    q = a + bv[..., None] * ab + bw[..., None] * ac
    region = xp.zeros(d1.shape, dtype=np.int8 if xp is np else jnp.int8)
    # Edges and vertices, in reverse order of Ericson's precedence so the first test wins.
    bc_mask = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    q = xp.where(bc_mask[..., None], b + t_bc[..., None] * (c - b), q)
    region = xp.where(bc_mask, 5, region)
    ac_mask = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t_ac = safe_div(d2, d2 - d6)
    q = xp.where(ac_mask[..., None], a + t_ac[..., None] * ac, q)
    region = xp.where(ac_mask, 6, region)
    c_mask = (d6 >= 0) & (d5 <= d6)
    q = xp.where(c_mask[..., None], c, q)
    region = xp.where(c_mask, 3, region)
    ab_mask = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t_ab = safe_div(d1, d1 - d3)
    q = xp.where(ab_mask[..., None], a + t_ab[..., None] * ab, q)
    region = xp.where(ab_mask, 4, region)
    b_mask = (d3 >= 0) & (d4 <= d3)
    q = xp.where(b_mask[..., None], b, q)
    region = xp.where(b_mask, 2, region)
    a_mask = (d1 <= 0) & (d2 <= 0)
    q = xp.where(a_mask[..., None], a, q)
    region = xp.where(a_mask, 1, region)
    bu = 1.0 - bv - bw
    inside = (s != 0) & (bu >= -tol) & (bv >= -tol) & (bw >= -tol)
    return q, region, inside


def _simplex_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit "+" normals and areas (lengths in 2D) of triangles / segments."""
    if vertices.shape[1] == 3:
        tri = vertices[faces]
        cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        size = 0.5 * np.linalg.norm(cr, axis=-1)
        return safe_normalize_np(cr), size
    seg = vertices[faces]
    t = seg[:, 1] - seg[:, 0]
    size = np.linalg.norm(t, axis=-1)
    return safe_normalize_np(np.stack([t[:, 1], -t[:, 0]], axis=-1)), size


def _mesh_topology(vertices: np.ndarray, faces: np.ndarray, name: str) -> dict:
    """Consistency, closedness and feature pseudo-normals of a triangle mesh or segment set.

    Returns a dict with ``face_normals``, ``vertex_normals`` (angle-weighted pseudo-normals),
    ``vertex_boundary``; in 3D also ``edges (E, 2)``, ``face_edges (F, 3)`` (edge k of a
    face joins its corners k and k+1), ``edge_normals``, ``edge_boundary``; and ``closed``.

    Raises:
        SceneError: inconsistent winding (a directed edge used twice, or in 2D a vertex
            where two segments both start or both end).
    """
    nv, dim = vertices.shape
    fn, _ = _simplex_normals(vertices, faces)
    out: dict = {"face_normals": fn}
    if dim == 2:
        outdeg = np.bincount(faces[:, 0], minlength=nv)
        indeg = np.bincount(faces[:, 1], minlength=nv)
        if np.any(outdeg > 1) or np.any(indeg > 1):
            raise SceneError(
                f"collider {name!r}: inconsistent winding — segments must form chains a->b->c "
                "(a vertex is the start, or the end, of two segments)"
            )
        deg = outdeg + indeg
        vn = np.zeros((nv, 2))
        np.add.at(vn, faces[:, 0], fn)
        np.add.at(vn, faces[:, 1], fn)
        out["vertex_normals"] = safe_normalize_np(vn)
        out["vertex_boundary"] = deg == 1
        out["closed"] = bool(np.all(deg[deg > 0] == 2))
        return out
    f = faces
    directed = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)  # (3F, 2)
    key = directed[:, 0].astype(np.int64) * nv + directed[:, 1]
    if np.unique(key).size != key.size:
        raise SceneError(
            f"collider {name!r}: inconsistent winding — some edge is used twice in the same "
            "direction (flipped faces or a non-manifold edge); trimesh.repair.fix_winding may fix it"
        )
    und = np.sort(directed, axis=1)
    edges, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    face_edges = inverse.reshape(-1, 3)
    en = np.zeros((len(edges), 3))
    np.add.at(en, inverse, np.repeat(fn, 3, axis=0))
    fallback = np.zeros((len(edges), 3))
    fallback[inverse] = np.repeat(fn, 3, axis=0)
    out["edges"] = edges
    out["face_edges"] = face_edges
    out["edge_normals"] = safe_normalize_np(en, fallback)
    out["edge_boundary"] = counts == 1
    # Angle-weighted vertex pseudo-normals (Baerentzen & Aanaes 2005).
    tri = vertices[f]
    vn = np.zeros((nv, 3))
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        cosang = np.sum(safe_normalize_np(e1) * safe_normalize_np(e2), axis=-1)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        np.add.at(vn, f[:, k], ang[:, None] * fn)
    out["vertex_normals"] = safe_normalize_np(vn)
    vb = np.zeros(nv, bool)
    vb[edges[counts == 1].reshape(-1)] = True
    out["vertex_boundary"] = vb
    out["closed"] = bool(np.all(counts == 2))
    return out


class MeshCollider(RigidCollider):
    """A triangle mesh (3D) or a set of segments (2D) placed in the world at t = 0.

    Open surfaces are fine (a bowl, a sheet): the side of a point comes from the normal of
    its nearest face (or the pseudo-normal of the nearest edge/vertex), never from ray
    parity. Closed meshes/polygons are re-oriented on construction so that their normals
    point outward (``+`` = outside).

    Attributes:
        vertices: ``(V, D)`` metres (rest frame = world at t = 0), :class:`StaticArray`.
        faces: ``(F, D)`` int vertex indices (triangles in 3D, segments in 2D).
        face_normals: ``(F, D)`` unit ``+`` normals.
        vertex_normals, vertex_boundary: angle-weighted pseudo-normals, and whether the
            vertex lies on the boundary of an open surface.
        edges, face_edges, edge_normals, edge_boundary: 3D only (``None`` in 2D).
        closed: whether the surface is closed (watertight / closed polygons).
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    vertices: StaticArray = eqx.field(static=True)
    faces: StaticArray = eqx.field(static=True)
    face_normals: StaticArray = eqx.field(static=True)
    vertex_normals: StaticArray = eqx.field(static=True)
    vertex_boundary: StaticArray = eqx.field(static=True)
    edges: StaticArray | None = eqx.field(static=True)
    face_edges: StaticArray | None = eqx.field(static=True)
    edge_normals: StaticArray | None = eqx.field(static=True)
    edge_boundary: StaticArray | None = eqx.field(static=True)
    closed: bool = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "mesh"

    def __init__(
        self,
        vertices,
        faces,
        contact: str = "sticky",
        name: str = "mesh",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        v = np.asarray(vertices, float)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] not in (2, 3) or len(v) == 0:
            raise SceneError(f"collider {name!r}: vertices must be an (V, 2) or (V, 3) array, got shape {v.shape}")
        dim = v.shape[1]
        if f.size == 0:
            raise SceneError(f"collider {name!r}: the mesh has no faces")
        if f.ndim != 2 or f.shape[1] != dim or not np.issubdtype(f.dtype, np.integer):
            raise SceneError(
                f"collider {name!r}: faces must be an integer (F, {dim}) array "
                f"({'triangles' if dim == 3 else 'segments'}), got shape {f.shape}"
            )
        if f.min() < 0 or f.max() >= len(v):
            raise SceneError(f"collider {name!r}: face indices out of range [0, {len(v)})")
        if not np.all(np.isfinite(v)):
            raise SceneError(f"collider {name!r}: vertices contain NaN or infinite values")
        f = f.astype(np.int64)
        # Drop degenerate faces (repeated vertices or zero area/length): no normal.
        scale = float(np.max(np.ptp(v, axis=0))) or 1.0
        _, size = _simplex_normals(v, f)
        distinct = np.all(f != np.roll(f, 1, axis=1), axis=1)
        keep = distinct & (size > (1e-12 * scale ** (dim - 1)))
        f = f[keep]
        if len(f) == 0:
            raise SceneError(f"collider {name!r}: the mesh has no faces (all are degenerate)")
        topo = _mesh_topology(v, f, name)
        if topo["closed"]:
            fn, size = _simplex_normals(v, f)
            centroid = np.mean(v[f], axis=1)
            signed = np.sum(size * np.sum(centroid * fn, axis=-1)) / dim  # volume / area
            if signed < 0:  # inward-facing closed surface: flip so that "+" is outside
                f = f[:, ::-1].copy()
                topo = _mesh_topology(v, f, name)
        self.vertices = StaticArray(v)
        self.faces = StaticArray(f)
        self.face_normals = StaticArray(topo["face_normals"])
        self.vertex_normals = StaticArray(topo["vertex_normals"])
        self.vertex_boundary = StaticArray(topo["vertex_boundary"])
        if dim == 3:
            self.edges = StaticArray(topo["edges"])
            self.face_edges = StaticArray(topo["face_edges"])
            self.edge_normals = StaticArray(topo["edge_normals"])
            self.edge_boundary = StaticArray(topo["edge_boundary"])
        else:
            self.edges = self.face_edges = self.edge_normals = self.edge_boundary = None
        self.closed = topo["closed"]
        used = v[np.unique(f)]
        default_pivot = 0.5 * (used.min(axis=0) + used.max(axis=0))
        init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, default_pivot, motion)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> np.ndarray:
        v = np.asarray(self.vertices)[np.unique(np.asarray(self.faces))]
        return np.stack([v.min(axis=0), v.max(axis=0)])

    def to_trimesh(self):
        """The (3D) mesh as a ``trimesh.Trimesh`` (rest frame), e.g. for rendering."""
        import trimesh

        return trimesh.Trimesh(np.asarray(self.vertices), np.asarray(self.faces), process=False)

    def region_normals(self) -> np.ndarray:
        """Per face, the pseudo-normal of each closest-point region, ``(F, 7, 3)`` (2D: ``(F, 3, 2)``).

        Region codes as in :func:`closest_on_simplices`: 0 face, 1..3 vertices,
        4..6 edges ab, bc, ca.
        """
        f = np.asarray(self.faces)
        fn = np.asarray(self.face_normals)
        vn = np.asarray(self.vertex_normals)[f]  # (F, D, D)
        if self.dim == 2:
            return np.concatenate([fn[:, None], vn], axis=1)
        en = np.asarray(self.edge_normals)[np.asarray(self.face_edges)]  # (F, 3, 3)
        return np.concatenate([fn[:, None], vn, en], axis=1)

    def _local_signed_distance(self, X):
        """Exact brute-force signed distance over all faces (O(M F)); sign from the nearest
        feature's pseudo-normal. Meant for checks, small meshes and few points — the
        simulator uses the precomputed collision field (``jaxmpm.cpic``)."""
        corners, rn, valid = _mesh_tables(self)
        return _brute_mesh_sdf(
            X, jnp.asarray(corners, X.dtype), jnp.asarray(rn, X.dtype), jnp.asarray(valid)
        )


_SDF_CHUNK = 256


@functools.lru_cache(maxsize=16)
def _mesh_tables(mesh: MeshCollider):
    """Face corners, region pseudo-normals and a validity mask, padded to whole chunks."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    rn = mesh.region_normals()
    nf, dim = f.shape
    nchunk = -(-nf // _SDF_CHUNK)
    pad = nchunk * _SDF_CHUNK - nf
    corners = np.concatenate([v[f], np.repeat(v[f[:1]], pad, axis=0)])
    rn = np.concatenate([rn, np.repeat(rn[:1], pad, axis=0)])
    valid = np.arange(nchunk * _SDF_CHUNK) < nf
    return (
        corners.reshape(nchunk, _SDF_CHUNK, dim, dim),
        rn.reshape(nchunk, _SDF_CHUNK, *rn.shape[1:]),
        valid.reshape(nchunk, _SDF_CHUNK),
    )


@jax.jit
def _brute_mesh_sdf(X, corners, rn, valid):
    """Scan over face chunks keeping, per point, the nearest face's signed distance/normal."""
    dtype = X.dtype
    m, dim = X.shape

    def body(carry, inp):
        best_d2, best_s, best_n = carry
        cor, reg_n, ok = inp
        p = X[:, None, :]
        a, b = cor[None, :, 0], cor[None, :, 1]
        c = cor[None, :, 2] if dim == 3 else None
        q, region, _ = closest_on_simplices(p, a, b, c, xp=jnp)
        diff = p - q
        d2 = jnp.where(ok[None, :], jnp.sum(diff * diff, axis=-1), jnp.inf)
        j = jnp.argmin(d2, axis=1)
        d2j = jnp.take_along_axis(d2, j[:, None], axis=1)[:, 0]
        regj = jnp.take_along_axis(region, j[:, None], axis=1)[:, 0].astype(jnp.int32)
        pn = reg_n[j, regj]  # (M, D) pseudo-normal of the nearest feature
        dj = jnp.take_along_axis(diff, j[:, None, None], axis=1)[:, 0]
        sgn = jnp.where(jnp.sum(dj * pn, axis=-1) >= 0, 1.0, -1.0).astype(dtype)
        has_len = d2j > 0
        dirn = dj / jnp.sqrt(jnp.where(has_len, d2j, 1.0))[:, None]
        use_pn = ((regj == 0) | ~has_len)[:, None]
        nrm = jnp.where(use_pn, pn, sgn[:, None] * dirn)
        better = d2j < best_d2
        return (
            jnp.where(better, d2j, best_d2),
            jnp.where(better, sgn, best_s),
            jnp.where(better[:, None], nrm, best_n),
        ), None

    init = (jnp.full((m,), jnp.inf, dtype), jnp.ones((m,), dtype), jnp.zeros((m, dim), dtype))
    (d2, s, n), _ = jax.lax.scan(body, init, (corners, rn, valid))
    pos = d2 > 0
    dist = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
    return s * dist, n
