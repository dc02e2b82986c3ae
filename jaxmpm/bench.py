"""``jaxmpm bench step | scaling | memory | grad``: performance of the MLS-MPM step.

* ``step``: one step against Taichi and Warp on the same machine, forward and forward +
  backward, per material.
* ``scaling``: forward time per step versus particle count (fixed grid) and versus grid size
  (fixed particle count), with the fitted exponent of time ~ N^p.
* ``memory``: peak RSS of the gradient through a long checkpointed rollout (default
  16 frames x 200 substeps at 25k particles).
* ``grad``: one reverse-mode gradient of a rollout loss against Taichi's autodiff
  (``benchmarks/peers/taichi_grad.py``), and forward-mode Jacobians for k <= 6 parameters
  against one forward rollout (issue 15, target 6).

The scene (:mod:`jaxmpm.bench_scene`, shared with the peers): a cube of elastic material at ~8
particles per cell in the unit box (64^3 grid by default), dt = 1e-4, gravity, slip walls.
Each measurement runs in its own subprocess so that its peak RSS is its own. The jaxmpm rows
work from an installed package; the Taichi/Warp columns need the peers in ``benchmarks/peers/``
of a source checkout (found next to the package or in the working directory) and are reported
as unavailable, in one line, elsewhere.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _scene_model(n_particles: int, grid_n: int, material: str, dtype, v0=(0.0, 0.0, 0.0), center=None):
    """The peers' cube (:func:`jaxmpm.bench_scene.initial_state` with ``v0`` and ``center``)
    as a jaxmpm model with the peers' slip walls.

    The peers take the outward velocity off the nodes of index ``i < bound`` or
    ``i > grid_n - bound`` (positions ``<= (bound - 1) dx`` or ``>= 1 - (bound - 1) dx``);
    jaxmpm's domain walls act on the nodes on or beyond the domain's faces, so the domain is
    the unit box less ``bound - 1`` cells on each side (``tests/test_peers.py`` checks that
    the two codes then land a cube alike)."""
    import jax.numpy as jnp

    from .bench_scene import MPMParams, initial_state
    from .constitutive import MATERIALS
    from .model import Body, Model
    from .state import Grid

    p = MPMParams(grid_n=grid_n)
    state = initial_state(n_particles, grid_n, v0=v0, center=center)
    dx = p.dx
    wall = (p.bound - 1) * dx
    grid = Grid(lo=(wall,) * 3, hi=(1.0 - wall,) * 3, dx=dx)
    body = Body(
        name="cube",
        material=MATERIALS[material](),
        x0=jnp.asarray(state["x"], dtype),
        vol0=jnp.full((len(state["x"]),), p.p_vol, dtype),
    )
    model = Model(grid=grid, bodies=(body,), frame_dt=p.dt, substeps=1, frames=2)
    values = {"elastic": {"E": p.E, "nu": p.nu}, "corotated": {"E": p.E, "nu": p.nu},
              "newtonian": {"mu": 1.0, "kappa": p.E}, "sand": {"friction_angle": 30.0, "E": p.E, "nu": p.nu},
              "viscoplastic": {"mu": p.mu, "kappa": p.lam + 2 * p.mu / 3, "yield_stress": 1e3, "eta": 1.0}}[material]
    params = {
        "gravity": jnp.asarray(p.gravity, dtype),
        "bodies": ({**{k: jnp.asarray(v, dtype) for k, v in values.items()}, "density": jnp.asarray(p.rho, dtype),
                    "velocity": jnp.asarray(v0, dtype)},),
        "colliders": (),
    }
    return model, params


def peers_root() -> Path | None:
    """The source checkout whose ``benchmarks/peers/`` holds the Taichi/Warp peers: the folder
    above the package, else the working directory; None when neither has them (an installed wheel)."""
    for root in (Path(__file__).resolve().parent.parent, Path.cwd()):
        if (root / "benchmarks" / "peers" / "common.py").is_file():
            return root
    return None


#: Why the peer columns are empty outside a source checkout (one line in the table).
NO_PEERS = "the Taichi/Warp peers live in benchmarks/peers/ of a source checkout; run from its root to time them"


def measure_jax(material: str, n_particles: int, grid_n: int, steps: int, mode: str) -> dict:
    """Time ``steps`` jitted steps (``mode="forward"``) or their gradient (``"backward"``)."""
    import jax
    import jax.numpy as jnp

    from .model import initial_state
    from .step import step

    model, params = _scene_model(n_particles, grid_n, material, jnp.float32)
    state0 = initial_state(model, params)

    def rollout(params, state):
        def body(s, _):
            return jax.checkpoint(lambda s: step(model, params, s))(s), None

        return jax.lax.scan(body, state, None, length=steps)[0]

    if mode == "forward":
        fn = jax.jit(rollout)
    else:
        def loss(params, state):
            return jnp.mean(rollout(params, state).x ** 2)

        fn = jax.jit(jax.grad(loss))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(params, state0))
    compile_s = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(params, state0))
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"ms_per_step": 1e3 * float(np.median(times)) / steps, "compile_s": compile_s,
            "cpu_ms_per_step": 1e3 * float(np.median(cpu)) / steps,
            "n_particles": int(model.num_particles), "version": jax.__version__}


def measure_memory(material: str, n_particles: int, grid_n: int, frames: int, substeps: int, checkpoint: str) -> dict:
    """Time and peak RSS of ``jax.grad`` through ``simulate`` over ``frames x substeps`` steps."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from .step import simulate

    model, params = _scene_model(n_particles, grid_n, material, jnp.float32)
    model = dataclasses.replace(model, frames=frames + 1, substeps=substeps)

    def loss(params):
        return jnp.mean(simulate(model, params, checkpoint=checkpoint).x[-1] ** 2)

    fn = jax.jit(jax.grad(loss))
    t0 = time.perf_counter()
    grads = jax.block_until_ready(fn(params))
    seconds = time.perf_counter() - t0
    finite = all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
    return {"seconds_with_compile": seconds, "steps": frames * substeps, "finite": finite,
            "n_particles": int(model.num_particles), "checkpoint": checkpoint}


