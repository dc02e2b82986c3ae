"""Collider benchmark: penetration / leaks versus dx per collision mode, cost per step, pictures.

    python benchmarks/bench_colliders.py                 # everything (minutes on 2 cores)
    python benchmarks/bench_colliders.py --accuracy      # penetration depth and leaks vs dx
    python benchmarks/bench_colliders.py --cost          # CPU time per step at 25k particles
    python benchmarks/bench_colliders.py --cost --breakdown  # ... and where CPIC's time goes
    python benchmarks/bench_colliders.py --images        # docs/img/colliders_*.png
    python benchmarks/bench_colliders.py --thickness     # pile height vs plate thickness (+ its picture)
    python benchmarks/bench_colliders.py --placement     # a resting block vs where the face lies between node rows
    python benchmarks/bench_colliders.py --convergence   # the drop's pile on a plane and on boxes vs dx

Modes (``collision`` scene key): ``cpic`` (particle-wise CPIC, the default), ``grid``
(grid-level signed-distance condition, AS-DiffMPM's GOP-DiffMPM) and ``particles`` (heavy
rigid boundary particles, RP-DiffMPM). Results are recorded in docs/colliders.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.model import initial_state
from jaxmpm.scene import load_scene
from jaxmpm.step import simulate, stable_substeps, step

MODES = ("cpic", "grid", "particles")
FLUID = {"model": "newtonian", "mu": 1.0, "kappa": 1e4}
SAND = {"model": "sand", "friction_angle": 35.0, "E": 2e5}
ELASTIC = {"model": "elastic", "E": 1e5, "nu": 0.3}
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the drop scenes are shared with tests/test_collider_thickness.py
import collider_scenes  # noqa: E402


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


def plate_height(dx: float, on_node_row: bool = False) -> float:
    """Height of the thin plate near y = 0.405: half-way between two node rows (the hard case for
    a grid-level condition, which then sees no node on or inside the plate) or on a node row."""
    k = math.floor(0.405 / dx + 1e-9)
    return (k if on_node_row else k + 0.5) * dx


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


def disk_shell(dim: int, centre: np.ndarray, radius: float, count: int) -> dict:
    """``count`` Gaussian disks on a circle (2D) or sphere (3D, Fibonacci lattice), normals outward,
    sigma = their spacing (npz arrays)."""
    if dim == 2:
        a = 2 * np.pi * np.arange(count) / count
        n = np.stack([np.cos(a), np.sin(a)], -1)
        spacing = 2 * np.pi * radius / count
    else:
        k = np.arange(count) + 0.5
        polar, azimuth = np.arccos(1 - 2 * k / count), np.pi * (1 + 5**0.5) * k
        n = np.stack([np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], -1)
        spacing = np.sqrt(4 * np.pi / count) * radius
    return {"centers": centre + radius * n, "normals": n, "scales": np.full((count, dim - 1), spacing)}


#: The disk shells of the leak table: (dim, dx, disks, radius).
DISK_SHELLS = ((2, 0.02, 120, 0.2), (3, 0.04, 1500, 0.2))


def disks_drop(dim: int, dx: float, count: int, radius: float, collision: str, folder: Path) -> tuple[dict, np.ndarray]:
    """A fluid block dropped at 2 m/s onto a closed shell of disks (a ring in 2D, a sphere in
    3D) centred at (0.5, 0.35[, 0.5]), 10 frames of 1/24 s, ``substeps = 2/dx``; returns the spec
    and the shell's centre."""
    centre = np.array([0.5, 0.35, 0.5][:dim])
    path = folder / f"shell_{dim}d_{count}.npz"
    np.savez(path, **disk_shell(dim, centre, radius, count))
    half = 0.1
    return {
        "dim": dim, "dx": dx, "domain": {"lo": [0.0] * dim, "hi": [1.0] * dim}, "frames": 10, "frame_dt": 1 / 24,
        "substeps": int(round(2.0 / dx)), "gravity": [0.0, -9.8, 0.0][:dim], "collision": collision,
        "bodies": [{"shape": "box", "lo": [0.5 - half, 0.6, 0.5 - half][:dim], "hi": [0.5 + half, 0.75, 0.5 + half][:dim],
                    "velocity": [0.0, -2.0, 0.0][:dim], "material": FLUID}],
        "colliders": [{"type": "plane", "name": "floor", "point": [0.0] * dim, "normal": [0.0, 1.0, 0.0][:dim]},
                      {"type": "disks", "name": "shell", "path": str(path)}],
    }, centre


