"""The ``jaxmpm`` command (DESIGN §5.3). User errors print one line and exit with code 2."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from .errors import JaxmpmError, JaxmpmWarning

EXIT_USER_ERROR = 2


def _progress_bar(total: int, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="frame", disable=not sys.stderr.isatty(), leave=False)


#: Video file extensions ``--video`` accepts (ffmpeg containers, or a GIF).
VIDEO_SUFFIXES = (".mp4", ".mov", ".mkv", ".webm", ".gif")


def _check_output_file(flag: str, value: str, suffixes: tuple[str, ...] = ()) -> None:
    """Fail before a long run when the file ``value`` (given as ``flag``) cannot be written."""
    path = Path(value)
    if path.is_dir():
        raise JaxmpmError(f"{flag} {value} is a folder; give a file name")
    if suffixes and path.suffix.lower() not in suffixes:
        raise JaxmpmError(f"{flag} {value}: unsupported file type {path.suffix or '(none)'!r}; use one of {', '.join(suffixes)}")
    _check_can_write(flag, value, path.parent)


def _check_output_folder(flag: str, value: str) -> None:
    """Fail before a long run when the folder ``value`` (given as ``flag``) cannot be written."""
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise JaxmpmError(f"{flag} {value} is a file; give a folder")
    _check_can_write(flag, value, path)


def _check_can_write(flag: str, value: str, folder: Path) -> None:
    """Create ``folder`` (as the command would) and write and remove a probe file in it."""
    import tempfile

    existing = next((p for p in (folder, *folder.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise JaxmpmError(f"{flag} {value}: {existing} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise JaxmpmError(f"{flag} {value}: cannot write into {folder}: {err.strerror or err}") from None


def _param_names(flag: str, text: str | None) -> list[str] | None:
    """The comma-separated names of ``--params``; None when not given. Empty or repeated names are errors."""
    from .identify.parameters import check_names

    return None if text is None else check_names([n.strip() for n in text.split(",")], f"{flag} {text!r}")


def parse_scan(text: str | None) -> tuple[float, ...] | None:
    """:attr:`jaxmpm.FitConfig.scan` from ``--scan``: ``auto`` (or not given) None, the automatic
    choice; ``none`` no scan, ``()``; else comma-separated decade offsets."""
    if text is None or text.strip() == "auto":
        return None
    if text.strip() == "none":
        return ()
    try:
        out = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise JaxmpmError(f"--scan must be auto, none or comma-separated decade offsets such as -1,1,2,3, "
                          f"got {text!r}") from None
    if not all(np.isfinite(out)):
        raise JaxmpmError(f"--scan offsets must be finite, got {text!r}")
    return out


def _check_at_least(flag: str, value: int | None, least: int) -> None:
    if value is not None and value < least:
        raise JaxmpmError(f"{flag} must be >= {least}, got {value}")


# --------------------------------------------------------------------------- simulate


def cmd_simulate(args) -> int:
    from .observe import Observation, save_observation
    from .step import run_frames
    from .scene import load_scene

    _check_output_file("--out", args.out)
    if args.video:
        _check_output_file("--video", args.video, VIDEO_SUFFIXES)
    if args.views:
        _check_at_least("--views", args.views, 1)
        _check_at_least("--res", args.res, 8)
    scene = load_scene(args.scene, dtype=_dtype(args))
    model = scene.model
    if args.views and model.dim != 3:
        raise JaxmpmError("--views needs a 3D scene")
    print(f"scene {args.scene}: {model.num_particles} particles, grid {model.grid.shape}, {model.frames} frames",
          file=sys.stderr)
    _say_step(model, scene.params)
    with _progress_bar(model.frames - 1, "simulate") as bar:
        traj = run_frames(model, scene.params, on_frame=lambda i: bar.update(1))
    positions = np.asarray(traj.x)
    obs = Observation(times=np.asarray(traj.times), positions=positions, point_ids="particles", scene=scene.to_json())
    if args.views:
        obs = _render_into(obs, scene, positions, args)
    out = Path(args.out)
    save_observation(out, obs)
    print(f"wrote {out} ({len(obs.times)} frames, {positions.shape[1]} points)")
    if args.video:
        _write_particle_video(Path(args.video), positions, model, obs)
        print(f"wrote {args.video}")
    return 0


def _render_into(obs, scene, positions, args):
    """Render the trajectory from ``args.views`` cameras of a PAC-NeRF-like rig (45° field of view)
    centred on the particles' bounding box over all frames, far enough to see all of it."""
    from .render import pacnerf_rig, render_views

    lo, hi = positions.min(axis=(0, 1)), positions.max(axis=(0, 1))
    radius = 1.1 * 0.5 * float(np.linalg.norm(hi - lo)) / np.sin(np.deg2rad(45.0) / 2)
    cameras = pacnerf_rig(args.views, radius=radius, target=tuple((lo + hi) / 2), fov_deg=45.0, res=args.res)
    print(f"rendering {args.views} views at {args.res}x{args.res} with the {args.renderer} renderer", file=sys.stderr)
    rendered = render_views(positions, cameras, renderer=args.renderer)
    obs.masks = rendered["masks"]
    obs.images = rendered["images"]
    obs.intrinsics = rendered["intrinsics"]
    obs.cam_to_world = rendered["cam_to_world"]
    obs.validate()
    return obs


