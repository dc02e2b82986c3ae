"""Tiny identify datasets rendered by jaxmpm itself (a body dropped on a collider), for tests
and for benchmarks/identify_accuracy.py."""

from __future__ import annotations

import numpy as np

BOX_LO = np.array([0.15, 0.0, 0.15])
BOX_HI = np.array([0.45, 0.2, 0.45])
TRUTH = {"mu": 200.0, "kappa": 1e5}

#: Ground truths of the benchmark materials at this scale (dx = 0.05 m), and substeps per
#: 1/24 s frame that keep the explicit step stable (sand: p-wave speed 20 m/s).
MATERIAL_TRUTHS = {
    "newtonian": TRUTH,
    "viscoplastic": {"mu": 2e3, "kappa": 1e5, "yield_stress": 500.0, "eta": 5.0},
    "sand": {"friction_angle": 35.0, "E": 3e5},
    "elastic": {"E": 5e4, "nu": 0.3},
}
SUBSTEPS = {"newtonian": 40, "viscoplastic": 40, "sand": 80, "elastic": 40}

#: The true colliders on the floor: the box under the body, a box whose edge is under the
#: body's centre (half the body lands beside it), and the Stanford bunny 0.2 m long.
COLLIDERS = {
    "box": {"type": "box", "name": "box", "lo": BOX_LO.tolist(), "hi": BOX_HI.tolist()},
    "edge": {"type": "box", "name": "box", "lo": [0.3, 0.0, 0.15], "hi": [0.5, 0.2, 0.45]},
    "bunny": {"type": "mesh", "name": "bunny", "path": "bunny.obj", "scale": 0.2,
              "translate": [0.3, 0.2 * 0.494076, 0.3]},
}


def tiny_spec(collider: str = "box", frames: int = 6, material: str = "newtonian") -> dict:
    """A 3D scene: a 0.2 m block of ``material`` thrown down at 1 m/s from 0.1 m above a
    collider (:data:`COLLIDERS`, or ``"none"``) on a sticky floor (dx = 0.05, ~250 particles)."""
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


def true_collider_mesh(spec: dict):
    """The ``trimesh.Trimesh`` of a box or mesh collider spec (:data:`COLLIDERS`), world coordinates."""
    import trimesh

    if spec["type"] == "box":
        lo, hi = np.asarray(spec["lo"], float), np.asarray(spec["hi"], float)
        return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    from jaxmpm.colliders.spec import load_mesh, place, resolve_path

    verts, faces = load_mesh(resolve_path(spec["path"], None, "collider"))
    return trimesh.Trimesh(place(verts, spec, "collider"), faces, process=False)


def collider_masks(cameras, spec: dict) -> np.ndarray:
    """Exact silhouettes ``(V, H, W)`` bool of a box or mesh collider spec (:data:`COLLIDERS`)."""
    if spec["type"] == "box":
        return box_masks(cameras, np.asarray(spec["lo"], float), np.asarray(spec["hi"], float))
    mesh = true_collider_mesh(spec)
    out = []
    for v in range(cameras.num_views):
        o, d = (np.asarray(a, float).reshape(-1, 3) for a in cameras.view(v).rays())
        out.append(mesh.ray.intersects_any(o, d).reshape(cameras.height, cameras.width))
    return np.stack(out)


def box_masks(cameras, lo=BOX_LO, hi=BOX_HI) -> np.ndarray:
    """Exact silhouettes ``(V, H, W)`` bool of the axis-aligned box ``[lo, hi]`` (ray–box slabs)."""
    out = []
    for v in range(cameras.num_views):
        o, d = (np.asarray(a, float) for a in cameras.view(v).rays())
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        near = np.nanmax(np.minimum(t1, t2), axis=-1)
        far = np.nanmin(np.maximum(t1, t2), axis=-1)
        out.append(((far >= near) & (far > 0)).reshape(cameras.height, cameras.width))
    return np.stack(out)


def sphere_masks(cameras, center, radius) -> np.ndarray:
    """Exact silhouettes ``(V, H, W)`` bool of a sphere (rays that meet it)."""
    out = []
    for v in range(cameras.num_views):
        o, d = (np.asarray(a, float) for a in cameras.view(v).rays())
        oc = o - np.asarray(center, float)
        b = np.sum(oc * d, axis=-1)
        out.append((b * b - np.sum(oc * oc, axis=-1) + radius**2 > 0).reshape(cameras.height, cameras.width))
    return np.stack(out)


