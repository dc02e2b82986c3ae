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


import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, Int8

from .colliders import (
    Box,
    Collider,
    GaussianDisks,
    MeshCollider,
    Plane,
    RigidCollider,
    closest_on_simplices,
    project_velocity,
    rigid_transform,
    row_dot,
    row_matvec,
    rows_times,
)
from .errors import SceneError
from .fusion import always_true, compute_once, materialize, scale_rows, spread, symmetric_pair_sum
from .state import (
    Grid,
    Stencil,
    flat_index,
    gather_rows,
    node_indices,
    offset_weight,
    stencil_index,
    stencil_offsets,
    stencil_terms,
)


class CollisionField(eqx.Module):
    """Per-node collision data of one collider (flattened in the grid's C order).

    Attributes:
        affinity: ``(G,)`` bool — the node is within the band of the surface and its nearest
            surface feature is a face it projects onto, or (unless built with
            ``strict=True``) an edge/vertex interior to the surface.
        side: ``(G,)`` int8 in {-1, 0, +1}.
        distance: ``(G,)`` unsigned distance, metres (``band_width`` where not affine).
        normal: ``(G, D)`` unit ``+``-side normal (zero where not affine).
        rows: ``(G, 1 + D)`` packed ``[side * distance, normal]`` (zero where not affine).
        stencil_bits: ``(G, 2)`` int32: for the quadratic stencil whose lowest node is this
            node, bit ``o`` (offset ``o`` in :func:`~jaxmpm.state.stencil_offsets` order) of
            column 0 / 1 is set when that stencil node is affine on the ``+`` / ``-`` side —
            one gather gives a particle the sides of all its 3^D stencil nodes.
        shape: the grid's node shape (static).
        band_width: the band half-width in metres, ``band * dx`` (static).
        name: the collider's name (static).
        thin: some node's stencil holds affine nodes of *opposed* surfaces (normals more than
            120 degrees apart: the two faces of a solid thinner than the stencil); particles
            then judge compatibility against the surface they are near as well (static; see
            :func:`gather_contact`).
    """

    affinity: Bool[Array, " G"]
    side: Int8[Array, " G"]
    distance: Float[Array, " G"]
    normal: Float[Array, "G D"]
    stencil_bits: Int[Array, "G 2"]
    rows: Float[Array, "G D1"]
    shape: tuple[int, ...] = eqx.field(static=True)
    band_width: float = eqx.field(static=True)
    name: str = eqx.field(static=True)
    origin: tuple[float, ...] | None = eqx.field(static=True, default=None)
    dx: float | None = eqx.field(static=True, default=None)
    thin: bool = eqx.field(static=True, default=False)

    def astype(self, dtype) -> CollisionField:
        """The same field with ``distance`` and ``normal`` in ``dtype``."""
        return CollisionField(
            self.affinity,
            self.side,
            self.distance.astype(dtype),
            self.normal.astype(dtype),
            self.stencil_bits,
            self.rows.astype(dtype),
            self.shape,
            self.band_width,
            self.name,
            self.origin,
            self.dx,
            self.thin,
        )

    def on_grid(self, grid: Grid) -> bool:
        """Whether the field's nodes are exactly the nodes of ``grid`` (static check)."""
        return self.shape == tuple(grid.shape) and self.origin == tuple(grid.origin) and self.dx == grid.dx

    @property
    def num_affine(self) -> int:
        return int(np.count_nonzero(np.asarray(self.affinity)))

    def signed_distance(self) -> tuple[Float[Array, " G"], Float[Array, "G D"]]:
        """Per-node ``side * distance`` (``+band_width`` where not affine) and the normal.

        A grid-level (GOP-style) boundary condition can use this on static colliders instead
        of evaluating ``collider.signed_distance`` on every node (see
        :func:`node_signed_distance`, which also handles open surfaces and moving colliders).
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
        stencil_bits=jnp.asarray(stencil_side_bits(side.astype(np.int8).reshape(grid.shape))),
        # the signed distance of a node on the surface keeps its side (side_bits)
        rows=jnp.asarray(np.concatenate([np.where(aff, side * np.maximum(dist, ON_SURFACE * grid.dx), 0.0)[:, None], np.where(aff[:, None], nrm, 0.0)], -1), dtype),
        shape=tuple(grid.shape),
        band_width=width,
        name=collider.name,
        origin=tuple(grid.origin),
        dx=grid.dx,
        thin=has_opposed_neighbours(aff.reshape(grid.shape), nrm.reshape(tuple(grid.shape) + (-1,))),
    )


#: Two surfaces are *opposed* when their unit normals' dot product is below this (more than
#: 120 degrees apart): the two faces of a thin solid, never the faces meeting at a box's edge.
OPPOSED_COS = -0.5
#: The choice of the reference face in :func:`surface_estimate` is soft over this many cells of
#: the ranking key: a particle's velocity moves continuously where the choice switches faces.
#: (Session 20 had it at 1e-4, hard in practice, because at 1e-2 the choice's own slope made
#: the Jacobians so steep that sand fits stopped at false stationary points; since session 32
#: the choice carries no derivative, and 1e-2 fits the CPIC track cases as well or better:
#: docs/benchmark_sysid.md.)
REFERENCE_TEMPERATURE = 1e-2
#: In the ranking of :func:`surface_estimate` a face the particle lies behind ranks below every
#: face in front of it within this many cells: its key drops by that much over its first
#: ``BEHIND_DROP / BEHIND_SLOPE`` cells of depth.
BEHIND_DROP = 5.0
BEHIND_SLOPE = 100.0
#: Nodes whose normals are less than about 45 degrees apart propose one face between them
#: (:func:`same_face_fraction`, ramped over :data:`SAME_FACE_RAMP` of the cosine): the facets
#: of a curved surface one cell apart, not the two walls of a crease or the faces at a box's edge.
SAME_FACE_COS = 0.7
SAME_FACE_RAMP = 0.2
#: :func:`concave_share` ramps over this many cells of the distance by which one face's surface
#: point lies in front of another face's plane.
CONCAVE_RAMP = 0.25


def has_opposed_neighbours(affinity: np.ndarray, normal: np.ndarray) -> bool:
    """Whether two affine nodes at most 2 cells apart per axis (so both in one particle's
    stencil) have opposed normals (NumPy; ``affinity`` shaped like the grid, ``normal`` with a
    trailing ``D`` axis)."""
    dim = affinity.ndim
    n = np.where(affinity[..., None], normal, 0.0)
    for shift in itertools.product(range(-2, 3), repeat=dim):
        if shift <= (0,) * dim:  # each unordered pair once
            continue
        a = tuple(slice(max(k, 0), n.shape[d] + min(k, 0)) for d, k in enumerate(shift))
        b = tuple(slice(max(-k, 0), n.shape[d] + min(-k, 0)) for d, k in enumerate(shift))
        if np.any(np.sum(n[a] * n[b], axis=-1) < OPPOSED_COS):
            return True
    return False


def stencil_side_bits(side: np.ndarray) -> np.ndarray:
    """Per node j, the ``+``/``-`` side bits of the stencil nodes ``j + o`` (NumPy, ``(G, 2)`` int32).

    ``side`` is the dense ``(n_1, ..., n_D)`` side array (0 = not affine); nodes past the
    grid count as not affine.
    """
    dim = side.ndim
    padded = np.pad(side, [(0, 2)] * dim)
    plus = np.zeros(side.shape, np.int64)
    minus = np.zeros(side.shape, np.int64)
    for o, offset in enumerate(stencil_offsets(dim)):
        view = padded[tuple(slice(k, k + n) for k, n in zip(offset, side.shape))]
        plus |= (view > 0).astype(np.int64) << o
        minus |= (view < 0).astype(np.int64) << o
    return np.stack([plus.reshape(-1), minus.reshape(-1)], axis=-1).astype(np.int32)


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


#: A node within this many cells of a collider's surface lies *on* it (round-off).
ON_SURFACE = 1e-9


def _sign(x: np.ndarray, dx: float) -> np.ndarray:
    """The side of a node at signed distance ``x`` (m). A node on the surface
    (:data:`ON_SURFACE`) is on its ``-`` side, as a grid-level plane counts it
    (:func:`jaxmpm.step.apply_grid_colliders`): counted on the ``+`` side, a node on a face with
    material resting on it supported nothing, and the material was squashed into the face
    (docs/colliders.md, "Where a face lies between node rows"). The field builders put a node
    on a convex edge or corner back on the ``+`` side (:func:`_on_convex_crease`)."""
    return np.where(x > ON_SURFACE * dx, 1, -1).astype(np.int8)


def _on_convex_crease(
    node: list[np.ndarray], touching: list[np.ndarray], centre: np.ndarray, normal: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Which of the nodes that lie on a collider's surface lie on a convex edge or corner
    (NumPy).

    ``node`` and ``touching`` (batches of ``(P_b,)`` indices, as the field builders' loops
    find them) pair each such node with every primitive (a mesh's face, a surfel) it lies on,
    to within ``tol`` (m); ``centre (F, D)`` and ``normal (F, D)`` are the primitives'
    centroids and unit normals. A node is on a convex crease when no primitive it lies on has
    another's centre in front of its plane, and some has one behind: a box's edge or corner;
    not a vertex or an edge inside a flat face, nor two coplanar surfels (all centres on the
    plane), nor a concave crease. Returns the nodes (sorted, unique) and a flag for each.
    """
    node = np.concatenate([np.zeros(0, np.int64), *node])
    order = np.argsort(node, kind="stable")
    prim = np.concatenate([np.zeros(0, np.int64), *touching])[order]
    nodes, start, count = np.unique(node[order], return_index=True, return_counts=True)
    if len(nodes) == 0:
        return nodes, np.zeros(0, bool)
    # every (f, g) pair of one node's primitives, grouped by node: f runs over the node's
    # primitives, and for each f, g runs over them again
    size = np.repeat(count, count)  # for each (node, primitive) pair, its node's primitive count
    f = np.repeat(np.arange(len(prim)), size)
    g = np.repeat(np.repeat(start, count), size) + np.arange(len(f)) - np.repeat(np.cumsum(size) - size, size)
    height = np.sum((centre[prim[g]] - centre[prim[f]]) * normal[prim[f]], axis=-1)  # g's centre over f's plane
    first = np.cumsum(count * count) - count * count  # where each node's pairs begin
    return nodes, (np.maximum.reduceat(height, first) <= tol) & (np.minimum.reduceat(height, first) < -tol)


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
    side[aff] = _sign(h[aff], grid.dx)
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
    # a node on an edge or a corner (on two faces' planes or more) is outside (_sign)
    tie = ON_SURFACE * grid.dx
    on_edge = (np.abs(sd) <= tie) & (np.sum(np.abs(q) <= tie, axis=-1) >= 2)
    side[sel] = np.where(on_edge[ok], 1, _sign(sd[ok], grid.dx))
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
    tie = ON_SURFACE * grid.dx
    touch_node, touch_face = [], []  # the (node, face) pairs with the node on the face

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
        on = d2 <= tie * tie
        touch_node.append(nid[on])
        touch_face.append(prim[on])

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
    s = np.where(inside, _sign(h_face, grid.dx), _sign(np.sum(diff * pn, axis=-1), grid.dx))
    # a node on a convex edge or corner is outside (_sign)
    crease, convex = _on_convex_crease(touch_node, touch_face, centre, fn, tie)
    s[np.isin(nodes, crease[convex])] = 1
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
    ext = col.half_extents(tan, s, col.cutoff)
    i0, dims = _node_boxes(c - ext - width, c + ext + width, grid)
    best = np.full(grid.num_nodes, np.inf)
    best_disk = np.full(grid.num_nodes, -1, np.int64)
    cut2 = col.cutoff**2
    tie = ON_SURFACE * grid.dx
    touch_node, touch_disk = [], []  # the (node, disk) pairs with the node on the disk
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
        on = keep & (np.abs(h) <= tie)
        touch_node.append(nid[on])
        touch_disk.append(prim[on])
    nodes = np.flatnonzero(best_disk >= 0)
    if nodes.size == 0:
        return aff, side, dist, nrm
    k = best_disk[nodes]
    h = np.sum((_node_positions(grid, nodes) - c[k]) * n[k], axis=-1)
    aff[nodes] = True
    side[nodes] = _sign(h, grid.dx)
    # a node on a convex crease of the surfels (_sign), as on a mesh's
    crease, convex = _on_convex_crease(touch_node, touch_disk, c, n, tie)
    side[crease[convex]] = 1
    dist[nodes] = np.abs(h)
    nrm[nodes] = n[k]
    return aff, side, dist, nrm


