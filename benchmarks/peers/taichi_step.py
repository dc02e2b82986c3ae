"""Taichi peer of the reference MLS-MPM step (3D, float32, CPU backend).

One full step (grid clear, P2G, grid update, G2P) is a single Taichi kernel; its
four top-level loops run one after the other, each parallelised over the CPU
threads, with atomic scatter in P2G. See ``README.md`` for the physics.

Run ``python -m benchmarks.peers.taichi_step`` to print the benchmark dict.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from .common import (
    DEFAULT_GRID_N,
    DEFAULT_N_PARTICLES,
    MPMParams,
    default_threads,
    initial_state,
    time_steps,
)

try:  # pragma: no cover - depends on the environment
    import taichi as ti

    _IMPORT_ERROR: str | None = None
except Exception as exc:  # noqa: BLE001 - any import failure means "unavailable"
    ti = None
    _IMPORT_ERROR = f"{type(exc).__name__}: {exc}"


def available() -> tuple[bool, str]:
    """Whether Taichi can be imported (and if not, why)."""
    if ti is None:
        return False, f"taichi cannot be imported ({_IMPORT_ERROR}); pip install taichi"
    return True, f"taichi {version()}"


def version() -> str:
    if ti is None:
        return "unavailable"
    return ".".join(str(p) for p in ti.__version__)


def _init(threads: int | None, cold: bool = True) -> int:
    """(Re)initialise Taichi on the CPU; returns the thread count it was given.

    With ``cold`` the offline (on-disk) kernel cache is disabled, so the first step
    always pays the full JIT compilation.
    """
    n_threads = int(threads) if threads else default_threads()
    ti.init(
        arch=ti.cpu,
        default_fp=ti.f32,
        default_ip=ti.i32,
        cpu_max_num_threads=n_threads,
        offline_cache=not cold,
        random_seed=0,
        log_level=ti.WARN,
    )
    return n_threads


if ti is not None:

    @ti.data_oriented
    class TaichiMPM:
        """Particle and grid fields plus the step kernel.

        Scalar parameters are Python attributes, so Taichi bakes them into the
        compiled kernel as constants.
        """

        def __init__(self, state: dict[str, np.ndarray], params: MPMParams):
            n = len(state["x"])
            g = params.grid_n
            self.n = n
            self.grid_n = g
            self.bound = params.bound
            self.dx = float(params.dx)
            self.inv_dx = float(params.inv_dx)
            self.dt = float(params.dt)
            self.p_vol = float(params.p_vol)
            self.p_mass = float(params.p_mass)
            self.mu = float(params.mu)
            self.lam = float(params.lam)
            self.gx, self.gy, self.gz = (float(c) for c in params.gravity)

            self.x = ti.Vector.field(3, ti.f32, shape=n)
            self.v = ti.Vector.field(3, ti.f32, shape=n)
            self.C = ti.Matrix.field(3, 3, ti.f32, shape=n)
            self.F = ti.Matrix.field(3, 3, ti.f32, shape=n)
            self.grid_mv = ti.Vector.field(3, ti.f32, shape=(g, g, g))
            self.grid_m = ti.field(ti.f32, shape=(g, g, g))

            self.x.from_numpy(state["x"])
            self.v.from_numpy(state["v"])
            self.C.from_numpy(state["C"])
            self.F.from_numpy(state["F"])

        @ti.kernel
        def step(self):
            dx = self.dx
            inv_dx = self.inv_dx
            dt = self.dt
            p_mass = self.p_mass
            gn = self.grid_n

            # -- clear the grid ------------------------------------------------
            for I in ti.grouped(self.grid_m):
                self.grid_mv[I] = ti.Vector.zero(ti.f32, 3)
                self.grid_m[I] = 0.0

            # -- P2G -----------------------------------------------------------
            for p in self.x:
                xg = self.x[p] * inv_dx
                base = ti.cast(ti.floor(xg - 0.5), ti.i32)
                base = ti.max(ti.min(base, gn - 3), 0)  # never write outside the grid
                fx = xg - ti.cast(base, ti.f32)
                w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]

                C = self.C[p]
                F = (ti.Matrix.identity(ti.f32, 3) + dt * C) @ self.F[p]
                self.F[p] = F
                # fixed corotated Kirchhoff stress: 2 mu (F - R) F^T + lam (J - 1) J I
                U, sig, V = ti.svd(F, ti.f32)
                R = U @ V.transpose()
                J = F.determinant()
                tau = 2.0 * self.mu * (F - R) @ F.transpose() + ti.Matrix.identity(
                    ti.f32, 3
                ) * (self.lam * (J - 1.0) * J)
                affine = (-dt * self.p_vol * 4.0 * inv_dx * inv_dx) * tau + p_mass * C
                mv = p_mass * self.v[p]

                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    offset = ti.Vector([i, j, k])
                    dpos = (ti.cast(offset, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[k][2]
                    self.grid_mv[base + offset] += weight * (mv + affine @ dpos)
                    self.grid_m[base + offset] += weight * p_mass

            # -- grid update: momentum -> velocity, gravity, slip walls ---------
            for I in ti.grouped(self.grid_m):
                m = self.grid_m[I]
                if m > 0.0:
                    vi = self.grid_mv[I] / m + dt * ti.Vector([self.gx, self.gy, self.gz])
                    for d in ti.static(range(3)):
                        if I[d] < self.bound and vi[d] < 0.0:
                            vi[d] = 0.0
                        if I[d] > gn - self.bound and vi[d] > 0.0:
                            vi[d] = 0.0
                    self.grid_mv[I] = vi  # the buffer now holds velocities

            # -- G2P -----------------------------------------------------------
            for p in self.x:
                xg = self.x[p] * inv_dx
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
                    vi = self.grid_mv[base + offset]
                    new_v += weight * vi
                    new_C += (4.0 * inv_dx * inv_dx * weight) * vi.outer_product(dpos)
                self.v[p] = new_v
                self.C[p] = new_C
                self.x[p] += dt * new_v

        def numpy_state(self) -> dict[str, np.ndarray]:
            return {"x": self.x.to_numpy(), "v": self.v.to_numpy()}


def _require():
    ok, why = available()
    if not ok:
        raise RuntimeError(why)


def bench(
    n_particles: int = DEFAULT_N_PARTICLES,
    grid_n: int = DEFAULT_GRID_N,
    steps: int = 100,
    warmup: int = 10,
    threads: int | None = None,
    cold: bool = True,
) -> dict:
    """Time full MLS-MPM steps on the Taichi CPU backend.

    Arguments:
        n_particles: particles in the cube (up to ~1.4M fits a 64^3 grid).
        grid_n: nodes per axis (dx = 1 / grid_n).
        steps: timed steps.
        warmup: untimed steps before timing (the first one includes JIT compilation).
        threads: ``cpu_max_num_threads``; default all CPUs this process may use.
        cold: disable Taichi's offline kernel cache so ``compile_s`` is a cold
            compile; ``False`` uses (and fills) the cache in ``~/.cache/taichi``.

    Returns:
        ``{"ms_per_step", "compile_s", "n_particles", "backend": "cpu", "version",
        "threads", "grid_n", "steps"}``. ``compile_s`` is the wall time of the first
        step call: JIT compilation plus one step (``ti.init`` itself is not counted).
    """
    _require()
    n_threads = _init(threads, cold)
    params = MPMParams(grid_n=grid_n)
    sim = TaichiMPM(initial_state(n_particles, grid_n), params)
    compile_s, ms = time_steps(sim.step, ti.sync, steps, max(1, warmup))
    return {
        "ms_per_step": float(ms),
        "compile_s": float(compile_s),
        "n_particles": int(sim.n),
        "backend": "cpu",
        "version": version(),
        "threads": n_threads,
        "grid_n": int(grid_n),
        "steps": int(steps),
    }


def final_state(
    n_particles: int = DEFAULT_N_PARTICLES,
    grid_n: int = DEFAULT_GRID_N,
    steps: int = 100,
    *,
    v0: tuple[float, float, float] = (0.0, 0.0, 0.0),
    center: tuple[float, float, float] | None = None,
    threads: int | None = None,
) -> dict[str, np.ndarray]:
    """Particle positions and velocities after ``steps`` steps, ``{"x", "v"}`` (N, 3) float32.

    ``v0`` (initial velocity of every particle) and ``center`` (cube centre) let a
    test drop the cube onto the bottom wall; by default it is the benchmark scene.
    """
    _require()
    _init(threads)
    state = initial_state(n_particles, grid_n, v0=v0, center=center)
    sim = TaichiMPM(state, MPMParams(grid_n=grid_n))
    for _ in range(steps):
        sim.step()
    ti.sync()
    return sim.numpy_state()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-particles", type=int, default=DEFAULT_N_PARTICLES)
    parser.add_argument("--grid-n", type=int, default=DEFAULT_GRID_N)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    ok, why = available()
    if not ok:
        print(json.dumps({"available": False, "reason": why}))
        return
    print(json.dumps(bench(args.n_particles, args.grid_n, args.steps, args.warmup, args.threads)))


if __name__ == "__main__":
    main()
