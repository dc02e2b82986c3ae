"""Does the transfer bias what a fit identifies? APIC against the FLIP blend in fits.

    python benchmarks/flip_fit.py [--material newtonian] [--mu 0.5,5,50] [--cells 10,20] [--ref-cells 40] [--out DIR]
    python benchmarks/flip_fit.py --material viscoplastic [--yield-stress 500] [--eta 0.5,5] ...
    python benchmarks/flip_fit.py --material elastic [--E 2e4,2e5] [--nu 0.3] ...
    python benchmarks/flip_fit.py --material sand [--friction-angle 30] [--angle-offset 3] [--float64] ...
    python benchmarks/flip_fit.py ... --numerics

A 2D column (0.1 m wide, 0.2 m high) collapses on a free-slip floor for 0.3 s: PAC-NeRF's
Newtonian fluid (a weakly compressible bulk modulus, sqrt(kappa / rho) = 22 m/s; ``mu``
fitted), its viscoplastic material (shear modulus 2 kPa, kappa 100 kPa; ``yield_stress`` and
``eta`` fitted) or sand (E = 300 kPa as in the sysid benchmark, nu 0.3; ``friction_angle``
fitted), read by four depth gauges (``jaxmpm.identify.depth_gauge`` at x = 0.05, 0.15, 0.25
and 0.35 m, each 2 cm wide). An elastic solid (``E`` and ``nu`` fitted; a column would only
sag, which ties E to nu) is instead a 0.1 m square dropped from 0.15 m onto the floor, where
it lands at 1.7 m/s, rings and bounces, read by its centre's height and its spread (the
standard deviations of its particles' x and y: its width and height over sqrt(12)). The
data are these probes read every frame (10 ms) from a *reference* run on a fine
grid (``--ref-cells`` cells across the column, the FLIP blend 0.99, and APIC as a check of the
reference itself). At the coarse grids (``--cells``) the script fits the fitted parameters
(Levenberg-Marquardt, one stage over all frames, each started at three times its truth) once
with APIC (``flip = 0``) and once with ``flip = 0.99``, and reports them against the truth
(log10 of fitted over true for parameters fitted in log10, the difference for ``nu`` and
the friction angle, which start at the truth plus :data:`START_OFFSET` instead).
APIC's transfers take kinetic energy out at every step (docs/materials.md, "Transfers"), a
numerical viscosity a fit can only absorb into the material's parameters; the blend keeps
most of it. This measures how much that moves what a fit identifies. The true values are
every combination of the fitted parameters' lists (``--mu``, ``--yield-stress``, ``--eta``).
With ``--numerics`` each fit also runs its numerics check (``FitConfig.numerics``): the
moves a refit at dt/2 and one with the other transfer would make (row key ``numerics``), to
set against the other transfer's own fit in the next row.

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

import numpy as np

G = 9.81
WIDTH, HEIGHT = 0.1, 0.2
LENGTH = 0.6
FRAMES, FRAME_DT = 30, 0.01
GAUGES = (0.05, 0.15, 0.25, 0.35)
#: the elastic square: its lower left corner, m
DROP = (0.25, 0.15)
GAUGE_WIDTH = 0.02
#: material -> (its fixed parameters, the fitted ones); the Newtonian bulk modulus gives
#: sqrt(kappa / rho) = 22.4 m/s, 8 times the column's Ritter front speed
MATERIALS = {
    "newtonian": ({"kappa": 1000.0 * 22.4**2}, ("mu",)),
    "viscoplastic": ({"mu": 2e3, "kappa": 1e5}, ("yield_stress", "eta")),
    "elastic": ({}, ("E", "nu")),
    "sand": ({"E": 3e5, "nu": 0.3}, ("friction_angle",)),
}
#: the true values tried by default
DEFAULT_TRUTHS = {"mu": "0.5,5,50", "yield_stress": "500", "eta": "0.5,5", "E": "2e4,2e5", "nu": "0.3",
                  "friction_angle": "30"}
#: parameters fitted in linear space start at the truth plus this (the others at three times
#: it); from 10 degrees above the truth the friction angle's fits stalled where the column
#: barely moves (``--angle-offset 10``; docs/materials.md, "In fits")
START_OFFSET = {"nu": -0.1, "friction_angle": 3.0}


def start(name: str, truth: float) -> float:
    return truth + START_OFFSET[name] if name in START_OFFSET else 3.0 * truth


def spec(cells: int, material: str, values: dict, flip: float) -> dict:
    """The column (the elastic square) at ``cells`` cells across its width (2 x 2 particles a
    cell) with the material's fixed parameters and ``values``."""
    fixed, _ = MATERIALS[material]
    (x0, y0), (w, h) = (DROP, (WIDTH, WIDTH)) if material == "elastic" else ((0.0, 0.0), (WIDTH, HEIGHT))
    return {
        "dim": 2, "dx": WIDTH / cells, "domain": {"lo": [0.0, 0.0], "hi": [LENGTH, 1.5 * HEIGHT]},
        "gravity": [0.0, -G], "frames": FRAMES, "frame_dt": FRAME_DT, "substeps": 1, "flip": flip,
        "bodies": [{"name": "body", "shape": "box", "lo": [x0, y0], "hi": [x0 + w, y0 + h], "ppc": 4,
                    "material": {"model": material, **fixed, **values, "density": 1000.0}}],
        "colliders": [{"type": "plane", "name": "floor", "point": [0.0, 0.0], "normal": [0.0, 1.0], "contact": "slip"}],
    }