# ==========================================================================================
# Fields carried by the model (built once, NumPy, outside traced code)
# ==========================================================================================


def is_particle_wise(collider: Collider) -> bool:
    """Whether ``collider`` has a collision field (every collider but a :class:`Plane`)."""
    return not isinstance(collider, Plane)


def collider_lattice(collider: RigidCollider, dx: float, band: float = 2.0) -> Grid:
    """A lattice of spacing ``dx`` around a collider's rest placement (for moving colliders:
    their field is built here, in the rest frame, and looked up at ``to_local(x, t)``)."""
    b = collider.bounds()
    margin = (band + 1.0) * dx
    return Grid(lo=tuple((b[0] - margin).tolist()), hi=tuple((b[1] + margin).tolist()), dx=dx)


def check_planes(colliders, grid: Grid) -> None:
    """Raise if a plane's solid side contains the whole domain at t = 0 (every particle
    would start inside it; usually a flipped normal)."""
    for col in colliders:
        if not isinstance(col, Plane):
            continue
        corners = np.stack(np.meshgrid(*zip(grid.lo, grid.hi), indexing="ij"), -1).reshape(-1, grid.dim)
        h = (corners - np.asarray(col.point)) @ np.asarray(col.normal)
        if np.all(h < 0):
            raise SceneError(
                f"collider {col.name!r}: the whole domain [{list(grid.lo)}, {list(grid.hi)}] lies on the solid "
                f"side of the plane (point {list(col.point)}, normal {list(col.normal)}); is the normal flipped?"
            )


