"""Taichi autodiff peer: the gradient of a rollout loss, the way PAC-NeRF and GIC compute theirs.

The step is the reference MLS-MPM step of ``README.md`` (3D, float32, fixed corotated), split
into kernels that obey Taichi's global data access rule, with

* the particle state stored per step (``x``, ``v``, ``C``, ``F`` of shape ``(steps + 1, N)``,
  ``needs_grad=True``), the material parameters per particle (``mu``, ``lam``, ``mass``,
  PAC-NeRF's layout) derived from the scalar fields ``E``, ``nu``, ``density`` and the
  initial velocity ``v0`` in a first kernel;
* one grid, cleared at every step. A kernel's adjoint reads the primal values it read, so
  the backward of step ``s`` first recomputes that step's grid (clear, P2G, grid update) and
  then runs the adjoint kernels in reverse order -- PAC-NeRF's ``substep_grad``
  (``lib/engine/mpm_simulator.py``), which calls ``kernel.grad()`` by hand. Here the step is a
  ``ti.ad.grad_replaced`` function whose gradient is that recompute-then-adjoint sequence, so
  the whole rollout is differentiated by ``with ti.ad.Tape(loss=...)``. (Recording the plain
  kernels on the Tape with one shared grid would give wrong gradients: by the time the
  backward reaches step ``s`` the grid holds the last step's values. A grid per step would be
  correct but needs ``steps x 64^3 x 7 x 2`` floats, 2.9 GB at 200 steps.)
* the SVD: ``ti.svd`` (the forward peer's) in a kernel of its own, whose adjoint is written by
  hand as PAC-NeRF does (it replaces the SVD kernel's gradient with the closed-form SVD
  backward). The stress uses only ``R = U V^T``, whose adjoint is
  ``dL/dF = U [(A - A^T)_ij / (s_i + s_j)] V^T`` with ``A = U^T (dL/dR) V`` -- the exact
  derivative of the polar rotation, finite at repeated singular values (``F = I``), where the
  general SVD backward (``1 / (s_j^2 - s_i^2)``) is not. ``R`` is recomputed per step, not
  stored.
* the stencil loops are ``ti.static`` (unrolled), as in PAC-NeRF and ``taichi_step.py``. Taichi
  then compiles the adjoints of P2G and G2P in ~90 s (its CFG/simplify passes, independent of
  N; counted in ``compile_s``). Non-static inner loops compile in a few seconds, but Taichi
  1.7.4's autodiff returned wrong gradients with them (28x too large for the initial velocity,
  against jaxmpm and finite differences), so they are not used.

Loss: ``mean(x_final ** 2)`` over all ``3 N`` entries, jaxmpm's ``measure_jax`` backward loss.
Gradient with respect to ``(E, nu, density, vx, vy, vz)``: the material and the initial
velocity, what a system identification fits. The scene is the peers' cube with the initial
velocity field ``v0 + L (x - c)`` (``jaxmpm.bench_scene.grad_scene_velocity``) so that the cube
deforms and the loss depends on the material.

Run ``python -m benchmarks.peers.taichi_grad`` to print the benchmark dict.
"""

# no "from __future__ import annotations": Taichi reads the kernels' argument annotations as objects

import argparse
import json
import time

import numpy as np

from .common import (
    DEFAULT_GRID_N,
    DEFAULT_N_PARTICLES,
    GRAD_PARAMETERS,
    MPMParams,
    grad_scene_velocity,
    initial_state,
)
from .taichi_step import _init, available, ti, version

#: The differentiated parameters, in order: ``("E", "nu", "density", "vx", "vy", "vz")``.
PARAMETERS = GRAD_PARAMETERS

__all__ = ["PARAMETERS", "available", "bench", "gradient", "version"]