def grad_problem(n_particles: int, grid_n: int, steps: int, dtype=None):
    """The gradient benchmark as a function of ``theta = (E, nu, density, vx, vy, vz)``
    (:data:`jaxmpm.bench_scene.GRAD_PARAMETERS`).

    The peers' cube (fixed corotated, ``_scene_model``) starting with the velocity
    ``(vx, vy, vz) + L (x - c)`` (:func:`jaxmpm.bench_scene.grad_scene_velocity`), ``steps`` steps.

    Returns:
        ``(final_x, theta0)``: ``final_x(theta, checkpoint=False)`` gives the final positions
        ``(N, 3)`` (each step under ``jax.checkpoint`` when ``checkpoint``), ``theta0`` the
        scene's values ``(1e5, 0.3, 1000, 0, 0, 0)``.
    """
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from .bench_scene import MPMParams, grad_scene_velocity
    from .model import initial_state
    from .step import step

    dtype = dtype or jnp.float32
    model, params = _scene_model(n_particles, grid_n, "corotated", dtype)
    v_field = jnp.asarray(grad_scene_velocity(np.asarray(model.bodies[0].x0)), dtype)
    p = MPMParams(grid_n=grid_n)
    theta0 = jnp.asarray([p.E, p.nu, p.rho, 0.0, 0.0, 0.0], dtype)

    def final_x(theta, checkpoint: bool = False):
        body = {**params["bodies"][0], "E": theta[0], "nu": theta[1], "density": theta[2], "velocity": theta[3:6]}
        prm = {**params, "bodies": (body,)}
        s0 = initial_state(model, prm)
        s0 = eqx.tree_at(lambda s: s.v, s0, s0.v + v_field)

        def one(s):
            return step(model, prm, s)

        advance = jax.checkpoint(one) if checkpoint else one
        return jax.lax.scan(lambda s, _: (advance(s), None), s0, None, length=steps)[0].x

    return final_x, theta0