def build_fields(colliders, grid: Grid, dtype=None, band: float = 2.0) -> tuple[CollisionField | None, ...]:
    """The collision field of every collider (``None`` for planes, which stay analytic).

    A static collider's field lives on the simulation grid's own nodes (exact per-node
    look-ups); a moving one's on :func:`collider_lattice`, in its rest frame.
    """
    out = []
    for col in colliders:
        if not is_particle_wise(col):
            out.append(None)
        elif getattr(col, "moving", False):
            out.append(build_collision_field(col, collider_lattice(col, grid.dx, band), band, dtype=dtype))
        else:
            out.append(build_collision_field(col, grid, band, dtype=dtype))
    return tuple(out)


class BoundaryParticles(eqx.Module):
    """Rigid boundary particles of one collider (the ``"particles"`` collision mode).

    Attributes:
        x: rest-frame positions sampled on the surface, ``(M, D)``, metres.
        name: the collider's name (static).
    """

    x: Float[Array, "M D"]
    name: str = eqx.field(static=True)


def _sample_simplices(corners: np.ndarray, spacing: float) -> np.ndarray:
    """Points on triangles ``(F, 3, 3)`` or segments ``(F, 2, 2)`` at most ``spacing`` apart."""
    nv = corners.shape[1]
    edges = [np.linalg.norm(corners[:, (k + 1) % nv] - corners[:, k], axis=-1) for k in range(nv)]
    n_sub = np.maximum(np.ceil(np.max(edges, axis=0) / spacing).astype(int), 1)
    points = []
    for n in np.unique(n_sub):
        c = corners[n_sub == n]
        if nv == 2:
            t = np.linspace(0.0, 1.0, n + 1)
            points.append((c[:, None, 0] * (1 - t)[None, :, None] + c[:, None, 1] * t[None, :, None]).reshape(-1, 2))
        else:
            i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
            keep = i + j <= n
            u, v = i[keep] / n, j[keep] / n
            w = np.stack([1 - u - v, u, v], axis=-1)  # (S, 3)
            points.append(np.einsum("sk,fkd->fsd", w, c).reshape(-1, 3))
    return np.unique(np.round(np.concatenate(points), 12), axis=0)


def _box_surface(col: Box) -> np.ndarray:
    """Corners of the box's faces as triangles (3D) or segments (2D), world frame at t = 0."""
    dim = col.dim
    he = col.half_extent
    r = np.asarray(col.rotation)
    if dim == 2:
        sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * he
        segs = np.stack([sq, np.roll(sq, -1, axis=0)], axis=1)
        return segs @ r.T + col.center
    import trimesh

    tm = trimesh.creation.box(extents=2 * he)
    return np.asarray(tm.triangles) @ r.T + col.center


def sample_boundary(collider: Collider, spacing: float) -> np.ndarray:
    """Points on a collider's surface (rest frame), at most ``spacing`` apart (NumPy ``(M, D)``)."""
    if isinstance(collider, MeshCollider):
        v, f = np.asarray(collider.vertices), np.asarray(collider.faces)
        return _sample_simplices(v[f], spacing)
    if isinstance(collider, Box):
        return _sample_simplices(_box_surface(collider), spacing)
    if isinstance(collider, GaussianDisks):
        c, tan, sc = np.asarray(collider.centers), np.asarray(collider.tangents), np.asarray(collider.scales)
        out = []
        for k in range(len(c)):
            radius = collider.cutoff * sc[k]
            axes = [np.arange(-r, r + 1e-12, spacing) for r in radius]
            grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
            grid = grid[np.sum((grid / radius) ** 2, axis=-1) <= 1.0]
            out.append(c[k] + grid @ tan[k])
        return np.concatenate(out)
    raise TypeError(f"no boundary-particle sampler for {type(collider).__name__}")


def build_boundary(colliders, grid: Grid, dtype=None, spacing: float = 0.5) -> tuple[BoundaryParticles | None, ...]:
    """Boundary particles of every non-plane collider, ``spacing * dx`` apart (RP-DiffMPM)."""
    dtype = dtype or jnp.result_type(float)
    out = []
    for col in colliders:
        if not is_particle_wise(col):
            out.append(None)
            continue
        x = sample_boundary(col, spacing * grid.dx)
        out.append(BoundaryParticles(x=jnp.asarray(x, dtype), name=col.name))
    return tuple(out)


# ==========================================================================================
# Per-substep, particle-wise transfer (traced)
# ==========================================================================================


def _safe_normalize(v):
    n2 = row_dot(v, v)
    ok = n2 > 1e-24
    return v * jnp.where(ok, jax.lax.rsqrt(jnp.where(ok, n2, 1.0)), 0.0)[:, None]


def _lattice_lookup(field: CollisionField, table, X):
    """Nearest-node rows of ``table`` at rest-frame points ``X (M, D)``, with the node positions.

    Points outside the field's lattice get a zero row (no affinity). Both are constant between
    nodes (no derivative with respect to ``X``) and stored once: their consumers (the surface
    estimate's pairwise sums, and in reverse mode their transposes, per node) would otherwise
    re-derive each node's index from the particle's position, through the collider's motion,
    for every entry they write.
    """
    return compute_once(functools.partial(_nearest_rows, field), table, jax.lax.stop_gradient(X),
                        token=always_true(X))


