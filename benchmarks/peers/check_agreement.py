"""Check by hand that the Taichi and Warp peers compute the same physics.

    python -m benchmarks.peers.check_agreement [--n-particles 25000]

Two scenes, both from the same NumPy particles (``common.initial_state``):

1. free fall: the benchmark scene (cube at rest in the middle of the box) for 100
   steps. The centre of mass must follow the discrete free-fall law exactly (MLS-MPM
   transfers conserve momentum), and the peers must agree particle by particle.
2. drop: the cube starts 5 cells above the floor moving down at 2 m/s; about 120
   steps of free fall, then a few hundred steps of it hitting and squashing against
   the bottom slip wall. The peers' centres of mass must agree within 1e-3 m.

Exits with status 1 if a check fails.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from . import taichi_step, warp_step
from .common import MPMParams, cube_cells, free_fall_com, initial_state


def _run(name, mod, **kw):
    t0 = time.perf_counter()
    out = mod.final_state(**kw)
    print(f"  {name:6s} {kw.get('steps')} steps in {time.perf_counter() - t0:.1f} s")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Taichi vs Warp MLS-MPM agreement check")
    parser.add_argument("--n-particles", type=int, default=25_000)
    parser.add_argument("--grid-n", type=int, default=64)
    parser.add_argument("--drop-steps", type=int, default=500)
    args = parser.parse_args(argv)

    for mod in (taichi_step, warp_step):
        ok, why = mod.available()
        if not ok:
            print(f"skip: {why}")
            return 0

    n, g = args.n_particles, args.grid_n
    params = MPMParams(grid_n=g)
    failures = []

    def check(label, value, tol):
        ok = bool(np.isfinite(value) and value <= tol)
        print(f"  {'ok  ' if ok else 'FAIL'} {label}: {value:.3e} (tol {tol:.0e})")
        if not ok:
            failures.append(label)

    # -- 1. free fall --------------------------------------------------------------
    print(f"free fall: {n} particles, {g}^3 grid, 100 steps")
    steps = 100
    a = _run("taichi", taichi_step, n_particles=n, grid_n=g, steps=steps)
    b = _run("warp", warp_step, n_particles=n, grid_n=g, steps=steps)
    x0 = initial_state(n, g)["x"]
    com_ref = free_fall_com(x0, (0.0, 0.0, 0.0), steps, params)
    for name, s in (("taichi", a), ("warp", b)):
        com = s["x"].astype(np.float64).mean(axis=0)
        check(f"{name} COM vs discrete free fall [m]", np.abs(com - com_ref).max(), 1e-5)
    check("max |x_taichi - x_warp| [m]", np.abs(a["x"] - b["x"]).max(), 1e-5)
    check("max |v_taichi - v_warp| [m/s]", np.abs(a["v"] - b["v"]).max(), 1e-3)

    # -- 2. drop onto the bottom wall ----------------------------------------------
    s_cells = cube_cells(n)
    dx = params.dx
    center = (0.5, (5.0 + 0.5 * s_cells) * dx, 0.5)
    v0 = (0.0, -2.0, 0.0)
    steps = args.drop_steps
    print(f"drop: cube bottom 5 cells above the floor, v0 = {v0} m/s, {steps} steps")
    a = _run("taichi", taichi_step, n_particles=n, grid_n=g, steps=steps, v0=v0, center=center)
    b = _run("warp", warp_step, n_particles=n, grid_n=g, steps=steps, v0=v0, center=center)
    com_a = a["x"].astype(np.float64).mean(axis=0)
    com_b = b["x"].astype(np.float64).mean(axis=0)
    free = free_fall_com(initial_state(n, g, v0=v0, center=center)["x"], v0, steps, params)
    print(f"  COM taichi {np.round(com_a, 5)}  warp {np.round(com_b, 5)}")
    print(f"  (unobstructed free fall would put the COM at y = {free[1]:.5f})")
    print(
        f"  COM velocity y: taichi {a['v'][:, 1].mean():+.4f}  warp {b['v'][:, 1].mean():+.4f} m/s;"
        f"  lowest particle y: taichi {a['x'][:, 1].min():.4f}  warp {b['x'][:, 1].min():.4f} m"
    )
    landed = com_a[1] - free[1] > 0.01 and a["x"][:, 1].min() > 0.0
    print(f"  {'ok  ' if landed else 'FAIL'} the cube landed on the wall (COM well above free fall)")
    if not landed:
        failures.append("landing")
    check("|COM_taichi - COM_warp| [m]", np.abs(com_a - com_b).max(), 1e-3)
    check("mean |x_taichi - x_warp| [m]", np.abs(a["x"] - b["x"]).mean(), 1e-3)
    print(f"  (max |x_taichi - x_warp| = {np.abs(a['x'] - b['x']).max():.3e} m)")

    print("PASS" if not failures else f"FAILED: {failures}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
