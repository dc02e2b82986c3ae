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

import equinox as eqx
import jax

F = TypeVar("F", bound=Callable)


def full_precision(fn: F) -> F:
    """``fn`` with every matrix product it traces at full float32 (or float64) precision."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def compiled_entry(fn: F) -> F:
    """An entry point (a renderer's ``render``, :func:`jaxmpm.simulate`): traced at full
    precision (:func:`full_precision`) and compiled once per static arguments and input shapes
    (``equinox.filter_jit``: arrays are inputs, everything else is part of the key). Called
    outside a jitted function it runs one compiled program instead of executing (and
    compiling) operation by operation, and a second call with the same shapes reuses it;
    inside a jitted function it is inlined. It stays a plain function (or method), so
    ``jax.jit(renderer.render)`` works as for any other."""
    compiled = eqx.filter_jit(full_precision(fn))

    @functools.wraps(fn)
    def entry(*args, **kwargs):
        return compiled(*args, **kwargs)

    return entry  # type: ignore[return-value]
