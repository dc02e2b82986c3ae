"""Float32 matrix products at the precision of their inputs.

On GPUs with tensor cores JAX's default precision for a float32 matrix product is lower
than float32 (TF32 on NVIDIA: a 10-bit mantissa); XLA on the CPU computes them in full. A
silhouette fit is sensitive to it: on an H200, ``jaxmpm demo --video`` stalled on a rough
loss and found μ 0.08 decades off, and with ``JAX_DEFAULT_MATMUL_PRECISION=highest`` it
found the CPU's answer (0.0066; docs/benchmarks.md). The simulator's and the renderers'
entry points are therefore traced with ``jax.default_matmul_precision("highest")``; on the
CPU this changes nothing.
"""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import jax

F = TypeVar("F", bound=Callable)


def full_precision(fn: F) -> F:
    """``fn`` with every matrix product it traces at full float32 (or float64) precision."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