def _write_particle_video(path: Path, positions: np.ndarray, model, obs) -> None:
    from .plots import particle_video

    if obs.images is not None:
        from .render import tile_views, write_video

        write_video(path, tile_views(obs.images), fps=max(1, round(1 / model.frame_dt)))
    else:
        particle_video(path, positions, model)


def _say_step(model, params, when: str = "") -> None:
    """One line on stderr: the substeps and the stress-wave stability floor
    (:func:`jaxmpm.step.stable_substeps`), so that a user neither over-refines dt nor waits for
    a run that will stop at its first frame."""
    from .step import stable_substeps

    need = stable_substeps(model, params)
    line = (f"explicit step: {model.substeps} substeps per frame (dt = {model.dt:.3g} s); stable from {need}{when} "
            f"(stress wave c dt/dx <= 1; particle speeds are checked every frame)")
    if model.substeps < need:
        line = f"WARNING: {line}: the step is unstable{when}; set substeps >= {need} in the scene"
    elif model.substeps >= 2 * need:
        line += (f"; {model.substeps / need:.1f}x the floor: fewer substeps would be faster, if a dt/2 rerun "
                 "shows the accuracy holds")
    print(line, file=sys.stderr)


# --------------------------------------------------------------------------- fit


def cmd_fit(args) -> int:
    from .fit import REFINE_VELOCITY, FitConfig, fit_scene
    from .fit_report import format_table, format_timing, write_json
    from .identify.parameters import default_names
    from .observe import load_observation
    from .scene import load_scene

    _check_output_file("--out", args.out)
    _check_at_least("--max-steps", args.max_steps, 1)
    scan = parse_scan(args.scan)
    given = _param_names("--params", args.params)
    scene = load_scene(args.scene, dtype=_dtype(args))
    obs = load_observation(args.observations)
    names = given or default_names(scene.model)
    weights = parse_weights(args.weights)
    say = (lambda msg: None) if args.quiet else (lambda msg: print(f"  {msg}", file=sys.stderr, flush=True))
    print(f"fitting {', '.join(names)} to {args.observations} ({len(obs.times)} frames) with {args.method}",
          file=sys.stderr)
    _say_step(scene.model, scene.params, when=" at the initial guess")

    def progress(i, loss):
        if not args.quiet:
            print(f"  iteration {i:3d}  loss {loss:.4e}", file=sys.stderr, flush=True)

    config = FitConfig(method=args.method, stages=None if args.stages == "single" else "auto", weights=weights,
                       max_steps=args.max_steps, renderer=args.renderer, num_pixels=args.pixels,
                       velocity_until=args.velocity_until, scan=scan, resolution=args.resolution, numerics=args.numerics,
                       refine_velocity=REFINE_VELOCITY[args.refine_velocity],
                       polish=None if args.polish == "auto" else ())
    result = fit_scene(scene, obs, names, config, progress=progress, log=say)
    payload = result.to_json()
    write_json(Path(args.out), payload)
    print(format_table(result))
    if args.profile:
        print(format_timing(result))
    if result.converged:
        print(result.message + f" ({result.seconds:.1f} s); wrote {args.out}")
        return 0
    print(f"WARNING: the fit did not converge: {result.message} ({result.seconds:.1f} s); wrote {args.out} "
          "with \"converged\": false", file=sys.stderr)
    print(f"NOT CONVERGED: {result.message}; wrote {args.out}")
    return 1


