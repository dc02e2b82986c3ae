"""Identify datasets rendered by jaxmpm itself: a block dropped on a collider, seen by a small
rig, optionally degraded the way real footage is (used by ``jaxmpm demo --video``, the tests
and ``benchmarks/identify_accuracy.py``; docs/identify.md).

    from jaxmpm.reconstruct.synthetic import render_drop_dataset
    render_drop_dataset("drop", views=6, res=96, min_elevation_deg=0.0, collider="edge")

writes a PAC-NeRF folder (``all_data.json``, ``data/r_*``, plates, ``c_*`` collider masks and
a ``scene_hint.toml`` with the floor, dx, frame rate and substeps) that
``jaxmpm identify drop --material newtonian`` reads.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

__all__ = [
    "MATERIAL_TRUTHS",
    "SUBSTEPS",
    "COLLIDERS",
    "DEGRADATIONS",
    "jitter_masks",
    "drop_scene",
    "drop_cameras",
    "collider_mesh",
    "collider_masks",
    "collider_texture",
    "collider_layer",
    "box_masks",
    "mesh_masks",
    "degrade",
    "render_drop_dataset",
]

#: Ground truths of the materials at this scale (dx = 0.05 m).
MATERIAL_TRUTHS = {
    "newtonian": {"mu": 200.0, "kappa": 1e5},
    "viscoplastic": {"mu": 2e3, "kappa": 1e5, "yield_stress": 500.0, "eta": 5.0},
    "sand": {"friction_angle": 35.0, "E": 3e5},
    "elastic": {"E": 5e4, "nu": 0.3},
}
#: Substeps per 1/24 s frame that keep the explicit step stable (sand: p-wave speed 20 m/s).
SUBSTEPS = {"newtonian": 40, "viscoplastic": 40, "sand": 80, "elastic": 40}

#: The true colliders on the floor: a box under the whole body, a box whose edge is under the
#: body's centre (half the body lands beside it), and the Stanford bunny 0.2 m long.
COLLIDERS = {
    "box": {"type": "box", "name": "box", "lo": [0.15, 0.0, 0.15], "hi": [0.45, 0.2, 0.45]},
    "edge": {"type": "box", "name": "box", "lo": [0.3, 0.0, 0.15], "hi": [0.5, 0.2, 0.45]},
    "bunny": {"type": "mesh", "name": "bunny", "path": "bunny.obj", "scale": 0.2,
              "translate": [0.3, 0.2 * 0.494076, 0.3]},
}

#: What :func:`degrade` can do to a rendered dataset.
DEGRADATIONS = ("clean", "jitter", "shift", "drop", "drop_high", "blur", "dark")


def drop_scene(collider: str = "box", frames: int = 6, material: str = "newtonian") -> dict:
    """A 3D scene spec: a 0.2 m block of ``material`` (:data:`MATERIAL_TRUTHS`) thrown down at
    1 m/s from 0.1 m above a collider (a key of :data:`COLLIDERS`, or ``"none"``) on a sticky
    floor; dx = 0.05 m, 8 particles per cell (256 particles), ``frames`` frames of 1/24 s."""
    if collider != "none" and collider not in COLLIDERS:
        raise ValueError(f"unknown collider {collider!r}; one of {sorted(COLLIDERS)} or 'none'")
    if material not in MATERIAL_TRUTHS:
        raise ValueError(f"unknown material {material!r}; one of {sorted(MATERIAL_TRUTHS)}")
    colliders = [{"type": "plane", "name": "floor", "point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]}]
    if collider != "none":
        colliders.append(dict(COLLIDERS[collider]))
    return {
        "dim": 3, "dx": 0.05, "domain": {"lo": [0.0, 0.0, 0.0], "hi": [0.6, 0.6, 0.6]}, "frames": frames,
        "frame_dt": 1 / 24, "substeps": SUBSTEPS[material], "gravity": [0.0, -9.8, 0.0],
        "bodies": [{"shape": "box", "lo": [0.2, 0.3, 0.2], "hi": [0.4, 0.4, 0.4], "ppc": 8,
                    "velocity": [0.0, -1.0, 0.0],
                    "material": {"model": material, "density": 1000.0, **MATERIAL_TRUTHS[material]}}],
        "colliders": colliders,
    }


def drop_cameras(views: int = 4, res: int = 48, min_elevation_deg: float = 15.0):
    """The rig: ``views`` cameras of ``res``² pixels 1 m from the collider top's centre
    (0.3, 0.2, 0.3), elevations from ``min_elevation_deg`` (0: level with the top, which
    carves the collider's roof, see :func:`jaxmpm.reconstruct.roof_height`) to 60°."""
    from ..render import pacnerf_rig

    return pacnerf_rig(views, radius=1.0, target=(0.3, 0.2, 0.3), res=res, min_elevation_deg=min_elevation_deg,
                       max_elevation_deg=60.0)


def collider_mesh(spec: dict):
    """The ``trimesh.Trimesh`` of a box or mesh collider spec, in world coordinates (m)."""
    import trimesh

    if spec["type"] == "box":
        lo, hi = np.asarray(spec["lo"], float), np.asarray(spec["hi"], float)
        return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    from ..colliders.spec import load_mesh, place, resolve_path

    verts, faces = load_mesh(resolve_path(spec["path"], None, "collider"))
    return trimesh.Trimesh(place(verts, spec, "collider"), faces, process=False)


def box_masks(cameras, lo, hi) -> np.ndarray:
    """Exact silhouettes ``(V, H, W)`` bool of the axis-aligned box ``[lo, hi]`` (m): the pixels
    whose centre ray meets it (ray–slab test)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    out = []
    for v in range(cameras.num_views):
        o, d = (np.asarray(a, float) for a in cameras.view(v).rays())
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        near = np.nanmax(np.minimum(t1, t2), axis=-1)
        far = np.nanmin(np.maximum(t1, t2), axis=-1)
        out.append(((far >= near) & (far > 0)).reshape(cameras.height, cameras.width))
    return np.stack(out)


def mesh_masks(cameras, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Silhouettes ``(V, H, W)`` bool of a triangle mesh in front of every camera: the pixels
    whose centre lies in some projected triangle (each triangle filled with scikit-image's
    polygon rasteriser; pixel centres at +0.5, as :meth:`jaxmpm.render.Camera.rays`).

    Raises:
        ValueError: if a vertex is behind a camera (the projection would fold).
    """
    from skimage.draw import polygon

    out = np.zeros((cameras.num_views, cameras.height, cameras.width), bool)
    for v in range(cameras.num_views):
        uv, depth = (np.asarray(a, float) for a in cameras.view(v).project(np.asarray(vertices, np.float32)))
        if np.any(depth <= 0):
            raise ValueError(f"view {v}: part of the mesh is behind the camera")
        for tri in uv[np.asarray(faces)]:
            rr, cc = polygon(tri[:, 1] - 0.5, tri[:, 0] - 0.5, shape=out.shape[1:])
            out[v, rr, cc] = True
    return out


def collider_masks(cameras, spec: dict) -> np.ndarray:
    """Silhouettes ``(V, H, W)`` bool of a box (:func:`box_masks`) or mesh
    (:func:`mesh_masks`) collider spec."""
    if spec["type"] == "box":
        return box_masks(cameras, spec["lo"], spec["hi"])
    mesh = collider_mesh(spec)
    return mesh_masks(cameras, np.asarray(mesh.vertices), np.asarray(mesh.faces))


#: The texture's period on the collider, m (about 7 px at 96 px from the rig's 1 m).
TEXTURE_PERIOD = 0.06


def collider_texture(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The synthetic colliders' paint: ``(N, 3)`` RGB in [0, 1] at surface ``points`` ``(N, 3)``
    (m) with outward ``normals`` ``(N, 3)``: three sinusoids of period :data:`TEXTURE_PERIOD`
    along different directions (one per channel, so every patch of a face differs from its
    neighbours), shaded by a fixed light (Lambert, view-independent as photo-consistency
    assumes)."""
    k = 2.0 * np.pi / TEXTURE_PERIOD
    p = np.asarray(points, float)
    paint = np.stack([np.sin(k * (p[:, 0] + 1.3 * p[:, 1])), np.sin(k * (p[:, 2] - 0.7 * p[:, 0])),
                      np.sin(0.8 * k * (p[:, 1] + p[:, 2]))], axis=-1)
    light = np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3])
    shade = 0.55 + 0.45 * np.clip(np.asarray(normals, float) @ light, 0.0, 1.0)
    return (0.5 + 0.4 * paint) * shade[:, None]


def collider_layer(cameras, spec: dict) -> tuple[np.ndarray, np.ndarray]:
    """The painted collider (:func:`collider_texture`) as each camera sees it: surface samples
    about half a pixel apart rendered as surfels with the mesh's normals (depth-sorted).

    Returns:
        ``(color, alpha)``: ``(V, H, W, 3)`` colour premultiplied by ``alpha`` ``(V, H, W)``;
        the plate over a background ``b`` is ``color + (1 − alpha) · b``.
    """
    import jax.numpy as jnp
    import trimesh

    from ..render import SurfelRenderer

    mesh = collider_mesh(spec)
    H, W = cameras.height, cameras.width
    K = np.asarray(cameras.K, float)
    pixel = 1.0 / float(K[0, 1, 1])  # a pixel's width at 1 m, m (the rig's distance)
    count = int(min(mesh.area / (0.5 * pixel) ** 2, 60000))
    points, face = trimesh.sample.sample_surface_even(mesh, count, seed=0)
    normals = np.asarray(mesh.face_normals[face], float)
    spacing = float(np.sqrt(mesh.area / len(points)))
    renderer = SurfelRenderer(scale=0.6 * spacing, background=(0.0, 0.0, 0.0))
    x, n = jnp.asarray(points, jnp.float32), jnp.asarray(normals, jnp.float32)
    paint = jnp.asarray(collider_texture(points, normals), jnp.float32)
    color, alpha = np.zeros((cameras.num_views, H, W, 3)), np.zeros((cameras.num_views, H, W))
    for v in range(cameras.num_views):
        out = renderer.render(x, cameras.view(v), paint, normals=n)
        color[v], alpha[v] = np.asarray(out.rgb, float), np.asarray(out.alpha, float)
    return color, alpha


def backdrop(views: int, height: int, width: int, kind: str, rng) -> np.ndarray:
    """``(V, H, W, 3)`` float 0–255: the scene behind everything: white, or (``kind="dark"``)
    smooth random blotches, a backdrop that a mask by plate difference must tell apart."""
    from scipy.ndimage import gaussian_filter

    if kind != "dark":
        return np.full((views, height, width, 3), 255.0)
    texture = gaussian_filter(rng.uniform(60, 200, (views, height, width, 3)), sigma=(0, 2, 2, 0))
    return np.clip((texture - texture.mean()) * 4 + 130, 0, 255)


def jitter_masks(masks: np.ndarray, seed: int = 0) -> np.ndarray:
    """``masks (V, T, H, W)`` (bool, or uint8 0/255) with every silhouette's border moved 1 or 2
    px out or in, at random per view and frame (``degrade``'s ``jitter``); same dtype."""
    from scipy.ndimage import binary_dilation, binary_erosion

    rng = np.random.default_rng(seed)
    out = np.asarray(masks).copy()
    for v in range(out.shape[0]):
        for t in range(out.shape[1]):
            op = binary_dilation if rng.random() < 0.5 else binary_erosion
            moved = op(out[v, t] > 0, iterations=int(rng.integers(1, 3)))
            out[v, t] = moved if out.dtype == bool else np.where(moved, 255, 0)
    return out


def degrade(obs, plate: np.ndarray, cmasks: np.ndarray | None, kind: str, seed: int = 0):
    """What real footage does to a rendered dataset:

    * ``jitter``: every material mask's boundary moved 1 or 2 px out or in (random per view and frame);
    * ``shift``: view 0 miscalibrated by 3 px (its images, masks and collider mask shifted right);
    * ``drop``: view 0 missing (the lowest: in :func:`drop_cameras` elevations rise with the index);
    * ``drop_high``: the last (highest) view missing;
    * ``blur``: images and masks blurred (Gaussian, σ = 1 px; masks read back at alpha ≥ 128);
    * ``dark``: no alpha — the plate (the frames' backdrop: :func:`backdrop` blotches for
      this kind) is written at 70 % exposure, and the masks come from the difference with it.

    Arguments:
        obs: the rendered :class:`jaxmpm.Observation` (masks ``(V, T, H, W)`` uint8 0/255,
            images ``(V, T, H, W, 3)`` uint8, the material over the plate); plate
            ``(V, H, W, 3)`` uint8; cmasks ``(V, H, W)`` bool collider masks or None.
        kind: one of :data:`DEGRADATIONS`.
        seed: the random seed of ``jitter``.

    Returns:
        ``(obs, plate, cmasks, alpha)``: degraded copies and whether to write the masks as alpha.
    """
    from scipy.ndimage import gaussian_filter

    if kind not in DEGRADATIONS:
        raise ValueError(f"unknown degradation {kind!r}; one of {DEGRADATIONS}")
    masks, images = obs.masks.copy(), obs.images.copy()
    alpha = True
    if kind == "jitter":
        masks = jitter_masks(masks, seed)
    elif kind == "shift":
        masks[0], images[0] = np.roll(masks[0], 3, axis=-1), np.roll(images[0], 3, axis=-2)
        if cmasks is not None:
            cmasks = cmasks.copy()
            cmasks[0] = np.roll(cmasks[0], 3, axis=-1)
    elif kind in ("drop", "drop_high"):
        keep = slice(1, None) if kind == "drop" else slice(0, -1)
        return (dataclasses.replace(obs, masks=masks[keep], images=images[keep], intrinsics=obs.intrinsics[keep],
                                    cam_to_world=obs.cam_to_world[keep]), plate[keep],
                None if cmasks is None else cmasks[keep], True)
    elif kind == "blur":
        masks = np.round(gaussian_filter(masks.astype(float), sigma=(0, 0, 1, 1))).astype(np.uint8)
        images = np.round(gaussian_filter(images.astype(float), sigma=(0, 0, 1, 1, 0))).astype(np.uint8)
    elif kind == "dark":
        plate, alpha = np.round(0.7 * plate.astype(float)).astype(np.uint8), False
    return dataclasses.replace(obs, masks=masks, images=images), plate, cmasks, alpha


def render_drop_dataset(folder: str | os.PathLike, views: int = 4, res: int = 48, frames: int = 6,
                        hint: bool = True, min_elevation_deg: float = 15.0, material: str = "newtonian",
                        collider: str = "box", degradation: str = "clean", seed: int = 0) -> tuple[Path, np.ndarray]:
    """Simulate :func:`drop_scene`, render it with surfels from :func:`drop_cameras` in front
    of a plate (white, or :func:`backdrop` blotches for ``dark``, with the painted collider
    of :func:`collider_layer`), :func:`degrade` it and write a PAC-NeRF folder (frames,
    plates, ``c_`` collider masks) with,
    when ``hint``, a ``scene_hint.toml`` holding what a person knows: dx, the frame rate,
    substeps, the domain and the floor (not the collider, not the material). ``seed``: the
    random seed of the degradation (:func:`degrade`).

    Returns:
        ``(folder, x)``: the folder and the true positions ``(T, N, 3)`` (m).
    """
    from ..datasets import save_pacnerf
    from ..observe import Observation
    from ..render import render_views
    from ..scene import load_scene
    from ..step import run_frames
    from .pipeline import to_toml

    spec = drop_scene(collider, frames, material)
    if degradation not in DEGRADATIONS:
        raise ValueError(f"unknown degradation {degradation!r}; one of {DEGRADATIONS}")
    scene = load_scene(spec)
    traj = run_frames(scene.model, scene.params)
    cams = drop_cameras(views, res, min_elevation_deg)
    r = render_views(np.asarray(traj.x), cams, "surfels", spacing=0.025)
    plate = backdrop(views, res, res, degradation, np.random.default_rng(0))
    cmasks = None
    if collider != "none":
        cmasks = collider_masks(cams, COLLIDERS[collider])
        color, a = collider_layer(cams, COLLIDERS[collider])
        plate = 255.0 * color + (1.0 - a[..., None]) * plate
    m = r["masks"][..., None] / 255.0  # the material in front of the plate
    images = np.round(m * r["images"] + (1.0 - m) * plate[:, None]).astype(np.uint8)
    obs = Observation(times=np.asarray(traj.times), masks=r["masks"], images=images, intrinsics=r["intrinsics"],
                      cam_to_world=r["cam_to_world"])
    obs, plate, cmasks, alpha = degrade(obs, np.round(plate).astype(np.uint8), cmasks, degradation, seed=seed)
    folder = save_pacnerf(folder, obs, background=plate, collider_masks=cmasks, alpha=alpha)
    if hint:
        known = {k: spec[k] for k in ("dx", "frame_dt", "substeps", "domain")}
        (folder / "scene_hint.toml").write_text(to_toml({**known, "colliders": spec["colliders"][:1]}))
    return folder, np.asarray(traj.x)
