"""Tiny identify datasets rendered by jaxmpm itself (a body dropped on a box), for tests."""

from __future__ import annotations

import numpy as np

BOX_LO = np.array([0.15, 0.0, 0.15])
BOX_HI = np.array([0.45, 0.2, 0.45])
TRUTH = {"mu": 200.0, "kappa": 1e5}


def tiny_spec(collider: str = "box", frames: int = 6) -> dict:
    """A 3D scene: a Newtonian block dropped on a box on a sticky floor (dx = 0.05, ~250 particles)."""
    colliders = [{"type": "plane", "name": "floor", "point": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0]}]
    if collider == "box":
        colliders.append({"type": "box", "name": "box", "lo": BOX_LO.tolist(), "hi": BOX_HI.tolist()})
    return {
        "dim": 3, "dx": 0.05, "domain": {"lo": [0.0, 0.0, 0.0], "hi": [0.6, 0.6, 0.6]}, "frames": frames,
        "frame_dt": 1 / 24, "substeps": 40, "gravity": [0.0, -9.8, 0.0],
        "bodies": [{"shape": "box", "lo": [0.2, 0.3, 0.2], "hi": [0.4, 0.4, 0.4], "ppc": 8,
                    "velocity": [0.0, -1.0, 0.0], "material": {"model": "newtonian", "density": 1000.0, **TRUTH}}],
        "colliders": colliders,
    }


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


def tiny_cameras(views: int = 4, res: int = 48):
    from jaxmpm.render import pacnerf_rig

    return pacnerf_rig(views, radius=1.0, target=(0.3, 0.2, 0.3), res=res, min_elevation_deg=15.0, max_elevation_deg=60.0)


def make_dataset(folder, views: int = 4, res: int = 48, frames: int = 6, hint: bool = True):
    """Simulate :func:`tiny_spec`, render it, write a PAC-NeRF folder with ``c_`` box masks and a hint."""
    from jaxmpm.datasets import save_pacnerf
    from jaxmpm.observe import Observation
    from jaxmpm.render import render_views
    from jaxmpm.scene import load_scene
    from jaxmpm.step import run_frames

    scene = load_scene(tiny_spec(frames=frames))
    traj = run_frames(scene.model, scene.params)
    cams = tiny_cameras(views, res)
    r = render_views(np.asarray(traj.x), cams, "surfels", spacing=0.025)
    obs = Observation(times=np.asarray(traj.times), masks=r["masks"], images=r["images"], intrinsics=r["intrinsics"],
                      cam_to_world=r["cam_to_world"])
    plate = np.full((views, res, res, 3), 255, np.uint8)
    save_pacnerf(folder, obs, background=plate, collider_masks=box_masks(cams))
    if hint:
        (folder / "scene_hint.toml").write_text(
            'dx = 0.05\nframe_dt = 0.041666667\nsubsteps = 40\ndomain = { lo = [0.0, 0.0, 0.0], hi = [0.6, 0.6, 0.6] }\n'
            '[[colliders]]\ntype = "plane"\npoint = [0.0, 0.0, 0.0]\nnormal = [0.0, 1.0, 0.0]\n'
        )
    return folder, np.asarray(traj.x)