def rollout_loss(x):
    """The rollout loss of the gradient benchmark (and of ``measure_jax``'s backward mode)."""
    import jax.numpy as jnp

    return jnp.mean(x**2)


def measure_grad(n_particles: int, grid_n: int, steps: int, ks=(1, 2, 3, 4, 5, 6), repeats: int = 3) -> dict:
    """Time, in one process, a forward rollout, the reverse-mode gradient of ``mean(x_final^2)``
    with respect to the 6 parameters (each step checkpointed), and forward-mode Jacobians of the
    final positions with respect to the first ``k`` parameters (``jax.jvp`` vmapped over ``k``
    basis tangents: one primal and ``k`` tangent rollouts), each as the median of ``repeats``
    after one untimed (compiling) call."""
    import jax
    import jax.numpy as jnp

    final_x, theta0 = grad_problem(n_particles, grid_n, steps)

    def forward(theta):
        return final_x(theta)

    def reverse(theta):
        return jax.grad(lambda t: rollout_loss(final_x(t, checkpoint=True)))(theta)

    def jacobian(k):
        basis = jnp.eye(theta0.shape[0], dtype=theta0.dtype)[:k]

        def jac(theta):
            return jax.vmap(lambda t: jax.jvp(final_x, (theta,), (t,))[1])(basis)

        return jac

    def timed(fn):
        fn = jax.jit(fn)
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(theta0))
        compile_s = time.perf_counter() - t0
        times, cpu = [], []
        for _ in range(max(1, repeats)):
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(theta0))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return out, {"ms": 1e3 * float(np.median(times)), "cpu_ms": 1e3 * float(np.median(cpu)),
                     "compile_s": compile_s}

    x, fwd = timed(forward)
    grad, rev = timed(reverse)
    out = {"forward": fwd, "reverse": {**rev, "grad": [float(g) for g in grad],
                                       "loss": float(rollout_loss(x))},
           "jvp": {}}
    for k in ks:
        _, r = timed(jacobian(int(k)))
        out["jvp"][str(int(k))] = r
    from .bench_scene import GRAD_PARAMETERS

    out.update({"parameters": list(GRAD_PARAMETERS), "n_particles": int(x.shape[0]), "grid_n": int(grid_n),
                "steps": int(steps), "version": jax.__version__})
    return out


def _child(argv: list[str]) -> None:
    """Run one measurement and print its JSON with the process's peak RSS."""
    import resource

    kind, rest = argv[0], json.loads(argv[1])
    if kind == "jax":
        out = measure_jax(**rest)
    elif kind == "memory":
        out = measure_memory(**rest)
    elif kind == "jax_grad":
        out = measure_grad(**rest)
    else:
        root = peers_root()
        if root is None:
            raise RuntimeError(NO_PEERS)
        sys.path.insert(0, str(root))
        name = kind if kind.endswith("_grad") else f"{kind}_step"
        module = __import__(f"benchmarks.peers.{name}", fromlist=["bench"])
        ok, why = module.available()
        if not ok:
            out = {"skipped": why}
        else:
            out = module.bench(**rest)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print("BENCH-JSON " + json.dumps(out))


