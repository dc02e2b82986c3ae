"""Cost of the two renderers: time and peak memory per view, forward and forward+backward.

Usage::

    python benchmarks/bench_render.py                       # the table in docs/rendering.md
    python benchmarks/bench_render.py --n 10000 --res 64 --renderers volume

Every configuration runs in a fresh subprocess (so memory numbers do not mix) that
builds a particle blob (a jittered lattice filling a sphere of radius 0.3 m, coloured by
position) seen by one 40° camera 2 m away, compiles the function ahead of time, runs it
once to warm up and then ``--repeats`` times; the median wall time and the median
process CPU time (all threads; less sensitive to other jobs on a shared machine) are
reported.

Memory is reported two ways:

* ``xla``: XLA's buffer assignment of the compiled executable
  (``compiled.memory_analysis()``: temporaries + arguments + outputs) — the peak working
  set of the computation itself, deterministic;
* ``rss``: growth of the process's peak resident set size (``ru_maxrss``) while running
  the already compiled function — includes allocator overheads; a lower bound when the
  compiler's own peak was higher.

Forward = ``render`` of the full image (rgb, alpha, depth). Forward+backward =
``value_and_grad`` of ``mean((rgb − target)²) + mean((alpha − target)²)`` w.r.t. the
particle positions.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time


def _blob(n: int, seed: int = 0):
    import numpy as np

    R = 0.3
    h = R * (4.0 * np.pi / (3.0 * n)) ** (1.0 / 3.0)
    k = int(np.ceil(R / h)) + 2
    g = np.arange(-k, k + 1) * h
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.argsort(np.linalg.norm(x, axis=1), kind="stable")[:n]]
    rng = np.random.default_rng(seed)
    x = x + rng.uniform(-0.1 * h, 0.1 * h, x.shape)
    colors = np.clip(0.5 + x / (2 * R), 0.0, 1.0)
    return x.astype(np.float32), colors.astype(np.float32), float(h)


def run_one(renderer: str, n: int, res: int, mode: str, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxmpm.render import look_at, make_renderer

    x, colors, h = _blob(n)
    cam = look_at((0.4, 0.5, -1.9), (0.0, 0.0, 0.0), fov_deg=40.0, width=res, dtype=jnp.float32)
    rend = make_renderer(renderer, x, spacing=h)
    xj, cj = jnp.asarray(x), jnp.asarray(colors)
    if mode == "forward":
        fn = jax.jit(lambda x, c: rend.render(x, cam, c))
        args = (xj, cj)
    else:
        target = rend.render(xj + 0.01, cam, cj)

        def loss(x, c):
            out = rend.render(x, cam, c)
            return jnp.mean((out.rgb - target.rgb) ** 2) + jnp.mean((out.alpha - target.alpha) ** 2)

        fn = jax.jit(jax.value_and_grad(loss))
        args = (xj, cj)
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    t_compile = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    xla_bytes = None
    if mem is not None:
        xla_bytes = (
            mem.temp_size_in_bytes + mem.argument_size_in_bytes + mem.output_size_in_bytes
        )
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    jax.block_until_ready(compiled(*args))  # warm-up
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "renderer": renderer,
        "n": n,
        "res": res,
        "mode": mode,
        "ms": 1e3 * statistics.median(times),
        "cpu_ms": 1e3 * statistics.median(cpu),
        "compile_s": t_compile,
        "xla_mb": None if xla_bytes is None else xla_bytes / 2**20,
        "rss_mb": (rss1 - rss0) / 1024.0,  # ru_maxrss is in KiB on Linux
        "grid": list(getattr(rend, "shape", ())) or None,
        "samples": getattr(rend, "num_samples", None),
    }


def _torus_scene(h: float = 0.02):
    """A sheared torus resting on a flattened blob: a frame of a 'particles' scene."""
    import numpy as np

    k = int(np.ceil(0.7 / h))
    g = np.arange(-k, k + 1) * h
    p = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    R, r = 0.3, 0.11
    q = np.hypot(p[:, 0], p[:, 2]) - R
    torus = p[q * q + p[:, 1] ** 2 < r * r]
    F = np.array([[1.0, 0.35, 0.0], [0.0, 0.9, 0.0], [0.1, 0.0, 1.1]])
    theta = np.radians(-20.0)
    rot = np.array([[1, 0, 0], [0, np.cos(theta), -np.sin(theta)], [0, np.sin(theta), np.cos(theta)]])
    torus = torus @ (rot @ F).T + np.array([0.0, 0.32, 0.0])
    blob = p[(p[:, 0] / 0.45) ** 2 + (p[:, 1] / 0.12) ** 2 + (p[:, 2] / 0.45) ** 2 < 1.0]
    x = np.concatenate([torus, blob])
    t = (x[:, 1] - x[:, 1].min()) / np.ptp(x[:, 1])
    import matplotlib

    colors = matplotlib.colormaps["viridis"](t)[:, :3]
    return x.astype(np.float32), colors.astype(np.float32), h


def make_figure(path: str, res: int = 192) -> None:
    """docs/img/render_compare.png: one frame rendered by both renderers, side by side."""
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxmpm.render import look_at, make_renderer

    x, colors, h = _torus_scene()
    cam = look_at((0.9, 1.5, -1.7), (0.0, 0.15, 0.0), fov_deg=40.0, width=res, dtype=jnp.float32)
    xj, cj = jnp.asarray(x), jnp.asarray(colors)
    outs, secs = {}, {}
    for kind in ("volume", "surfels"):
        rend = make_renderer(kind, x, spacing=h)
        f = jax.jit(lambda x, c: rend.render(x, cam, c))
        jax.block_until_ready(f(xj, cj))
        t0 = time.perf_counter()
        outs[kind] = jax.tree_util.tree_map(np.asarray, f(xj, cj))
        secs[kind] = time.perf_counter() - t0
    a = outs["volume"].alpha > 0.5
    b = outs["surfels"].alpha > 0.5
    iou = (a & b).sum() / (a | b).sum()
    diff = np.ones((res, res, 3))
    diff[a & ~b] = (0.85, 0.2, 0.2)
    diff[b & ~a] = (0.2, 0.3, 0.9)
    diff[a & b] = (0.8, 0.8, 0.8)
    fig, ax = plt.subplots(1, 4, figsize=(13, 3.6))
    ax[0].imshow(np.clip(outs["volume"].rgb, 0, 1))
    ax[0].set_title("volume (voxel ray march)")
    ax[1].imshow(np.clip(outs["surfels"].rgb, 0, 1))
    ax[1].set_title("2D Gaussian surfels")
    ax[2].imshow(diff)
    ax[2].set_title(f"masks: both grey, volume only red,\nsurfels only blue (IoU {iou:.3f})")
    d = np.where(outs["volume"].alpha > 0.5, outs["volume"].depth, np.nan)
    im = ax[3].imshow(d, cmap="magma")
    ax[3].set_title("volume depth (m)")
    fig.colorbar(im, ax=ax[3], fraction=0.046)
    for axis in ax:
        axis.set_xticks([])
        axis.set_yticks([])
    fig.suptitle(f"one frame: {x.shape[0]} particles, {res}×{res} px, default settings of both renderers", y=0.99)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}: IoU {iou:.3f}, volume {secs['volume']:.2f} s, surfels {secs['surfels']:.2f} s")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, nargs="+", default=[10_000, 25_000])
    p.add_argument("--res", type=int, nargs="+", default=[64, 128])
    p.add_argument("--renderers", nargs="+", default=["volume", "surfels"])
    p.add_argument("--modes", nargs="+", default=["forward", "backward"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--figure", help="only write the comparison figure to this PNG")
    p.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one config, print JSON
    a = p.parse_args(argv)
    if a.figure:
        make_figure(a.figure)
        return
    if a.one:
        r, n, res, mode = a.one.split(",")
        print(json.dumps(run_one(r, int(n), int(res), mode, a.repeats)))
        return
    print(f"# machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"python {platform.python_version()}; load average at start {os.getloadavg()}")
    rows = []
    print("| renderer | N | pixels | pass | wall ms / view | CPU ms / view | peak MB (XLA) | peak MB (RSS growth) | compile s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in a.renderers:
        for n in a.n:
            for res in a.res:
                for mode in a.modes:
                    cmd = [sys.executable, __file__, "--one", f"{r},{n},{res},{mode}", "--repeats", str(a.repeats)]
                    out = subprocess.run(cmd, capture_output=True, text=True)
                    if out.returncode != 0:
                        print(f"| {r} | {n} | {res}² | {mode} | failed: {out.stderr.strip().splitlines()[-1]} |")
                        continue
                    row = json.loads(out.stdout.strip().splitlines()[-1])
                    rows.append(row)
                    name = "fwd" if mode == "forward" else "fwd+bwd"
                    xla = "n/a" if row["xla_mb"] is None else f"{row['xla_mb']:.0f}"
                    print(f"| {r} | {n} | {res}² | {name} | {row['ms']:.0f} | {row['cpu_ms']:.0f} | {xla} | "
                          f"{row['rss_mb']:.0f} | {row['compile_s']:.1f} |", flush=True)
    print(f"# load average at end {os.getloadavg()}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
