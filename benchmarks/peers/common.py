"""Shared setup for the Taichi and Warp peer implementations of one MLS-MPM step.

The scene itself (parameters, particles) is :mod:`jaxmpm.bench_scene`, re-exported here, so
that both peers and ``jaxmpm bench`` start from bit-identical particles and parameters.
"""

from __future__ import annotations

import os
import time

import numpy as np

from jaxmpm.bench_scene import DEFAULT_GRID_N as DEFAULT_GRID_N
from jaxmpm.bench_scene import DEFAULT_N_PARTICLES as DEFAULT_N_PARTICLES
from jaxmpm.bench_scene import MPMParams as MPMParams
from jaxmpm.bench_scene import GRAD_PARAMETERS as GRAD_PARAMETERS
from jaxmpm.bench_scene import GRAD_SCENE_VELOCITY_GRADIENT as GRAD_SCENE_VELOCITY_GRADIENT
from jaxmpm.bench_scene import cube_cells as cube_cells
from jaxmpm.bench_scene import grad_scene_velocity as grad_scene_velocity
from jaxmpm.bench_scene import initial_state as initial_state


def default_threads() -> int:
    """CPU threads available to this process (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        return os.cpu_count() or 1


def time_steps(step, sync, steps: int, warmup: int) -> tuple[float, float]:
    """Time a step function.

    The first call (JIT compilation + one step) is timed as the compile time; then
    ``warmup - 1`` more steps run untimed, and ``steps`` steps are timed between two
    synchronisations.

    Returns:
        ``(compile_s, ms_per_step)``.
    """
    t0 = time.perf_counter()
    step()
    sync()
    compile_s = time.perf_counter() - t0
    for _ in range(max(0, warmup - 1)):
        step()
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync()
    elapsed = time.perf_counter() - t0
    return compile_s, 1e3 * elapsed / max(steps, 1)


def free_fall_com(x0: np.ndarray, v0, steps: int, params: MPMParams) -> np.ndarray:
    """Centre of mass after ``steps`` steps of free fall under this time stepping.

    Gravity is added to the grid velocity and positions advance with the new
    velocity, so after ``n`` steps ``com = com0 + n dt v0 + g dt^2 n (n + 1) / 2``
    (exact while no particle touches a wall; MLS-MPM transfers conserve momentum).
    """
    n = steps
    g = np.asarray(params.gravity, np.float64)
    return (
        x0.astype(np.float64).mean(axis=0)
        + n * params.dt * np.asarray(v0, np.float64)
        + g * params.dt**2 * n * (n + 1) / 2.0
    )
