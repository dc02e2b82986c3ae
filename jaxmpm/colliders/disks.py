"""Sets of 2D Gaussian surfels (planar elliptical disks) as a collision surface."""

from __future__ import annotations

from typing import Callable, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import SceneError
from .base import RigidCollider, StaticArray, init_motion, safe_normalize_np

def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions ``(w, x, y, z)`` (normalised here), ``(K, 3, 3)``."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def _any_perpendicular(n: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit row of ``n`` (3D)."""
    ref = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    return safe_normalize_np(np.cross(n, ref))


def orient_normals(centers, normals, k: int = 10, weights=None) -> np.ndarray:
    """Make sign-ambiguous surfel normals consistent (Hoppe et al. 1992 style).

    Builds a symmetric k-nearest-neighbour graph on the centres with edge cost
    ``1 - |n_i . n_j| + |e_ij . n_i| + |e_ij . n_j|`` (``e_ij`` the unit vector between the
    centres: the last two terms steer the propagation along the surface rather than across
    two close sheets), takes its minimum spanning tree, and propagates the sign along it so
    that neighbours agree (``n_i . n_j >= 0``). Each connected piece is then flipped as a
    whole if needed so that ``sum_k w_k (c_k - c) . n_k >= 0`` (``c`` the piece's centroid,
    ``w`` the weights, e.g. disk areas) — outward for closed shapes (the sum is 3x the enclosed
    volume); for an open piece this picks the side facing away from its centroid.

    Returns:
        The re-signed normals, ``(K, D)`` (NumPy).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.spatial import cKDTree

    x = np.asarray(centers, float)
    n = safe_normalize_np(np.asarray(normals, float))
    kk = len(x)
    w = np.ones(kk) if weights is None else np.asarray(weights, float)
    sign = np.ones(kk)
    if kk > 1:
        nb = min(k + 1, kk)
        _, idx = cKDTree(x).query(x, nb)
        rows = np.repeat(np.arange(kk), nb - 1)
        cols = idx[:, 1:].reshape(-1)
        keep = rows != cols
        rows, cols = rows[keep], cols[keep]
        lo_, hi_ = np.minimum(rows, cols), np.maximum(rows, cols)
        pairs = np.unique(np.stack([lo_, hi_], axis=1), axis=0)
        i, j = pairs[:, 0], pairs[:, 1]
        e = safe_normalize_np(x[j] - x[i])
        cost = (
            1.0
            - np.abs(np.sum(n[i] * n[j], -1))
            + np.abs(np.sum(e * n[i], -1))
            + np.abs(np.sum(e * n[j], -1))
            + 1e-6
        )
        graph = coo_matrix((cost, (i, j)), shape=(kk, kk)).tocsr()
        tree = minimum_spanning_tree(graph)
        tree = tree + tree.T
        ncomp, labels = connected_components(tree, directed=False)
        parent = np.arange(kk)
        for comp in range(ncomp):
            root = int(np.flatnonzero(labels == comp)[0])
            _, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
            members = pred >= 0
            parent[members] = pred[members]
        rel = np.where(np.sum(n * n[parent], -1) >= 0, 1.0, -1.0)
        rel[parent == np.arange(kk)] = 1.0
        # Product of relative signs up to the root, by pointer jumping.
        acc, anc = rel.copy(), parent.copy()
        while np.any(anc[anc] != anc):
            acc = acc * acc[anc]
            anc = anc[anc]
        sign = acc
    else:
        labels = np.zeros(1, int)
        ncomp = 1
    n = n * sign[:, None]
    for comp in range(int(np.max(labels)) + 1):
        sel = labels == comp
        c = np.average(x[sel], axis=0, weights=w[sel])
        if np.sum(w[sel] * np.sum((x[sel] - c) * n[sel], -1)) < 0:
            n[sel] = -n[sel]
    return n



class GaussianDisks(RigidCollider):
    """A set of 2D Gaussian surfels (planar elliptical disks) used as a collision surface.

    Disk k has centre ``c_k``, unit normal ``n_k`` (its ``+`` side), tangent axes
    ``t_k1, t_k2`` with standard deviations ``s_k1, s_k2`` (2D: one tangent), and opacity
    ``o_k``. A point belongs to the disk's footprint when
    ``sum_j ((x - c_k) . t_kj / s_kj)^2 <= cutoff^2``. Disks with ``o_k < min_opacity`` are
    dropped. Normals are made consistent on construction (``orient``): ``"knn"`` (default,
    :func:`orient_normals`: minimum-spanning-tree propagation over a k-NN graph, each piece then
    facing away from its centroid, i.e. outward for closed shapes), ``"centroid"`` (each disk
    independently faces away from the centroid of all centres; for star-shaped closed shapes)
    or ``"none"`` (trust the given signs). ``flip`` reverses all normals afterwards.

    Attributes:
        centers ``(K, D)``, normals ``(K, D)``, tangents ``(K, D-1, D)``, scales ``(K, D-1)``,
        opacity ``(K,)``: :class:`StaticArray`.
        cutoff: footprint radius in standard deviations.
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    centers: StaticArray = eqx.field(static=True)
    normals: StaticArray = eqx.field(static=True)
    tangents: StaticArray = eqx.field(static=True)
    scales: StaticArray = eqx.field(static=True)
    opacity: StaticArray = eqx.field(static=True)
    cutoff: float = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "disks"

    def __init__(
        self,
        centers,
        normals=None,
        scales=None,
        tangents=None,
        opacity=None,
        rotations=None,
        cutoff: float = 3.0,
        min_opacity: float = 0.05,
        orient: str = "knn",
        flip: bool = False,
        contact: str = "sticky",
        name: str = "disks",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        c = np.asarray(centers, float)
        if c.ndim != 2 or c.shape[1] not in (2, 3) or len(c) == 0:
            raise SceneError(f"collider {name!r}: 'centers' must be a non-empty (K, 2) or (K, 3) array, got {c.shape}")
        kk, dim = c.shape
        if not np.all(np.isfinite(c)):
            raise SceneError(f"collider {name!r}: disk centres contain NaN or infinite values")
        if rotations is not None:
            if dim != 3:
                raise SceneError(f"collider {name!r}: 'rotations' are for 3D disks")
            q = np.asarray(rotations, float).reshape(kk, 4)
            qn = np.linalg.norm(q, axis=-1)
            if not np.all(np.isfinite(qn)) or np.any(qn < 1e-12):
                bad = int(np.flatnonzero(~(qn >= 1e-12))[0])
                raise SceneError(f"collider {name!r}: disk {bad} has a zero rotation quaternion (no normal)")
            r = quaternion_to_matrix(q)
            n, t1 = r[:, :, 2], r[:, :, 0]
        else:
            if normals is None:
                raise SceneError(f"collider {name!r}: disks need 'normals' (or 'rotations')")
            n = np.asarray(normals, float).reshape(kk, dim)
            t1 = None if tangents is None else np.asarray(tangents, float).reshape(kk, dim)
        nn = np.linalg.norm(n, axis=-1)
        bad = ~(np.isfinite(nn) & (nn > 1e-12))
        if np.any(bad):
            first = int(np.flatnonzero(bad)[0])
            raise SceneError(
                f"collider {name!r}: {int(bad.sum())} disk(s) have zero or invalid normals (first: disk {first})"
            )
        n = n / nn[:, None]
        if scales is None:
            raise SceneError(f"collider {name!r}: disks need 'scales'")
        s = np.asarray(scales, float)
        s = s.reshape(kk, -1)
        if s.shape[1] == 1:
            s = np.repeat(s, dim - 1, axis=1)
        if s.shape[1] != dim - 1:
            raise SceneError(f"collider {name!r}: 'scales' must be (K,) or (K, {dim - 1}), got {np.shape(scales)}")
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise SceneError(f"collider {name!r}: disk scales must be positive and finite")
        o = np.ones(kk) if opacity is None else np.asarray(opacity, float).reshape(kk)
        if not np.all(np.isfinite(o)):
            raise SceneError(f"collider {name!r}: disk opacity contains NaN")
        if not (np.isfinite(cutoff) and cutoff > 0):
            raise SceneError(f"collider {name!r}: 'cutoff' must be positive, got {cutoff}")
        keep = o >= min_opacity
        if not np.any(keep):
            raise SceneError(f"collider {name!r}: every disk has opacity below min_opacity={min_opacity}")
        c, n, s, o = c[keep], n[keep], s[keep], o[keep]
        t1 = None if t1 is None else t1[keep]
        if orient == "knn":
            n = orient_normals(c, n, weights=np.prod(s, axis=1))
        elif orient == "centroid":
            n = n * np.where(np.sum((c - c.mean(axis=0)) * n, -1) >= 0, 1.0, -1.0)[:, None]
        elif orient != "none":
            raise SceneError(f"collider {name!r}: 'orient' must be 'knn', 'centroid' or 'none', got {orient!r}")
        if flip:
            n = -n
        if dim == 2:
            tan = np.stack([-n[:, 1], n[:, 0]], axis=-1)[:, None, :]
        else:
            if t1 is None:
                if np.any(np.abs(s[:, 0] - s[:, 1]) > 1e-12 * np.maximum(s[:, 0], s[:, 1])):
                    raise SceneError(f"collider {name!r}: anisotropic disk scales need 'tangents' or 'rotations'")
                u = _any_perpendicular(n)
            else:
                u = t1 - np.sum(t1 * n, -1, keepdims=True) * n
                u = safe_normalize_np(u, _any_perpendicular(n))
            tan = np.stack([u, np.cross(n, u)], axis=1)
        self.centers = StaticArray(c)
        self.normals = StaticArray(n)
        self.tangents = StaticArray(tan)
        self.scales = StaticArray(s)
        self.opacity = StaticArray(o)
        self.cutoff = float(cutoff)
        bounds = self._bounds_np(c, tan, s, float(cutoff))
        init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, bounds.mean(axis=0), motion)

    @staticmethod
    def half_extents(tan, s, cutoff):
        """Bounding half-extent of each elliptical footprint along every world axis, ``(K, D)``."""
        return cutoff * np.sqrt(np.sum((s[:, :, None] * tan) ** 2, axis=1))

    @classmethod
    def _bounds_np(cls, c, tan, s, cutoff):
        ext = cls.half_extents(tan, s, cutoff)
        return np.stack([(c - ext).min(axis=0), (c + ext).max(axis=0)])

    @property
    def num_disks(self) -> int:
        return len(self.centers)

    def bounds(self) -> np.ndarray:
        return self._bounds_np(
            np.asarray(self.centers), np.asarray(self.tangents), np.asarray(self.scales), self.cutoff
        )

    def _local_signed_distance(self, X):
        """Approximate signed distance to the union of footprints (brute force, O(M K)):
        ``sqrt(h^2 + e^2)`` with ``h`` the offset along the normal and ``e`` the in-plane
        distance beyond the footprint's ellipse (exact for round disks), signed by ``h``; the
        normal is the nearest disk's."""
        dtype = X.dtype
        c = jnp.asarray(np.asarray(self.centers), dtype)
        n = jnp.asarray(np.asarray(self.normals), dtype)
        tan = jnp.asarray(np.asarray(self.tangents), dtype)
        s = jnp.asarray(np.asarray(self.scales), dtype)
        d = X[:, None, :] - c[None]  # (M, K, D)
        h = jnp.sum(d * n[None], -1)
        a = jnp.einsum("mkd,kjd->mkj", d, tan)  # in-plane coordinates
        rho2 = jnp.sum((a / s[None]) ** 2, -1)
        a2 = jnp.sum(a * a, -1)
        pos = rho2 > 0
        rho = jnp.sqrt(jnp.where(pos, rho2, 1.0))
        alen = jnp.sqrt(jnp.where(pos, a2, 1.0))
        e = jnp.where(pos & (rho > self.cutoff), alen * (1.0 - self.cutoff / rho), 0.0)
        d2 = h * h + e * e
        j = jnp.argmin(d2, axis=1)
        d2j = jnp.take_along_axis(d2, j[:, None], 1)[:, 0]
        hj = jnp.take_along_axis(h, j[:, None], 1)[:, 0]
        ok = d2j > 0
        dist = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2j, 1.0)), 0.0)
        return jnp.where(hj >= 0, dist, -dist), n[j]
