"""Collider benchmark: penetration / leaks versus dx per collision mode, cost per step, pictures.

    python benchmarks/bench_colliders.py                 # everything (minutes on 2 cores)
    python benchmarks/bench_colliders.py --accuracy      # penetration depth and leaks vs dx
    python benchmarks/bench_colliders.py --cost          # CPU time per step at ~25k particles
    python benchmarks/bench_colliders.py --images        # docs/img/colliders_*.png

Modes (``collision`` scene key): ``cpic`` (particle-wise CPIC, the default), ``grid``
(grid-level signed-distance condition, AS-DiffMPM's GOP-DiffMPM) and ``particles`` (heavy
rigid boundary particles, RP-DiffMPM). Results are recorded in docs/colliders.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.model import initial_state
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate, step

MODES = ("cpic", "grid", "particles")
FLUID = {"model": "newtonian", "mu": 1.0, "kappa": 1e4}
SAND = {"model": "sand", "friction_angle": 35.0, "E": 2e5}
ELASTIC = {"model": "elastic", "E": 1e5, "nu": 0.3}
ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- scenes


def bunny_drop(dx: float, collision: str, frames: int = 10) -> dict:
    """Fluid, sand and an elastic ball dropped at 2 m/s on the bunny (3D)."""
    bodies = [
        {"shape": "sphere", "center": [0.3 + 0.2 * k, 0.72, 0.5], "radius": 0.1, "velocity": [0.0, -2.0, 0.0],
         "material": m, "name": name}
        for k, (m, name) in enumerate(((FLUID, "fluid"), (SAND, "sand"), (ELASTIC, "elastic")))
    ]
    return {
        "dim": 3, "dx": dx, "domain": {"lo": [0, 0, 0], "hi": [1, 1, 1]}, "frames": frames, "frame_dt": 1 / 24,
        "substeps": int(round(2.0 / dx)), "gravity": [0, -9.8, 0], "collision": collision, "bodies": bodies,
        "colliders": [
            {"type": "plane", "name": "floor", "point": [0, 0, 0], "normal": [0, 1, 0]},
            {"type": "mesh", "name": "bunny", "path": "bunny.obj", "scale": 0.6, "translate": [0.5, 0.3, 0.5],
             "contact": "slip"},
        ],
    }


def thin_plate(dx: float, collision: str, y0: float = 0.405) -> dict:
    """Fluid, sand and an elastic block dropped at 2 m/s on a full-width segment of zero thickness (2D)."""
    bodies = [
        {"shape": "box", "lo": [x0, 0.55], "hi": [x0 + 0.2, 0.7], "velocity": [0.0, -2.0], "material": m, "name": n}
        for x0, m, n in ((0.08, FLUID, "fluid"), (0.4, SAND, "sand"), (0.72, ELASTIC, "elastic"))
    ]
    return {
        "dim": 2, "dx": dx, "domain": {"lo": [0, 0], "hi": [1, 1]}, "frames": 10, "frame_dt": 1 / 24,
        "substeps": int(round(1.6 / dx)), "gravity": [0, -9.8], "collision": collision, "bodies": bodies,
        "colliders": [{"type": "mesh", "name": "plate", "points": [[1.1, y0], [-0.1, y0]], "contact": "slip"}],
    }


def cost_scene(collision: str | None, dx: float = 1 / 48) -> dict:
    """~22-25k particles of fluid over the bunny (3D), for timing."""
    spec = bunny_drop(dx, collision or "cpic")
    spec["bodies"] = [{"shape": "box", "lo": [0.35, 0.45, 0.35], "hi": [0.66, 0.76, 0.66], "material": FLUID,
                       "velocity": [0.0, -1.0, 0.0]}]
    if collision is None:
        spec["colliders"] = spec["colliders"][:1]
    return spec


# --------------------------------------------------------------------------- helpers


def rollout(spec):
    scene = load_scene(spec)
    t0 = time.perf_counter()
    traj = jax.jit(lambda p: simulate(scene.model, p, checkpoint=None))(scene.params)
    x = np.asarray(traj.x)
    return scene, np.asarray(traj.times), x, bool(np.asarray(traj.nan).any()), time.perf_counter() - t0


def depth_inside(collider, x: np.ndarray, margin: float = 0.1) -> np.ndarray:
    """``-signed distance`` (exact, brute force) of every particle of every frame (static collider)."""
    flat = x.reshape(-1, x.shape[-1])
    out = np.full(len(flat), -margin)
    lo, hi = collider.bounds()
    pick = np.flatnonzero(np.all((flat > lo - margin) & (flat < hi + margin), axis=1))
    for s in range(0, len(pick), 8192):
        part = pick[s : s + 8192]
        out[part] = -np.asarray(collider.signed_distance(jnp.asarray(flat[part]), jnp.asarray(0.0, x.dtype))[0])
    return out.reshape(x.shape[:2])


# --------------------------------------------------------------------------- accuracy


def accuracy(quick: bool = False) -> list[dict]:
    rows = []
    print("\n### Penetration and leaks versus dx\n")
    print("| scene | dx | mode | particles | max depth (dx) | max depth (mm) | particles ever deeper than dx/2 | NaN | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for dx in (0.05, 0.04) if quick else (0.05, 0.04, 0.03):
        for mode in MODES:
            scene, _, x, nan, secs = rollout(bunny_drop(dx, mode))
            depth = depth_inside(scene.model.colliders[1], x)
            row = dict(scene="bunny 3D", dx=dx, mode=mode, n=x.shape[1], depth=np.nanmax(depth),
                       leaked=int(np.sum(np.nanmax(depth, axis=0) > 0.5 * dx)), nan=nan, secs=secs)
            rows.append(row)
            _print_row(row)
    for dx in (0.02, 0.01) if quick else (0.02, 0.01, 0.005):
        for mode in MODES:
            _, _, x, nan, secs = rollout(thin_plate(dx, mode))
            depth = 0.405 - x[..., 1]  # below the plate = through it
            row = dict(scene="thin plate 2D", dx=dx, mode=mode, n=x.shape[1], depth=np.nanmax(depth),
                       leaked=int(np.sum(np.nanmax(depth, axis=0) > 0.5 * dx)), nan=nan, secs=secs)
            rows.append(row)
            _print_row(row)
    return rows


def _print_row(r):
    print(f"| {r['scene']} | {r['dx']} | {r['mode']} | {r['n']} | {r['depth'] / r['dx']:+.2f} | "
          f"{1e3 * r['depth']:+.1f} | {r['leaked']} | {'yes' if r['nan'] else 'no'} | {r['secs']:.0f} |", flush=True)


# --------------------------------------------------------------------------- cost


def cost(steps: int = 20, reps: int = 5) -> dict:
    """CPU time per step (process time, best of ``reps`` scans of ``steps`` steps)."""
    print("\n### Cost per step (CPU time; the block sits on the bunny so contacts are active)\n")
    print("| mode | particles | grid nodes | ms / step | relative to no collider |")
    print("|---|---|---|---|---|")
    out = {}
    for mode in (None,) + MODES:
        scene = load_scene(cost_scene(mode))
        m, p = scene.model, scene.params
        s0 = initial_state(m, p)
        # lower the block onto the bunny's top: most particles near the collider have contacts
        s0 = _with_x(s0, s0.x - jnp.asarray([0.0, 0.2, 0.0], s0.x.dtype))
        run = jax.jit(lambda s: jax.lax.scan(lambda c, _: (step(m, p, c), None), s, None, length=steps)[0])
        jax.block_until_ready(run(s0))
        best = np.inf
        for _ in range(reps):
            t = time.process_time()
            jax.block_until_ready(run(s0))
            best = min(best, (time.process_time() - t) / steps * 1e3)
        out[mode] = best
        ratio = best / out[None]
        print(f"| {mode or 'no collider'} | {m.num_particles} | {m.grid.num_nodes} | {best:.2f} | {ratio:.2f} |", flush=True)
    return out


def _with_x(state, x):
    import equinox as eqx

    return eqx.tree_at(lambda s: s.x, state, x)


# --------------------------------------------------------------------------- pictures


def images(out_dir: Path = ROOT / "docs" / "img") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    scenes = {
        "bunny": (ROOT / "examples" / "bunny.toml", 1),
        "bowl": (ROOT / "examples" / "bowl.toml", 1),
    }
    for name, (path, k) in scenes.items():
        scene = load_scene(path)
        traj = jax.jit(lambda p: simulate(scene.model, p, checkpoint=None))(scene.params)
        x = np.asarray(traj.x)
        col = scene.model.colliders[k]
        surf = np.asarray(col.vertices)
        picks = np.linspace(0, x.shape[0] - 1, 6).round().astype(int)
        fig, axes = plt.subplots(1, len(picks), figsize=(3 * len(picks), 3.2), sharex=True, sharey=True)
        z = x[..., 2]
        for ax, f in zip(axes, picks):
            ax.scatter(surf[:, 0], surf[:, 1], s=0.3, c="0.6", rasterized=True)
            order = np.argsort(z[f])
            ax.scatter(x[f, order, 0], x[f, order, 1], s=1.5, c=z[f, order], cmap="Blues", vmin=z.min() - 0.2,
                       vmax=z.max(), rasterized=True)
            ax.set_title(f"t = {float(traj.times[f]):.2f} s", fontsize=9)
            ax.set_aspect("equal")
            ax.set_xlim(scene.model.grid.lo[0], scene.model.grid.hi[0])
            ax.set_ylim(scene.model.grid.lo[1], scene.model.grid.hi[1])
            ax.set_xticks([])
            ax.set_yticks([])
        fig.suptitle(f"{path.name}: fluid and the {col.name} (grey: mesh vertices; side view, colour = depth)",
                     fontsize=10)
        fig.tight_layout()
        target = out_dir / f"colliders_{name}.png"
        fig.savefig(target, dpi=110)
        plt.close(fig)
        print(f"wrote {target}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--accuracy", action="store_true")
    parser.add_argument("--cost", action="store_true")
    parser.add_argument("--images", action="store_true")
    parser.add_argument("--quick", action="store_true", help="fewer resolutions")
    args = parser.parse_args(argv)
    every = not (args.accuracy or args.cost or args.images)
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, x64={jax.config.jax_enable_x64}")
    if every or args.accuracy:
        accuracy(args.quick)
    if every or args.cost:
        cost()
    if every or args.images:
        images()
    return 0


if __name__ == "__main__":
    sys.exit(main())