def _run_child(kind: str, **kwargs) -> dict:
    cmd = [sys.executable, "-c", "import sys; from jaxmpm.bench import _child; _child(sys.argv[1:])",
           kind, json.dumps(kwargs)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=peers_root())
    for line in proc.stdout.splitlines():
        if line.startswith("BENCH-JSON "):
            return json.loads(line[len("BENCH-JSON "):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"skipped": "failed: " + " | ".join(tail)}


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def bench_step(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="jaxmpm bench step", description=__doc__)
    parser.add_argument("--particles", type=int, default=25_000)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--steps", type=int, default=50, help="steps per timed rollout")
    parser.add_argument("--materials", default="elastic,corotated,newtonian,sand,viscoplastic")
    parser.add_argument("--modes", default="forward,backward", help="forward and/or backward (forward + gradient)")
    parser.add_argument("--no-peers", action="store_true", help="skip Taichi and Warp")
    parser.add_argument("--json", default=None, help="also write the results as JSON")
    args = parser.parse_args(argv)
    if not set(args.modes.split(",")) <= {"forward", "backward"}:
        parser.error(f"--modes takes forward and/or backward, got {args.modes!r}")
    common = {"n_particles": args.particles, "grid_n": args.grid, "steps": args.steps}
    rows, peers = [], {}
    if not args.no_peers and peers_root() is None:
        print(f"Taichi/Warp: not available: {NO_PEERS}")
    elif not args.no_peers:
        for kind in ("taichi", "warp"):
            print(f"timing {kind} ...", file=sys.stderr, flush=True)
            peers[kind] = _run_child(kind, **{**common, "steps": max(args.steps, 100)})
    for material in args.materials.split(","):
        for mode in args.modes.split(","):
            print(f"timing jaxmpm {material} {mode} ...", file=sys.stderr, flush=True)
            rows.append({"material": material, "mode": mode, **_run_child("jax", material=material, mode=mode, **common)})
    taichi_ms = peers.get("taichi", {}).get("ms_per_step")
    print(f"\nmachine: {machine_description()}; {args.particles} particles, {args.grid}^3 grid, dt = 1e-4, float32\n")
    print(f"{'code':<32}{'ms/step':>10}{'x Taichi':>10}{'compile s':>11}{'peak RSS MB':>13}")
    for kind, res in peers.items():
        if "skipped" in res:
            print(f"{kind + ' (fixed corotated)':<32}  skipped: {res['skipped']}")
        else:
            ratio = res["ms_per_step"] / taichi_ms if taichi_ms else float("nan")
            print(f"{kind + ' (fixed corotated)':<32}{res['ms_per_step']:>10.2f}{ratio:>10.2f}"
                  f"{res['compile_s']:>11.1f}{res['peak_rss_mb']:>13.0f}")
    for r in rows:
        name = f"jaxmpm {r['material']} {r['mode'] if r['mode'] == 'forward' else 'fwd+bwd'}"
        if "skipped" in r:
            print(f"{name:<32}  {r['skipped']}")
            continue
        ratio = r["ms_per_step"] / taichi_ms if taichi_ms else float("nan")
        print(f"{name:<32}{r['ms_per_step']:>10.2f}{ratio:>10.2f}{r['compile_s']:>11.1f}{r['peak_rss_mb']:>13.0f}")
    if peers and all("skipped" in p for p in peers.values()):
        print("\n(Taichi/Warp peers not timed: install them with pip install -e \".[bench]\" and run from the repo root)")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine_description(), "peers": peers, "jaxmpm": rows}, indent=2))
    return 0


