"""What the background plates' colours add to the collider surfels (issue 13, item 3).

The synthetic collider is painted (:func:`jaxmpm.reconstruct.synthetic.collider_texture`) and
seen by the rig of :func:`~jaxmpm.reconstruct.synthetic.drop_cameras`. For each rig size the
surfels are fitted from the pipeline's coarse hull (dx / 2) four ways — to the masks or to the
masks and the plates' RGB, each left where the fit put them or snapped onto the hull — and
compared with the true collider: the symmetric Chamfer distance of the surfel centres, their
mean distance to the true surface, the height of the "roof" (surfels over the inner part of
the top, mean height above the true top), and what a user sees: an elastic block (E = 100 kPa)
thrown onto the surfels as a ``disks`` collider rests at a height compared with the same block
on the true box (in cells), and how deep it goes into the true box.

    PYTHONPATH=. python benchmarks/collider_rgb.py [--views 6 12] [--res 96] [--elevation 15]
        [--collider box] [--steps 200] [--rgb 10] [--json results/collider_rgb.jsonl]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def rest_height(spec: dict, collider: dict, truth) -> tuple[float, float]:
    """The block's final mean height (m) and its deepest point inside the ``truth`` mesh (m)
    with ``collider`` in place of the scene's."""
    import trimesh

    from jaxmpm.scene import load_scene
    from jaxmpm.step import run_frames

    scene = load_scene(dict(spec, colliders=spec["colliders"][:1] + [collider]))
    x = np.asarray(run_frames(scene.model, scene.params).x)
    depth = trimesh.proximity.signed_distance(truth, x.reshape(-1, 3)).max()
    return float(x[-1, :, 1].mean()), float(max(depth, 0.0))


def main() -> None:
    import trimesh

    from jaxmpm.reconstruct import chamfer_distance, fit_surfels, hull_mesh, visual_hull
    from jaxmpm.reconstruct.synthetic import (COLLIDERS, collider_layer, collider_masks, collider_mesh, drop_cameras,
                                              drop_scene)

    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, nargs="+", default=[6, 12])
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--elevation", type=float, default=15.0, help="the lowest camera's elevation, degrees")
    ap.add_argument("--collider", default="box", choices=["box", "edge"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rgb", type=float, default=10.0, help="the colour term's weight")
    ap.add_argument("--json", default=None, help="append one row per variant to this .jsonl")
    args = ap.parse_args()
    true = COLLIDERS[args.collider]
    lo, hi = np.asarray(true["lo"], float), np.asarray(true["hi"], float)
    true_mesh = collider_mesh(true)
    truth = true_mesh.sample(20000, seed=0)
    spec = drop_scene(args.collider, frames=10)
    spec["bodies"][0]["material"] = {"model": "elastic", "density": 1000.0, "E": 1e5, "nu": 0.3}
    y_true, _ = rest_height(spec, true, true_mesh)
    dx = spec["dx"]

    def inner(c):  # points over the top's inner part (4 cm from its edges), near or above it
        xz = c[:, [0, 2]]
        return np.all((xz > lo[[0, 2]] + 0.04) & (xz < hi[[0, 2]] - 0.04), axis=1) & (c[:, 1] > hi[1] - 0.05)

    print(f"{args.collider}, lowest view {args.elevation:g} deg, {args.res} px; block on the true collider rests at "
          f"{y_true:.4f} m")
    for views in args.views:
        cams = drop_cameras(views, args.res, args.elevation)
        K, P = np.asarray(cams.K, float), np.asarray(cams.cam_to_world, float)
        masks = collider_masks(cams, true)
        color, alpha = collider_layer(cams, true)
        plates = np.round(255.0 * color + 255.0 * (1.0 - alpha[..., None])).astype(np.uint8)
        mesh = hull_mesh(visual_hull(masks, K, P, spec["domain"]["lo"], spec["domain"]["hi"], 0.5 * dx))
        roof_hull = mesh.sample(20000, seed=0)
        print(f"  {views} views: hull roof {1e3 * (roof_hull[inner(roof_hull), 1].mean() - hi[1]):.1f} mm")
        for rgb in (False, True):
            for snap in (False, True):
                t0 = time.perf_counter()
                s = fit_surfels(mesh, masks, K, P, steps=args.steps, images=plates if rgb else None,
                                rgb_weight=args.rgb, snap=snap)
                seconds = time.perf_counter() - t0
                d = trimesh.proximity.closest_point(true_mesh, s.centers)[1]
                with tempfile.TemporaryDirectory() as tmp:
                    s.save(Path(tmp) / "disks.npz")
                    disks = {"type": "disks", "name": "c", "path": str(Path(tmp) / "disks.npz")}
                    y, depth = rest_height(spec, disks, true_mesh)
                row = {"collider": args.collider, "views": views, "res": args.res, "elevation": args.elevation,
                       "steps": args.steps, "fit": "masks+rgb" if rgb else "masks", "rgb_weight": args.rgb if rgb else 0.0,
                       "snap": snap, "surfels": len(s.centers), "chamfer_m": chamfer_distance(s.centers, truth),
                       "mean_distance_m": float(d.mean()), "roof_m": float(s.centers[inner(s.centers), 1].mean() - hi[1]),
                       "iou_min": float(s.iou.min()), "rest_offset_dx": (y - y_true) / dx, "depth_in_truth_m": depth,
                       "seconds": seconds}
                print(f"    {row['fit']:9s} snap={snap!s:5s} chamfer {1e3 * row['chamfer_m']:.1f} mm, mean distance "
                      f"{1e3 * row['mean_distance_m']:.1f} mm, roof {1e3 * row['roof_m']:.1f} mm, IoU >= {row['iou_min']:.3f}; "
                      f"block rests {row['rest_offset_dx']:+.2f} dx from the truth, {1e3 * depth:.1f} mm deep in the box; "
                      f"{seconds:.0f} s", flush=True)
                if args.json:
                    with open(args.json, "a") as f:
                        f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
