"""The body's visual hull with k = 0 and k = 1 on the degraded drop data, and the k the
default chooses (``jaxmpm.reconstruct.reconstruct_body``: k = 1 when it raises the first
frame's mean silhouette IoU by 0.01 or more).

    python benchmarks/hull_tolerance.py [--min-elevation 0]

The data are ``identify_accuracy.py``'s (6 views of 96 px, the Newtonian drop onto the box;
the body's first frame does not depend on the collider). Prints particles (the truth's
lattice has about 256) and the mean and lowest IoU of the particles' silhouettes with the
first frame's masks. Results: docs/identify.md §4, "Session 50".
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from jaxmpm.reconstruct import read_dataset, reconstruct_body, scene_skeleton
from jaxmpm.reconstruct.synthetic import DEGRADATIONS, render_drop_dataset


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--min-elevation", type=float, default=0.0, help="the lowest camera's elevation, degrees")
    args = ap.parse_args(argv)
    print("| degradation | k = 0: particles, IoU mean / min | k = 1: particles, IoU mean / min | k chosen |")
    print("|---|---|---|---|")
    for degradation in DEGRADATIONS:
        with tempfile.TemporaryDirectory() as tmp:
            folder, _ = render_drop_dataset(Path(tmp) / "ds", views=6, res=96, min_elevation_deg=args.min_elevation,
                                            degradation=degradation)
            ds = read_dataset(folder)
            spec = scene_skeleton(ds, "newtonian")
            cells = []
            for k in (0, 1):
                points, _, iou = reconstruct_body(ds, spec, tolerance=k)
                cells.append(f"{len(points)}, {iou.mean():.3f} / {iou.min():.3f}")
            _, hull, _ = reconstruct_body(ds, spec)
            print(f"| {degradation} | {cells[0]} | {cells[1]} | {hull.tolerance} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
