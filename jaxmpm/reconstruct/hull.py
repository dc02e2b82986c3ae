"""Visual hulls on a voxel grid, particles inside a hull, silhouette IoU.

A voxel is kept when at least ``V − k`` of the V views see its centre inside their mask
(``k = tolerance``): with ``k = 1`` one bad or missing mask does not erase the body.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import ObservationError


@dataclass(frozen=True)
class Hull:
    """A voxel occupancy grid.

    Attributes:
        occupied: ``(nx, ny, nz)`` bool, voxel ``(i, j, k)`` centred at ``lo + (i + ½) voxel``.
        lo: ``(3,)`` lower corner of the grid, m.
        voxel: voxel edge length, m.
        votes: ``(nx, ny, nz)`` int, how many views see the voxel inside their mask.
        views: V, the number of views that voted.
        tolerance: k, how many of them may disagree: ``occupied = votes >= V - k``.
    """

    occupied: np.ndarray
    lo: np.ndarray
    voxel: float
    votes: np.ndarray
    views: int
    tolerance: int

    def with_tolerance(self, tolerance: int) -> "Hull":
        """The same votes with another k (no view is projected again)."""
        _check_tolerance(tolerance, self.views)
        return replace(self, occupied=self.votes >= self.views - tolerance, tolerance=tolerance)

    @property
    def volume(self) -> float:
        """Occupied volume, m³."""
        return float(self.occupied.sum()) * self.voxel**3

    def centers(self) -> np.ndarray:
        """Centres of the occupied voxels, ``(M, 3)`` m."""
        return self.lo + (np.argwhere(self.occupied) + 0.5) * self.voxel

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each point ``(N, 3)`` lies in an occupied voxel, ``(N,)`` bool."""
        idx = np.floor((np.asarray(points, float) - self.lo) / self.voxel).astype(np.int64)
        shape = np.asarray(self.occupied.shape)
        ok = np.all((idx >= 0) & (idx < shape), axis=-1)
        out = np.zeros(len(idx), bool)
        out[ok] = self.occupied[tuple(idx[ok].T)]
        return out


def _check_tolerance(tolerance: int, views: int) -> None:
    if not 0 <= tolerance < views:
        raise ObservationError(f"visual_hull: tolerance k must be in [0, {views - 1}] for {views} views, got {tolerance}")


def inside_masks(points: np.ndarray, masks: np.ndarray, intrinsics: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """Per view, whether each point projects inside that view's mask.

    Arguments:
        points: ``(N, 3)`` world points.
        masks: ``(V, H, W)`` bool.
        intrinsics, cam_to_world: ``(V, 3, 3)``, ``(V, 4, 4)``.

    Returns:
        ``(V, N)`` bool; a point behind a camera or outside its image counts as outside.
    """
    from ..render.camera import pixel_of

    V, H, W = masks.shape
    out = np.zeros((V, len(points)), bool)
    for v in range(V):
        row, col, ok = pixel_of(points, intrinsics[v], cam_to_world[v], H, W)
        out[v, ok] = masks[v, row[ok], col[ok]]
    return out


def visual_hull(
    masks: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    lo,
    hi,
    voxel: float,
    *,
    tolerance: int = 0,
) -> Hull:
    """The visual hull of V silhouettes on a voxel grid covering ``[lo, hi]``.

    Arguments:
        masks: ``(V, H, W)`` bool or 0/255 silhouettes.
        intrinsics, cam_to_world: ``(V, 3, 3)`` and ``(V, 4, 4)`` cameras (OpenCV axes).
        lo, hi: ``(3,)`` corners of the region to carve, m.
        voxel: voxel edge, m.
        tolerance: k — a voxel is kept when at least ``V − k`` views see it inside.

    Returns:
        A :class:`Hull`.

    Raises:
        ObservationError: bad shapes, a non-positive voxel or a tolerance outside [0, V).
    """
    masks = np.asarray(masks) > 0
    if masks.ndim != 3:
        raise ObservationError(f"visual_hull: masks must be (V, H, W), got {masks.shape}")
    V = masks.shape[0]
    if np.shape(intrinsics) != (V, 3, 3) or np.shape(cam_to_world) != (V, 4, 4):
        raise ObservationError(f"visual_hull: need {V} cameras, got intrinsics {np.shape(intrinsics)} and poses {np.shape(cam_to_world)}")
    _check_tolerance(tolerance, V)
    if not voxel > 0:
        raise ObservationError(f"visual_hull: voxel must be positive, got {voxel}")
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    shape = np.maximum(np.ceil((hi - lo) / voxel).astype(int), 1)
    axes = [lo[i] + (np.arange(shape[i]) + 0.5) * voxel for i in range(3)]
    centers = np.stack([a.reshape(-1) for a in np.meshgrid(*axes, indexing="ij")], axis=-1)
    votes = inside_masks(centers, masks, np.asarray(intrinsics, float), np.asarray(cam_to_world, float)).sum(axis=0)
    votes = votes.reshape(tuple(shape))
    return Hull(occupied=votes >= V - tolerance, lo=lo, voxel=float(voxel), votes=votes, views=V, tolerance=tolerance)


def hull_particles(hull: Hull, spacing: float) -> np.ndarray:
    """Particles on a lattice of the given spacing that fill the hull's occupied voxels.

    The lattice is aligned with the hull's grid corner (points at ``lo + (i + ½) spacing``,
    as the scene's own samplers place them). A point is kept when at least half of its
    cell — probed at the 8 points ``±spacing/4`` around it — lies in occupied voxels, so the
    particles' volume follows the hull's volume.

    Arguments:
        hull: the body's hull.
        spacing: lattice spacing, m (the scene's ``dx / ppc^(1/3)``).

    Returns:
        ``(N, 3)`` positions, m.
    """
    if not np.any(hull.occupied):
        return np.zeros((0, 3))
    idx = np.argwhere(hull.occupied)
    lo = hull.lo + idx.min(axis=0) * hull.voxel
    hi = hull.lo + (idx.max(axis=0) + 1) * hull.voxel
    first = np.floor((lo - hull.lo) / spacing).astype(int)
    last = np.ceil((hi - hull.lo) / spacing).astype(int)
    axes = [hull.lo[i] + (np.arange(first[i], last[i]) + 0.5) * spacing for i in range(3)]
    pts = np.stack([a.reshape(-1) for a in np.meshgrid(*axes, indexing="ij")], axis=-1)
    probes = 0.25 * spacing * np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], float)
    filled = np.mean([hull.contains(pts + d) for d in probes], axis=0)
    return pts[filled >= 0.5]


def silhouette_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection over union of two mask stacks ``(..., H, W)`` (bool or 0/255), ``(...)``.

    An empty union counts as IoU 1 (both masks agree that nothing is there).
    """
    a, b = np.asarray(a) > 0, np.asarray(b) > 0
    inter = np.sum(a & b, axis=(-2, -1))
    union = np.sum(a | b, axis=(-2, -1))
    return np.where(union > 0, inter / np.maximum(union, 1), 1.0)
