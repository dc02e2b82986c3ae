"""How much the silhouettes of a raw-view identification case see each parameter.

The case of benchmarks/identify_accuracy.py (a block of ``--material`` thrown onto the
``--collider``, rendered from 6 views of 96 px, the lowest level with the collider's top) is
reconstructed from its views (body hull, the collider's hull mesh; ``--degrade`` degrades the views first, as
``identify_accuracy.py --degrade``); the reconstructed scene is
then simulated with the true parameters and true velocity, and with one parameter at a time
moved by each of ``--decades`` (log10 parameters; the friction angle and ν by ``--offsets``
degrees / units), and each run's silhouettes are compared with the observed masks (IoU, mean
and minimum over views and frames, and the pixels where they differ, summed over views and
frames: the squared silhouette error of binary masks, what the fit's loss measures). A parameter whose moves barely change the IoU, or change
it less than the reconstruction's own mismatch (the truth's IoU below 1), cannot be found
from these views.

    PYTHONPATH=. python benchmarks/identify_sensitivity.py --material viscoplastic --collider edge \
        [--decades -2,-1,1 --set eta=0.0209,mu=3822]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    from jaxmpm.identify.parameters import with_values
    from jaxmpm.reconstruct import read_dataset, reconstruct, silhouette_iou, write_scene
    from jaxmpm.reconstruct.pipeline import simulated_masks
    from jaxmpm.reconstruct.synthetic import COLLIDERS, DEGRADATIONS, MATERIAL_TRUTHS, drop_scene, render_drop_dataset
    from jaxmpm.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--material", default="viscoplastic", choices=sorted(MATERIAL_TRUTHS))
    ap.add_argument("--collider", default="edge", choices=sorted(COLLIDERS))
    ap.add_argument("--degrade", default="clean", choices=DEGRADATIONS)
    ap.add_argument("--decades", default="-2,-1,1", help="moves of log10 parameters")
    ap.add_argument("--offsets", default="-5,5", help="moves of the friction angle (degrees) and nu (x 0.02)")
    ap.add_argument("--velocity", default=None, help="x,y,z (m/s) of every row (default: the true velocity), e.g. "
                                                     "a fit's estimate")
    ap.add_argument("--set", default="", help="extra rows: name=value,... (e.g. a fit's estimates), one per name "
                                              "and one with all of them")
    args = ap.parse_args()
    truth = MATERIAL_TRUTHS[args.material]
    velocity = np.asarray(drop_scene(args.collider, material=args.material)["bodies"][0]["velocity"], float)
    which = "true"
    if args.velocity:
        velocity, which = np.asarray([float(v) for v in args.velocity.split(",")]), "given"
    with tempfile.TemporaryDirectory() as tmp:
        folder, _ = render_drop_dataset(Path(tmp) / "ds", views=6, res=96, min_elevation_deg=0.0,
                                        material=args.material, collider=args.collider, degradation=args.degrade)
        ds = read_dataset(folder)
        obs = ds.observation
        scene = load_scene(write_scene(reconstruct(ds, args.material, surfels=False), Path(tmp) / "scene"))

        def row(label: str, values: dict) -> None:
            p = with_values(scene.model, scene.params, {**values, "velocity": velocity})
            sim = simulated_masks(scene, p, obs)
            i = silhouette_iou(sim, obs.masks)
            differ = int(np.sum((sim > 127) != (np.asarray(obs.masks) > 127)))
            print(f"| {label} | {i.mean():.4f} | {i.min():.4f} | {differ} | {' '.join(f'{x:.3f}' for x in i.mean(axis=0))} |",
                  flush=True)

        print(f"{args.material} on the {args.collider} ({args.degrade}), reconstructed scene, {which} velocity "
              f"{velocity.tolist()}\n")
        print("| parameters | IoU mean | IoU min | pixels differing | IoU per frame (mean over views) |\n|---|---|---|---|---|")
        row("truth " + ", ".join(f"{k} {v:g}" for k, v in truth.items()), truth)
        for name, value in truth.items():
            linear = name in ("friction_angle", "nu")
            moves = args.offsets if linear else args.decades
            for d in (float(m) for m in moves.split(",")):
                moved = value + (0.02 * d if name == "nu" else d) if linear else value * 10**d
                row(f"{name} {moved:.4g} ({'%+g' % d}{'' if linear else ' decades'})", {**truth, name: moved})
        extra = {k: float(v) for k, v in (kv.split("=") for kv in args.set.split(",") if kv)}
        for name, value in extra.items():
            row(f"{name} {value:.4g}", {**truth, name: value})
        if len(extra) > 1:
            row("all of " + ", ".join(extra), {**truth, **extra})


if __name__ == "__main__":
    main()
