"""Is a scene linear in a hidden gravity error over the size `discover` is asked to find?

`discover` screens candidate causes with a score test: a linearisation at the base model.
That can only point at a cause whose effect on the trajectory is close to linear over the
size of the hidden error. For the thrown block of ``discover_time.py`` (same options) this
prints, for each size ``d`` of a gravity error along ``--direction``: the RMS change of the
particles' positions, and the cosine between the secant ``(x(d) - x(0)) / d`` and the
forward-mode derivative at 0 (1: linear; near 0: the derivative says nothing about the
effect), with the secant's norm relative to the derivative's. For scale it prints the RMS
change dt/2 makes (the numerical error `discover` compares gains with).

    PYTHONPATH=. python benchmarks/discover_linearity.py --E 3e4 --velocity 0.5,0 --contact sticky
        [--direction 1,0] [--sizes 0.001,0.01,0.1,1]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> None:
    import jax
    import jax.numpy as jnp
    from discover_time import block_scene, scene_arguments

    from jaxmpm import extensions as X
    from jaxmpm.discover import _rollout, _rollout_jvp

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    scene_arguments(ap)
    ap.add_argument("--direction", default="1,0", help="the gravity error's direction (x,y)")
    ap.add_argument("--sizes", default="0.001,0.01,0.1,1", help="the error sizes, m/s^2")
    args = ap.parse_args()
    scene = block_scene(args)
    m, p = scene.model, scene.params
    ids = [e for e in X.EXTENSIONS if X.applicable(m, e) is None]
    u = np.asarray([float(v) for v in args.direction.split(",")])
    u = u / np.linalg.norm(u)

    def positions(model, delta):
        theta = X.enable(model, p, ids, {"gravity": {"delta": [float(c) for c in delta]}})
        return np.asarray(_rollout(model, theta, args.frames)[0].x, float)

    x0 = positions(m, 0 * u)
    theta = X.enable(m, p, ids, {"gravity": {"delta": [0.0] * len(u)}})
    tangent = jax.tree_util.tree_map(jnp.zeros_like, theta)
    g = tangent["extensions"]["gravity"]["delta"]
    tangent["extensions"]["gravity"]["delta"] = jnp.asarray(u, g.dtype)
    derivative = np.asarray(_rollout_jvp(m, theta, tangent, args.frames)[1].x, float).ravel()
    rms = lambda a: float(np.sqrt(np.mean(a**2)))  # noqa: E731
    half = positions(m.with_substeps(2 * m.substeps), 0 * u)
    print(f"{m.num_particles} particles, {args.frames} frames x {m.substeps} substeps; E {args.E:g} Pa, thrown at "
          f"{args.velocity} m/s, {args.contact} floor; gravity error along {u.round(3).tolist()}")
    print(f"dt/2 moves the particles {1e3 * rms(half - x0):.2f} mm RMS; the derivative's RMS is "
          f"{1e3 * rms(derivative):.1f} mm per m/s^2")
    for d in (float(v) for v in args.sizes.split(",")):
        secant = (positions(m, d * u) - x0).ravel() / d
        cos = float(secant @ derivative / (np.linalg.norm(secant) * np.linalg.norm(derivative)))
        print(f"  d = {d:g} m/s^2: effect {1e3 * d * rms(secant):.2f} mm RMS; cos(secant, derivative) {cos:.3f}; "
              f"|secant| / |derivative| {np.linalg.norm(secant) / np.linalg.norm(derivative):.3f}", flush=True)


if __name__ == "__main__":
    main()