def bench_scaling(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="jaxmpm bench scaling", description=__doc__)
    parser.add_argument("--particles", default="10000,25000,50000,100000,200000,400000")
    parser.add_argument("--grids", default="32,48,64,96,128", help="grid sizes at 25,000 particles")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--material", default="elastic")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    by_n, by_grid = [], []
    for n in (int(v) for v in args.particles.split(",")):
        print(f"timing {n} particles on 64^3 ...", file=sys.stderr, flush=True)
        by_n.append(_run_child("jax", material=args.material, mode="forward", n_particles=n, grid_n=64, steps=args.steps))
    for g in (int(v) for v in args.grids.split(",")):
        print(f"timing 25000 particles on {g}^3 ...", file=sys.stderr, flush=True)
        by_grid.append({"grid": g, **_run_child("jax", material=args.material, mode="forward", n_particles=25_000,
                                                 grid_n=g, steps=args.steps)})
    ok = [r for r in by_n if "skipped" not in r]
    exponent = {"wall": float("nan"), "cpu": float("nan")}
    if len(ok) >= 2:
        logn = np.log([r["n_particles"] for r in ok])
        for key, column in (("wall", "ms_per_step"), ("cpu", "cpu_ms_per_step")):
            exponent[key] = float(np.polyfit(logn, np.log([r[column] for r in ok]), 1)[0])
    print(f"\nmachine: {machine_description()}; {args.material}, float32, forward step\n")
    print(f"{'particles':>10}{'grid':>6}{'ms/step':>10}{'CPU ms/step':>13}{'CPU us/particle':>17}{'compile s':>11}"
          f"{'peak RSS MB':>13}")
    for r, g in [(r, 64) for r in by_n] + [(r, r["grid"]) for r in by_grid]:
        if "skipped" in r:
            print(f"{'':>10}{g:>6}  {r['skipped']}")
            continue
        print(f"{r['n_particles']:>10}{g:>6}{r['ms_per_step']:>10.2f}{r['cpu_ms_per_step']:>13.2f}"
              f"{1e3 * r['cpu_ms_per_step'] / r['n_particles']:>17.3f}{r['compile_s']:>11.1f}{r['peak_rss_mb']:>13.0f}")
    print(f"\nfitted exponent of time ~ N^p over {len(ok)} particle counts: p = {exponent['wall']:.2f} (wall), "
          f"{exponent['cpu']:.2f} (CPU time, less sensitive to other load)")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine_description(), "by_particles": by_n,
                                               "by_grid": by_grid, "exponent": exponent}, indent=2))
    return 0


def bench_memory(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="jaxmpm bench memory", description=__doc__)
    parser.add_argument("--particles", type=int, default=25_000)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--substeps", type=int, default=200)
    parser.add_argument("--checkpoint", default="nested", choices=("step", "frame", "nested"))
    parser.add_argument("--material", default="elastic")
    args = parser.parse_args(argv)
    print(f"gradient through {args.frames} x {args.substeps} steps ...", file=sys.stderr, flush=True)
    r = _run_child("memory", material=args.material, n_particles=args.particles, grid_n=args.grid,
                   frames=args.frames, substeps=args.substeps, checkpoint=args.checkpoint)
    print(f"\nmachine: {machine_description()}")
    if "skipped" in r:
        print(f"gradient run failed: {r['skipped']}")
        return 1
    print(f"{r['n_particles']} particles, {args.grid}^3 grid, {r['steps']} steps, checkpoint={r['checkpoint']}: "
          f"peak RSS {r['peak_rss_mb']:.0f} MB, {r['seconds_with_compile']:.0f} s including compilation, "
          f"gradient finite: {r['finite']}")
    return 0


