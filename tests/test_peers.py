"""jaxmpm's step against the independent Taichi step of ``benchmarks/peers/taichi_step.py``
(written apart from jaxmpm, in Taichi's kernel language: one kernel of atomic P2G, grid update
and G2P, Taichi's own SVD): the same cube, dropped onto the same slip wall, lands alike.

Skipped with a message when Taichi is not installed (the ``test`` extra installs it where
Taichi has a wheel: Python < 3.13 on x86-64). Taichi compiles its step in ~5-10 s on 2 cores.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("taichi", reason="Taichi is not installed (pip install -e '.[test]'): Taichi cross-check skipped")

ROOT = Path(__file__).resolve().parents[1]


def _jaxmpm_final_state(n: int, grid_n: int, steps: int, v0, center):
    from jaxmpm.bench import _scene_model
    from jaxmpm.step import simulate

    model, params = _scene_model(n, grid_n, "corotated", jnp.float32, v0=v0, center=center)  # one step a frame
    final = jax.jit(lambda p: simulate(model, p, checkpoint=None, frames=steps + 1).final)(params)
    return np.asarray(final.x), np.asarray(final.v)


def test_a_cube_dropped_on_a_slip_wall_lands_as_in_the_taichi_step():
    """1,000 particles of fixed-corotated solid (E = 100 kPa) thrown at 2 m/s onto the bottom
    wall from a cell above it, 400 steps of 0.1 ms: free fall, impact, the squash. Both codes
    start from the same particles (``jaxmpm.bench_scene``) and must agree particle by particle
    to float32 round-off (measured: 4e-7 m in position, 2e-5 m/s in velocity); the drop must
    really have hit the wall and squashed the cube."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from benchmarks.peers import taichi_step

    from jaxmpm.bench_scene import MPMParams, cube_cells
    from jaxmpm.bench_scene import initial_state as peer_state

    n, grid_n, steps = 1000, 32, 400
    p = MPMParams(grid_n=grid_n)
    cells = cube_cells(n)
    v0 = (0.0, -2.0, 0.0)
    center = (0.5, (p.bound + 1.0 + 0.5 * cells) * p.dx, 0.5)  # its bottom one cell above the walled nodes
    taichi = taichi_step.final_state(n, grid_n, steps, v0=v0, center=center)
    x, v = _jaxmpm_final_state(n, grid_n, steps, v0, center)

    np.testing.assert_allclose(x, taichi["x"], rtol=0, atol=1e-5)
    np.testing.assert_allclose(v, taichi["v"], rtol=0, atol=1e-3)

    x0 = peer_state(n, grid_n, v0=v0, center=center)["x"]
    t = steps * p.dt
    free_fall = x0[:, 1].mean() + v0[1] * t - 0.5 * 9.8 * t**2
    assert x[:, 1].mean() > free_fall + 0.02  # the wall stopped it ...
    assert x[:, 1].min() > (p.bound - 1) * p.dx  # ... above the walled nodes
    assert np.ptp(x[:, 1]) < 0.9 * np.ptp(x0[:, 1])  # ... and squashed it
    assert np.abs(v).max() > 0.1  # (and it is still moving: a rebound, not a rest state)