def _nearest_rows(field: CollisionField, table, X):
    dtype = X.dtype
    origin = jnp.asarray(field.origin, dtype)
    shape = field.shape
    jf = jnp.round((X - origin) / field.dx)
    upper = jnp.asarray([n - 1 for n in shape], dtype)
    valid = jnp.all((jf >= 0) & (jf <= upper), axis=-1)
    ji = jnp.clip(jf, 0, upper).astype(jnp.int32)
    flat = flat_index(shape, ji)
    row = jnp.where(valid[:, None], table[flat], 0.0)  # rows [T·D, N]
    return row, origin + ji.astype(dtype) * field.dx


class Contact(eqx.Module):
    """What a substep knows about particles and the particle-wise colliders (CPIC).

    Per particle-wise collider ``c`` (the ``c``-th entry of ``index``):

    Attributes:
        tag: the updated persistent side tags of all colliders, ``(N, K)`` int8 (planes: 0).
        index: the model's collider index of each particle-wise collider (static).
        phi: signed distance on the particle's own side (``tag * phi``; negative =
            penetrated; 0 where the particle is not near), ``(N,)`` per collider.
        normal: unit normal pointing to the particle's own side, ``(N, D)`` per collider.
        incompatible: bit ``o`` set where stencil node ``o`` lies on the other side, ``(N,)``
            int32 per collider.
        owned: the incompatible bits attributed to collider ``c`` (those not already
            incompatible with an earlier collider), ``(N,)`` int32 per collider.
        any_incompatible: OR of ``incompatible``, ``(N,)`` int32.
        v_collider: collider surface velocity at the particle, ``(N, D)`` per collider.
    """

    tag: Int8[Array, "N K"]
    index: tuple[int, ...] = eqx.field(static=True)
    phi: tuple[Float[Array, " N"], ...]
    normal: tuple[Float[Array, "N D"], ...]
    incompatible: tuple[Int[Array, " N"], ...]
    owned: tuple[Int[Array, " N"], ...]
    any_incompatible: Int[Array, " N"]
    v_collider: tuple[Float[Array, "N D"], ...]

    def incompatible_mask(self) -> Bool[Array, "K N"]:
        """Whether each stencil node is incompatible with the particle (for any collider),
        ``(3^D, N)`` in the order of :func:`jaxmpm.state.stencil_offsets`."""
        return bit_mask(self.any_incompatible, 3 ** self.normal[0].shape[-1])

    def owned_mask(self, c: int) -> Bool[Array, "K N"]:
        """Whether each stencil node is an incompatible node attributed to collider ``c``, ``(3^D, N)``."""
        return bit_mask(self.owned[c], 3 ** self.normal[c].shape[-1])


def bit_mask(bits: Int[Array, " N"], count: int) -> Bool[Array, "K N"]:
    """Bits ``0 .. count - 1`` of every ``bits[n]``, ``(count, N)``."""
    shifts = jnp.arange(count, dtype=bits.dtype)[:, None]
    return jnp.bitwise_and(jnp.right_shift(bits[None, :], shifts), 1) > 0


class NodeSample(eqx.Module):
    """The ``K`` stencil or cell-corner nodes of every particle, as a collider's field sees
    them (stacked node-major: one whole-array operation treats every node).

    Attributes:
        weight: the nodes' interpolation weights for the particle, 0 where a node is not
            affine, ``(K, N)``.
        affine: whether each node is affine, ``(K, N)`` bool.
        node_sd: the nodes' signed distances (``+`` side), metres, ``(K, N)``.
        normal: the nodes' unit ``+`` normals (zero where not affine), ``(K, N, D)``.
        offset: ``x_node - x_p`` in the frame of ``normal``, metres, ``(K, N, D)``.
    """

    weight: Float[Array, "K N"]
    affine: Bool[Array, "K N"]
    node_sd: Float[Array, "K N"]
    normal: Float[Array, "K N D"]
    offset: Float[Array, "K N D"]


def _node_sample(weight, row, offset) -> NodeSample:
    """A :class:`NodeSample` from the nodes' packed field rows ``[side * distance, normal]``
    (``(K, N, 1 + D)``)."""
    nrm = row[..., 1:]
    affine = row_dot(nrm, nrm) > 0.5
    return NodeSample(jnp.where(affine, weight, 0.0), affine, row[..., 0], nrm, offset)