def bench_grad(argv: list[str]) -> int:
    """``jaxmpm bench grad``: issue 15 target 6 (reverse mode against Taichi's autodiff, forward-mode
    Jacobians against one forward rollout)."""
    parser = argparse.ArgumentParser(
        prog="jaxmpm bench grad",
        description="One reverse-mode gradient of a rollout loss against Taichi autodiff (ti.ad.Tape), and "
                    "forward-mode Jacobians for k parameters against one forward rollout (issue 15, target 6).")
    parser.add_argument("--particles", type=int, default=25_000)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--steps", type=int, default=200, help="steps of the differentiated rollout")
    parser.add_argument("--ks", default="1,2,3,4,5,6", help="numbers of parameters of the forward-mode Jacobians")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per measurement (median)")
    parser.add_argument("--no-peers", action="store_true", help="skip Taichi")
    parser.add_argument("--json", default=None, help="also write the results as JSON")
    args = parser.parse_args(argv)
    ks = [int(k) for k in args.ks.split(",") if k]
    if any(not 1 <= k <= 6 for k in ks):
        parser.error(f"--ks takes numbers from 1 to 6, got {args.ks!r}")
    common = {"n_particles": args.particles, "grid_n": args.grid, "steps": args.steps, "repeats": args.repeats}
    taichi: dict = {}
    if args.no_peers:
        pass
    elif peers_root() is None:
        taichi = {"skipped": NO_PEERS}
    else:
        print("timing taichi autodiff (ti.ad.Tape) ...", file=sys.stderr, flush=True)
        taichi = _run_child("taichi_grad", **common)
    print("timing jaxmpm forward, reverse and forward-mode Jacobians ...", file=sys.stderr, flush=True)
    jax_res = _run_child("jax_grad", ks=ks, **common)
    print(f"\nmachine: {machine_description()}; {args.particles} particles, {args.grid}^3 grid, {args.steps} steps, "
          f"dt = 1e-4, float32, fixed corotated")
    print("loss mean(x_final^2), gradient w.r.t. (E, nu, density, vx, vy, vz)\n")
    if "skipped" in jax_res:
        print(f"jaxmpm: {jax_res['skipped']}")
        return 1
    fwd = jax_res["forward"]["ms"]
    rev = jax_res["reverse"]
    print(f"{'measurement':<40}{'ms':>11}{'ratio':>9}{'target':>9}  {'met':<5}{'compile s':>10}")
    compile_fwd = jax_res["forward"]["compile_s"]
    print(f"{'jaxmpm forward rollout':<40}{fwd:>11.1f}{1.0:>9.2f}{'':>9}  {'':<5}{compile_fwd:>10.1f}")
    if args.no_peers:
        pass
    elif "skipped" in taichi:
        print(f"{'Taichi ti.ad.Tape forward+backward':<40}  skipped: {taichi['skipped']}")
    else:
        print(f"{'Taichi forward rollout (stored states)':<40}{taichi['forward_ms']:>11.1f}{'':>9}{'':>9}  {'':<5}")
        print(f"{'Taichi ti.ad.Tape forward+backward':<40}{taichi['ms']:>11.1f}{1.0:>9.2f}{'':>9}  {'':<5}"
              f"{taichi['compile_s']:>10.1f}")
    ratio, target, met = rev["ms"] / fwd, "", ""
    if taichi.get("ms"):
        ratio, target = rev["ms"] / taichi["ms"], "1.00"
        met = "yes" if ratio <= 1.0 else "no"
    label = "jaxmpm reverse (x Taichi Tape)" if target else "jaxmpm reverse (x own forward)"
    print(f"{label:<40}{rev['ms']:>11.1f}{ratio:>9.2f}{target:>9}  {met:<5}{rev['compile_s']:>10.1f}")
    for k, r in jax_res["jvp"].items():
        ratio, target = r["ms"] / fwd, 1.0 + 0.6 * int(k)
        print(f"{f'jaxmpm jvp Jacobian, k = {k} (x forward)':<40}{r['ms']:>11.1f}{ratio:>9.2f}{target:>9.2f}  "
              f"{'yes' if ratio <= target else 'no':<5}{r['compile_s']:>10.1f}")
    names = jax_res["parameters"]
    print("\ngradient  " + "  ".join(f"{n:>11}" for n in names))
    print("jaxmpm    " + "  ".join(f"{g:>11.4e}" for g in rev["grad"]))
    if taichi.get("grad"):
        print("Taichi    " + "  ".join(f"{g:>11.4e}" for g in taichi["grad"]))
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine_description(), "taichi": taichi, "jaxmpm": jax_res},
                                              indent=2))
    return 0


def bench_sysid(argv: list[str]) -> int:
    from .bench_sysid import run_sysid_bench

    return run_sysid_bench(argv)


BENCHES = {"step": bench_step, "scaling": bench_scaling, "memory": bench_memory, "sysid": bench_sysid,
           "grad": bench_grad}


def run_bench(what: str, argv: list[str]) -> int:
    return BENCHES[what](argv)
