"""``jaxmpm demo``: simulate a Newtonian droplet, identify mu and kappa from its tracks."""

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


def run_demo(out: Path, quick: bool = False) -> dict:
    """Run the demo and write ``out/{fit.json, loss.png, droplet.mp4, observation.npz}``."""
    from .fit import fit
    from .fit_report import format_table, write_json
    from .observe import Observation, save_observation
    from .plots import loss_curve, particle_video
    from .scene import load_scene
    from .step import run_frames

    out.mkdir(parents=True, exist_ok=True)
    spec = demo_scene(quick)
    scene = load_scene(spec)
    model = scene.model
    say = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    say(f"[1/3] ground truth: Newtonian droplet (mu = {TRUTH['mu']:g}, kappa = {TRUTH['kappa']:g}), "
        f"{model.num_particles} particles, {model.frames} frames x {model.substeps} substeps")
    t0 = time.perf_counter()
    truth_traj = run_frames(model, scene.params)
    positions = np.asarray(truth_traj.x)
    obs = Observation(times=np.asarray(truth_traj.times), positions=positions, point_ids="particles", scene=scene.to_json())
    save_observation(out / "observation.npz", obs)
    say(f"      simulated in {time.perf_counter() - t0:.1f} s")

    guess = dict(spec)
    guess["bodies"] = [dict(spec["bodies"][0], material={"model": "newtonian", "density": 1000.0, **INITIAL_GUESS})]
    start = load_scene(guess)
    say(f"[2/3] identifying mu, kappa from the tracks, starting from PAC-NeRF's guess {INITIAL_GUESS}")
    result = fit(start.model, start.params, obs, ["mu", "kappa"],
                 progress=lambda i, loss: say(f"      iteration {i:3d}  loss {loss:.3e} m^2"))
    fitted = np.asarray(run_frames(start.model.with_substeps(result.substeps), result.params).x)

    say("[3/3] writing results")
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
