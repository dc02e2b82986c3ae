"""Identification accuracy from raw views (issue 13): the tiny rendered dataset of
tests/recon_data.py (a Newtonian block, mu = 200 Pa s, kappa = 1e5 Pa, thrown down at 1 m/s
onto a box), identified from its silhouettes with the collider reconstructed from the views
(fitted surfels, as AS-DiffMPM; or the hull's mesh) and with the true box imported, as
AS-DiffMPM compares them. Prints one row per collider: |dlog10| of mu and kappa, the velocity
error, the free fall's estimates, the final IoU and the wall time.

    PYTHONPATH=. python benchmarks/identify_accuracy.py [--views 4 --res 48 --max-steps 30]

Rows measured for docs/identify.md: benchmarks/results/identify_accuracy.jsonl.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> None:
    from recon_data import BOX_HI, BOX_LO, TRUTH, make_dataset, tiny_spec

    from jaxmpm.reconstruct import read_dataset, reconstruct, silhouette_iou, write_scene
    from jaxmpm.reconstruct.pipeline import identify_material, simulated_masks
    from jaxmpm.scene import load_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--max-steps", type=int, default=30)
    ap.add_argument("--colliders", default="disks,mesh,true")
    ap.add_argument("--renderer", default="surfels", help="the fit's renderer (the data are rendered with surfels)")
    ap.add_argument("--num-pixels", type=int, default=256)
    ap.add_argument("--out", default=None, help="append the rows to this .jsonl file")
    args = ap.parse_args()
    truth_v = np.asarray(tiny_spec()["bodies"][0]["velocity"], float)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder, _ = make_dataset(Path(tmp) / "ds", views=args.views, res=args.res)
        ds = read_dataset(folder)
        obs = ds.observation
        for kind in args.colliders.split(","):
            t0 = time.perf_counter()
            rec = reconstruct(ds, "newtonian", collider="mesh" if kind == "mesh" else "disks")
            if kind == "true":  # the true box imported in place of the reconstruction
                rec = copy.copy(rec)
                rec.spec = copy.deepcopy(rec.spec)
                rec.spec["colliders"][-1] = {"type": "box", "name": "collider", "lo": BOX_LO.tolist(),
                                             "hi": BOX_HI.tolist(), "contact": "sticky"}
            scene = load_scene(write_scene(rec, Path(tmp) / f"scene_{kind}"))
            result = identify_material(scene, obs, ["mu", "kappa", "velocity"], max_steps=args.max_steps,
                                       renderer=args.renderer, num_pixels=args.num_pixels)
            iou = silhouette_iou(simulated_masks(scene, result.params, obs, result.substeps), obs.masks)
            secs = time.perf_counter() - t0
            fall = rec.free_fall
            row = {
                "collider": kind, "renderer": args.renderer, "num_pixels": args.num_pixels, "views": args.views, "res": args.res, "max_steps": args.max_steps,
                "mu": float(result.values["mu"]), "kappa": float(result.values["kappa"]),
                "dlog10_mu": abs(float(np.log10(result.values["mu"] / TRUTH["mu"]))),
                "dlog10_kappa": abs(float(np.log10(max(float(result.values["kappa"]), 1e-30) / TRUTH["kappa"]))),
                "velocity": np.asarray(result.values["velocity"]).tolist(),
                "velocity_error": float(np.linalg.norm(np.asarray(result.values["velocity"]) - truth_v)),
                "free_fall_frames": fall.frames, "free_fall_velocity": None if fall.velocity is None else fall.velocity.tolist(),
                "iou_mean": float(iou.mean()), "iou_min": float(iou.min()), "converged": bool(result.converged),
                "iterations": int(result.iterations), "notes": list(result.notes), "seconds": secs,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| collider | renderer | mu | kappa | |dlog10 mu| | |dlog10 kappa| | velocity error (m/s) | IoU mean / min | iterations | s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['collider']} | {r['renderer']} | {r['mu']:.4g} | {r['kappa']:.4g} | {r['dlog10_mu']:.3f} | {r['dlog10_kappa']:.3f} | "
              f"{r['velocity_error']:.3f} | {r['iou_mean']:.3f} / {r['iou_min']:.3f} | {r['iterations']} | {r['seconds']:.0f} |")
    if args.out:
        with open(args.out, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
