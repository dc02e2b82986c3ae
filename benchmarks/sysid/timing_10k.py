"""Cost of one identification step at ~10k particles (the timing target's scale).

Builds the benchmark's Newtonian-on-box case at dx = 0.02 (8,000 particles, a 0.2 m cube
at 8 particles per cell; 56^3 grid) and times, after compilation:

* one forward rollout of 16 frames (``simulate``),
* one Levenberg–Marquardt evaluation (residuals + forward-mode Jacobian for mu, kappa) on
  tracks,
* the same for silhouettes (11 views, 128 pixels per view and frame),

and the compile time of each. ``--fit`` also runs the whole staged identification (from
tracks, or with ``--fit-from silhouettes`` from the 11 views' masks and colours, weighted as
in the sysid benchmark's silhouette cases; `--scan`: the log10 parameters' starting
decades scanned first, as `jaxmpm identify` does). Prints one JSON line.

    python benchmarks/sysid/timing_10k.py [--substeps 100] [--fit | --fit-only] [--fit-from silhouettes] [--scan]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np


def main() -> None:
    from jaxmpm.bench_sysid import Case, INITIAL_GUESS, Preset, fit_reporters, rig, scene_spec, truth_values
    from jaxmpm.fit import FitConfig, fit
    from jaxmpm.identify.parameters import apply_unconstrained, to_unconstrained
    from jaxmpm.identify.residuals import build_objective, make_fit_renderer
    from jaxmpm.identify.solvers import residuals_and_jacobian
    from jaxmpm.observe import Observation
    from jaxmpm.render import render_views
    from jaxmpm.scene import load_scene
    from jaxmpm.step import simulate

    parser = argparse.ArgumentParser()
    parser.add_argument("--dx", type=float, default=0.02)
    parser.add_argument("--substeps", type=int, default=100)
    parser.add_argument("--fit", action="store_true", help="also run the whole identification from tracks")
    parser.add_argument("--fit-only", action="store_true", help="only the forward rollout and the identification")
    parser.add_argument("--no-images", action="store_true")
    parser.add_argument("--fit-from", choices=("tracks", "silhouettes"), default="tracks")
    parser.add_argument("--scan", action="store_true",
                        help="scan the log10 parameters' starting decades first (jaxmpm.fit.SCAN_DECADES); without "
                             "it no scan, as before session 34 (fit's default scans silhouette fits)")
    args = parser.parse_args()

    preset = Preset(dx=args.dx, substeps=args.substeps, frames=16, views=11, res=96, pixels=128, sets=1, max_steps=25)
    case = Case("newtonian", "box", 0, "tracks", "cpic")
    truth = truth_values("newtonian", 0)
    scene = load_scene(scene_spec(case, preset, truth))
    out = {"particles": scene.model.num_particles, "grid": list(scene.model.grid.shape), "dx": args.dx,
           "substeps": scene.model.substeps, "frames": 16}

    def partial():  # a partial line after every measurement (a shared machine may not finish)
        out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        out["load_average"] = os.getloadavg()[0]
        print("TIMING-PARTIAL " + json.dumps(out), flush=True)

    run = jax.jit(lambda p: simulate(scene.model, p, checkpoint=None).x)
    t0, c0 = time.perf_counter(), time.process_time()
    x = np.asarray(run(scene.params))
    out["forward_compile_and_run_s"] = time.perf_counter() - t0
    out["forward_compile_and_run_cpu_s"] = time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    x = np.asarray(run(scene.params))
    out["forward_s"] = time.perf_counter() - t0
    out["forward_cpu_s"] = time.process_time() - c0
    partial()
    times = np.arange(16) / 24.0
    names = ["mu", "kappa"]
    y = {n: to_unconstrained(n, jnp.asarray(INITIAL_GUESS["newtonian"][n] * 3.0, jnp.float32)) for n in names}

    def time_rj(obs, weights, label):
        objective = build_objective(scene.model, obs, weights=weights, num_pixels=preset.pixels, colors=None)

        def residuals(yy):
            return objective.residuals(apply_unconstrained(scene.model, scene.params, names, yy))

        rj, flat, _ = residuals_and_jacobian(residuals, y)
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(rj(flat))
        out[f"{label}_rj_compile_and_run_s"] = time.perf_counter() - t0
        out[f"{label}_rj_compile_and_run_cpu_s"] = time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(rj(flat))
        out[f"{label}_rj_s"] = time.perf_counter() - t0
        out[f"{label}_rj_cpu_s"] = time.process_time() - c0
        partial()

    tracks = Observation(times=times, positions=x, point_ids="particles")
    if not args.fit_only:
        time_rj(tracks, None, "tracks")
    images = None
    if not args.no_images and (not args.fit_only or args.fit_from == "silhouettes"):
        rendered = render_views(x, rig(preset), make_fit_renderer("volume", scene.model))
        images = Observation(times=times, masks=rendered["masks"], images=rendered["images"],
                             intrinsics=rendered["intrinsics"], cam_to_world=rendered["cam_to_world"])
    if images is not None and not args.fit_only:
        time_rj(images, {"silhouette": 1.0}, "silhouettes")
    if args.fit or args.fit_only:
        start = load_scene(scene_spec(case, preset, INITIAL_GUESS["newtonian"], velocity=(0.0, 0.0, 0.0)))
        if args.fit_from == "tracks":
            obs, config = tracks, FitConfig(max_steps=preset.max_steps)
        else:  # as the sysid benchmark's silhouette cases
            obs, config = images, FitConfig(weights={"silhouette": 1.0, "rgb": 0.1}, max_steps=preset.max_steps,
                                             num_pixels=preset.pixels, colors=None)
        from jaxmpm.fit import SCAN_DECADES

        config = dataclasses.replace(config, scan=SCAN_DECADES if args.scan else ())
        out["fit_from"], out["scan"] = args.fit_from, config.scan
        t0, c0 = time.perf_counter(), time.process_time()
        result = fit(start.model, start.params, obs, names + ["velocity"], config, **fit_reporters(t0))
        out["fit_s"] = time.perf_counter() - t0
        out["fit_cpu_s"] = time.process_time() - c0
        out["fit_message"] = result.message
        out["fit_iterations"] = result.iterations
        out["fit_converged"] = result.converged
        out["fit_errors"] = {n: abs(float(np.log10(result.values[n] / truth[n]))) for n in names}
        out["fit_timing"] = json.loads(json.dumps(result.timing, default=float))
        out["fit_stages"] = [{k: r.get(k) for k in ("iterations", "message", "timing")} for r in result.stages]
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    out["load_average"] = os.getloadavg()[0]
    print("TIMING-JSON " + json.dumps(out))


if __name__ == "__main__":
    main()
