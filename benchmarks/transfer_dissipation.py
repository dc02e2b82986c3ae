"""How much energy one MPM step's transfers dissipate, whatever dt: why a rollout at fixed dx
does not converge as dt falls.

    python benchmarks/transfer_dissipation.py [--dx 0.02] [--float32] [--flip 0.99]
    python benchmarks/transfer_dissipation.py --case-study-3d [--dx 0.05] [--flip 0.99]

A 2D dam break (a 0.4 m water column, PAC-NeRF's Newtonian fluid with water's viscosity, a
weakly compressible bulk modulus with sqrt(kappa / rho) = 6 sqrt(g h)) is run for 0.2 s
at 80 substeps a frame. From that state the script takes 10 steps at dt = 2.5e-4 ... 2.5e-8 s
and reports the kinetic energy (APIC's: ``m |v|^2 / 2`` plus the affine part
``m (dx^2 / 4) |C|^2 / 2``) each step adds. As dt -> 0 the physics' share vanishes and what
is left is the transfers' own loss per step (P2G then G2P project the particles' velocity
fields onto the grid's and back). Then it reruns the whole 0.6 s at 40 ... 320 substeps a
frame and prints the mechanical energy lost: the dissipation a rollout pays grows with its
step count. ``--flip`` blends FLIP's update into APIC's (``Model.flip``) to see how much of it
that keeps. ``--case-study-3d`` measures the loss per step on the 3D dam break of
``examples/dam_break_3d_obstacle.py`` instead (float32, 88 substeps a frame to t = 0.5 s, as
its dx = 0.05 m runs). Results: docs/case_studies/dam_break_3d_obstacle.md ("Why a finer dt moves the
prediction").
"""

from __future__ import annotations

import argparse
import math

import jax
import jax.numpy as jnp
import numpy as np

G = 9.81
HEIGHT = 0.4


def spec(dx: float, substeps: int, frames: int, flip: float = 0.0) -> dict:
    u = math.sqrt(G * HEIGHT)
    return {
        "flip": flip, "dim": 2, "dx": dx, "domain": {"lo": [0, 0], "hi": [1.6, 0.8]}, "frames": frames, "frame_dt": 0.02,
        "substeps": substeps, "gravity": [0, -G],
        "bodies": [{"shape": "box", "lo": [0.0, 0.0], "hi": [HEIGHT, HEIGHT],
                    "material": {"model": "newtonian", "mu": 0.002, "kappa": 1000 * (6 * u) ** 2}}],
    }


def kinetic(state, dx: float) -> float:
    """APIC's kinetic energy (J per metre of depth): translational plus affine."""
    m, v, C = (np.asarray(a, np.float64) for a in (state.mass, state.v, state.C))
    return float(0.5 * (m * (v**2).sum(-1)).sum() + 0.5 * (m * (dx**2 / 4) * (C**2).sum((-1, -2))).sum())


def mechanical(state, dx: float) -> float:
    return kinetic(state, dx) + float((np.asarray(state.mass) * G * np.asarray(state.x)[:, 1]).sum())


def added_per_step(make_spec, start, dx: float, dtype, substeps: list[int]) -> None:
    """Print the kinetic energy 10 steps from ``start`` add per step, for each substep count
    (``make_spec(substeps)``: the scene at that dt)."""
    from jaxmpm.scene import load_scene
    from jaxmpm.step import step

    ke0 = kinetic(start, dx)
    print("| dt (s) | kinetic energy added per step (J or J/m) | per step, of the kinetic energy |")
    print("|---|---|---|")
    for n in substeps:
        short = load_scene(make_spec(n), dtype=dtype)
        ten = jax.jit(lambda s: jax.lax.scan(lambda q, _: (step(short.model, short.params, q), None), s, None,
                                             length=10)[0])
        added = (kinetic(ten(start), dx) - ke0) / 10
        print(f"| {short.model.dt:.1e} | {added:+.3e} | {added / ke0:+.2e} |", flush=True)


def case_study_3d(dx: float, flip: float = 0.0) -> None:
    import pathlib
    import sys

    from jaxmpm.scene import load_scene
    from jaxmpm.step import simulate

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "examples"))
    import dam_break_3d_obstacle as case

    base = case.scene_spec(dx=dx, t_end=0.5, flip=flip)
    scene = load_scene(dict(base, substeps=88))
    start = simulate(scene.model, scene.params).final
    print(f"3D dam break with the box, dx = {dx} m, flip = {flip}, {scene.model.num_particles} particles, float32; "
          f"kinetic energy at t = {float(start.time):.2f} s: {kinetic(start, dx):.3f} J")
    added_per_step(lambda n: dict(base, substeps=n, frames=2), start, dx, jnp.float32,
                   [88, 880, 8800, 88000, 880000])


def main(argv=None) -> int:
    from jaxmpm.scene import load_scene
    from jaxmpm.step import simulate

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dx", type=float, default=None, help="grid spacing (default 0.02 m; 0.05 m for the case study)")
    ap.add_argument("--float32", action="store_true", help="float32 (default float64)")
    ap.add_argument("--case-study-3d", action="store_true", help="the 3D dam break's scene instead")
    ap.add_argument("--flip", type=float, default=0.0, help="FLIP share of the velocity update (Model.flip; 0 = APIC)")
    args = ap.parse_args(argv)
    if args.case_study_3d:
        case_study_3d(args.dx or 0.05, args.flip)
        return 0
    dx = args.dx or 0.02
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float32 if args.float32 else jnp.float64

    scene = load_scene(spec(dx, 80, 11, args.flip), dtype=dtype)
    start = simulate(scene.model, scene.params).final
    print(f"dam break, dx = {dx} m, {scene.model.num_particles} particles, {jnp.dtype(dtype).name}; "
          f"kinetic energy at t = 0.2 s: {kinetic(start, dx):.3f} J/m")
    added_per_step(lambda n: spec(dx, n, 2, args.flip), start, dx, dtype, [80, 800, 8000, 80000, 800000])

    print("\n| substeps per frame | mechanical energy lost by 0.2 / 0.4 / 0.58 s (J/m) |")
    print("|---|---|")
    for substeps in (40, 80, 160, 320):
        whole = load_scene(spec(dx, substeps, 30, args.flip), dtype=dtype)
        traj = simulate(whole.model, whole.params, observe=lambda s: s)
        e = [mechanical(jax.tree.map(lambda a, i=i: a[i], traj.extra), dx) for i in range(30)]
        print(f"| {substeps} | " + " / ".join(f"{e[0] - e[i]:.2f}" for i in (10, 20, 29)) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