COST_PARTICLES = 25_000


def cost_points(dx: float = 1 / 48, n: int = COST_PARTICLES) -> np.ndarray:
    """``n`` fluid particles resting on the bunny's top: the lattice (8 per cell) of a box around
    the bunny's upper half, less every point within half a particle spacing of the bunny or
    inside it, keeping the ``n`` highest points (so the fluid conforms to the bunny's back, ears
    and head and about a third of the particles are within 1.5 dx of its surface)."""
    spec = bunny_drop(dx, "cpic")
    bunny = load_scene(spec).model.colliders[1]
    h = dx / 2
    axes = [np.arange(lo + h / 2, hi, h) for lo, hi in zip((0.25, 0.25, 0.3), (0.75, 0.66, 0.7))]
    x = np.stack([a.reshape(-1) for a in np.meshgrid(*axes, indexing="ij")], axis=-1)
    sd = np.concatenate([np.asarray(bunny.signed_distance(jnp.asarray(x[s : s + 8192]), jnp.asarray(0.0))[0])
                         for s in range(0, len(x), 8192)])
    x = x[sd > 0.5 * h]
    return x[np.argsort(-x[:, 1], kind="stable")[:n]]


def cost_scene(collision: str | None, points: Path, dx: float = 1 / 48) -> dict:
    """25k particles of fluid resting on the bunny (3D), for timing; ``collision=None``: the same
    particles with only the floor (the collider-free reference)."""
    spec = bunny_drop(dx, collision or "cpic")
    spec["bodies"] = [{"shape": "points", "path": str(points), "material": FLUID, "velocity": [0.0, -1.0, 0.0]}]
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
    """The leak table: disk shells (2D ring, 3D sphere), the bunny (3D) and the thin plate (2D)."""
    print("\n### Penetration and leaks versus dx\n")
    print("| scene | dx | mode | particles | max depth (dx) | max depth (mm) | particles ever deeper than dx/2 | NaN | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    return _accuracy_disks() + _accuracy_bunny(quick) + _accuracy_plate(quick)


def _accuracy_disks() -> list[dict]:
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for dim, dx, count, radius in DISK_SHELLS:
            for mode in MODES:
                spec, centre = disks_drop(dim, dx, count, radius, mode, Path(tmp))
                _, _, x, nan, secs = rollout(spec)
                depth = radius - np.linalg.norm(x - centre, axis=-1)  # inside the shell
                rows.append(_leak_row(f"disks {dim}D ({count} disks)", dx, mode, x, depth, nan, secs))
    return rows


def _accuracy_bunny(quick: bool) -> list[dict]:
    rows = []
    for dx in (0.05, 0.04) if quick else (0.05, 0.04, 0.03):
        for mode in MODES:
            scene, _, x, nan, secs = rollout(bunny_drop(dx, mode))
            rows.append(_leak_row("bunny 3D", dx, mode, x, depth_inside(scene.model.colliders[1], x), nan, secs))
    return rows


def _accuracy_plate(quick: bool) -> list[dict]:
    rows = []
    for on_row in (False, True):
        for dx in (0.02, 0.01) if quick else (0.02, 0.01, 0.005):
            y0 = plate_height(dx, on_row)
            for mode in MODES:
                _, _, x, nan, secs = rollout(thin_plate(dx, mode, y0))
                where = "on a node row" if on_row else "between node rows"
                # below the plate = through it
                rows.append(_leak_row(f"thin plate 2D, y = {y0:.4f} ({where})", dx, mode, x, y0 - x[..., 1], nan, secs))
    return rows


def _leak_row(scene: str, dx: float, mode: str, x: np.ndarray, depth: np.ndarray, nan: bool, secs: float) -> dict:
    """One row of the leak table (printed): the deepest any particle got and how many got deeper than dx/2."""
    row = dict(scene=scene, dx=dx, mode=mode, n=x.shape[1], depth=np.nanmax(depth),
               leaked=int(np.sum(np.nanmax(depth, axis=0) > 0.5 * dx)), nan=nan, secs=secs)
    _print_row(row)
    return row


# --------------------------------------------------------------------------- thickness


def thickness(out_dir: Path = ROOT / "docs" / "img") -> list[dict]:
    """Pile thickness of the 2D sand drop (tests/collider_scenes.py: dx = 0.02 m, 0.4 s) on
    boxes 0.1 to 8 cells thick, on and between node rows, per mode, against the plane's; and
    the picture ``docs/img/colliders_thickness.png``."""
    import tempfile

    cs = collider_scenes
    dx = cs.drop_substeps(2)[0]
    rows = []
    print("\n### Pile on thin boxes (2D sand, dx = 0.02 m)\n")
    print("| box thickness (dx) | placement | mode | pile thickness (mm) | footprint (mm) | lowest particle (mm) |")
    print("|---|---|---|---|---|---|")
    plates = list(cs.THICKNESSES) + [cs.THICK]
    snapshots = {}
    with tempfile.TemporaryDirectory() as tmp:
        spec, tops = cs.drop_spec(2, "sand", [("plane", None, True)], tmp)
        plane = cs.drop_run(spec, tops)[0][0]
        print(f"| plane | on a node row | analytic | {1e3 * plane['thickness']:.1f} | {1e3 * plane['footprint']:.0f} | "
              f"{1e3 * plane['lowest']:+.1f} |", flush=True)
        for mode in ("cpic", "grid"):
            for on_row in (True, False):
                stations = [("box", t, on_row) for t in plates]
                spec, tops = cs.drop_spec(2, "sand", stations, tmp, collision=mode)
                piles, traj = cs.drop_run(spec, tops)
                for i, (t, p) in enumerate(zip(plates, piles)):
                    row = dict(plate=t, on_row=on_row, mode=mode, **p)
                    rows.append(row)
                    where = "on a node row" if on_row else "between rows"
                    print(f"| {t:g} | {where} | {mode} | {1e3 * p['thickness']:.1f} | {1e3 * p['footprint']:.0f} | "
                          f"{1e3 * p['lowest']:+.1f} |", flush=True)
                    if t == 0.3 and not on_row:
                        sl = load_scene(spec).model.body_slices()[i]
                        snapshots[mode] = (np.asarray(traj.x[-1, sl]), tops[i], cs.station_centre(i))
    _thickness_plot(rows, plane, snapshots, dx, out_dir / "colliders_thickness.png")
    return rows


def _thickness_plot(rows, plane, snapshots, dx, target: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), gridspec_kw={"width_ratios": [1.3, 1, 1]})
    ax = axes[0]
    for mode, colour in (("cpic", "C0"), ("grid", "C3")):
        for on_row, style in ((True, "o-"), (False, "s--")):
            pick = [r for r in rows if r["mode"] == mode and r["on_row"] == on_row]
            where = "on a node row" if on_row else "between rows"
            held = [r for r in pick if r["lowest"] >= -0.5 * dx]
            fell = [r for r in pick if r["lowest"] < -0.5 * dx]
            ax.plot([r["plate"] for r in held], [1e3 * r["height"] for r in held], style, color=colour,
                    label=f"{mode}, {where}")
            if fell:
                ax.plot([r["plate"] for r in fell], [0.0] * len(fell), "x", color=colour, ms=9,
                        label=f"{mode}, {where}: fell through")
    ax.axhline(1e3 * plane["height"], color="0.4", lw=1, label="plane")
    ax.set_xscale("log")
    ax.set_xlabel("box thickness (cells)")
    ax.set_ylabel("pile top above the box (mm)")
    ax.set_title("sand dropped on a box (2D, dx = 20 mm), 0.4 s", fontsize=10)
    ax.legend(fontsize=7)
    for ax, mode in zip(axes[1:], ("cpic", "grid")):
        x, top, x0 = snapshots[mode]
        ax.add_patch(plt.Rectangle((x0 - 0.3, top - 0.3 * dx), 0.6, 0.3 * dx, color="k"))
        ax.scatter(x[:, 0], x[:, 1], s=2)
        ax.set_xlim(x0 - 0.35, x0 + 0.35)
        ax.set_ylim(0.0, top + 0.15)
        ax.set_aspect("equal")
        ax.set_title(f"{mode}: box 0.3 dx thick, between node rows", fontsize=10)
    fig.tight_layout()
    target.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(target, dpi=110)
    plt.close(fig)
    print(f"wrote {target}", flush=True)


