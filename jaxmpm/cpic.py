"""CPIC collision grid: the colored distance field of each collider on the grid nodes.

Built once per collider with NumPy outside the traced code (Hu et al. 2018, CPIC; the
AS-DiffMPM "collision grid"): for every grid node, whether it is *affine* to the collider
(near its surface, with a well-defined side), on which side it lies, its unsigned distance
to the surface and the surface's ``+``-side normal.

Conventions:

* ``side`` is ``+1`` on the collider's ``+`` side (outside closed solids; the side the face
  normals point to for open surfaces), ``-1`` on the other, ``0`` where not affine. It comes
  from the normal of the nearest face — never from ray parity or trimesh's
  ``signed_distance`` — so open meshes (a bowl, a sheet) work.
* ``normal`` is the unit normal pointing to the ``+`` side: the nearest face's normal when the
  node projects onto that face, otherwise ``side * (x - q) / |x - q|`` with ``q`` the nearest
  point on the edge/vertex. Zero where not affine.
* ``distance`` is the unsigned distance to the surface (metres) where affine and
  ``band * dx`` elsewhere.
* A moving collider's field is built in its rest frame, i.e. with the collider where it sits
  at t = 0, on the same grid nodes; query it at ``collider.to_local(x, t)`` and rotate
  normals back with ``collider.to_world_vectors(n, t)``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int8

from .colliders import Box, Collider, GaussianDisks, MeshCollider, Plane, closest_on_simplices
from .errors import SceneError
from .state import Grid


class CollisionField(eqx.Module):
    """Per-node collision data of one collider (flattened in the grid's C order).

    Attributes:
        affinity: ``(G,)`` bool — the node is within the band of the surface and its nearest
            surface feature is a face it projects onto, or (unless built with
            ``strict=True``) an edge/vertex interior to the surface.
        side: ``(G,)`` int8 in {-1, 0, +1}.
        distance: ``(G,)`` unsigned distance, metres (``band_width`` where not affine).
        normal: ``(G, D)`` unit ``+``-side normal (zero where not affine).
        shape: the grid's node shape (static).
        band_width: the band half-width in metres, ``band * dx`` (static).
        name: the collider's name (static).
    """

    affinity: Bool[Array, " G"]
    side: Int8[Array, " G"]
    distance: Float[Array, " G"]
    normal: Float[Array, "G D"]
    shape: tuple[int, ...] = eqx.field(static=True)
    band_width: float = eqx.field(static=True)
    name: str = eqx.field(static=True)

    def astype(self, dtype) -> CollisionField:
        """The same field with ``distance`` and ``normal`` in ``dtype``."""
        return CollisionField(
            self.affinity,
            self.side,
            self.distance.astype(dtype),
            self.normal.astype(dtype),
            self.shape,
            self.band_width,
            self.name,
        )

    @property
    def num_affine(self) -> int:
        return int(np.count_nonzero(np.asarray(self.affinity)))

    def signed_distance(self) -> tuple[Float[Array, " G"], Float[Array, "G D"]]:
        """Per-node ``side * distance`` (``+band_width`` where not affine) and the normal.

        A grid-level (GOP-style) boundary condition can use this on static colliders instead
        of evaluating ``collider.signed_distance`` on every node.
        """
        sd = jnp.where(self.affinity, self.side.astype(self.distance.dtype) * self.distance, self.band_width)
        return sd, self.normal


def build_collision_field(
    collider: Collider,
    grid: Grid,
    band: float = 2.0,
    *,
    strict: bool = False,
    dtype=None,
    max_pairs: int = 2_000_000,
) -> CollisionField:
    """Precompute a collider's collision field on the grid nodes (NumPy; not traced).

    Arguments:
        collider: a :class:`~jaxmpm.colliders.Plane`, ``Box``, ``MeshCollider`` or
            ``GaussianDisks`` (moving colliders: in their t = 0 placement).
        grid: the background grid.
        band: half-width of the affinity band in cells (default 2, more than the quadratic
            B-spline's reach of 1.5 cells).
        strict: only nodes that project *inside* their nearest face are affine (the rule of
            TM's ``rasterize_rigid_boundary``). The default also accepts nodes whose nearest
            feature is an edge or vertex interior to the surface (the outer wedges of convex
            edges, which the strict rule leaves as holes in the band); nodes whose nearest
            feature lies on the boundary of an open surface (a bowl's rim, a sheet's edge)
            are never affine.
        dtype: float dtype of ``distance``/``normal`` (default: jax's default float).
        max_pairs: node-primitive pairs processed per batch (memory bound).

    Returns:
        The :class:`CollisionField`.

    Raises:
        SceneError: the collider lies entirely outside the domain (no grid node near its
            surface).
    """
    if band <= 0:
        raise ValueError(f"band must be positive, got {band}")
    width = float(band) * grid.dx
    _check_in_domain(collider, grid, width)
    if isinstance(collider, Plane):
        aff, side, dist, nrm = _field_plane(collider, grid, width)
    elif isinstance(collider, Box):
        aff, side, dist, nrm = _field_box(collider, grid, width, strict)
    elif isinstance(collider, MeshCollider):
        aff, side, dist, nrm = _field_mesh(collider, grid, width, strict, max_pairs)
    elif isinstance(collider, GaussianDisks):
        aff, side, dist, nrm = _field_disks(collider, grid, width, max_pairs)
    else:
        raise TypeError(f"no collision-field builder for {type(collider).__name__}")
    if not aff.any():
        raise SceneError(
            f"collider {collider.name!r}: no grid node lies within {band} cells of its surface "
            "(is it outside the domain, or does it enclose the whole domain?)"
        )
    dtype = dtype or jnp.result_type(float)
    return CollisionField(
        affinity=jnp.asarray(aff),
        side=jnp.asarray(side.astype(np.int8)),
        distance=jnp.asarray(dist, dtype),
        normal=jnp.asarray(nrm, dtype),
        shape=tuple(grid.shape),
        band_width=width,
        name=collider.name,
    )


def field_to_dense(field: CollisionField, grid: Grid | None = None) -> dict[str, np.ndarray]:
    """The field as NumPy arrays shaped like the grid: ``affinity``, ``side``, ``distance``
    (``grid.shape``) and ``normal`` (``grid.shape + (D,)``), e.g. for plotting."""
    shape = tuple(grid.shape) if grid is not None else field.shape
    return {
        "affinity": np.asarray(field.affinity).reshape(shape),
        "side": np.asarray(field.side).reshape(shape),
        "distance": np.asarray(field.distance).reshape(shape),
        "normal": np.asarray(field.normal).reshape(shape + (-1,)),
    }


# ------------------------------------------------------------------------------------------
# Helpers
# ------------------------------------------------------------------------------------------


def _check_in_domain(collider: Collider, grid: Grid, width: float) -> None:
    lo = np.asarray(grid.lo, float) - width
    hi = np.asarray(grid.hi, float) + width
    if isinstance(collider, Plane):
        corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, len(lo))
        h = (corners - np.asarray(collider.point)) @ np.asarray(collider.normal)
        if np.all(h > width) or np.all(h < -width):
            raise SceneError(
                f"collider {collider.name!r}: the plane does not cross the domain "
                f"[{list(grid.lo)}, {list(grid.hi)}]"
            )
        return
    b = collider.bounds()
    if np.any(b[1] < lo) or np.any(b[0] > hi):
        raise SceneError(
            f"collider {collider.name!r} lies entirely outside the domain "
            f"[{list(grid.lo)}, {list(grid.hi)}] (its bounds are {b[0].tolist()} .. {b[1].tolist()})"
        )


def _empty(grid: Grid, width: float):
    g, d = grid.num_nodes, grid.dim
    return (
        np.zeros(g, bool),
        np.zeros(g, np.int8),
        np.full(g, width),
        np.zeros((g, d)),
    )


def _node_boxes(lo: np.ndarray, hi: np.ndarray, grid: Grid):
    """Integer node boxes ``[i0, i0 + dims)`` covering the world boxes ``[lo, hi]`` (rows)."""
    origin = np.asarray(grid.origin, float)
    shape = np.asarray(grid.shape, np.int64)
    i0 = np.ceil((lo - origin) / grid.dx - 1e-9).astype(np.int64)
    i1 = np.floor((hi - origin) / grid.dx + 1e-9).astype(np.int64)
    i0 = np.clip(i0, 0, shape)
    i1 = np.clip(i1, -1, shape - 1)
    dims = np.maximum(i1 - i0 + 1, 0)
    return i0, dims


def _pair_batches(i0: np.ndarray, dims: np.ndarray, grid: Grid, max_pairs: int):
    """Yield ``(prim, positions, node_ids)`` for every (primitive, node in its box) pair."""
    origin = np.asarray(grid.origin, float)
    counts = np.prod(dims, axis=1)
    cum = np.concatenate([[0], np.cumsum(counts)])
    total = int(cum[-1])
    ndim = dims.shape[1]
    for start in range(0, total, max_pairs):
        g = np.arange(start, min(start + max_pairs, total), dtype=np.int64)
        prim = np.searchsorted(cum, g, side="right") - 1
        rem = g - cum[prim]
        d = dims[prim]
        ijk = np.empty((len(g), ndim), np.int64)
        for ax in range(ndim - 1, -1, -1):
            ijk[:, ax] = rem % d[:, ax]
            rem = rem // d[:, ax]
        ijk += i0[prim]
        nid = np.ravel_multi_index(tuple(ijk.T), grid.shape)
        yield prim, origin + ijk * grid.dx, nid


def _node_positions(grid: Grid, nodes: np.ndarray) -> np.ndarray:
    ijk = np.stack(np.unravel_index(nodes, grid.shape), axis=-1)
    return np.asarray(grid.origin, float) + ijk * grid.dx


def _sign(x: np.ndarray) -> np.ndarray:
    return np.where(x >= 0, 1, -1).astype(np.int8)


def _keep_nearest(best: np.ndarray, best_prim: np.ndarray, nid, key, prim) -> None:
    """Per node, keep the primitive with the smallest ``key`` seen so far."""
    np.minimum.at(best, nid, key)
    win = key <= best[nid]
    best_prim[nid[win]] = prim[win]


# ------------------------------------------------------------------------------------------
# Builders
# ------------------------------------------------------------------------------------------


def _field_plane(col: Plane, grid: Grid, width: float):
    aff, side, dist, nrm = _empty(grid, width)
    x = grid.node_positions()
    n = np.asarray(col.normal)
    h = (x - np.asarray(col.point)) @ n
    aff[:] = np.abs(h) < width
    side[aff] = _sign(h[aff])
    dist[aff] = np.abs(h[aff])
    nrm[aff] = n
    return aff, side, dist, nrm


def _field_box(col: Box, grid: Grid, width: float, strict: bool):
    aff, side, dist, nrm = _empty(grid, width)
    b = col.bounds()
    i0, dims = _node_boxes(b[:1] - width, b[1:] + width, grid)
    if np.prod(dims) == 0:
        return aff, side, dist, nrm
    (_, x, nid), = _pair_batches(i0, dims, grid, int(np.prod(dims)))
    r = np.asarray(col.rotation)
    y = (x - col.center) @ r
    q = np.abs(y) - col.half_extent
    qp = np.maximum(q, 0.0)
    out_len = np.linalg.norm(qp, axis=-1)
    outside = out_len > 0
    sd = np.where(outside, out_len, np.max(q, axis=-1))
    sgn = np.where(y >= 0, 1.0, -1.0)
    face = np.eye(y.shape[1])[np.argmax(q, axis=-1)]
    n_loc = np.where(outside[:, None], sgn * qp / np.where(outside, out_len, 1.0)[:, None], sgn * face)
    ok = np.abs(sd) < width
    if strict:  # projection onto the nearest face must fall inside it
        ok &= np.sum(q > 0, axis=-1) <= 1
    sel = nid[ok]
    aff[sel] = True
    side[sel] = _sign(sd[ok])
    dist[sel] = np.abs(sd[ok])
    nrm[sel] = n_loc[ok] @ r.T
    return aff, side, dist, nrm


def _field_mesh(col: MeshCollider, grid: Grid, width: float, strict: bool, max_pairs: int):
    aff, side, dist, nrm = _empty(grid, width)
    v = np.asarray(col.vertices)
    f = np.asarray(col.faces)
    fn = np.asarray(col.face_normals)
    dim = v.shape[1]
    corners = v[f]  # (F, D, D)
    i0, dims = _node_boxes(corners.min(axis=1) - width, corners.max(axis=1) + width, grid)
    best = np.full(grid.num_nodes, np.inf)
    best_face = np.full(grid.num_nodes, -1, np.int64)
    w2 = width * width

    def closest(p, face):
        c = corners[face]
        return closest_on_simplices(p, c[:, 0], c[:, 1], c[:, 2] if dim == 3 else None)

    centre = corners.mean(axis=1)
    reach = np.sqrt(np.max(np.sum((corners - centre[:, None]) ** 2, axis=-1), axis=1)) + width
    reach2 = reach * reach
    for prim, x, nid in _pair_batches(i0, dims, grid, max_pairs):
        # Cheap filters first: the bounding sphere of the face grown by the band, and the
        # distance to the face's plane.
        dc = x - centre[prim]
        h = np.sum(dc * fn[prim], axis=-1)
        keep = (np.abs(h) < width) & (np.sum(dc * dc, axis=-1) < reach2[prim])
        if not keep.any():
            continue
        prim, x, nid = prim[keep], x[keep], nid[keep]
        q, _, _ = closest(x, prim)
        d2 = np.sum((x - q) ** 2, axis=-1)
        keep = d2 < w2
        if keep.any():
            _keep_nearest(best, best_face, nid[keep], d2[keep], prim[keep])

    nodes = np.flatnonzero(best_face >= 0)
    if nodes.size == 0:
        return aff, side, dist, nrm
    face = best_face[nodes]
    x = _node_positions(grid, nodes)
    q, region, inside = closest(x, face)
    diff = x - q
    d = np.linalg.norm(diff, axis=-1)
    # The nearest feature's pseudo-normal and whether it is on the surface's boundary.
    pn = fn[face].copy()
    boundary = np.zeros(len(nodes), bool)
    is_vertex = (region >= 1) & (region <= 3)
    vid = f[face[is_vertex], region[is_vertex] - 1]
    pn[is_vertex] = np.asarray(col.vertex_normals)[vid]
    boundary[is_vertex] = np.asarray(col.vertex_boundary)[vid]
    if dim == 3:
        is_edge = region >= 4
        eid = np.asarray(col.face_edges)[face[is_edge], region[is_edge] - 4]
        pn[is_edge] = np.asarray(col.edge_normals)[eid]
        boundary[is_edge] = np.asarray(col.edge_boundary)[eid]
    h_face = np.sum(diff * fn[face], axis=-1)
    s = np.where(inside, _sign(h_face), _sign(np.sum(diff * pn, axis=-1)))
    safe_d = np.where(d > 0, d, 1.0)[:, None]
    n_feature = np.where((d > 0)[:, None], s[:, None] * diff / safe_d, pn)
    n_out = np.where(inside[:, None], fn[face], n_feature)
    ok = inside | (~boundary & (not strict))
    sel = nodes[ok]
    aff[sel] = True
    side[sel] = s[ok]
    dist[sel] = np.where(inside, np.abs(h_face), d)[ok]
    nrm[sel] = n_out[ok]
    return aff, side, dist, nrm


def _field_disks(col: GaussianDisks, grid: Grid, width: float, max_pairs: int):
    aff, side, dist, nrm = _empty(grid, width)
    c = np.asarray(col.centers)
    n = np.asarray(col.normals)
    tan = np.asarray(col.tangents)
    s = np.asarray(col.scales)
    ext = col._half_extents(tan, s, col.cutoff)
    i0, dims = _node_boxes(c - ext - width, c + ext + width, grid)
    best = np.full(grid.num_nodes, np.inf)
    best_disk = np.full(grid.num_nodes, -1, np.int64)
    cut2 = col.cutoff**2
    for prim, x, nid in _pair_batches(i0, dims, grid, max_pairs):
        dlt = x - c[prim]
        h = np.sum(dlt * n[prim], axis=-1)
        keep = np.abs(h) < width
        if not keep.any():
            continue
        prim, dlt, nid, h = prim[keep], dlt[keep], nid[keep], h[keep]
        a = np.einsum("nd,njd->nj", dlt, tan[prim]) / s[prim]
        keep = np.sum(a * a, axis=-1) <= cut2
        if keep.any():
            _keep_nearest(best, best_disk, nid[keep], h[keep] ** 2, prim[keep])
    nodes = np.flatnonzero(best_disk >= 0)
    if nodes.size == 0:
        return aff, side, dist, nrm
    k = best_disk[nodes]
    h = np.sum((_node_positions(grid, nodes) - c[k]) * n[k], axis=-1)
    aff[nodes] = True
    side[nodes] = _sign(h)
    dist[nodes] = np.abs(h)
    nrm[nodes] = n[k]
    return aff, side, dist, nrm
