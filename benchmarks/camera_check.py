"""The cameras' consistency check (``jaxmpm.reconstruct.view_offsets``) on rendered datasets:
does it find a view shifted by 3 px, by how much, and does it leave consistent views alone?

    python benchmarks/camera_check.py [--out rows.jsonl]

Each case renders a drop dataset (6 views of 96 px, ``render_drop_dataset``) and runs the
check as ``jaxmpm identify`` does; a row per case: the flagged views and their offsets, the
largest offset of the others, and the check's wall time. Figures in docs/identify.md, stage 2.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

#: (material, collider, lowest view's elevation in degrees, degradation)
CASES = (
    [("newtonian", "box", 0.0, d) for d in ("clean", "shift", "jitter", "drop", "drop_high", "blur", "dark")]
    + [("newtonian", "edge", 0.0, "clean"), ("elastic", "edge", 0.0, "clean"), ("sand", "bunny", 0.0, "clean"),
       ("viscoplastic", "bunny", 0.0, "clean"), ("newtonian", "box", 15.0, "clean"),
       ("newtonian", "bunny", 0.0, "shift"), ("sand", "edge", 0.0, "shift")]
)


def main() -> None:
    from jaxmpm.reconstruct import read_dataset, scene_skeleton, view_offsets
    from jaxmpm.reconstruct.synthetic import render_drop_dataset

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None, help="append the rows to this .jsonl file")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (material, collider, elevation, degradation) in enumerate(CASES):
            folder, _ = render_drop_dataset(Path(tmp) / f"ds{i}", views=6, res=96, min_elevation_deg=elevation,
                                            material=material, collider=collider, degradation=degradation)
            ds = read_dataset(folder)
            obs, domain = ds.observation, scene_skeleton(ds, material)["domain"]
            t0 = time.perf_counter()
            res = view_offsets(obs.masks, obs.intrinsics, obs.cam_to_world, domain["lo"], domain["hi"])
            seconds = time.perf_counter() - t0
            flagged = res.flagged()
            row = {"material": material, "collider": collider, "min_elevation": elevation, "degrade": degradation,
                   "views": int(obs.masks.shape[0]), "flagged": np.flatnonzero(flagged).tolist(),
                   "flagged_offsets_px": np.round(res.offsets[flagged], 3).tolist(),
                   "largest_other_offset_px": round(float(np.abs(res.offsets[~flagged]).max()), 3),
                   "offsets_px": np.round(res.offsets, 3).tolist(), "seconds": round(seconds, 2)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| material | collider | lowest view | data | flagged (offset px) | largest other offset px | s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        flagged = ", ".join(f"view {v} ({o[0]:+.2f}, {o[1]:+.2f})" for v, o in zip(r["flagged"], r["flagged_offsets_px"]))
        print(f"| {r['material']} | {r['collider']} | {r['min_elevation']:g}° | {r['degrade']} | {flagged or 'none'} | "
              f"{r['largest_other_offset_px']:.2f} | {r['seconds']:.1f} |")
    if args.out:
        with open(args.out, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
