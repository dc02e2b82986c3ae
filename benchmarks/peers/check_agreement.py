"""Check by hand that the Taichi and Warp peers compute the same physics, and that Taichi's
autodiff and jaxmpm compute the same gradient.

    python -m benchmarks.peers.check_agreement [--n-particles 25000]
    python -m benchmarks.peers.check_agreement --grad [--n-particles 1000] [--steps 20]

Two scenes, both from the same NumPy particles (``common.initial_state``):

1. free fall: the benchmark scene (cube at rest in the middle of the box) for 100
   steps. The centre of mass must follow the discrete free-fall law exactly (MLS-MPM
   transfers conserve momentum), and the peers must agree particle by particle.
2. drop: the cube starts 5 cells above the floor moving down at 2 m/s; about 120
   steps of free fall, then a few hundred steps of it hitting and squashing against
   the bottom slip wall. The peers' centres of mass must agree within 1e-3 m.

With ``--grad`` (:func:`check_grad_agreement`, Taichi only): the gradient of the rollout loss
``mean(x_final^2)`` with respect to ``(E, nu, density, vx, vy, vz)`` from Taichi's autodiff
(``taichi_grad.py``, float32) and from ``jax.grad`` of jaxmpm's step (float32) must agree
within a relative 1e-3 per parameter, and both must match central finite differences of
jaxmpm's loss in float64 within the same tolerance.

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


#: Finite-difference steps of the 6 parameters (E, nu, density, vx, vy, vz), in their units.
FD_STEPS = (10.0, 3e-5, 0.1, 1e-3, 1e-3, 1e-3)


def _jax_gradient(n_particles: int, grid_n: int, steps: int):
    """jaxmpm's float32 loss, gradient and final positions, and float64 central differences."""
    import jax
    import jax.numpy as jnp

    from jaxmpm.bench import grad_problem, rollout_loss

    final_x, theta = grad_problem(n_particles, grid_n, steps, jnp.float32)
    loss, grad = jax.jit(jax.value_and_grad(lambda t: rollout_loss(final_x(t, checkpoint=True))))(theta)
    x = np.asarray(jax.jit(final_x)(theta))
    with jax.enable_x64(True):
        final_x64, theta64 = grad_problem(n_particles, grid_n, steps, jnp.float64)
        loss64 = jax.jit(lambda t: rollout_loss(final_x64(t)))
        fd = []
        for i, h in enumerate(FD_STEPS):
            e = jnp.zeros_like(theta64).at[i].set(h)
            fd.append((float(loss64(theta64 + e)) - float(loss64(theta64 - e))) / (2.0 * h))
    return float(loss), np.asarray(grad, np.float64), x, np.asarray(fd)


def check_grad_agreement(
    n_particles: int = 1000, grid_n: int = 64, steps: int = 20, tol: float = 1e-3, threads: int | None = None,
    verbose: bool = True,
) -> dict:
    """Taichi autodiff vs jaxmpm ``jax.grad`` vs float64 central differences (see the module doc).

    Returns:
        ``{"ok", "parameters", "taichi", "jaxmpm", "fd", "rel_taichi_jaxmpm", "rel_taichi_fd",
        "rel_jaxmpm_fd", "loss_taichi", "loss_jaxmpm", "max_dx"}`` (gradients in the order of
        ``parameters``), or ``{"skipped": reason}`` when Taichi cannot be imported.
    """
    from . import taichi_grad

    ok, why = taichi_grad.available()
    if not ok:
        return {"skipped": why}
    t0 = time.perf_counter()
    ti_res = taichi_grad.gradient(n_particles, grid_n, steps, threads=threads)
    t_ti = time.perf_counter() - t0
    t0 = time.perf_counter()
    loss_j, grad_j, x_j, fd = _jax_gradient(n_particles, grid_n, steps)
    t_j = time.perf_counter() - t0
    grad_t = ti_res["grad"]

    def rel(a, b):
        return np.abs(a - b) / np.maximum(np.abs(b), 1e-30)

    out = {
        "parameters": list(taichi_grad.PARAMETERS), "taichi": grad_t.tolist(), "jaxmpm": grad_j.tolist(),
        "fd": fd.tolist(), "rel_taichi_jaxmpm": rel(grad_t, grad_j).tolist(), "rel_taichi_fd": rel(grad_t, fd).tolist(),
        "rel_jaxmpm_fd": rel(grad_j, fd).tolist(), "loss_taichi": ti_res["loss"], "loss_jaxmpm": loss_j,
        "max_dx": float(np.abs(ti_res["x"] - x_j).max()), "seconds_taichi": t_ti, "seconds_jaxmpm": t_j,
    }
    worst = max(max(out[k]) for k in ("rel_taichi_jaxmpm", "rel_taichi_fd", "rel_jaxmpm_fd"))
    out["ok"] = bool(np.isfinite(worst) and worst <= tol and out["max_dx"] <= 1e-5)
    if verbose:
        print(f"gradient of mean(x_final^2): {n_particles} particles, {grid_n}^3 grid, {steps} steps "
              f"(Taichi {t_ti:.0f} s, jaxmpm {t_j:.0f} s including compilation)")
        print(f"  loss: Taichi {out['loss_taichi']:.9g}  jaxmpm {loss_j:.9g};  max |x_taichi - x_jaxmpm| = "
              f"{out['max_dx']:.2e} m")
        print(f"  {'':>8}{'Taichi':>14}{'jaxmpm':>14}{'FD (f64)':>14}{'rel T-j':>10}{'rel T-FD':>10}{'rel j-FD':>10}")
        for i, name in enumerate(out["parameters"]):
            print(f"  {name:>8}{grad_t[i]:>14.6e}{grad_j[i]:>14.6e}{fd[i]:>14.6e}{out['rel_taichi_jaxmpm'][i]:>10.1e}"
                  f"{out['rel_taichi_fd'][i]:>10.1e}{out['rel_jaxmpm_fd'][i]:>10.1e}")
        print(f"  {'ok  ' if out['ok'] else 'FAIL'} worst relative difference {worst:.1e} (tol {tol:.0e})")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Taichi vs Warp MLS-MPM agreement check")
    parser.add_argument("--n-particles", type=int, default=None, help="default 25000 (1000 with --grad)")
    parser.add_argument("--grid-n", type=int, default=64)
    parser.add_argument("--drop-steps", type=int, default=500)
    parser.add_argument("--grad", action="store_true", help="check Taichi autodiff against jaxmpm's gradient")
    parser.add_argument("--steps", type=int, default=20, help="rollout steps of the --grad check")
    args = parser.parse_args(argv)
    if args.grad:
        res = check_grad_agreement(args.n_particles or 1000, args.grid_n, args.steps)
        if "skipped" in res:
            print(f"skip: {res['skipped']}")
            return 0
        print("PASS" if res["ok"] else "FAILED")
        return 0 if res["ok"] else 1
    args.n_particles = args.n_particles or 25_000

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