def surface_estimate(nodes: NodeSample, dx: float, opposed: bool = True):
    """The particle's signed distance and normal (``+`` side) from the affine nodes around it.

    Each affine node's signed distance is carried to the particle along its normal,
    ``c_i = s_i - N_i·(x_i - x_p)`` (exact for a planar face) and averaged with the nodes'
    weights; the normal is the normalised weighted sum of the nodes' normals.

    Where the field has opposed faces (``opposed``: thin fields and moving colliders), nodes
    whose normal is opposed to that of the *reference* face (:data:`OPPOSED_COS`) are left
    out. The reference is the nearest face the particle is in front of
    (smallest ``c >= 0``) or, where it lies behind every face's plane (penetrated), the face it
    penetrated least deeply (largest ``c < 0``). Beside a solid thinner than the stencil the
    nodes past it belong to its far face, whose plane the particle lies behind (their carried
    value is minus the particle's distance through the solid): averaging them in gave a wrong
    side, a normal near zero and a penetration the particle did not have. In a crease, whose
    two walls face each other, both carry values ``>= 0`` and the nearer wall is the one the
    particle may cross (ranking the largest first took the farther wall: sand went 0.29 dx into
    the scaled bunny instead of 0.17 dx). A particle that has crossed one wall of a crease
    lies behind that wall and in front of the other, which is no evidence that it is outside:
    the walls face each other (:func:`concave_share`), the solid is the union of the two
    half-spaces, so the wall it is behind competes by its distance ``-c`` as if in front
    (with the facing wall ranked first, a sand particle 0.02 dx inside the bunny was measured
    from a face 1.1 dx away, with that face's normal, and pushed 0.49 dx into the solid in one
    substep; session 40).

    The choice ranks faces, not single nodes (a node of negligible weight, whose carried value
    is the least accurate, chose the face alone before). Node ``i`` proposes its face: the
    weighted mean ``f_i`` of the values carried by the nodes whose normals are near its own
    (:func:`same_face_fraction`). The face ranks by ``key_i = -f_i`` (``f_i >= 0``) or
    ``max(BEHIND_SLOPE f_i, f_i - BEHIND_DROP dx)`` (``f_i < 0``: below every face in front
    within 5 cells, then the largest first), blended towards ``f_i`` by the face's concave
    share, and is the reference with probability ``p_i ∝
    w_i exp(key_i / (REFERENCE_TEMPERATURE dx))`` (a node of zero weight has no say); node ``j``
    then keeps the share ``sum_i p_i [N_i·N_j >= OPPOSED_COS]`` of its weight (a test between
    two nodes' fixed normals: only the ``p_i`` move with the particle). At the temperature used
    (a hundredth of a cell) the estimate moves continuously where the ranking switches between
    two faces. The shares ``p_i`` carry no derivative: the tangents and cotangents are those
    of the estimate with its faces fixed. (The shares' own slope, ~1/temperature per cell, made
    forward-mode Jacobians spike, to 1e17 at the earlier 1e-4 cells, and fits stop at false
    floors; docs/benchmark_sysid.md, sessions 20 and 32.)

    Arguments:
        nodes: the particle's nodes, ``K`` of them.
        dx: the grid spacing, metres.
        opposed: whether opposed faces can be among the nodes (static); without them nothing
            is left out and no reference is needed.

    Returns:
        ``phi (N,)`` (``+2 dx`` where no node is affine), ``normal (N, D)`` (``+`` side),
        whether some node has weight ``(N,)`` bool.
    """
    carried = nodes.node_sd - row_dot(nodes.normal, nodes.offset)  # (K, N)
    w = nodes.weight
    if opposed:
        # The pairwise terms are summed one partner node at a time, each a (K, N) array: the
        # (K, K, N) cosines (73 MB at 25k particles in 3D) were stored and read three times.
        cos = [row_dot(nodes.normal, n_j) for n_j in node_rows(nodes.normal)]  # [j][i, n], symmetric
        same = [same_face_fraction(c) for c in cos]  # how much node j counts on node i's face
        sums = (symmetric_pair_sum(same, w * carried), symmetric_pair_sum(same, w))
        if w.shape[0] >= _STORED_PAIR_SUMS:
            # stored once (in forward mode with their tangents): the ratio's tangent re-derived
            # both, K^2 pair terms, for each tangent and entry (a moving collider's 3-tangent
            # Jacobian: contact stage 99 -> 66 CPU ms per step). Over the 8 cell corners storing
            # them costs more (the tangents' layout changes; the bunny's contact 20 -> 33 ms).
            sums = materialize(sums, always_true(nodes.affine))
        face = materialize(_safe_ratio(*sums), always_true(nodes.affine))  # read by key's two branches
        behind = jnp.maximum(BEHIND_SLOPE * face, face - BEHIND_DROP * dx)
        # behind a face of a concave pair the particle is inside: that face competes by distance
        # (computed once, from values without tangents: it only ranks the faces)
        concave = compute_once(functools.partial(concave_share, dx=dx), *jax.lax.stop_gradient((nodes, face, same)),
                               token=always_true(nodes.affine))
        behind = behind + concave * (face - behind)
        key = jnp.where(face >= 0, -face, behind) / (REFERENCE_TEMPERATURE * dx)
        live = nodes.affine & (w > 0) & jnp.isfinite(key)
        top = jax.lax.stop_gradient(jnp.max(jnp.where(live, key, -jnp.inf), axis=0))
        p = jnp.where(live, w * jnp.exp(jnp.where(live, key - top, 0.0)), 0.0)  # (K, N), unnormalised
        # stored once (in forward mode with its tangents): the sum below would otherwise re-derive
        # every p_i, through the pairwise face sums, for each node j (on the bunny's thin field
        # the contact stage's 3-tangent Jacobian cost 16-18x its step; docs/benchmarks.md)
        p = materialize(_safe_ratio(p, jnp.sum(p, axis=0)), always_true(nodes.affine))
        # the choice carries no derivative: near a tie its slope is ~1 / REFERENCE_TEMPERATURE
        # times any other's (at 1e-4 cells a normal's tangent of 1e6 per unit of a fitted
        # parameter, where the branch has ~1), so a Jacobian taken there was a spike that
        # stopped fits at false floors
        p = jax.lax.stop_gradient(p)
        # node j keeps sum_i p_i [N_i.N_j >= OPPOSED_COS]; cos[i][j] = N_i.N_j. The share is
        # stored once (with its tangents): w's tangent re-derived it, and p, per tangent
        share = symmetric_pair_sum([(c >= OPPOSED_COS).astype(w.dtype) for c in cos], p)
        w = w * materialize(share, always_true(nodes.affine))
    # the sums over the nodes as adds (XLA's CPU backend hands a reduction over them to YNNPACK)
    w_rows = node_rows(w)
    sw = sum(w_rows)[0]
    sphi = sum(w_i * c_i for w_i, c_i in zip(w_rows, node_rows(carried)))[0]
    snrm = sum(scale_rows(w_i, n_i) for w_i, n_i in zip(w_rows, node_rows(nodes.normal)))[0]
    # stored once: in reverse mode each node's weight cotangent reads them (the sum over the
    # nodes was re-derived in each of the nodes' transposes)
    sw, sphi, snrm = materialize((sw, sphi, snrm), always_true(nodes.affine))
    near = sw > 0
    return jnp.where(near, _safe_ratio(sphi, sw), 2.0 * dx), _safe_normalize(snrm), near


#: From how many nodes the surface estimate stores its pairwise face sums (the 3^3 stencil
#: nodes of a moving collider; not the 2^D cell corners of a static field).
_STORED_PAIR_SUMS = 27


def concave_share(nodes: NodeSample, face, same: list[Array], dx: float):
    """How much each node's face forms a *concave* pair with a face the particle is in front
    of, ``(K, N)`` in [0, 1] (it only ranks the faces: :func:`surface_estimate` passes values
    without derivatives).

    Node ``i``'s surface point ``q_i = x_i - s_i N_i`` (exact: its nearest surface point) lies
    in front of node ``j``'s face by ``f_j + N_j·(q_i - x_p)`` (the face's plane carried to
    ``q_i``). Where a face the particle is in front of (``f_i >= 0``, a node with weight)
    lies in front of ``j``'s face, the two face each other: a crease, where the solid is the
    *union* of the half-spaces behind them, so a particle behind ``j``'s plane is inside
    the solid through ``j``. At a convex edge, or across a solid thinner than the stencil,
    the face in front lies behind ``j``'s plane (the solid is their *intersection*) and the
    particle behind ``j``'s plane is outside. The share ramps from 0 to 1 over
    :data:`CONCAVE_RAMP` cells of that distance (the maximum over the partner nodes, other
    faces only: :func:`same_face_fraction`).
    """
    reach = nodes.offset - nodes.node_sd[..., None] * nodes.normal  # q_i - x_p (K, N, D)
    front = nodes.affine & (nodes.weight > 0) & (face >= 0)
    share = jnp.zeros_like(face)
    for i, (r_i, front_i) in enumerate(zip(node_rows(reach), node_rows(front))):
        ahead = face + row_dot(nodes.normal, r_i)  # (K, N): q_i against each node's face
        pair = jnp.clip(ahead / (CONCAVE_RAMP * dx), 0.0, 1.0) * (1.0 - same[i])
        share = jnp.maximum(share, jnp.where(front_i, pair, 0.0))
    return share