def _centre_y(state, model):
    return state.x[:, 1].mean()


def _spread(axis: int):
    def fn(state, model):
        return state.x[:, axis].std()

    return fn


def probes(material: str) -> dict:
    """The probes the data are read with (name -> ``fn(state, model)``, m)."""
    from jaxmpm.identify import depth_gauge

    if material == "elastic":
        return {"centre_y": _centre_y, "spread_x": _spread(0), "spread_y": _spread(1)}
    return {f"depth_{i}": depth_gauge(x, width=GAUGE_WIDTH) for i, x in enumerate(GAUGES)}


#: the scenes' float type (``--float64`` switches JAX to 64 bits and sets it)
DTYPE = "float32"


def load(cells: int, material: str, values: dict, flip: float):
    """The scene at a stable substep count (stress-wave CFL number 0.5)."""
    import jax.numpy as jnp

    from jaxmpm import load_scene, stable_substeps

    scene = load_scene(spec(cells, material, values, flip), dtype=jnp.dtype(DTYPE))
    n = stable_substeps(scene.model, scene.params, limit=0.5)
    return scene.model.with_substeps(n), scene.params


def readings(cells: int, material: str, truth: dict, flip: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Probe readings ``(P, frames)`` in m of a healthy run (:func:`probes`), the times, and
    the substeps it ran."""
    from jaxmpm import simulate_healthy
    from jaxmpm.identify import probe_series

    model, params = load(cells, material, truth, flip)
    traj, ran, discarded = simulate_healthy(model, params)
    for why in discarded:
        print(why, file=sys.stderr)
    h = np.array([probe_series(fn, ran, traj) for fn in probes(material).values()])
    return h, np.arange(h.shape[1]) * model.frame_dt, ran.substeps


def observation(t: np.ndarray, h: np.ndarray, material: str = "newtonian"):
    from jaxmpm import Observation

    keep = t > 0  # t = 0 is the initial state, the same at every resolution
    return Observation(times=t[keep], probe_names=tuple(probes(material)),
                       probe_times=np.broadcast_to(t[keep], h[:, keep].shape).copy(), probe_values=h[:, keep])


def fit_material(cells: int, material: str, truth: dict, flip: float, obs, numerics: bool = False) -> dict:
    """Fit the material's fitted parameters at ``cells``, each from :func:`start`; the row:
    fitted ``values``, ``log10_error`` (log10 of fitted over true; None where the fit drove a
    value to 0) for those started at three times the truth, ``error`` (fitted less true) for
    the others, ``std``, with ``numerics`` the numerics check's moves, and the fit's figures."""
    from jaxmpm import FitConfig, fit

    names = list(truth)
    model, params = load(cells, material, {k: start(k, v) for k, v in truth.items()}, flip)
    config = FitConfig(stages=None, probes=probes(material), scan=(), numerics=numerics)
    t0 = time.perf_counter()
    res = fit(model, params, obs, names, config)
    values = {k: float(res.values[k]) for k in names}
    log_names = [k for k in names if k not in START_OFFSET]
    return {"values": values,
            "log10_error": {k: math.log10(values[k] / truth[k]) if values[k] > 0 else None for k in log_names},
            "error": {k: values[k] - truth[k] for k in names if k in START_OFFSET},
            "std": {k: float(res.std[k]) for k in names}, "loss": float(res.loss[-1]),
            **({"numerics": res.to_json()["numerics"], "numerics_s": res.timing["numerics_s"]} if numerics else {}),
            "iterations": res.iterations, "converged": res.converged, "substeps": res.substeps,
            "seconds": time.perf_counter() - t0, "message": res.message, "notes": res.notes}


def truths(material: str, lists: dict) -> list[dict]:
    """Every combination of the fitted parameters' true values (``lists``: name -> "a,b,...")."""
    _, names = MATERIALS[material]
    combos = [{}]
    for name in names:
        combos = [{**c, name: float(v)} for c in combos for v in lists[name].split(",")]
    return combos


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--material", choices=sorted(MATERIALS), default="newtonian")
    for name, default in DEFAULT_TRUTHS.items():
        ap.add_argument(f"--{name.replace('_', '-')}", dest=name, default=default,
                        help=f"true values of {name} when it is fitted (default {default})")
    ap.add_argument("--cells", default="10,20", help="coarse grids: cells across the column's width")
    ap.add_argument("--ref-cells", type=int, default=40)
    ap.add_argument("--angle-offset", type=float, default=START_OFFSET["friction_angle"],
                    help="the friction angle's fits start this many degrees above the truth (default 3)")
    ap.add_argument("--float64", action="store_true",
                    help="simulate and fit in float64 (rows get \"float64\": true in their key; references "
                         "already in OUT are reused, whatever their precision)")
    ap.add_argument("--numerics", action="store_true",
                    help="run each fit's numerics check (rows get \"numerics\": true in their key)")
    ap.add_argument("--out", default="flip_fit_out")
    a = ap.parse_args(argv)
    START_OFFSET["friction_angle"] = a.angle_offset
    if a.float64:
        import jax

        global DTYPE
        jax.config.update("jax_enable_x64", True)
        DTYPE = "float64"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    done = {json.dumps(r["key"]) for r in map(json.loads, rows_path.read_text().splitlines())} if rows_path.exists() else set()

    def record(key: dict, row: dict):
        row = {"key": key, **row}
        print(json.dumps(row), flush=True)
        with rows_path.open("a") as f:
            f.write(json.dumps(row) + "\n")

    for truth in truths(a.material, vars(a)):
        case = {"material": a.material, **truth}
        tag = "_".join([a.material] + [f"{k}{v:g}" for k, v in truth.items()])
        ref = {}
        for flip in (0.99, 0.0):
            path = out / f"reference_{tag}_cells{a.ref_cells}_flip{flip:g}.npz"
            if path.exists():
                z = np.load(path)
                h, t = z["h"], z["t"]
            else:
                t0 = time.perf_counter()
                h, t, substeps = readings(a.ref_cells, a.material, truth, flip)
                np.savez(path, h=h, t=t, substeps=substeps, seconds=time.perf_counter() - t0)
            ref[flip] = (h, t)
        gap = float(np.sqrt(np.mean((ref[0.99][0] - ref[0.0][0]) ** 2)))
        key = {**case, "reference": "transfers", "cells": a.ref_cells}
        if json.dumps(key) not in done:
            record(key, {"rms_apic_vs_flip_m": gap, "probe_rms_m": float(np.sqrt(np.mean(ref[0.99][0] ** 2)))})
        obs = observation(ref[0.99][1], ref[0.99][0], a.material)
        for cells in [int(c) for c in a.cells.split(",")]:
            for flip in (0.0, 0.99):
                key = {**case, "cells": cells, "flip": flip, **({"float64": True} if a.float64 else {}),
                       **({"numerics": True} if a.numerics else {})}
                if json.dumps(key) not in done:
                    record(key, fit_material(cells, a.material, truth, flip, obs, a.numerics))
    return 0


if __name__ == "__main__":
    sys.exit(main())