def parse_weights(text: str | None) -> dict | None:
    """``"tracks=1,silhouette=0.5"`` -> ``{"tracks": 1.0, "silhouette": 0.5}``."""
    if not text:
        return None
    out = {}
    for item in text.split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise JaxmpmError(f"--weights: expected name=number pairs (e.g. tracks=1,silhouette=0.5), got {item!r}") from None
        if not sep:
            raise JaxmpmError(f"--weights: expected name=number pairs, got {item!r}")
    return out


# --------------------------------------------------------------------------- discover


def cmd_discover(args) -> int:
    """``jaxmpm discover SCENE OBS.npz --out DIR``: the discrepancy workflow (report.md, report.json, plots)."""
    from .discover import discover
    from .discover_report import format_timing, write_report
    from .observe import load_observation
    from .scene import load_scene

    out = Path(args.out)
    _check_output_folder("--out", args.out)
    _check_at_least("--max-iter", args.max_iter, 1)
    names = _param_names("--params", args.params)
    scene = load_scene(args.scene, dtype=_dtype(args))
    obs = load_observation(args.observations)
    exts = [e.strip() for e in args.extensions.split(",") if e.strip()] if args.extensions else None

    def say(line):
        if not args.quiet:
            print(line, file=sys.stderr)

    _say_step(scene.model, scene.params, when=" at the initial guess")
    result = discover(
        scene.model, scene.params, obs, names=names, extensions=exts, holdout=args.holdout, top=args.top,
        min_gain=args.min_gain, alpha=args.alpha, max_extensions=args.max_extensions, max_iter=args.max_iter,
        convergence=not args.no_convergence, numerics=args.numerics, noise_floor=args.noise, num_pixels=args.pixels,
        prune=not args.refit_all, progress=say,
    )
    files = write_report(result, out, title=f"Discrepancy report: {Path(args.scene).name} vs {Path(args.observations).name}")
    if args.profile:
        print(format_timing(result))
    print(result.verdict)
    print(f"wrote {files['report.md']}, {files['report.json']} and {len(files['plots'])} plots")
    return 0


# --------------------------------------------------------------------------- identify


def cmd_identify(args) -> int:
    """``jaxmpm identify DATASET_DIR --material MODEL``: reconstruct, fit, report (jaxmpm.reconstruct)."""
    from .reconstruct.cli import run_identify

    return run_identify(args)


# --------------------------------------------------------------------------- demo, bench


def cmd_demo(args) -> int:
    from .demo import run_demo, run_video_demo

    if args.collider is not None and not args.video:
        raise JaxmpmError("--collider is for the video demo: add --video")
    _check_output_folder("--out", args.out)
    if args.video:
        return 0 if run_video_demo(Path(args.out), quick=args.quick, collider=args.collider or "edge")["converged"] else 1
    run_demo(Path(args.out), quick=args.quick)
    return 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    return run_bench(args.what, args.rest)


