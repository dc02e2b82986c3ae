"""Does the transfer bias the viscosity a fit identifies? APIC against the FLIP blend in fits.

    python benchmarks/flip_fit.py [--mu 0.5,5,50] [--cells 10,20] [--ref-cells 40] [--out DIR]

A 2D column of a Newtonian fluid (0.1 m wide, 0.2 m high, PAC-NeRF's model with a weakly
compressible bulk modulus, sqrt(kappa / rho) = 22 m/s) collapses on a free-slip floor for
0.3 s. The data are four depth gauges (``jaxmpm.identify.depth_gauge`` at x = 0.05, 0.15,
0.25 and 0.35 m, each 2 cm wide) read every frame (10 ms) from a *reference* run on a fine
grid (``--ref-cells`` cells across the column, the FLIP blend 0.99, and APIC as a check of the
reference itself). At the coarse grids (``--cells``) the script fits the viscosity ``mu``
alone (Levenberg-Marquardt, one stage over all frames, started at three times the truth)
once with APIC (``flip = 0``) and once with ``flip = 0.99``, and reports the identified
``mu`` against the truth. APIC's transfers take kinetic energy out at every step
(docs/materials.md, "Transfers"), a numerical viscosity a fit can only absorb into ``mu``;
the blend keeps most of it. This measures how much that moves an identified viscosity.

Each row goes to ``OUT/rows.jsonl`` as soon as it is measured (a rerun skips the rows it
already has), the reference readings to ``OUT/reference_*.npz``; results in docs/materials.md
("In fits").
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

G = 9.81
WIDTH, HEIGHT = 0.1, 0.2
LENGTH = 0.6
FRAMES, FRAME_DT = 30, 0.01
GAUGES = (0.05, 0.15, 0.25, 0.35)
GAUGE_WIDTH = 0.02
KAPPA = 1000.0 * 22.4**2


def spec(cells: int, mu: float, flip: float) -> dict:
    """The column at ``cells`` cells across its width (2 x 2 particles a cell)."""
    return {
        "dim": 2, "dx": WIDTH / cells, "domain": {"lo": [0.0, 0.0], "hi": [LENGTH, 1.5 * HEIGHT]},
        "gravity": [0.0, -G], "frames": FRAMES, "frame_dt": FRAME_DT, "substeps": 1, "flip": flip,
        "bodies": [{"name": "fluid", "shape": "box", "lo": [0.0, 0.0], "hi": [WIDTH, HEIGHT], "ppc": 4,
                    "material": {"model": "newtonian", "mu": mu, "kappa": KAPPA, "density": 1000.0}}],
        "colliders": [{"type": "plane", "name": "floor", "point": [0.0, 0.0], "normal": [0.0, 1.0], "contact": "slip"}],
    }


def probes() -> dict:
    from jaxmpm.identify import depth_gauge

    return {f"depth_{i}": depth_gauge(x, width=GAUGE_WIDTH) for i, x in enumerate(GAUGES)}


class _State:
    """What a depth gauge reads: particle positions and reference volumes (2D)."""

    dim = 2

    def __init__(self, x, vol0):
        self.x, self.vol0 = x, vol0


def load(cells: int, mu: float, flip: float):
    """The scene at a stable substep count (stress-wave CFL number 0.5)."""
    from jaxmpm import load_scene, stable_substeps

    scene = load_scene(spec(cells, mu, flip))
    n = stable_substeps(scene.model, scene.params, limit=0.5)
    return scene.model.with_substeps(n), scene.params


def readings(cells: int, mu: float, flip: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Gauge readings ``(G, frames)`` in m of a healthy run, the times, and the substeps it ran."""
    from jaxmpm import simulate_healthy

    model, params = load(cells, mu, flip)
    traj, ran, discarded = simulate_healthy(model, params)
    for why in discarded:
        print(why, file=sys.stderr)
    x = np.asarray(traj.x)
    vol0 = jnp.concatenate([jnp.asarray(b.vol0) for b in model.bodies])
    fns = probes()
    h = np.array([[float(fns[f"depth_{i}"](_State(jnp.asarray(x[f]), vol0), model)) for f in range(len(x))]
                  for i in range(len(GAUGES))])
    return h, np.arange(len(x)) * model.frame_dt, ran.substeps


def observation(t: np.ndarray, h: np.ndarray):
    from jaxmpm import Observation

    keep = t > 0  # t = 0 is the initial state, the same at every resolution
    names = tuple(f"depth_{i}" for i in range(len(GAUGES)))
    return Observation(times=t[keep], probe_names=names, probe_times=np.broadcast_to(t[keep], h[:, keep].shape).copy(),
                       probe_values=h[:, keep])


def fit_mu(cells: int, mu_true: float, flip: float, obs) -> dict:
    """Fit ``mu`` alone at ``cells`` from three times ``mu_true``; the row (``log10_error``:
    log10 of the fitted over the true ``mu``, None where the fit drove it to 0)."""
    from jaxmpm import FitConfig, fit

    model, params = load(cells, mu_true * 3.0, flip)  # start at three times the truth
    config = FitConfig(stages=None, probes=probes(), scan=())
    t0 = time.perf_counter()
    res = fit(model, params, obs, ["mu"], config)
    mu = float(res.values["mu"])
    return {"mu": mu, "log10_error": math.log10(mu / mu_true) if mu > 0 else None,  # None: fitted to 0
            "std": float(res.std["mu"]), "loss": float(res.loss[-1]),
            "iterations": res.iterations, "converged": res.converged, "substeps": res.substeps,
            "seconds": time.perf_counter() - t0, "message": res.message}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mu", default="0.5,5,50", help="true viscosities, Pa s")
    ap.add_argument("--cells", default="10,20", help="coarse grids: cells across the column's width")
    ap.add_argument("--ref-cells", type=int, default=40)
    ap.add_argument("--out", default="flip_fit_out")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    done = {json.dumps(r["key"]) for r in map(json.loads, rows_path.read_text().splitlines())} if rows_path.exists() else set()

    def record(key: dict, row: dict):
        row = {"key": key, **row}
        print(json.dumps(row), flush=True)
        with rows_path.open("a") as f:
            f.write(json.dumps(row) + "\n")

    for mu in [float(v) for v in a.mu.split(",")]:
        ref = {}
        for flip in (0.99, 0.0):
            path = out / f"reference_mu{mu:g}_cells{a.ref_cells}_flip{flip:g}.npz"
            if path.exists():
                z = np.load(path)
                h, t = z["h"], z["t"]
            else:
                t0 = time.perf_counter()
                h, t, substeps = readings(a.ref_cells, mu, flip)
                np.savez(path, h=h, t=t, substeps=substeps, seconds=time.perf_counter() - t0)
            ref[flip] = (h, t)
        gap = float(np.sqrt(np.mean((ref[0.99][0] - ref[0.0][0]) ** 2)))
        key = {"mu": mu, "reference": "transfers", "cells": a.ref_cells}
        if json.dumps(key) not in done:
            record(key, {"rms_apic_vs_flip_m": gap, "depth_rms_m": float(np.sqrt(np.mean(ref[0.99][0] ** 2)))})
        obs = observation(ref[0.99][1], ref[0.99][0])
        for cells in [int(c) for c in a.cells.split(",")]:
            for flip in (0.0, 0.99):
                key = {"mu": mu, "cells": cells, "flip": flip}
                if json.dumps(key) in done:
                    continue
                record(key, fit_mu(cells, mu, flip, obs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