def placement(out_dir: Path = ROOT / "docs" / "img", steps: int = 11) -> list[dict]:
    """How high an elastic block rests on a flat face, and how tall it stays, as the face moves
    across one cell (docs/colliders.md, "Where a face lies between node rows";
    ``collider_scenes.placement_spec``, shared with tests/test_collider_thickness.py): CPIC boxes
    (slip) and the grid-level plane, dx = 0.05 m; the picture ``docs/img/colliders_placement.png``."""
    from jaxmpm.step import run_frames

    dx = 0.05
    offsets = [dx * i / (steps - 1) * 0.999 for i in range(steps)]  # [0, 0.999 dx]: the last stops short of the next row
    offsets = sorted(set(offsets + [0.01 * dx]))
    rows = []
    print("\n### A resting elastic block vs where the face lies (2D, dx = 0.05 m, 2 s)\n")
    print("| face above the node row (dx) | mode | lowest particle above the face (mm) | block height (mm, 75 unloaded) |")
    print("|---|---|---|---|")
    runs = [("cpic box", [offsets])] + [("grid plane", [[o] for o in offsets])]
    for mode, groups in runs:
        for group in groups:
            spec, tops = collider_scenes.placement_spec(group, "box" if mode == "cpic box" else "plane", dx=dx)
            scene = load_scene(spec)
            x = np.asarray(run_frames(scene.model, scene.params).x)
            for o, top, sl in zip(group, tops, scene.model.body_slices()):
                y = x[-1, sl, 1] - top
                row = {"offset": o / dx, "mode": mode, "lowest": float(y.min()), "height": float(np.ptp(y)),
                       "height0": float(np.ptp(x[0, sl, 1]))}
                rows.append(row)
                print(f"| {row['offset']:.3f} | {mode} | {1e3 * row['lowest']:.1f} | {1e3 * row['height']:.1f} |", flush=True)
    _placement_plot(rows, dx, out_dir / "colliders_placement.png")
    return rows