if ti is not None:

    @ti.data_oriented
    class TaichiMPMGrad:
        """Per-step particle storage, one grid, and the kernels of one step plus their adjoints."""

        def __init__(self, state: dict[str, np.ndarray], params: MPMParams, steps: int, v_field: np.ndarray):
            n, g = len(state["x"]), params.grid_n
            self.n, self.grid_n, self.steps = n, g, steps
            self.bound = params.bound
            self.dx = float(params.dx)
            self.inv_dx = float(params.inv_dx)
            self.dt = float(params.dt)
            self.p_vol = float(params.p_vol)
            self.gx, self.gy, self.gz = (float(c) for c in params.gravity)

            f32 = ti.f32
            self.x = ti.Vector.field(3, f32, shape=(steps + 1, n), needs_grad=True)
            self.v = ti.Vector.field(3, f32, shape=(steps + 1, n), needs_grad=True)
            self.C = ti.Matrix.field(3, 3, f32, shape=(steps + 1, n), needs_grad=True)
            self.F = ti.Matrix.field(3, 3, f32, shape=(steps + 1, n), needs_grad=True)
            self.R = ti.Matrix.field(3, 3, f32, shape=n, needs_grad=True)  # polar rotation of this step
            self.mu = ti.field(f32, shape=n, needs_grad=True)
            self.lam = ti.field(f32, shape=n, needs_grad=True)
            self.mass = ti.field(f32, shape=n, needs_grad=True)
            self.v_field = ti.Vector.field(3, f32, shape=n)
            self.E = ti.field(f32, shape=(), needs_grad=True)
            self.nu = ti.field(f32, shape=(), needs_grad=True)
            self.rho = ti.field(f32, shape=(), needs_grad=True)
            self.v0 = ti.Vector.field(3, f32, shape=(), needs_grad=True)
            self.grid_m = ti.field(f32, shape=(g, g, g), needs_grad=True)
            self.grid_mv = ti.Vector.field(3, f32, shape=(g, g, g), needs_grad=True)
            self.grid_v = ti.Vector.field(3, f32, shape=(g, g, g), needs_grad=True)
            self.loss = ti.field(f32, shape=(), needs_grad=True)

            self.load(state["x"], state["C"], state["F"])
            self.v_field.from_numpy(np.ascontiguousarray(v_field, np.float32))
            self.E[None] = params.E
            self.nu[None] = params.nu
            self.rho[None] = params.rho
            self.v0[None] = [float(c) for c in state["v"][0]]

        # -- setup and parameters (outside / at the start of the tape) ---------------------
        @ti.kernel
        def load(self, x0: ti.types.ndarray(), C0: ti.types.ndarray(), F0: ti.types.ndarray()):
            for p in range(self.n):
                for i in ti.static(range(3)):
                    self.x[0, p][i] = x0[p, i]
                    for j in ti.static(range(3)):
                        self.C[0, p][i, j] = C0[p, i, j]
                        self.F[0, p][i, j] = F0[p, i, j]

        @ti.kernel
        def init_particles(self):
            for p in range(self.n):
                E, nu = self.E[None], self.nu[None]
                self.mu[p] = E / (2.0 * (1.0 + nu))
                self.lam[p] = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
                self.mass[p] = self.rho[None] * self.p_vol
                self.v[0, p] = self.v0[None] + self.v_field[p]

        # -- one step ---------------------------------------------------------------------
        @ti.kernel
        def clear_grid(self):
            for I in ti.grouped(self.grid_m):
                self.grid_m[I] = 0.0
                self.grid_mv[I] = ti.Vector.zero(ti.f32, 3)
                self.grid_v[I] = ti.Vector.zero(ti.f32, 3)

        @ti.kernel
        def clear_step_grads(self):
            for I in ti.grouped(self.grid_m):
                self.grid_m.grad[I] = 0.0
                self.grid_mv.grad[I] = ti.Vector.zero(ti.f32, 3)
                self.grid_v.grad[I] = ti.Vector.zero(ti.f32, 3)
            for p in range(self.n):
                self.R.grad[p] = ti.Matrix.zero(ti.f32, 3, 3)

        @ti.kernel
        def update_F(self, s: ti.i32):
            for p in range(self.n):
                self.F[s + 1, p] = (ti.Matrix.identity(ti.f32, 3) + self.dt * self.C[s, p]) @ self.F[s, p]

        @ti.kernel
        def polar(self, s: ti.i32):
            for p in range(self.n):
                U, sig, V = ti.svd(self.F[s + 1, p], ti.f32)
                self.R[p] = U @ V.transpose()

        @ti.kernel
        def polar_grad(self, s: ti.i32):
            """Adjoint of ``polar``: ``F.grad += U [(A - A^T)_ij / (s_i + s_j)] V^T``, ``A = U^T R.grad V``."""
            for p in range(self.n):
                U, sig, V = ti.svd(self.F[s + 1, p], ti.f32)
                A = U.transpose() @ self.R.grad[p] @ V
                G = ti.Matrix.zero(ti.f32, 3, 3)
                for i, j in ti.static(ti.ndrange(3, 3)):
                    if ti.static(i != j):
                        den = sig[i, i] + sig[j, j]
                        if ti.abs(den) < 1e-6:
                            den = ti.select(den >= 0.0, 1e-6, -1e-6)
                        G[i, j] = (A[i, j] - A[j, i]) / den
                self.F.grad[s + 1, p] += U @ G @ V.transpose()

        @ti.kernel
        def p2g(self, s: ti.i32):
            for p in range(self.n):
                dx, inv_dx, dt, gn = self.dx, self.inv_dx, self.dt, self.grid_n
                xg = self.x[s, p] * inv_dx
                base = ti.cast(ti.floor(xg - 0.5), ti.i32)
                base = ti.max(ti.min(base, gn - 3), 0)
                fx = xg - ti.cast(base, ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
                F = self.F[s + 1, p]
                J = F.determinant()
                tau = 2.0 * self.mu[p] * (F - self.R[p]) @ F.transpose() + ti.Matrix.identity(ti.f32, 3) * (
                    self.lam[p] * (J - 1.0) * J
                )
                m = self.mass[p]
                affine = (-dt * self.p_vol * 4.0 * inv_dx * inv_dx) * tau + m * self.C[s, p]
                mv = m * self.v[s, p]
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    offset = ti.Vector([i, j, k])
                    dpos = (ti.cast(offset, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[k][2]
                    self.grid_mv[base + offset] += weight * (mv + affine @ dpos)
                    self.grid_m[base + offset] += weight * m

        @ti.kernel
        def grid_op(self):
            for I in ti.grouped(self.grid_m):
                gn = self.grid_n
                m = self.grid_m[I]
                if m > 0.0:
                    vi = self.grid_mv[I] / m + self.dt * ti.Vector([self.gx, self.gy, self.gz])
                    for d in ti.static(range(3)):
                        if I[d] < self.bound and vi[d] < 0.0:
                            vi[d] = 0.0
                        if I[d] > gn - self.bound and vi[d] > 0.0:
                            vi[d] = 0.0
                    self.grid_v[I] = vi

        @ti.kernel
        def g2p(self, s: ti.i32):
            for p in range(self.n):
                dx, inv_dx, gn = self.dx, self.inv_dx, self.grid_n
                xg = self.x[s, p] * inv_dx
                base = ti.cast(ti.floor(xg - 0.5), ti.i32)
                base = ti.max(ti.min(base, gn - 3), 0)
                fx = xg - ti.cast(base, ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
                new_v = ti.Vector.zero(ti.f32, 3)
                new_C = ti.Matrix.zero(ti.f32, 3, 3)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    offset = ti.Vector([i, j, k])
                    dpos = (ti.cast(offset, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[k][2]
                    vi = self.grid_v[base + offset]
                    new_v += weight * vi
                    new_C += (4.0 * inv_dx * inv_dx * weight) * vi.outer_product(dpos)
                self.v[s + 1, p] = new_v
                self.C[s + 1, p] = new_C
                self.x[s + 1, p] = self.x[s, p] + self.dt * new_v

        @ti.kernel
        def compute_loss(self):
            for p in range(self.n):
                scale = 1.0 / (3.0 * self.n)
                xp = self.x[self.steps, p]
                self.loss[None] += scale * xp.dot(xp)

        def _grid(self, s: int):
            self.clear_grid()
            self.polar(s)
            self.p2g(s)
            self.grid_op()

        @ti.ad.grad_replaced
        def substep(self, s: int):
            self.update_F(s)
            self._grid(s)
            self.g2p(s)

        @ti.ad.grad_for(substep)
        def substep_grad(self, s: int):
            self._grid(s)  # this step's grid and R again (the fields hold the last step's)
            self.clear_step_grads()
            self.g2p.grad(s)
            self.grid_op.grad()
            self.p2g.grad(s)
            self.polar_grad(s)
            self.update_F.grad(s)

        # -- drivers ----------------------------------------------------------------------
        def forward(self):
            self.init_particles()
            for s in range(self.steps):
                self.substep(s)
            self.loss[None] = 0.0
            self.compute_loss()

        def forward_backward(self):
            with ti.ad.Tape(loss=self.loss):
                self.init_particles()
                for s in range(self.steps):
                    self.substep(s)
                self.compute_loss()

        def gradient(self) -> np.ndarray:
            v0 = self.v0.grad[None]
            return np.array([self.E.grad[None], self.nu.grad[None], self.rho.grad[None], v0[0], v0[1], v0[2]],
                            np.float64)

        def final_x(self) -> np.ndarray:
            return self.x.to_numpy()[self.steps]


def _require():
    ok, why = available()
    if not ok:
        raise RuntimeError(why)


def _make(n_particles: int, grid_n: int, steps: int, v0=(0.0, 0.0, 0.0)):
    state = initial_state(n_particles, grid_n, v0=v0)
    return TaichiMPMGrad(state, MPMParams(grid_n=grid_n), steps, grad_scene_velocity(state["x"]))


def gradient(
    n_particles: int, grid_n: int = DEFAULT_GRID_N, steps: int = 50, threads: int | None = None
) -> dict:
    """One forward + backward: ``{"loss", "grad": (6,) in PARAMETERS order, "x": final positions}``."""
    _require()
    _init(threads)
    sim = _make(n_particles, grid_n, steps)
    sim.forward_backward()
    ti.sync()
    return {"loss": float(sim.loss[None]), "grad": sim.gradient(), "x": sim.final_x()}


def bench(
    n_particles: int = DEFAULT_N_PARTICLES,
    grid_n: int = DEFAULT_GRID_N,
    steps: int = 200,
    repeats: int = 3,
    threads: int | None = None,
    cold: bool = True,
) -> dict:
    """Time one reverse-mode gradient of the rollout loss (forward + backward under ``ti.ad.Tape``).

    The first forward + backward (JIT compilation of the kernels and their adjoints, plus
    one run) is ``compile_s``; then ``repeats`` runs are timed, each synchronised, and the
    median is reported, as ``ms`` (whole rollout) and ``ms_per_step``. ``forward_ms`` is the
    median of ``repeats`` plain forward rollouts with the same kernels and storage.

    Returns:
        ``{"ms", "ms_per_step", "forward_ms", "compile_s", "loss", "grad", "parameters",
        "n_particles", "grid_n", "steps", "backend": "cpu", "version", "threads"}``.
    """
    _require()
    n_threads = _init(threads, cold)
    sim = _make(n_particles, grid_n, steps)
    t0 = time.perf_counter()
    sim.forward_backward()
    ti.sync()
    compile_s = time.perf_counter() - t0
    times, fwd = [], []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        sim.forward_backward()
        ti.sync()
        times.append(time.perf_counter() - t0)
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        sim.forward()
        ti.sync()
        fwd.append(time.perf_counter() - t0)
    sim.forward_backward()  # leave the gradient of the timed problem in the fields
    ms = 1e3 * float(np.median(times))
    return {
        "ms": ms,
        "ms_per_step": ms / steps,
        "forward_ms": 1e3 * float(np.median(fwd)),
        "compile_s": float(compile_s),
        "loss": float(sim.loss[None]),
        "grad": [float(g) for g in sim.gradient()],
        "parameters": list(PARAMETERS),
        "n_particles": int(sim.n),
        "grid_n": int(grid_n),
        "steps": int(steps),
        "backend": "cpu",
        "version": version(),
        "threads": n_threads,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-particles", type=int, default=DEFAULT_N_PARTICLES)
    parser.add_argument("--grid-n", type=int, default=DEFAULT_GRID_N)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    ok, why = available()
    if not ok:
        print(json.dumps({"available": False, "reason": why}))
        return
    print(json.dumps(bench(args.n_particles, args.grid_n, args.steps, args.repeats, args.threads)))


if __name__ == "__main__":
    main()
