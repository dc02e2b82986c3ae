"""NVIDIA Warp peer of the reference MLS-MPM step (3D, float32, CPU device).

One full step is: zero the two grid arrays, then three kernel launches (P2G with
atomic scatter, grid update, G2P). See ``README.md`` for the physics.

Note that Warp runs a CPU launch on a single thread (a serial loop over the launch
dimension), so this peer uses one core whatever the machine has.

Run ``python -m benchmarks.peers.warp_step`` to print the benchmark dict.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import tempfile

import numpy as np

from .common import (
    DEFAULT_GRID_N,
    DEFAULT_N_PARTICLES,
    MPMParams,
    initial_state,
    time_steps,
)

try:  # pragma: no cover - depends on the environment
    import warp as wp

    _IMPORT_ERROR: str | None = None
except Exception as exc:  # noqa: BLE001 - any import failure means "unavailable"
    wp = None
    _IMPORT_ERROR = f"{type(exc).__name__}: {exc}"

_DEVICE = "cpu"
_PRIVATE_CACHE: str | None = None


def available() -> tuple[bool, str]:
    """Whether Warp can be imported and initialised on the CPU (and if not, why)."""
    if wp is None:
        return False, f"warp cannot be imported ({_IMPORT_ERROR}); pip install warp-lang"
    try:
        _init()
    except Exception as exc:  # noqa: BLE001
        return False, f"warp cannot initialise the CPU device ({type(exc).__name__}: {exc})"
    return True, f"warp {version()}"


def version() -> str:
    return "unavailable" if wp is None else str(wp.__version__)


def _init() -> None:
    """Initialise Warp once, quietly, with a kernel cache private to this process.

    The private cache (when this module is the one that initialises Warp) keeps the
    user's ``~/.cache/warp`` untouched and lets :func:`bench` measure a cold compile
    by clearing it.
    """
    global _PRIVATE_CACHE
    from warp._src import context as _ctx  # noqa: PLC0415

    if _ctx.runtime is None:
        wp.config.quiet = True
        wp.config.log_level = wp.LOG_WARNING  # no greeting / per-module load lines
        _PRIVATE_CACHE = tempfile.mkdtemp(prefix="jaxmpm-warp-cache-")
        atexit.register(shutil.rmtree, _PRIVATE_CACHE, ignore_errors=True)
        wp.config.kernel_cache_dir = _PRIVATE_CACHE
        wp.init()


if wp is not None:
    # Forward only: no adjoint kernels are needed (and they would double compile time).
    wp.set_module_options({"enable_backward": False})

    @wp.func
    def _bspline_weights(fx: wp.vec3):
        """Quadratic B-spline weights of the three stencil nodes, one vec3 per node."""
        w0 = wp.vec3(
            0.5 * (1.5 - fx[0]) * (1.5 - fx[0]),
            0.5 * (1.5 - fx[1]) * (1.5 - fx[1]),
            0.5 * (1.5 - fx[2]) * (1.5 - fx[2]),
        )
        w1 = wp.vec3(
            0.75 - (fx[0] - 1.0) * (fx[0] - 1.0),
            0.75 - (fx[1] - 1.0) * (fx[1] - 1.0),
            0.75 - (fx[2] - 1.0) * (fx[2] - 1.0),
        )
        w2 = wp.vec3(
            0.5 * (fx[0] - 0.5) * (fx[0] - 0.5),
            0.5 * (fx[1] - 0.5) * (fx[1] - 0.5),
            0.5 * (fx[2] - 0.5) * (fx[2] - 0.5),
        )
        # transpose so that row d holds the three weights along axis d
        return wp.mat33(w0[0], w1[0], w2[0], w0[1], w1[1], w2[1], w0[2], w1[2], w2[2])

    @wp.func
    def _base_node(xg: wp.vec3, grid_n: int):
        """Lower stencil corner floor(x/dx - 0.5), clamped so the stencil stays in the grid."""
        bx = wp.clamp(int(wp.floor(xg[0] - 0.5)), 0, grid_n - 3)
        by = wp.clamp(int(wp.floor(xg[1] - 0.5)), 0, grid_n - 3)
        bz = wp.clamp(int(wp.floor(xg[2] - 0.5)), 0, grid_n - 3)
        return wp.vec3i(bx, by, bz)

    @wp.kernel
    def _p2g(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33),
        grid_mv: wp.array3d(dtype=wp.vec3),
        grid_m: wp.array3d(dtype=float),
        grid_n: int,
        dx: float,
        inv_dx: float,
        dt: float,
        p_vol: float,
        p_mass: float,
        mu: float,
        lam: float,
    ):
        p = wp.tid()
        xg = x[p] * inv_dx
        base = _base_node(xg, grid_n)
        fx = xg - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        w = _bspline_weights(fx)

        Cp = C[p]
        ident = wp.identity(n=3, dtype=float)
        Fp = (ident + dt * Cp) @ F[p]
        F[p] = Fp
        # fixed corotated Kirchhoff stress: 2 mu (F - R) F^T + lam (J - 1) J I
        U = wp.mat33()
        sig = wp.vec3()
        V = wp.mat33()
        wp.svd3(Fp, U, sig, V)
        R = U @ wp.transpose(V)
        J = wp.determinant(Fp)
        tau = 2.0 * mu * (Fp - R) @ wp.transpose(Fp) + ident * (lam * (J - 1.0) * J)
        affine = (-dt * p_vol * 4.0 * inv_dx * inv_dx) * tau + p_mass * Cp
        mv = p_mass * v[p]

        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                    weight = w[0, i] * w[1, j] * w[2, k]
                    gi = base[0] + i
                    gj = base[1] + j
                    gk = base[2] + k
                    wp.atomic_add(grid_mv, gi, gj, gk, weight * (mv + affine @ dpos))
                    wp.atomic_add(grid_m, gi, gj, gk, weight * p_mass)

    @wp.kernel
    def _grid_update(
        grid_mv: wp.array3d(dtype=wp.vec3),
        grid_m: wp.array3d(dtype=float),
        grid_n: int,
        bound: int,
        dt: float,
        gravity: wp.vec3,
    ):
        i, j, k = wp.tid()
        m = grid_m[i, j, k]
        if m > 0.0:
            vi = grid_mv[i, j, k] / m + dt * gravity
            idx = wp.vec3i(i, j, k)
            for d in range(3):
                if idx[d] < bound and vi[d] < 0.0:
                    vi[d] = 0.0
                if idx[d] > grid_n - bound and vi[d] > 0.0:
                    vi[d] = 0.0
            grid_mv[i, j, k] = vi  # the buffer now holds velocities

    @wp.kernel
    def _g2p(
        x: wp.array(dtype=wp.vec3),
        v: wp.array(dtype=wp.vec3),
        C: wp.array(dtype=wp.mat33),
        grid_v: wp.array3d(dtype=wp.vec3),
        grid_n: int,
        dx: float,
        inv_dx: float,
        dt: float,
    ):
        p = wp.tid()
        xp = x[p]
        xg = xp * inv_dx
        base = _base_node(xg, grid_n)
        fx = xg - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
        w = _bspline_weights(fx)
        new_v = wp.vec3()
        new_C = wp.mat33()
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                    weight = w[0, i] * w[1, j] * w[2, k]
                    vi = grid_v[base[0] + i, base[1] + j, base[2] + k]
                    new_v += weight * vi
                    new_C += (4.0 * inv_dx * inv_dx * weight) * wp.outer(vi, dpos)
        v[p] = new_v
        C[p] = new_C
        x[p] = xp + dt * new_v


class WarpMPM:
    """Particle and grid arrays on the Warp CPU device, and the step."""

    def __init__(self, state: dict[str, np.ndarray], params: MPMParams):
        _init()
        dev = _DEVICE
        g = params.grid_n
        self.params = params
        self.n = len(state["x"])
        self.x = wp.array(state["x"], dtype=wp.vec3, device=dev)
        self.v = wp.array(state["v"], dtype=wp.vec3, device=dev)
        self.C = wp.array(state["C"], dtype=wp.mat33, device=dev)
        self.F = wp.array(state["F"], dtype=wp.mat33, device=dev)
        self.grid_mv = wp.zeros((g, g, g), dtype=wp.vec3, device=dev)
        self.grid_m = wp.zeros((g, g, g), dtype=float, device=dev)
        p = params
        self._p2g_args = [
            self.x, self.v, self.C, self.F, self.grid_mv, self.grid_m,
            g, p.dx, p.inv_dx, p.dt, p.p_vol, p.p_mass, p.mu, p.lam,
        ]  # fmt: skip
        self._grid_args = [self.grid_mv, self.grid_m, g, p.bound, p.dt, wp.vec3(*p.gravity)]
        self._g2p_args = [self.x, self.v, self.C, self.grid_mv, g, p.dx, p.inv_dx, p.dt]

    def step(self) -> None:
        g = self.params.grid_n
        self.grid_mv.zero_()
        self.grid_m.zero_()
        wp.launch(_p2g, dim=self.n, inputs=self._p2g_args, device=_DEVICE)
        wp.launch(_grid_update, dim=(g, g, g), inputs=self._grid_args, device=_DEVICE)
        wp.launch(_g2p, dim=self.n, inputs=self._g2p_args, device=_DEVICE)

    @staticmethod
    def sync() -> None:
        wp.synchronize_device(_DEVICE)

    def numpy_state(self) -> dict[str, np.ndarray]:
        self.sync()
        return {"x": self.x.numpy().copy(), "v": self.v.numpy().copy()}


def _require():
    ok, why = available()
    if not ok:
        raise RuntimeError(why)


def _make_cold() -> None:
    """Unload the compiled kernels and clear the (private) kernel cache."""
    _p2g.module.unload()
    if _PRIVATE_CACHE is None:
        return
    # Warp appends its version to the directory it was given.
    cache = os.path.realpath(wp.config.kernel_cache_dir)
    private = os.path.realpath(_PRIVATE_CACHE)
    if cache == private or cache.startswith(private + os.sep):
        wp.clear_kernel_cache()


def bench(
    n_particles: int = DEFAULT_N_PARTICLES,
    grid_n: int = DEFAULT_GRID_N,
    steps: int = 100,
    warmup: int = 10,
    cold: bool = True,
) -> dict:
    """Time full MLS-MPM steps on the Warp CPU device.

    Arguments:
        n_particles: particles in the cube (up to ~1.4M fits a 64^3 grid).
        grid_n: nodes per axis (dx = 1 / grid_n).
        steps: timed steps.
        warmup: untimed steps before timing (the first one includes compilation).
        cold: unload the kernels and clear this process's private kernel cache
            first, so ``compile_s`` is a cold compile (only possible when this module
            initialised Warp; otherwise the cache is left alone).

    Returns:
        ``{"ms_per_step", "compile_s", "n_particles", "backend": "cpu", "version",
        "threads": 1, "grid_n", "steps"}``. ``compile_s`` is the wall time of the
        first step: code generation + C++ compilation + one step.
    """
    _require()
    if cold:
        _make_cold()
    sim = WarpMPM(initial_state(n_particles, grid_n), MPMParams(grid_n=grid_n))
    compile_s, ms = time_steps(sim.step, sim.sync, steps, max(1, warmup))
    return {
        "ms_per_step": float(ms),
        "compile_s": float(compile_s),
        "n_particles": int(sim.n),
        "backend": "cpu",
        "version": version(),
        "threads": 1,
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
) -> dict[str, np.ndarray]:
    """Particle positions and velocities after ``steps`` steps, ``{"x", "v"}`` (N, 3) float32.

    ``v0`` (initial velocity of every particle) and ``center`` (cube centre) let a
    test drop the cube onto the bottom wall; by default it is the benchmark scene.
    """
    _require()
    state = initial_state(n_particles, grid_n, v0=v0, center=center)
    sim = WarpMPM(state, MPMParams(grid_n=grid_n))
    for _ in range(steps):
        sim.step()
    return sim.numpy_state()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-particles", type=int, default=DEFAULT_N_PARTICLES)
    parser.add_argument("--grid-n", type=int, default=DEFAULT_GRID_N)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--warmup", type=int, default=10)
    args = parser.parse_args(argv)
    ok, why = available()
    if not ok:
        print(json.dumps({"available": False, "reason": why}))
        return
    print(json.dumps(bench(args.n_particles, args.grid_n, args.steps, args.warmup)))


if __name__ == "__main__":
    main()