def node_rows(x: Array) -> list[Array]:
    """The ``K`` rows ``x[k:k + 1]`` of a node-major array ``(K, ...)``, each ``(1, ...)``, as one
    split: reverse mode gathers their cotangents with one concatenation, where indexing
    ``x[k]`` transposes into a zero-padded ``(K, ...)`` array per row, summed (``K^2``
    entries: in the surface estimate's backward pass on a moving collider, 27 sums of 27
    padded arrays, re-derived in each of their 27 consumers)."""
    return jnp.split(x, x.shape[0], axis=0)


def _safe_ratio(a, b):
    """``a / b`` where ``b > 0``, else 0, with finite tangents and cotangents everywhere."""
    ok = b > 0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def same_face_fraction(cos):
    """How much a node whose unit normal makes cosine ``cos`` with another's counts as on the
    same face (:func:`surface_estimate`'s ranking): 0 up to :data:`SAME_FACE_COS`, 1 from
    ``SAME_FACE_COS + SAME_FACE_RAMP``, linear between."""
    return jnp.clip((cos - SAME_FACE_COS) / SAME_FACE_RAMP, 0.0, 1.0)


def side_bits(nodes: NodeSample, phi, normal):
    """Per particle, bit ``o`` (stencil node ``o``) set where the node is affine on the ``+``
    side, on the ``-`` side, and where it is an *opposed* node (its normal opposed to the
    particle's, :data:`OPPOSED_COS`) lying behind / in front of the particle's surface (the
    plane of signed distance ``phi`` and ``+`` normal ``normal``): four ``(N,)`` int32.

    A node behind the surface a particle is near belongs to the collider for that particle,
    whatever its own side: below a plate thinner than the stencil the nodes are on the
    plate's outside like the nodes above, and only the surface the particle is near tells
    them apart.
    """
    affine = nodes.affine
    opposed = affine & (row_dot(nodes.normal, normal[None]) < OPPOSED_COS)
    ahead = phi[None] + row_dot(normal[None], nodes.offset)
    flags = (affine & (nodes.node_sd > 0), affine & (nodes.node_sd <= 0), opposed & (ahead < 0), opposed & (ahead > 0))
    # node o's flag as bit o, OR-ed over the nodes with elementwise ops (a reduction over the
    # node axis is a slow loop on XLA's CPU backend)
    def bits(f):
        return functools.reduce(jnp.bitwise_or, [jnp.left_shift(f[o].astype(jnp.int32), o) for o in range(f.shape[0])])

    return tuple(bits(f) for f in flags)


def _corner_lookup(grid: Grid, table, x, opposed: bool):
    """Signed distance and normal at ``x`` from the ``2^D`` corners of its cell (multilinear
    weights, :func:`surface_estimate`; ``opposed``: the field is thin).

    Returns:
        ``phi (N,)`` (``+2 dx`` where no corner is affine), ``normal (N, D)`` (``+`` side), and
        whether some corner is affine (``phi`` is meaningful), ``(N,)`` bool.
    """
    dtype = x.dtype
    xi = (x - jnp.asarray(grid.origin, dtype)) / grid.dx
    cell = jnp.clip(jnp.floor(xi), 0, jnp.asarray(grid.shape, dtype) - 2)
    f = xi - cell
    base = cell.astype(jnp.int32)
    corners = np.asarray(_corners(x.shape[1]), np.int32)  # (K, D)
    idx = node_indices(grid.shape, base, corners)
    on = jnp.asarray(corners, bool)[:, None, :]
    fk = spread(f, len(corners))  # (K, N, D)
    w = jnp.prod(jnp.where(on, fk, 1.0 - fk), axis=-1)
    offset = grid.dx * (jnp.asarray(corners, dtype)[:, None, :] - fk)
    rows = jnp.stack(gather_rows(table, list(idx)))  # (K, N, 1 + D); cells are clipped into the grid
    return materialize(surface_estimate(_node_sample(w, rows, offset), grid.dx, opposed), jnp.isfinite(x[0, 0]))


def _corners(dim: int):
    return tuple(itertools.product((0, 1), repeat=dim))


def _stencil_lookup(grid: Grid, st: Stencil, x, table):
    """Side bits of the 3^D stencil nodes (:func:`side_bits`) of a static field on the
    simulation grid, and the particle's signed distance, normal and whether it is measured
    (from its cell's corners, :func:`_corner_lookup`, as for every static field). Used for thin
    fields, whose opposed nodes are told apart by the particle's surface."""
    phi, nrm, near = _corner_lookup(grid, table, x, opposed=True)
    _, weight, dpos = stencil_terms(grid, st)
    rows = jnp.stack(gather_rows(table, stencil_index(grid, st)))  # (K, N, 1 + D), as the G2P gather
    return side_bits(_node_sample(weight, rows, grid.dx * dpos), phi, nrm), phi, nrm, near


def _moving_lookup(grid: Grid, st: Stencil, x, field: CollisionField, table, collider, time):
    """Side bits of the (world) stencil nodes (:func:`side_bits`) and the particle's signed
    distance, normal and whether it is measured, for a moving collider: each stencil node is
    looked up in the collider's rest frame at ``R(t)^T (x_i - c(t)) + c0`` (nearest lattice
    node ``j`` plus the first-order correction ``N_j·(X - X_j)``, so sides move continuously
    with the collider)."""
    dx = grid.dx
    # stored once (a few numbers, with their tangents): the offsets' tangent re-derived the
    # rotation's from the time's for every node and entry (45 CPU ms per step at 3 tangents)
    c, rot = materialize(rigid_transform(collider, time, x.dtype), always_true(st.base))
    pivot = jnp.asarray(collider.pivot, x.dtype)
    _, weight, dpos = stencil_terms(grid, st)
    count = weight.shape[0]
    Xp = spread(pivot + rows_times(x - c, rot), count)  # the particle in the rest frame, per node (K, N, D)
    offset = rows_times(dx * dpos, rot)  # X_i - X_p (K, N, D)
    row, Xj = _lattice_lookup(field, table, (Xp + offset).reshape(-1, x.shape[-1]))
    row, Xj = row.reshape(offset.shape[:2] + row.shape[-1:]), Xj.reshape(offset.shape)
    sample = _node_sample(weight, row, offset)
    sample = eqx.tree_at(lambda s: s.node_sd, sample, row[..., 0] + row_dot(sample.normal, Xp + offset - Xj))
    # stored once: the surface estimate's pairwise sums (and in reverse mode their transposes,
    # one per node) would otherwise each re-derive every node's rest-frame offset and distance
    nodes = materialize(sample, always_true(row))
    # stored once, as in _corner_lookup: the side bits below, and the tags made from them, read
    # phi and the normal for every stencil node
    phi, nrm, near = materialize(surface_estimate(nodes, dx), always_true(row))
    return side_bits(nodes, phi, nrm), phi, rows_times(nrm, rot.T), near


