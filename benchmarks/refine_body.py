"""What the first-frame refinement (`jaxmpm.reconstruct.refine_body`) does to a visual hull.

A sphere of radius 0.1 m (or a 0.2 m cube, ``--shape cube``), textured with smooth colour
blotches (or one colour, ``--plain``), is rendered with surfels from a few views of the rig
of `jaxmpm.reconstruct.synthetic.drop_cameras`; its visual hull gives particles on the body
lattice (spacing 0.025 m), which are refined from the masks only and from masks + RGB. Prints,
for the hull and each refinement: particles, volume error against the truth, particles outside
the true shape (excess) and true-shape particles lost, first-frame IoU per view.

    PYTHONPATH=. python benchmarks/refine_body.py [--views 4 --res 96 --min-elevation 15 --steps 60]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    from jaxmpm.reconstruct import hull_particles, refine_body, visual_hull
    from jaxmpm.reconstruct.synthetic import drop_cameras
    from jaxmpm.render import render_views

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shape", choices=("sphere", "cube"), default="sphere")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--min-elevation", type=float, default=15.0)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--plain", action="store_true", help="one colour: the RGB carries nothing the masks do not")
    args = ap.parse_args()
    spacing, centre, r = 0.025, np.array([0.3, 0.3, 0.3]), 0.1
    fine = spacing / 2
    g = np.arange(-r + fine / 2, r, fine)
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    inside = (lambda p: np.linalg.norm(p - centre, axis=1) <= r) if args.shape == "sphere" else \
        (lambda p: np.all(np.abs(p - centre) <= r, axis=1))
    truth = centre + cube[inside(centre + cube)]
    true_volume = 4 / 3 * np.pi * r**3 if args.shape == "sphere" else (2 * r) ** 3
    if args.plain:
        colors = np.full((len(truth), 3), 0.7)
    else:  # smooth blotches: three sines of the position with different phases per channel
        k = 2 * np.pi / 0.08
        colors = 0.5 + 0.4 * np.stack([np.sin(k * truth[:, 0] + 2 * c) * np.cos(k * truth[:, 1 + c % 2] - c) for c in range(3)], 1)
    cams = drop_cameras(args.views, args.res, args.min_elevation)
    rendered = render_views(truth[None].astype(np.float32), cams, "surfels", colors=colors, spacing=fine)
    masks, images = rendered["masks"][:, 0], rendered["images"][:, 0]
    K, P = rendered["intrinsics"], rendered["cam_to_world"]
    hull = visual_hull(masks, K, P, centre - 2 * r, centre + 2 * r, spacing)
    points = hull_particles(hull, spacing)

    def describe(name, pts, iou, seconds=None):
        excess = int((~inside(pts)).sum())
        vol = len(pts) * spacing**3
        print(f"{name:>18}: {len(pts):4d} particles, volume {vol / true_volume - 1:+.1%}, outside the truth {excess:3d}, "
              f"IoU {' '.join(f'{v:.3f}' for v in iou)}" + (f"  ({seconds:.0f} s)" if seconds else ""))

    print(f"{args.shape} r = {r} m, {'plain' if args.plain else 'textured'}; {args.views} views x {args.res} px, "
          f"lowest {args.min_elevation}°; lattice spacing {spacing} m (truth {true_volume / spacing**3:.0f} particles)")
    base = refine_body(points, masks, K, P, spacing, steps=0)
    describe("hull", points, base.iou_before)
    lost_ref = inside(points)
    for name, imgs in (("masks", None), ("masks + RGB", images)):
        t0 = time.perf_counter()
        ref = refine_body(points, masks, K, P, spacing, images=imgs, steps=args.steps)
        describe(name, ref.points, ref.iou_after, time.perf_counter() - t0)
        kept = ref.opacity >= 0.5
        print(f"{'':>18}  removed {ref.removed} ({int((~kept & ~lost_ref).sum())} outside the truth, "
              f"{int((~kept & lost_ref).sum())} inside); loss {ref.loss[0]:.4g} -> {ref.loss[-1]:.4g}")


if __name__ == "__main__":
    main()