# --------------------------------------------------------------------------- entry point


def _dtype(args):
    import jax
    import jax.numpy as jnp

    if getattr(args, "float64", False):
        jax.config.update("jax_enable_x64", True)
        return jnp.float64
    return jnp.float32


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxmpm", description="Differentiable MPM in JAX: simulate, render, identify parameters.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulate a ground truth, identify its parameters, print the table")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--quick", action="store_true", help="a smaller, faster version of the demo")
    p.add_argument("--video", action="store_true",
                   help="identify from rendered multi-view silhouettes (jaxmpm identify) instead of tracks: "
                        "the body and the collider are reconstructed from the views")
    p.add_argument("--collider", choices=("edge", "bunny"), default=None,
                   help="the video demo's collider: the edge of a box (default) or the Stanford bunny")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("simulate", help="run a scene and write an observation file")
    p.add_argument("scene", help="scene file (.toml or .json)")
    p.add_argument("--out", default="observation.npz", help="observation file to write (.npz)")
    p.add_argument("--views", type=int, default=0, help="render this many views (PAC-NeRF rig)")
    p.add_argument("--res", type=int, default=64, help="rendered image size in pixels")
    p.add_argument("--renderer", choices=("volume", "surfels"), default="volume")
    p.add_argument("--video", default=None, help="also write a video (.mp4 or .gif)")
    p.add_argument("--float64", action="store_true", help="simulate in float64")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("fit", help="identify parameters from an observation file")
    p.add_argument("scene", help="scene file (.toml or .json) holding the initial guess")
    p.add_argument("observations", help="observation file (.npz)")
    p.add_argument("--params", default=None, help="comma-separated parameter names (default: the material's)")
    p.add_argument("--out", default="fit.json", help="result file (default: fit.json)")
    p.add_argument("--method", choices=("lm", "adam", "bfgs"), default="lm",
                   help="optimiser: Levenberg-Marquardt (default), Adam (PAC-NeRF's reference) or BFGS")
    p.add_argument("--stages", choices=("auto", "single"), default="auto",
                   help="auto: velocity on pre-contact frames, then a growing frame window (PAC-NeRF); single: one stage")
    p.add_argument("--max-steps", type=int, default=None, help="maximum iterations per stage (default: 40 LM, 60 BFGS, 100 Adam)")
    p.add_argument("--weights", default=None, help="loss weights, e.g. tracks=1,silhouette=1,rgb=0.1,probes=1")
    p.add_argument("--renderer", choices=("volume", "surfels"), default="volume", help="renderer for image losses")
    p.add_argument("--pixels", type=int, default=256, help="pixels rendered per view and frame for image losses")
    p.add_argument("--velocity-until", type=float, default=None,
                   help="last observed time (s) of the velocity stage (default: detected contact)")
    p.add_argument("--refine-velocity", choices=("auto", "yes", "no"), default="auto",  # fit.REFINE_VELOCITY
                   help="refit the velocity with the material after its pre-contact stage: auto (when it rests on "
                        "one observed interval and no per-particle tracks), yes, or no (held, PAC-NeRF)")
    p.add_argument("--scan", default="auto", metavar="DECADES",
                   help="before fitting each log10 parameter, try its guess x 10^d for these d and start from the "
                        "best, e.g. -1,1,2,3 (silhouette losses have plateaus where LM stalls); auto (default): "
                        "-1,1,2,3 without per-particle tracks, none from them; none: no scan")
    p.add_argument("--polish", choices=("auto", "none"), default="auto",
                   help="where the last stage fitting the velocity stops without converging, try moving each "
                        "velocity component by a few mm/s and solve again from a lower loss: auto (default: without "
                        "per-particle tracks), none")
    p.add_argument("--resolution", action="store_true",
                   help="raise each std to the scale the loss resolves where it is rough (noise-free data, CPIC "
                        "contact): two loss evaluations per parameter and try")
    p.add_argument("--numerics", action="store_true",
                   help="after the fit, how far a refit at dt/2 and one with the other transfer (APIC / the FLIP "
                        "blend) move each parameter (a few iterations each, from the result): its numerical error, "
                        "which the std does not include")
    p.add_argument("--quiet", action="store_true", help="no per-iteration output")
    p.add_argument("--float64", action="store_true", help="fit in float64")
    p.add_argument("--profile", action="store_true",
                   help="print where the time went (compilation, iterations, checks, uncertainty) per stage")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("discover", help="show what the model gets wrong, name the cause, extend it, measure the gain")
    p.add_argument("scene", help="scene file (.toml or .json): the base model and the initial guess")
    p.add_argument("observations", help="observation file (.npz)")
    p.add_argument("--out", default="discover_out", help="output folder (default: discover_out)")
    p.add_argument("--params", default=None, help="comma-separated base parameters to fit (default: the materials')")
    p.add_argument("--extensions", default=None, help="comma-separated extension ids to consider (default: all)")
    p.add_argument("--holdout", type=float, default=0.3, help="fraction of the latest observed times held out (default 0.3)")
    p.add_argument("--top", type=int, default=3, help="extensions refitted per greedy step (default 3)")
    p.add_argument("--refit-all", action="store_true",
                   help="refit the --top best whatever their scores, from both starts (default: only significant "
                        "scores, none predicted below a passing refit; use it for silhouettes, where the score can "
                        "understate an effect)")
    p.add_argument("--min-gain", type=float, default=0.1, help="smallest held-out gain kept (default 0.1)")
    p.add_argument("--alpha", type=float, default=0.05, help="level of the likelihood-ratio test (default 0.05)")
    p.add_argument("--max-extensions", type=int, default=3, help="most extensions added greedily (default 3)")
    p.add_argument("--max-iter", type=int, default=25, help="Levenberg-Marquardt iterations per fit (default 25)")
    p.add_argument("--no-convergence", action="store_true",
                   help="skip the numerical checks (the fitted base model at dt/2 and with the other transfer)")
    p.add_argument("--numerics", action="store_true",
                   help="also refit the base and the extended model at dt/2 and with the other transfer (a few "
                        "iterations each, from their fits): how far each parameter moves, its numerical error, which "
                        "the std does not include")
    p.add_argument("--noise", type=float, default=None, help="known observation noise (RMS, data units)")
    p.add_argument("--pixels", type=int, default=256, help="pixels per view and frame for silhouettes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--float64", action="store_true", help="run in float64")
    p.add_argument("--profile", action="store_true",
                   help="print where the time went (rollouts, Jacobian rollouts, compilation, host work) per phase; "
                        "report.json and report.md carry it too")
    p.set_defaults(func=cmd_discover)

    from .reconstruct.cli import add_identify_parser

    add_identify_parser(sub, cmd_identify)

    p = sub.add_parser("bench", help="performance benchmarks")
    p.add_argument("what", choices=("step", "scaling", "memory", "sysid", "grad"),
                   help="step (vs Taichi/Warp), scaling (time vs particles and grid), memory (long gradient), "
                        "sysid (identification benchmark), grad (reverse mode vs Taichi autodiff, forward-mode "
                        "Jacobians)")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to the benchmark")
    p.set_defaults(func=cmd_bench)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """jaxmpm's own warnings as one plain line on stderr (others as Python shows them)."""
    if issubclass(category, JaxmpmWarning):
        print(f"warning: {message}", file=sys.stderr)
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def main(argv: list[str] | None = None) -> int:
    from .cache import enable_compilation_cache

    args = build_parser().parse_args(argv)
    enable_compilation_cache()  # compiled programs are reused by later runs (JAXMPM_CACHE_DIR=off: not)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return args.func(args)
    except (JaxmpmError, OSError) as err:  # OSError: an unwritable --out, a full disk
        print(f"jaxmpm {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
