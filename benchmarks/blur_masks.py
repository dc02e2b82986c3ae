"""What the ``blur`` degradation does to the material's masks, frame by frame (issue 13: why μ
comes out high on blurred views).

Renders the same drop (jaxmpm.reconstruct.synthetic.render_drop_dataset) clean and blurred
(σ = 1 px, masks read back at alpha >= 128), reads both folders as ``identify`` does and
prints, per frame, the blurred masks' area against the clean ones' (summed over views), their
IoU, the pixels the blur removed and added, and the clean masks' boundary pixels (for scale:
removing the whole boundary is a one-pixel erosion).

    PYTHONPATH=. python benchmarks/blur_masks.py [--collider box --views 6 --res 96 --min-elevation 0]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    from scipy.ndimage import binary_erosion

    from jaxmpm.reconstruct import read_dataset
    from jaxmpm.reconstruct.synthetic import COLLIDERS, render_drop_dataset

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--collider", default="box", choices=sorted(COLLIDERS))
    ap.add_argument("--material", default="newtonian")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--min-elevation", type=float, default=0.0)
    args = ap.parse_args()
    masks = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("clean", "blur"):
            folder, _ = render_drop_dataset(Path(tmp) / kind, views=args.views, res=args.res, material=args.material,
                                            min_elevation_deg=args.min_elevation, collider=args.collider,
                                            degradation=kind)
            ds = read_dataset(folder)
            masks[kind] = np.asarray(ds.observation.masks) > 127
            times = np.asarray(ds.observation.times)
    clean, blur = masks["clean"], masks["blur"]
    print("| frame | t (s) | clean area (px, all views) | blurred / clean area | IoU | removed px | added px "
          "| boundary px (clean) | removed / boundary |")
    print("|---|---|---|---|---|---|---|---|---|")
    for t in range(clean.shape[1]):
        c, b = clean[:, t], blur[:, t]
        boundary = int(sum((m & ~binary_erosion(m)).sum() for m in c))
        removed, added = int((c & ~b).sum()), int((b & ~c).sum())
        print(f"| {t} | {times[t]:.4f} | {int(c.sum())} | {b.sum() / c.sum():.3f} | {(c & b).sum() / (c | b).sum():.3f} "
              f"| {removed} | {added} | {boundary} | {removed / boundary:.2f} |")


if __name__ == "__main__":
    main()
