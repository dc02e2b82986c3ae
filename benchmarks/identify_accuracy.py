"""Identification accuracy from raw views (issue 13).

A tiny scene of jaxmpm.reconstruct.synthetic (a 0.2 m block thrown down at 1 m/s onto a box, the edge
of a box or the bunny; dx = 0.05 m, ~250 particles) is simulated, rendered from the views
with jaxmpm's surfel renderer, optionally degraded (noisy masks, a shifted or missing view,
blur, a darker plate), written as a PAC-NeRF folder and identified from it: the body and the
collider reconstructed from the views (the collider as fitted surfels, as AS-DiffMPM, or the
hull's mesh), the true collider imported in place of the reconstruction, as AS-DiffMPM
compares them, or 600 surfels placed on the true surface without a fit (``placed-disks``: the
disk field alone). Prints one JSON row per collider: the parameters' errors against the truth
(|Δlog10| for μ, κ, E, τ_Y, η; degrees for the friction angle; raw for ν), the velocity
error, the collider's Chamfer distance to the truth, the first-frame and final IoU, wall and
CPU seconds.

    PYTHONPATH=. python benchmarks/identify_accuracy.py --material newtonian --collider box \
        [--views 6 --res 96 --min-elevation 0 --degrade clean --colliders disks,mesh,true]

Rows measured for docs/identify.md: benchmarks/results/identify_accuracy*.jsonl.
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def print_table(rows: list[dict]) -> None:
    """The rows as one markdown table (errors: |Δlog10| for moduli and viscosities, degrees for
    the friction angle, raw for ν)."""
    print("\n| material | collider | degradation | used collider | refine / rgb / collider rgb | errors | velocity error (m/s) "
          "| Chamfer mesh / disks (mm) | IoU frame 0 min | IoU mean / min (at the truth) | iterations | wall / CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        errs = ", ".join(f"{n} {e:.2g}" if e >= 0.01 else f"{n} {e:.1e}" for n, e in r["errors"].items())
        truth = f" ({r['iou_truth_mean']:.3f} / {r['iou_truth_min']:.3f})" if "iou_truth_mean" in r else ""
        disks = "–" if r["chamfer_disks"] is None else f"{1e3 * r['chamfer_disks']:.1f}"
        print(f"| {r['material']} | {r['collider_shape']} | {r['degrade']} | {r['collider']} | "
              f"{r.get('refine', 0)} / {r.get('rgb', 0.0):g} / {r.get('collider_rgb', 0.0):g} | {errs} | {r['velocity_error']:.3f} | "
              f"{1e3 * r['chamfer_mesh']:.1f} / {disks} | {r['body_iou_min']:.3f} | "
              f"{r['iou_mean']:.3f} / {r['iou_min']:.3f}{truth} | {r['iterations']} | "
              f"{r['seconds']:.0f} / {r['cpu_seconds']:.0f} |")


def main() -> None:
    from jaxmpm.bench_sysid import FIT_NAMES, errors
    from jaxmpm.fit import REFINE_VELOCITY
    from jaxmpm.identify.parameters import with_values
    from jaxmpm.reconstruct import check_cameras, read_dataset, reconstruct, scene_skeleton, silhouette_iou, write_scene
    from jaxmpm.reconstruct.collider import chamfer_distance
    from jaxmpm.reconstruct.pipeline import identify_material, simulated_masks
    from jaxmpm.reconstruct.synthetic import (
        COLLIDERS, DEGRADATIONS, MATERIAL_TRUTHS, collider_mesh, drop_scene, render_drop_dataset,
    )
    from jaxmpm.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--material", default="newtonian", choices=sorted(MATERIAL_TRUTHS))
    ap.add_argument("--collider", default="box", choices=sorted(COLLIDERS))
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--min-elevation", type=float, default=15.0,
                    help="the lowest camera's elevation above the collider's top, degrees (0: level with it)")
    ap.add_argument("--degrade", default="clean", choices=DEGRADATIONS)
    ap.add_argument("--seed", type=int, default=0, help="random seed of the degradation (jitter)")
    ap.add_argument("--tolerance", type=int, default=None, help="k of the body's visual hull (default: chosen, "
                    "as identify does)")
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--colliders", default="disks,mesh,true",
                    help="reconstructed (disks, mesh), surfels placed on the true surface (placed-disks: the disk "
                         "field alone) and/or the true collider (true)")
    ap.add_argument("--renderer", default="surfels", help="the fit's renderer (the data are rendered with surfels)")
    ap.add_argument("--num-pixels", type=int, default=256)
    ap.add_argument("--refine", type=int, default=0, help="Adam steps of the first-frame refinement (0: none)")
    ap.add_argument("--rgb", type=float, default=0.0, help="weight of the masked-RGB term in the fit")
    ap.add_argument("--collider-rgb", type=float, default=0.0, help="weight of the plates' colours in the surfel fit")
    ap.add_argument("--refine-velocity", nargs="?", choices=("auto", "yes", "no"), default="auto", const="yes",
                    help="refit the velocity with the material (auto, the default: as identify, when the masks are "
                         "noisy)")
    ap.add_argument("--offset", action="store_true", help="fit the body's offset with its velocity")
    ap.add_argument("--at-truth", action="store_true",
                    help="also simulate the reconstructed scene with the true parameters and velocity and report its "
                         "IoU with the masks: above the fit's, the optimiser stopped short; at or below it, the data "
                         "(or the reconstruction) prefer the values found")
    ap.add_argument("--raise-collider", type=float, default=0.0, metavar="M",
                    help="raise a box's top by M metres (the data's and the true one's): off the node row it lies on")
    ap.add_argument("--recalibrate-views", action="store_true",
                    help="move the principal point of views the cameras' check flags (identify --recalibrate-views)")
    ap.add_argument("--out", default=None, help="append the rows to this .jsonl file")
    ap.add_argument("--table", nargs="+", default=None, metavar="JSONL",
                    help="only print the rows of these .jsonl files as one markdown table")
    args = ap.parse_args()
    if args.table:
        print_table([json.loads(line) for path in args.table for line in Path(path).read_text().splitlines() if line])
        return
    if args.raise_collider:
        if COLLIDERS[args.collider]["type"] != "box":
            ap.error("--raise-collider is for the box colliders")
        COLLIDERS[args.collider]["hi"][1] += args.raise_collider  # the scene, the data and the true collider
    spec = drop_scene(args.collider, material=args.material)
    truth = MATERIAL_TRUTHS[args.material]
    truth_v = np.asarray(spec["bodies"][0]["velocity"], float)
    names = FIT_NAMES[args.material]
    true_surface = collider_mesh(COLLIDERS[args.collider]).sample(20000, seed=0)
    rows = []

    def placed_disks(folder: Path, count: int = 600) -> Path:
        """``count`` surfels evenly placed on the true collider, with its normals and scales of
        half their spacing (the surfel fit's starting layout, without the fit)."""
        import trimesh

        surface = collider_mesh(COLLIDERS[args.collider])
        centers, face = trimesh.sample.sample_surface_even(surface, count, seed=0)
        path = folder / "placed_disks.npz"
        np.savez(path, centers=centers, normals=surface.face_normals[face],
                 scales=np.full(len(centers), np.sqrt(surface.area / len(centers)) / 2))
        return path

    with tempfile.TemporaryDirectory() as tmp:
        folder, _ = render_drop_dataset(Path(tmp) / "ds", views=args.views, res=args.res, min_elevation_deg=args.min_elevation,
                                 material=args.material, collider=args.collider, degradation=args.degrade,
                                        seed=args.seed)
        ds = read_dataset(folder)
        domain = scene_skeleton(ds, args.material)["domain"]
        ds, offsets = check_cameras(ds, domain["lo"], domain["hi"], recalibrate=args.recalibrate_views)
        obs = ds.observation
        for kind in args.colliders.split(","):
            t0, c0 = time.perf_counter(), time.process_time()
            rec = reconstruct(ds, args.material, tolerance=args.tolerance, collider="mesh" if kind == "mesh" else "disks",
                              refine=args.refine, collider_rgb=args.collider_rgb)
            chamfer = {"mesh": chamfer_distance(rec.collider_mesh.sample(20000, seed=0), true_surface),
                       "disks": None if rec.surfels is None else chamfer_distance(rec.surfels.centers, true_surface)}
            if kind in ("true", "placed-disks"):
                rec = copy.copy(rec)
                rec.spec = copy.deepcopy(rec.spec)
            if kind == "true":  # the true collider imported in place of the reconstruction
                rec.spec["colliders"][-1] = {**COLLIDERS[args.collider], "name": "collider", "contact": "sticky"}
            if kind == "placed-disks":  # surfels placed on the true surface (no fit): the disk field alone
                rec.spec["colliders"][-1] = {"type": "disks", "path": str(placed_disks(Path(tmp))), "name": "collider",
                                             "contact": "sticky"}
            scene = load_scene(write_scene(rec, Path(tmp) / f"scene_{kind}"))
            result = identify_material(scene, obs, names + ["velocity"] + (["offset"] if args.offset else []),
                                       max_steps=args.max_steps,
                                       renderer=args.renderer, num_pixels=args.num_pixels, rgb=args.rgb,
                                       refine_velocity=REFINE_VELOCITY[args.refine_velocity])
            evaluation_notes: list[str] = []
            iou = silhouette_iou(simulated_masks(scene, result.params, obs, result.substeps, notes=evaluation_notes),
                                 obs.masks)
            row = {
                "material": args.material, "collider_shape": args.collider, "collider": kind, "degrade": args.degrade, "seed": args.seed,
                "collider_raised_m": args.raise_collider,
                "tolerance": rec.body_hull.tolerance, "refine": args.refine, "rgb": args.rgb,
                "collider_rgb": args.collider_rgb, "refine_velocity": args.refine_velocity, "renderer": args.renderer, "num_pixels": args.num_pixels,
                "views": args.views, "res": args.res, "min_elevation": args.min_elevation, "max_steps": args.max_steps,
                "truth": truth, "values": {n: float(np.ravel(result.values[n])[0]) for n in names},
                "errors": errors(names, result.values, truth),
                "velocity": np.asarray(result.values["velocity"]).tolist(),
                "velocity_error": float(np.linalg.norm(np.asarray(result.values["velocity"]) - truth_v)),
                "offset": np.asarray(result.values["offset"]).tolist() if "offset" in result.values else None,
                "chamfer_mesh": chamfer["mesh"], "chamfer_disks": chamfer["disks"],
                "body_iou_min": float(np.min(rec.body_iou)), "particles": len(rec.points),
                "free_fall_frames": rec.free_fall.frames,
                "iou_mean": float(iou.mean()), "iou_min": float(iou.min()), "converged": bool(result.converged),
                "iterations": int(result.iterations), "notes": list(result.notes) + evaluation_notes,
                "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
                "view_offsets_px": None if offsets is None else np.round(offsets.offsets, 3).tolist(),
                "views_flagged": None if offsets is None else np.flatnonzero(offsets.flagged()).tolist(),
                "recalibrate_views": args.recalibrate_views,
            }
            if args.at_truth:
                at_truth = with_values(scene.model, result.params, {**truth, "velocity": truth_v})
                iou_t = silhouette_iou(simulated_masks(scene, at_truth, obs, result.substeps), obs.masks)
                row.update(iou_truth_mean=float(iou_t.mean()), iou_truth_min=float(iou_t.min()))
            rows.append(row)
            print(json.dumps(row), flush=True)
    print_table(rows)
    if args.out:
        with open(args.out, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
