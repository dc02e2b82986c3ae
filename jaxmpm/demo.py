"""``jaxmpm demo``: simulate a Newtonian droplet, identify mu and kappa from its tracks
(``--video``: from multi-view silhouettes, through ``jaxmpm identify``)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

#: Ground truth of the built-in scene: PAC-NeRF's droplet (mu = 200, kappa = 1e5) falling
#: onto a sticky floor. PAC-NeRF's initial guess for this scene is mu = 1, kappa = 1e3.
TRUTH = {"mu": 200.0, "kappa": 1e5}
INITIAL_GUESS = {"mu": 1.0, "kappa": 1e3}


def demo_scene(quick: bool = False) -> dict:
    """The built-in scene spec (3D; ``quick`` makes it coarser and shorter)."""
    dx = 0.05 if quick else 0.04
    return {
        "dim": 3,
        "dx": dx,
        "domain": {"lo": [0.0, 0.0, 0.0], "hi": [0.8, 0.8, 0.8]},
        "gravity": [0.0, -9.8, 0.0],
        "frames": 10 if quick else 14,
        "frame_dt": 1.0 / 24.0,
        "substeps": 80 if quick else 100,
        "bodies": [
            {
                "shape": "sphere",
                "center": [0.4, 0.3, 0.4],
                "radius": 0.12,
                "ppc": 8,
                "velocity": [0.5, -1.0, 0.0],
                "material": {"model": "newtonian", "density": 1000.0, **TRUTH},
            }
        ],
        "colliders": [{"type": "plane", "name": "floor", "point": [0.0, 0.1, 0.0], "normal": [0.0, 1.0, 0.0], "contact": "sticky"}],
    }


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _ground_truth(quick: bool):
    """Stage 1 of both demos: the built-in scene and its simulated truth, announced on stderr.
    Returns ``(spec, scene, trajectory)``."""
    from .scene import load_scene
    from .step import run_frames

    spec = demo_scene(quick)
    scene = load_scene(spec)
    model = scene.model
    _say(f"[1/3] ground truth: Newtonian droplet (mu = {TRUTH['mu']:g}, kappa = {TRUTH['kappa']:g}), "
         f"{model.num_particles} particles, {model.frames} frames x {model.substeps} substeps")
    return spec, scene, run_frames(model, scene.params)


def run_demo(out: Path, quick: bool = False) -> dict:
    """Run the demo and write ``out/{fit.json, loss.png, droplet.mp4, observation.npz}``."""
    from .fit import fit
    from .fit_report import format_table, write_json
    from .observe import Observation, save_observation
    from .plots import loss_curve, particle_video
    from .scene import load_scene
    from .step import run_frames

    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    spec, scene, truth_traj = _ground_truth(quick)
    model = scene.model
    positions = np.asarray(truth_traj.x)
    obs = Observation(times=np.asarray(truth_traj.times), positions=positions, point_ids="particles", scene=scene.to_json())
    save_observation(out / "observation.npz", obs)
    _say(f"      simulated in {time.perf_counter() - t0:.1f} s")

    guess = dict(spec)
    guess["bodies"] = [dict(spec["bodies"][0], material={"model": "newtonian", "density": 1000.0, **INITIAL_GUESS})]
    start = load_scene(guess)
    _say(f"[2/3] identifying mu, kappa from the tracks, starting from PAC-NeRF's guess {INITIAL_GUESS}")
    result = fit(start.model, start.params, obs, ["mu", "kappa"],
                 progress=lambda i, loss: _say(f"      iteration {i:3d}  loss {loss:.3e} m^2"),
                 log=lambda message: _say(f"      {message}"))
    fitted = np.asarray(run_frames(start.model.with_substeps(result.substeps), result.params).x)

    _say("[3/3] writing results")
    payload = result.to_json()
    payload["truth"] = TRUTH
    write_json(out / "fit.json", payload)
    loss_curve(out / "loss.png", result.loss, title="droplet: Levenberg–Marquardt on tracks")
    video = particle_video(out / "droplet.mp4", positions, model, overlay=fitted)
    print()
    print(format_table(result, truth=TRUTH))
    print()
    print(f"{result.message}; identification took {result.seconds:.1f} s")
    print(f"wrote {out / 'fit.json'}, {out / 'loss.png'}, {video}, {out / 'observation.npz'}")
    return json.loads(json.dumps(payload))


#: The video demo's rig: the identify benchmark's (docs/identify.md §3): 6 views of 96 px, the
#: lowest level with the collider's top (it carves the collider's roof), the highest at 60°.
VIDEO_VIEWS, VIDEO_RES = 6, 96
#: The video demo's colliders (:data:`jaxmpm.reconstruct.synthetic.COLLIDERS`).
VIDEO_COLLIDERS = ("edge", "bunny")


def run_video_demo(out: Path, quick: bool = False, max_steps: int | None = None, collider: str = "edge") -> dict:
    """The demo from video: a Newtonian block (mu = 200, kappa = 1e5) thrown down onto the
    edge of a box or onto the bunny (``collider``, one of :data:`VIDEO_COLLIDERS`) is
    simulated and rendered from :data:`VIDEO_VIEWS` cameras as a PAC-NeRF folder
    (``out/dataset``: silhouettes, images, plates (the painted collider on white), collider masks, and a hint with what a
    person knows: the floor, the frame rate, the domain and dx;
    :func:`jaxmpm.reconstruct.synthetic.render_drop_dataset`); then
    :func:`jaxmpm.identify_dataset` runs on it (``out/identify``: scene, fit.json, report.md,
    overlay video). The body's shape, its velocity, gravity and the collider (fitted 2D
    Gaussian surfels) come from the views. Prints the estimates against the truth and the
    reconstructed collider's Chamfer distance to the true one.

    ``quick``: 4 views of 64 px (the plumbing; the estimates are not meant to be accurate)."""
    from .fit_report import format_table
    from .reconstruct import chamfer_distance, identify
    from .reconstruct.synthetic import COLLIDERS, MATERIAL_TRUTHS, collider_mesh, drop_scene, render_drop_dataset

    if collider not in VIDEO_COLLIDERS:
        raise ValueError(f"unknown video demo collider {collider!r}; one of {VIDEO_COLLIDERS}")
    out.mkdir(parents=True, exist_ok=True)
    views, res = (4, 64) if quick else (VIDEO_VIEWS, VIDEO_RES)
    spec = drop_scene(collider)
    truth = {**MATERIAL_TRUTHS["newtonian"], "velocity": spec["bodies"][0]["velocity"]}
    where = "the edge of a box" if collider == "edge" else "the Stanford bunny"
    _say(f"[1/3] ground truth: a Newtonian block (mu = {truth['mu']:g}, kappa = {truth['kappa']:g}) thrown down onto "
         f"{where}, {spec['frames']} frames x {spec['substeps']} substeps; rendering {views} views at {res} px")
    folder, _ = render_drop_dataset(out / "dataset", views=views, res=res, frames=spec["frames"], min_elevation_deg=0.0,
                                    collider=collider)
    _say(f"[2/3] identifying from the silhouettes in {folder} (jaxmpm identify: reconstruct the body and the "
         "collider, free fall, fit)")
    result = identify(folder, "newtonian", out / "identify", max_steps=max_steps,
                      stage=lambda name: _say(f"      [identify] {name}"),
                      progress=lambda i, loss: _say(f"      iteration {i:3d}  loss {loss:.3e}"))
    _say("[3/3] results")
    print()
    print(format_table(result.fit, truth=truth))
    print()
    rec = result.reconstruction
    chamfer = {}
    if rec.collider_mesh is not None:
        true_surface = collider_mesh(COLLIDERS[collider]).sample(20000, seed=0)
        chamfer["mesh"] = chamfer_distance(np.asarray(rec.collider_mesh.sample(20000, seed=0)), true_surface)
        if rec.surfels is not None:
            chamfer["surfels"] = chamfer_distance(rec.surfels.centers, true_surface)
        print(f"collider from the views: {rec.collider}; Chamfer distance to the true {collider}: "
              + ", ".join(f"{k} {1e3 * v:.1f} mm" for k, v in chamfer.items()) + f" (dx = {1e3 * spec['dx']:g} mm)")
    for w in result.warnings:
        print(f"warning: {w}")
    fall = rec.free_fall
    if fall is not None and fall.gravity is not None:
        print(f"gravity from the free fall ({fall.frames} frames): "
              + ", ".join(f"{g:.2f}" for g in fall.gravity) + " m/s^2 (truth 0, -9.8, 0)")
    print(f"{result.fit.message}; identification took {result.fit.seconds:.1f} s")
    print(f"wrote {', '.join(str(p) for p in result.files.values())}")
    return {"params": {k: np.asarray(v).tolist() for k, v in result.fit.values.items()}, "truth": truth,
            "converged": bool(result.fit.converged), "files": {k: str(v) for k, v in result.files.items()},
            "collider": collider, "chamfer_m": chamfer}