def tiny_cameras(views: int = 4, res: int = 48, min_elevation_deg: float = 15.0):
    """The tiny rig: ``views`` cameras 1 m from the box top's centre, elevations from
    ``min_elevation_deg`` (0: level with the box top) to 60°."""
    from jaxmpm.render import pacnerf_rig

    return pacnerf_rig(views, radius=1.0, target=(0.3, 0.2, 0.3), res=res, min_elevation_deg=min_elevation_deg,
                       max_elevation_deg=60.0)


DEGRADATIONS = ("clean", "jitter", "shift", "drop", "drop_high", "blur", "dark")


def degrade(obs, plate: np.ndarray, cmasks: np.ndarray, kind: str, seed: int = 0):
    """What real footage does to a rendered dataset, as the issue's checks list it.

    * ``jitter``: every material mask's boundary moved 1 or 2 px out or in (random per view and frame);
    * ``shift``: view 0 miscalibrated by 3 px (its images, masks and collider mask shifted right);
    * ``drop``: view 0 missing (the lowest: in :func:`tiny_cameras` elevations rise with the index);
    * ``drop_high``: the last (highest) view missing;
    * ``blur``: images and masks blurred (Gaussian, σ = 1 px; masks read back at alpha ≥ 128);
    * ``dark``: no alpha — the frames are the material over a textured plate, the plate is
      written at 70 % exposure, and the masks come from the difference with it.

    Arguments:
        obs: the rendered :class:`jaxmpm.Observation`; plate ``(V, H, W, 3)`` uint8;
            cmasks ``(V, H, W)`` bool collider masks.

    Returns:
        ``(obs, plate, cmasks, alpha)``: degraded copies and whether to write the masks as alpha.
    """
    import dataclasses

    from scipy.ndimage import binary_dilation, binary_erosion, gaussian_filter

    rng = np.random.default_rng(seed)
    masks, images = obs.masks.copy(), obs.images.copy()
    alpha = True
    if kind == "jitter":
        for v in range(masks.shape[0]):
            for t in range(masks.shape[1]):
                op = binary_dilation if rng.random() < 0.5 else binary_erosion
                masks[v, t] = np.where(op(masks[v, t] > 0, iterations=int(rng.integers(1, 3))), 255, 0)
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
        V, T, H, W = masks.shape
        texture = gaussian_filter(rng.uniform(60, 200, (V, H, W, 3)), sigma=(0, 2, 2, 0))
        texture = (texture - texture.mean()) * 4 + 130  # smooth blotches, 0–255 after clipping
        texture = np.clip(texture, 0, 255)
        a = masks[..., None] / 255.0
        images = np.round(a * images + (1 - a) * texture[:, None]).astype(np.uint8)
        plate, alpha = np.round(0.7 * texture).astype(np.uint8), False
    elif kind != "clean":
        raise ValueError(f"unknown degradation {kind!r}; one of {DEGRADATIONS}")
    return dataclasses.replace(obs, masks=masks, images=images), plate, cmasks, alpha


def make_dataset(folder, views: int = 4, res: int = 48, frames: int = 6, hint: bool = True,
                 min_elevation_deg: float = 15.0, material: str = "newtonian", collider: str = "box",
                 degradation: str = "clean"):
    """Simulate :func:`tiny_spec`, render it, :func:`degrade` it, write a PAC-NeRF folder with
    ``c_`` collider masks and a hint (the floor, dx, frame rate, substeps). Returns
    ``(folder, x (T, N, 3))``."""
    from jaxmpm.datasets import save_pacnerf
    from jaxmpm.observe import Observation
    from jaxmpm.render import render_views
    from jaxmpm.scene import load_scene
    from jaxmpm.step import run_frames

    spec = tiny_spec(collider, frames, material)
    scene = load_scene(spec)
    traj = run_frames(scene.model, scene.params)
    cams = tiny_cameras(views, res, min_elevation_deg)
    r = render_views(np.asarray(traj.x), cams, "surfels", spacing=0.025)
    obs = Observation(times=np.asarray(traj.times), masks=r["masks"], images=r["images"], intrinsics=r["intrinsics"],
                      cam_to_world=r["cam_to_world"])
    plate = np.full((views, res, res, 3), 255, np.uint8)
    cmasks = collider_masks(cams, COLLIDERS[collider]) if collider != "none" else None
    obs, plate, cmasks, alpha = degrade(obs, plate, cmasks, degradation)
    save_pacnerf(folder, obs, background=plate, collider_masks=cmasks, alpha=alpha)
    if hint:  # what a person knows: the scale, the frame rate, the floor (not the collider)
        from jaxmpm.reconstruct.pipeline import to_toml

        known = {k: spec[k] for k in ("dx", "frame_dt", "substeps", "domain")}
        (folder / "scene_hint.toml").write_text(to_toml({**known, "colliders": spec["colliders"][:1]}))
    return folder, np.asarray(traj.x)
