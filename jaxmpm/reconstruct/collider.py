"""Colliders from views: a triangle mesh of a visual hull (marching cubes) and 2D Gaussian
surfels fitted to the collider's silhouettes with jaxmpm's surfel renderer.

The surfels are written as a ``disks`` collider file (``.npz``, :func:`jaxmpm.colliders.load_disks`
keys), which CPIC uses as-is.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..errors import ObservationError
from .hull import Hull
from .refine import adam_fit, color_logits, mean_view_error, view_targets


def hull_mesh(hull: Hull):
    """A closed triangle mesh of the hull's boundary (scikit-image's marching cubes).

    Arguments:
        hull: a :class:`~jaxmpm.reconstruct.Hull` with at least one occupied voxel.

    Returns:
        A ``trimesh.Trimesh`` in world coordinates (m), faces oriented outwards.
    """
    import trimesh
    from skimage.measure import marching_cubes

    if not hull.occupied.any():
        raise ObservationError("the collider's visual hull is empty: no voxel is inside every collider mask")
    padded = np.pad(hull.occupied.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level=0.5, spacing=(hull.voxel,) * 3)
    verts = verts + hull.lo - 0.5 * hull.voxel  # padding shifts by one voxel; centres sit at +½
    mesh = trimesh.Trimesh(verts, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def roof_height(mesh, cam_to_world: np.ndarray, up) -> tuple[float, float]:
    """An upper bound on how far above the true top a visual hull's top may stand, and the
    view angle behind it.

    A silhouette bounds a top face only where a view sees it edge-on: from a camera θ above
    a flat top of half-width r, a point above the top's centre at height h still projects
    inside the silhouette while h < r tan θ, so the hull may keep a "roof" up to
    ``r tan θ_min`` (θ_min: the lowest camera's elevation over the hull's top; r: half the
    hull's narrower horizontal extent). A flat top is the worst case; a rounded one is
    touched by the silhouettes' rims and keeps less (measured with the tests' rig, lowest
    view 15° above the top: box roof 0.05 m against the bound 0.040 m — the excess is a
    voxel of 0.025 m; bunny roof 0 against 0.020 m). With a view level with the top: 0.

    Arguments:
        mesh: the hull's mesh (``trimesh.Trimesh``, m).
        cam_to_world: ``(V, 4, 4)`` camera poses (their centres are what matters).
        up: the world's up direction (against gravity).

    Returns:
        ``(height m, theta_min degrees)``; 0 m when a camera is level with or below the top.
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    verts = np.asarray(mesh.vertices, float)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    r = 0.5 * min(np.ptp(verts @ a), np.ptp(verts @ np.cross(up, a)))
    d = np.asarray(cam_to_world, float)[:, :3, 3] - verts[np.argmax(verts @ up)]
    theta = max(float(np.min(np.arcsin(np.clip(d @ up / np.linalg.norm(d, axis=-1), -1.0, 1.0)))), 0.0)
    return float(r * np.tan(theta)), float(np.degrees(theta))


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance: the mean of the two mean nearest-neighbour distances, m.

    Arguments:
        a, b: ``(N, 3)`` and ``(M, 3)`` point sets (e.g. surface samples).
    """
    from scipy.spatial import cKDTree

    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return 0.5 * (float(np.mean(da)) + float(np.mean(db)))


@dataclass
class Surfels:
    """Fitted 2D Gaussian surfels (the ``disks`` collider file's content).

    Attributes:
        centers: ``(K, 3)`` m.
        normals: ``(K, 3)`` unit outward normals.
        tangents: ``(K, 3)`` unit first tangent axes.
        scales: ``(K, 2)`` standard deviations along the tangent axes, m.
        opacity: ``(K,)`` in [0, 1].
        iou: ``(V,)`` IoU of the returned surfels' silhouettes (snapped or as fitted) with the
            collider masks.
        colors: ``(K, 3)`` fitted RGB in [0, 1] when the plates' colours were fitted, else None.
    """

    centers: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    scales: np.ndarray
    opacity: np.ndarray
    iou: np.ndarray
    colors: np.ndarray | None = None

    def save(self, path: str | os.PathLike) -> None:
        """Write the ``.npz`` a ``disks`` collider reads (keys of :func:`jaxmpm.colliders.load_disks`)."""
        np.savez(path, centers=self.centers, normals=self.normals, tangents=self.tangents,
                 scales=self.scales, opacity=self.opacity)


def fit_surfels(
    mesh,
    masks: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    *,
    count: int = 600,
    steps: int = 80,
    learning_rate: float = 0.05,
    min_opacity: float = 0.2,
    images: np.ndarray | None = None,
    rgb_weight: float = 1.0,
    snap: bool = True,
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
) -> Surfels:
    """Fit 2D Gaussian surfels to a collider's silhouettes, starting from its hull's mesh.

    ``count`` surfels are placed evenly on ``mesh`` with its outward normals and a scale of
    half the mean spacing; Adam then fits their positions, normals, two scales and opacities
    so that the renderer's soft silhouettes (:meth:`jaxmpm.render.SurfelRenderer.silhouette`)
    match ``masks`` (mean squared error over all pixels of all views). With ``images`` (the
    background plates) each surfel also gets a colour (starting from its mean over the views)
    and the loss adds ``rgb_weight ×`` the mean of ``mask · |rgb − image|²``: the colours of a
    textured collider fix the surfels' depth where silhouettes cannot (photo-consistency).
    Surfels whose opacity ends below ``min_opacity`` are pruned, and with ``snap`` the others
    are put back onto the hull's surface with its normals (the nearest point): a silhouette
    does not see a surfel's depth or tilt on a face seen face-on, and as fitted to masks they
    drift (measured on the tests' box, lowest view level with its top: top surfels 25 mm apart
    in height and tilted by up to 87°; with the true parameters a Newtonian block's
    silhouettes on them matched the data at IoU 0.78, on the snapped surfels 0.95, on the
    hull's mesh 0.96, on the true box 0.99). Snapping also puts them back under the hull's
    roof, which the colours carve (benchmarks/collider_rgb.py, docs/identify.md §3).

    Arguments:
        mesh: the collider's visual-hull mesh (``trimesh.Trimesh``, m).
        masks: ``(V, H, W)`` bool collider masks.
        intrinsics, cam_to_world: ``(V, 3, 3)``, ``(V, 4, 4)`` cameras (OpenCV axes).
        count: surfels placed on the mesh.
        steps, learning_rate: Adam iterations and step size (in units of the initial scale
            for positions, per unit for the normals and log-scales and opacity logits).
        min_opacity: pruning threshold.
        images: ``(V, H, W, 3)`` uint8 background plates (the collider's colours), or None.
        rgb_weight: weight of the colour term (with ``images``).
        snap: put the fitted surfels onto the hull's surface with its normals.
        seed: sampling seed.
        progress: ``progress(step, loss)`` after each Adam step.

    Returns:
        :class:`Surfels` (float64 NumPy arrays).
    """
    import jax
    import jax.numpy as jnp
    import trimesh

    from ..render import Camera, SurfelRenderer
    from .hull import silhouette_iou

    masks = np.asarray(masks) > 0
    V, H, W = masks.shape
    pts, face = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    normals0 = np.asarray(mesh.face_normals[face], float)
    spacing = float(np.sqrt(mesh.area / max(len(pts), 1)))
    scale0 = 0.5 * spacing
    cams = [Camera(np.asarray(intrinsics[v], np.float32), np.asarray(cam_to_world[v], np.float32), W, H) for v in range(V)]
    renderer = SurfelRenderer(scale=scale0)
    if images is not None and np.shape(images) != (V, H, W, 3):
        raise ObservationError(f"fit_surfels: images have shape {np.shape(images)}; the masks need {(V, H, W, 3)}")
    data = {"x0": jnp.asarray(pts, jnp.float32), **view_targets(cams, masks, images)}

    def unpack(theta, x0):
        x = x0 + scale0 * theta["dx"]
        n = theta["n"] / jnp.sqrt(jnp.sum(theta["n"] ** 2, axis=-1, keepdims=True) + 1e-12)
        return x, n, scale0 * jnp.exp(theta["log_s"]), jax.nn.sigmoid(theta["logit"])

    def loss(theta, data):
        x, n, s, o = unpack(theta, data["x0"])

        def render(cam, colour):
            if not colour:
                return renderer.silhouette(x, cam, normals=n, scales=s, opacities=o)
            return renderer.render(x, cam, jax.nn.sigmoid(theta["color"]), normals=n, scales=s, opacities=o)

        return mean_view_error(render, data, rgb_weight)

    theta = {
        "dx": jnp.zeros((len(pts), 3), jnp.float32),
        "n": jnp.asarray(normals0, jnp.float32),
        "log_s": jnp.zeros((len(pts), 2), jnp.float32),
        "logit": jnp.full((len(pts),), 2.0, jnp.float32),
    }
    if images is not None:
        theta["color"] = color_logits(pts, images, masks, intrinsics, cam_to_world)
    theta, _ = adam_fit(loss, theta, data, steps, learning_rate, progress)
    x, n, s, o = (np.asarray(a, float) for a in unpack(theta, data["x0"]))
    colors = None if images is None else np.asarray(jax.nn.sigmoid(theta["color"]), float)
    if snap:
        # onto the hull: the silhouettes fix the surfels' footprints, not their depth or tilt
        # on a face seen face-on (left as fitted: top surfels of the tests' box 25 mm apart in
        # height, tilted up to 87°, and a block rested 0.5 dx too high on them)
        x, _, face = trimesh.proximity.closest_point(mesh, x)
        n = np.asarray(mesh.face_normals[face], float)
    final = [renderer.silhouette(jnp.asarray(x, jnp.float32), c, normals=jnp.asarray(n, jnp.float32),
                                 scales=jnp.asarray(s, jnp.float32), opacities=jnp.asarray(o, jnp.float32)) for c in cams]
    iou = silhouette_iou(np.asarray(jnp.stack(final)) > 0.5, masks)
    keep = o >= min_opacity
    if not keep.any():
        raise ObservationError("every fitted collider surfel became transparent: the collider masks hold no collider")
    axes_u, _ = renderer.surfel_axes(jnp.asarray(x[keep], jnp.float32), cams[0], normals=jnp.asarray(n[keep], jnp.float32),
                                     scales=jnp.ones((int(keep.sum()),), jnp.float32))
    return Surfels(centers=x[keep], normals=n[keep], tangents=np.asarray(axes_u, float), scales=s[keep],
                   opacity=o[keep], iou=iou, colors=None if colors is None else colors[keep])