def gather_contact(
    grid: Grid,
    st: Stencil,
    x: Float[Array, "N D"],
    tag: Int8[Array, "N K"],
    time: Float[Array, ""],
    colliders,
    fields,
) -> Contact | None:
    """Particle-wise collider data of one substep: sides of the stencil nodes, signed
    distance, normal, persistent tags, compatibility bits.

    * **Sides of the stencil nodes**: for a static collider one gather of the precomputed
      :attr:`CollisionField.stencil_bits` at the particle's lowest stencil node gives the
      side of all 3^D stencil nodes (0 = not affine). A particle is *near* a collider when
      some stencil node is affine.
    * **Signed distance and normal** of the particle (``+`` side): from the affine corners
      of its cell, each corner's signed distance carried to the particle along its normal
      (exact for planar surfaces) and averaged with multilinear weights, leaving out the
      nodes of an opposed face (:func:`surface_estimate`).
    * **Persistent tag**: acquired as ``sign(phi)`` when the particle first comes near (and
      ``phi`` is measured: some cell corner affine), kept while it stays near (this is what
      stops tunnelling: a particle pushed slightly through the surface keeps its side) and
      cleared when it leaves the band.
    * **Compatibility**: a stencil node is incompatible when it is affine and on the side
      opposite to the particle's tag, or (thin fields, moving colliders) when its normal is
      opposed to the particle's and it lies behind the particle's own surface
      (:func:`side_bits`): the nodes past a plate thinner than the stencil.

    Thin static fields (:attr:`CollisionField.thin`) and moving colliders read all 3^D
    stencil nodes (moving ones in their rest frame, ``_moving_lookup``, normals rotated back
    to the world, where the stencil's weights also give the particle's signed distance).

    Returns:
        A :class:`Contact`, or ``None`` when no collider is particle-wise.
    """
    index = tuple(k for k, f in enumerate(fields) if f is not None)
    if not index:
        return None
    dtype = x.dtype
    n = x.shape[0]
    base = flat_index(grid.shape, st.base)
    new_tag = jax.lax.stop_gradient(tag)
    phis, normals, incs, owned, vcs = [], [], [], [], []
    any_inc = jnp.zeros((n,), jnp.int32)
    for k in index:
        col, field = colliders[k], fields[k]
        table = field.rows.astype(dtype)
        moving = bool(getattr(col, "moving", False))
        behind = ahead = None
        if moving or not field.on_grid(grid):
            (plus, minus, behind, ahead), phi, nrm, measured = _moving_lookup(grid, st, x, field, table, col, time)
        elif field.thin:
            (plus, minus, behind, ahead), phi, nrm, measured = _stencil_lookup(grid, st, x, table)
        else:
            bits = field.stencil_bits[base]
            plus, minus = bits[:, 0], bits[:, 1]
            phi, nrm, measured = _corner_lookup(grid, table, x, opposed=False)
        near = (plus | minus) != 0
        old = new_tag[:, k]
        # acquire a side only where phi is measured (some cell corner affine: always the case
        # within 1.5 dx of the surface, i.e. before any stencil node can be on the other side)
        acquired = jnp.where(measured, jnp.where(jax.lax.stop_gradient(phi) >= 0, 1, -1), 0).astype(jnp.int8)
        t = jnp.where(near, jnp.where(old != 0, old, acquired), 0).astype(jnp.int8)
        new_tag = new_tag.at[:, k].set(t)
        tf = t.astype(dtype)
        inc = jnp.where(t > 0, minus, jnp.where(t < 0, plus, 0))
        if behind is not None:  # opposed nodes behind the particle's own surface
            inc = inc | jnp.where(t > 0, behind, jnp.where(t < 0, ahead, 0))
        phis.append(tf * phi)
        normals.append(tf[:, None] * nrm)
        incs.append(inc)
        owned.append(inc & ~any_inc)
        any_inc = any_inc | inc
        vcs.append(col.velocity_at(x, time) if moving else jnp.zeros_like(x))
    stop = jax.lax.stop_gradient
    contact = Contact(
        tag=stop(new_tag),
        index=index,
        phi=tuple(phis),
        normal=tuple(normals),
        incompatible=tuple(stop(i) for i in incs),
        owned=tuple(stop(i) for i in owned),
        any_incompatible=stop(any_inc),
        v_collider=tuple(vcs),
    )
    return materialize(contact, jnp.isfinite(time))


#: Floor of the incompatible-node weight ``W`` a ghost velocity is divided by (of a stencil's
#: total weight 1): below it the ghost's mean offset fades to zero, keeping its tangent finite.
GHOST_WEIGHT_MIN = 1e-6


def ghost_mean_offset(moment: Float[Array, "N D"], weight: Float[Array, " N"], dx: float) -> Float[Array, "N D"]:
    """``M / W`` (m): the weighted mean offset ``x_i - x_p`` of a particle's incompatible nodes,
    from ``moment = M / dx`` (cells) and ``weight = W``.

    ``W`` is floored at :data:`GHOST_WEIGHT_MIN`: where a stencil barely reaches the collider's
    nodes (``W`` ~ 1e-20 happens) the offset fades to zero instead of dividing by ``W``, whose
    square underflows in float32 and made the forward-mode tangent NaN while the value stayed
    finite. The nodes concerned carry less than 1e-6 of the particle's mass.
    """
    return (dx * moment) / jnp.maximum(weight, GHOST_WEIGHT_MIN)[:, None]


