"""The ``jaxmpm identify`` verb's options and driver (cli.py holds only its registration)."""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import JaxmpmError


def add_identify_parser(sub, func) -> None:
    """Register ``identify`` on the ``jaxmpm`` sub-parsers with ``func`` as its handler."""
    p = sub.add_parser("identify", help="reconstruct body and colliders from a PAC-NeRF-layout folder, then identify")
    p.add_argument("dataset", help="PAC-NeRF-layout folder (all_data.json, data/r_*, optional data/c_* and scene_hint.toml)")
    p.add_argument("--material", required=True, help="material model (newtonian, viscoplastic, sand, elastic, plasticine)")
    p.add_argument("--params", default=None, help="comma-separated parameters (default: the material's and velocity)")
    p.add_argument("--hint", default=None, help="scene hint (.toml/.json; default DATASET_DIR/scene_hint.toml)")
    p.add_argument("--out", default="identify_out", help="output folder (default: identify_out)")
    p.add_argument("--collider", choices=("mesh", "disks"), default="mesh",
                   help="reconstructed collider the scene uses: the hull mesh (default) or the fitted surfels "
                        "(both are written)")
    p.add_argument("--tolerance", type=int, default=None,
                   help="k: a hull voxel is kept when >= V-k views see it (default: 1 when that matches the first "
                        "frame's masks better and there are 4 views or more, else 0)")
    p.add_argument("--max-steps", type=int, default=None, help="fit iterations per stage (default: fit's)")
    p.add_argument("--pixels", type=int, default=256, help="pixels rendered per view and frame in the fit")
    p.add_argument("--surfel-steps", type=int, default=80, help="Adam steps of the collider surfel fit")
    p.add_argument("--refine", type=int, default=0, metavar="STEPS",
                   help="Adam steps of the first-frame refinement of the body's particles on the masks and RGB "
                        "(default 0: the visual hull's particles)")
    p.add_argument("--rgb", type=float, default=0.0, metavar="WEIGHT",
                   help="weight of the masked-RGB term in the fit, beside the silhouettes' 1 (default 0)")
    p.add_argument("--collider-rgb", type=float, default=0.0, metavar="WEIGHT",
                   help="weight of the background plates' colours in the collider surfel fit (default 0: masks only)")
    # the choices are fit.REFINE_VELOCITY's keys (not imported here: the CLI starts without jaxmpm.fit)
    p.add_argument("--refine-velocity", nargs="?", choices=("auto", "yes", "no"), default="auto", const="yes",
                   help="refit the initial velocity with the material after the pre-contact stage: yes (the flag "
                        "alone), no (keep the pre-contact estimate), auto (default: no, unless the masks' areas jump "
                        "from frame to frame by more than 10 %%)")
    p.add_argument("--numerics", action="store_true",
                   help="after the fit, how far a refit at dt/2 and one with the other transfer (APIC / the FLIP "
                        "blend) move each parameter: its numerical error, which the std does not include")
    p.add_argument("--recalibrate-views", action="store_true",
                   help="move the principal point of every view whose masks sit 1 px or more off the other views' "
                        "visual hull by that offset (default: only warn; the check runs on 3 views or more)")
    p.add_argument("--no-video", action="store_true", help="skip the overlay video")
    p.set_defaults(func=func)


def run_identify(args) -> int:
    """Run :func:`jaxmpm.reconstruct.identify` with a progress bar per stage; print the table."""
    from tqdm.auto import tqdm

    from ..fit import REFINE_VELOCITY
    from .pipeline import identify

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise JaxmpmError(f"--out {args.out} is a file; give a folder")
    names = [n.strip() for n in args.params.split(",") if n.strip()] if args.params else None
    bars: dict = {}

    def stage(name):
        for bar in bars.values():
            bar.close()
        bars.clear()
        print(f"[identify] {name}", file=sys.stderr, flush=True)
        bars["bar"] = tqdm(desc=name, unit="it", disable=not sys.stderr.isatty(), leave=False)

    told: list[str] = []

    def warn(message):
        told.append(message)
        print(f"warning: {message}", file=sys.stderr, flush=True)

    def progress(i, loss):
        if "bar" in bars:
            bars["bar"].update(1)
            bars["bar"].set_postfix(loss=f"{loss:.3e}")

    try:
        res = identify(args.dataset, args.material, out, params=names, hint=args.hint, tolerance=args.tolerance,
                       collider=args.collider, max_steps=args.max_steps, num_pixels=args.pixels,
                       surfel_steps=args.surfel_steps, refine=args.refine, rgb=args.rgb,
                       collider_rgb=args.collider_rgb, refine_velocity=REFINE_VELOCITY[args.refine_velocity],
                       numerics=args.numerics,
                       recalibrate_views=args.recalibrate_views, video=not args.no_video,
                       stage=stage, progress=progress, warn=warn)
    finally:
        for bar in bars.values():
            bar.close()
    fit = res.fit
    for name, value in fit.values.items():
        print(f"{name} = {value}  (std {fit.std.get(name)})")
    print(f"first-frame IoU per view: {', '.join(f'{x:.3f}' for x in res.reconstruction.body_iou)}; "
          f"IoU over all frames: min {res.iou.min():.3f}, mean {res.iou.mean():.3f}")
    for w in res.warnings:
        if w not in told:
            print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(str(p) for p in res.files.values())}")
    return 0 if fit.converged else 1
