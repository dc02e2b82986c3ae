"""G2P's gather: one gather of all stencil values, one per offset, or one with a per-offset
``custom_jvp`` tangent — forward, vjp (grid velocities, positions, both) and jvp, ms per call.

    python benchmarks/g2p_gather.py [--particles 25000] [--grid 64] [--variant one|per-offset|custom-jvp]

Prints one JSON line; run one variant per process (each patches ``jaxmpm.step.gather_rows``).
Measured in session 15 (docs/benchmarks.md, "G2P's gather, read per offset or once").
"""

from __future__ import annotations

import argparse
import importlib
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

state = importlib.import_module("jaxmpm.state")
step = importlib.import_module("jaxmpm.step")  # the module (``jaxmpm.step`` is also a function)


def per_offset(table, index):
    """``table[index[o]]`` for every offset, one gather each."""
    c = table.shape[-1]
    padded = jnp.pad(table, ((0, 0), (0, state._padded_width(c) - c)))
    return [padded.at[i].get(mode="promise_in_bounds")[:, :c] for i in index]


@jax.custom_jvp
def one_gather_per_offset_tangent(table, index):
    return state.gather_rows(table, index)


@one_gather_per_offset_tangent.defjvp
def _tangent(primals, tangents):
    table, index = primals
    return state.gather_rows(table, index), per_offset(tangents[0], index)


VARIANTS = {"one": state.gather_rows, "per-offset": per_offset, "custom-jvp": one_gather_per_offset_tangent}


def timed(f, *args, repeats: int = 20) -> float:
    compiled = jax.jit(f).lower(*args).compile()
    jax.block_until_ready(compiled(*args))
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = compiled(*args)
    jax.block_until_ready(out)
    return round((time.perf_counter() - t0) / repeats * 1e3, 2)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--particles", type=int, default=25000)
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--variant", choices=sorted(VARIANTS), default="one")
    args = parser.parse_args()
    step.gather_rows = VARIANTS[args.variant]
    grid = state.Grid(lo=(0.0,) * 3, hi=(1.0,) * 3, dx=1.0 / args.grid)
    x = jax.random.uniform(jax.random.PRNGKey(0), (args.particles, 3), jnp.float32, 0.3, 0.7)
    grid_v = jax.random.normal(jax.random.PRNGKey(3), (grid.num_nodes, 3), jnp.float32)

    def g2p(x, grid_v):
        return step.g2p(grid, state.compute_stencil(grid, x), grid_v)

    cot = (jnp.cos(7 * x), jnp.sin(x[:, :, None] * jnp.ones((1, 1, 3))))
    tangents = (jnp.cos(3 * x), jnp.sin(grid_v))
    out = {"variant": args.variant, "particles": args.particles, "grid": args.grid,
           "forward_ms": timed(g2p, x, grid_v),
           "vjp_grid_ms": timed(lambda x, g: jax.vjp(lambda gg: g2p(x, gg), g)[1](cot), x, grid_v),
           "vjp_x_ms": timed(lambda x, g: jax.vjp(lambda xx: g2p(xx, g), x)[1](cot), x, grid_v),
           "vjp_both_ms": timed(lambda x, g: jax.vjp(g2p, x, g)[1](cot), x, grid_v),
           "jvp_ms": timed(lambda x, g: jax.jvp(g2p, (x, g), tangents), x, grid_v)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