class GhostNodes(eqx.Module):
    """The velocity G2P reads from a particle's incompatible nodes (CPIC's "fake" velocity).

    Nodes on the other side of a collider belong, for this particle, to the collider. Had
    they been ordinary nodes they would have received only this particle's contribution
    ``w_i (m u + A (x_i - x_p))`` (``u = v_p + dt g``, ``A`` the MLS affine/stress matrix).
    Their mean velocity ``g = u + (A/m) M / W`` (``W = sum w_i``, ``M = sum w_i (x_i - x_p)``
    over the incompatible nodes of collider ``c``; ``M / W`` by :func:`ghost_mean_offset`) is
    the particle's velocity against the collider *including the push of its own stress*; it
    is projected once per particle and collider — Coulomb friction mu_b, restitution ``e``
    on the particle's own approach speed, relative to the collider's velocity — and every
    incompatible node of ``c`` reads the projected velocity ``P = proj(g)`` (as TM's CPIC
    reads a fake velocity built from the particle's own). The collider's impulse on the particle is ``m W (P - g)``: it lies in the
    friction cone of the particle's whole normal reaction, stress included, so a body sliding
    on a collider obeys ``a = g (sin θ - mu cos θ)`` and stops when ``tan θ < mu``.

    Attributes:
        contact: the substep's :class:`Contact`.
        u: ``v_p + dt g``, ``(N, D)``.
        B: ``A_p / m_p`` (APIC + stress), ``(N, D, D)``.
        weight, moment: per collider, ``W`` and ``M / dx`` (cells) of its incompatible nodes
            (:func:`incompatible_moments`).
        friction, restitution: per particle-wise collider, scalars (differentiable).
        kinds: per particle-wise collider, its ``contact`` (static).
    """

    contact: Contact
    u: Float[Array, "N D"]
    B: Float[Array, "N D D"]
    weight: tuple[Float[Array, " N"], ...]
    moment: tuple[Float[Array, "N D"], ...]
    friction: tuple[Float[Array, ""], ...]
    restitution: tuple[Float[Array, ""], ...]
    kinds: tuple[str, ...] = eqx.field(static=True)

    def projected(self, c: int, dx: float) -> Float[Array, "N D"]:
        """``P = proj(u + B M / W)`` for collider ``c``."""
        ct = self.contact
        mean = ghost_mean_offset(self.moment[c], self.weight[c], dx)
        g = self.u + row_matvec(self.B, mean)
        n, vc = ct.normal[c], ct.v_collider[c]
        kind = self.kinds[c]
        out = project_velocity(g, n, kind, friction=self.friction[c], restitution=0.0, v_collider=vc)
        if kind != "sticky":
            approach = row_dot(self.u - vc, n, keepdims=True)
            out = out + self.restitution[c] * jnp.maximum(-approach, 0.0) * n
        return out


def incompatible_moments(st: Stencil, contact: Contact):
    """Per collider, the total stencil weight ``W`` of its incompatible nodes and their first
    moment ``sum w_i (x_i - x_p) / dx`` (cells), from the bits and the stencil weights only
    (no gathers, so the 3^D terms fuse into one pass)."""
    weights, moments = [], []
    dim = st.dim
    for c in range(len(contact.index)):
        owned = contact.owned_mask(c)
        w_sum = jnp.zeros_like(st.fx[0])
        m_sum = [jnp.zeros_like(st.fx[0]) for _ in range(dim)]
        for o, offset in enumerate(stencil_offsets(dim)):
            w = jnp.where(owned[o], offset_weight(st, offset), 0.0)
            w_sum = w_sum + w
            m_sum = [m + w * (k - f) for m, k, f in zip(m_sum, offset, st.fx)]
        weights.append(w_sum)
        moments.append(jnp.stack(m_sum, axis=-1))
    return materialize((tuple(weights), tuple(moments)), jnp.isfinite(st.fx[0][0]))


def _smooth_relu(z, width):
    """0 for z <= 0, z^2 / (2 width) up to ``width``, then z - width / 2 (C1, compact support)."""
    zc = jnp.clip(z, 0.0, width)
    return zc * zc / (2.0 * width) + jnp.maximum(z - width, 0.0)


def penetration_correction(
    contact: Contact, v: Float[Array, "N D"], dt: float, dx: float, strength: float
) -> Float[Array, "N D"]:
    """Displacement that pushes penetrated particles back to their own side.

    The signed distance after this substep's move is predicted to first order,
    ``phi' = phi + dt (v - v_c)·n``; where it is negative the particle is moved back by
    ``strength · smooth_relu(-phi')`` along its own normal (C1 in the depth, zero for any
    particle that is not penetrated). It is a position correction applied with the
    advection (it does not change the particle's velocity, so it injects no energy).
    """
    disp = jnp.zeros_like(v)
    for c in range(len(contact.index)):
        n = contact.normal[c]
        predicted = contact.phi[c] + dt * row_dot(v - contact.v_collider[c], n)
        depth = _smooth_relu(-predicted, 0.05 * dx)
        disp = disp + (strength * depth)[:, None] * n
    return disp


# ------------------------------------------------------------------------------------------
# Grid-level (GOP) look-up and boundary particles at time t
# ------------------------------------------------------------------------------------------


def closed_surface(collider: Collider) -> bool:
    """Whether a collider bounds a solid (its ``-`` side is inside)."""
    if isinstance(collider, MeshCollider):
        return bool(collider.closed)
    return isinstance(collider, Box)


def node_signed_distance(
    field: CollisionField, collider: Collider, grid: Grid, nodes: Float[Array, "G D"], time
) -> tuple[Float[Array, " G"], Float[Array, "G D"]]:
    """Signed distance and ``+`` normal of a collider at the grid nodes, from its field.

    Closed solids: ``side * distance`` (negative inside). Open surfaces (a bowl, a sheet,
    disks) have no inside: their distance is unsigned, so a grid-level condition only sees
    nodes lying on them. Nodes outside the band: ``+band``.
    """
    dtype = nodes.dtype
    table = field.rows.astype(dtype)
    closed = closed_surface(collider)
    if not getattr(collider, "moving", False) and field.on_grid(grid):
        sd, nrm = table[:, 0], table[:, 1:]
        affine = field.affinity
    else:
        c, rot = rigid_transform(collider, time, dtype)
        pivot = jnp.asarray(collider.pivot, dtype)
        X = pivot + rows_times(nodes - c, rot)
        row, Xj = _lattice_lookup(field, table, X)
        nrm = row[:, 1:]
        sd = row[:, 0] + row_dot(nrm, X - Xj)
        affine = row_dot(nrm, nrm) > 0.5
        nrm = rows_times(nrm, rot.T)
    sd = sd if closed else jnp.abs(sd)
    return jnp.where(affine, sd, field.band_width), nrm


def boundary_positions(boundary: BoundaryParticles, collider: Collider, time):
    """World positions and velocities of a collider's boundary particles at ``time``."""
    X = boundary.x
    if not getattr(collider, "moving", False):
        return X, jnp.zeros_like(X)
    c, rot = rigid_transform(collider, time, X.dtype)
    x = c + rows_times(X - jnp.asarray(collider.pivot, X.dtype), rot.T)
    return x, collider.velocity_at(x, time)