def convergence(materials=("sand", "newtonian"), resolutions=(0.02, 0.01, 0.005), times=(0.4, 1.2)) -> list[dict]:
    """The thickness tests' 2D drop (``collider_scenes.drop_spec``: sticky, 1 m/s) on the plane
    and on thick CPIC boxes with their top on a node row and half a cell above one, at finer
    grids and for longer (docs/colliders.md, "Where a face lies between node rows"): the
    reference the tests' coarse piles are compared with. Each pile is measured over the
    0.1 s ending at each of ``times``."""
    import tempfile

    cs = collider_scenes
    frame_dt = 0.02
    last = int(round(0.1 / frame_dt))
    marks = [int(round(t / frame_dt)) for t in times]
    rows = []
    print("\n### The 2D drop's pile vs dx (sticky; thickness and footprint: all particles / 1st-99th percentile)\n")
    print("| material | dx (m) | substeps | collider | t (s) | thickness (mm) | bulk thickness (mm) | footprint (mm) | "
          "bulk footprint (mm) | centre of mass above the face (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for material in materials:
            for dx in resolutions:
                runs = [("plane", [("plane", None, True)]), ("box", [("box", None, True), ("box", None, False)])]
                for kind, stations in runs:
                    spec, tops = cs.drop_spec(2, material, stations, tmp, frames=max(marks), dx=dx)
                    # the viscous limit falls as dx^2: keep the stress-wave CFL number at or below the drop's 0.5
                    scene = load_scene(spec)
                    spec["substeps"] = max(spec["substeps"], stable_substeps(scene.model, scene.params, limit=0.5))
                    _, traj = cs.drop_run(spec, tops, last=last)
                    x = np.asarray(traj.x)
                    sls = scene.model.body_slices()
                    for i, (station, top, sl) in enumerate(zip(stations, tops, sls)):
                        name = "plane" if kind == "plane" else ("box, top on a row" if station[2] else "box, top half a cell up")
                        for t, mark in zip(times, marks):
                            p = cs.pile(x[mark + 1 - last : mark + 1, sl], top, cs.station_centre(i))
                            row = dict(material=material, dx=dx, substeps=spec["substeps"], collider=name, time=t, **p)
                            rows.append(row)
                            print(f"| {material} | {dx:g} | {spec['substeps']} | {name} | {t:g} | {1e3 * p['thickness']:.1f} | "
                                  f"{1e3 * p['bulk_thickness']:.1f} | {1e3 * p['footprint']:.0f} | "
                                  f"{1e3 * p['bulk_footprint']:.0f} | {1e3 * p['com'][1]:.1f} |", flush=True)
    return rows


def _placement_plot(rows, dx, target: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for mode, style in (("cpic box", "o-"), ("grid plane", "s--")):
        pick = sorted((r for r in rows if r["mode"] == mode), key=lambda r: r["offset"])
        off = [r["offset"] for r in pick]
        axes[0].plot(off, [1e3 * r["lowest"] for r in pick], style, label=mode)
        axes[1].plot(off, [r["height"] / r["height0"] for r in pick], style, label=mode)
    axes[0].axhline(1e3 * dx / 4, color="0.4", lw=1, label="material's edge on the face")
    axes[0].set_ylabel("lowest particle above the face (mm)")
    axes[1].axhline(1.0, color="0.4", lw=1)
    axes[1].set_ylabel("block height / unloaded")
    for ax in axes:
        ax.set_xlabel("face above the node row (cells)")
        ax.legend(fontsize=7)
    fig.suptitle("an elastic block at rest on a face, 2D, dx = 50 mm (2 s after a 1 m/s drop)", fontsize=10)
    fig.tight_layout()
    target.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(target, dpi=110)
    plt.close(fig)
    print(f"wrote {target}", flush=True)


def _print_row(r):
    print(f"| {r['scene']} | {r['dx']} | {r['mode']} | {r['n']} | {r['depth'] / r['dx']:+.2f} | "
          f"{1e3 * r['depth']:+.1f} | {r['leaked']} | {'yes' if r['nan'] else 'no'} | {r['secs']:.0f} |", flush=True)


# --------------------------------------------------------------------------- cost


def _timed(fn, s0, steps: int, reps: int) -> float:
    """CPU (process) time per step in ms: best of ``reps`` calls of ``fn`` (a jitted scan)."""
    jax.block_until_ready(fn(s0))
    best = np.inf
    for _ in range(reps):
        t = time.process_time()
        jax.block_until_ready(fn(s0))
        best = min(best, (time.process_time() - t) / steps * 1e3)
    return best


def _scan(step_fn, m, p, steps):
    return jax.jit(lambda s: jax.lax.scan(lambda c, _: (step_fn(m, p, c), None), s, None, length=steps)[0])


def cost(steps: int = 20, reps: int = 5, breakdown: bool = False) -> dict:
    """CPU time per step (process time, best of ``reps`` scans of ``steps`` steps)."""
    import tempfile

    print("\n### Cost per step (CPU time; 25k fluid particles resting on the bunny, contacts active)\n")
    print("| mode | particles | grid nodes | ms / step | relative to no collider |")
    print("|---|---|---|---|---|")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        points = Path(tmp) / "fluid.npy"
        np.save(points, cost_points())
        for mode in (None,) + MODES:
            scene = load_scene(cost_scene(mode, points))
            m, p = scene.model, scene.params
            out[mode] = _timed(_scan(step, m, p, steps), initial_state(m, p), steps, reps)
            ratio = out[mode] / out[None]
            print(f"| {mode or 'no collider'} | {m.num_particles} | {m.grid.num_nodes} | {out[mode]:.2f} | "
                  f"{ratio:.2f} |", flush=True)
        if breakdown:
            _breakdown(load_scene(cost_scene("cpic", points)), steps, reps, out[None])
    return out


def _breakdown(scene, steps: int, reps: int, reference: float) -> None:
    """Where CPIC's extra time goes: the step with its CPIC stages switched on one at a time.

    Mirrors :func:`jaxmpm.step.step` (stage functions of ``jaxmpm.step``); the partial variants
    are for timing only (they are not physical).
    """
    import importlib

    import equinox as eqx

    S = importlib.import_module("jaxmpm.step")  # the module (``jaxmpm.step`` is the function)

    def variant(gather: bool, mask: bool, ghosts: bool, correct: bool):
        def one(model, params, state):
            dt, grid = model.dt, model.grid
            st = S.compute_stencil(grid, state.x)
            contact = S.gather_contact(model, st, state) if gather else None
            F, aux, tau = S.material_update(model, params, state)
            mass, momentum = S.p2g(grid, st, state, tau, dt, contact if mask else None)
            grid_v = S.grid_update(model, params, mass, momentum, state.time)
            ghost = S.ghost_nodes(model, params, state, st, tau, contact) if ghosts else None
            v, C = S.g2p(grid, st, grid_v, ghost)
            x = S.advect(grid, state.x, v, dt, S.penetration_correction(model, contact, v) if correct else None)
            tag = contact.tag if gather else state.tag
            return eqx.tree_at(lambda s: (s.x, s.v, s.C, s.F, s.aux, s.tag, s.time), state,
                               (x, v, C, F, aux, tag, state.time + dt))

        return one

    m, p = scene.model, scene.params
    s0 = initial_state(m, p)
    print("\n#### Where CPIC's time goes (stages switched on one at a time; same particles)\n")
    print("| step | ms / step | relative to no collider |")
    print("|---|---|---|")
    for label, flags in (
        ("CPIC stages off (floor only)", (False, False, False, False)),
        ("+ gather (stencil sides, signed distance, normal, tags)", (True, False, False, False)),
        ("+ compatibility-masked P2G", (True, True, False, False)),
        ("+ ghost nodes in G2P (Coulomb projection)", (True, True, True, False)),
        ("+ penetration correction (= the CPIC step)", (True, True, True, True)),
    ):
        ms = _timed(_scan(variant(*flags), m, p, steps), s0, steps, reps)
        print(f"| {label} | {ms:.2f} | {ms / reference:.2f} |", flush=True)


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
    parser.add_argument("--thickness", action="store_true", help="pile thickness vs box thickness (+ picture)")
    parser.add_argument("--placement", action="store_true", help="a resting block vs the face's offset from a node row")
    parser.add_argument("--convergence", action="store_true", help="the drop's pile on a plane and on boxes vs dx")
    parser.add_argument("--dx", default="0.02,0.01,0.005", help="with --convergence: grid spacings, m")
    parser.add_argument("--materials", default="sand,newtonian", help="with --convergence: the drop's materials")
    parser.add_argument("--breakdown", action="store_true", help="with --cost: time CPIC's stages one by one")
    parser.add_argument("--quick", action="store_true", help="fewer resolutions")
    args = parser.parse_args(argv)
    every = not (args.accuracy or args.cost or args.images or args.thickness or args.placement or args.convergence)
    print(f"jax {jax.__version__}, {jax.devices()[0].platform}, x64={jax.config.jax_enable_x64}")
    if every or args.accuracy:
        accuracy(args.quick)
    if every or args.cost:
        cost(breakdown=args.breakdown)
    if every or args.images:
        images()
    if every or args.thickness:
        thickness()
    if every or args.placement:
        placement()
    if every or args.convergence:
        convergence(tuple(args.materials.split(",")), tuple(float(v) for v in args.dx.split(",")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
