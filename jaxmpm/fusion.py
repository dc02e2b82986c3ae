"""Fusion boundaries for XLA's CPU compiler: values computed once and stored.

XLA's CPU fusion treats elementwise arithmetic as cheap and re-computes it inside every
consumer: inside each of P2G's 3^D row fusions, per output entry of a sum over the stencil,
and in forward mode their tangents too (5x slower steps, or 2-3x slower Jacobians, measured
in docs/benchmarks.md). ``lax.optimization_barrier`` is expanded away before fusion on CPU.
A conditional is a fusion boundary: its operands and its output are materialised once.
JAX differentiates, batches and transposes both helpers as conditionals: ``materialize`` is
the identity, and ``compute_once`` is linear wherever its function is (a tangent gather).

:func:`sum_last` keeps a sum over a small last axis out of XLA's reductions altogether.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float


def always_true(x: Array) -> Bool[Array, ""]:
    """A traced ``True`` that XLA cannot fold away (a count of nonzeros is ``>= 0``); ``x`` is
    any array of the computation."""
    return jnp.count_nonzero(jnp.ravel(x)[:1]) >= 0


def materialize(tree, token: Bool[Array, ""]):
    """``tree`` itself, stored once (one copy). ``token``: a traced True computed from primal
    values only, never from a tangent, and not batched (:func:`always_true` of a stencil's node
    indices, say): under ``jax.vmap`` a batched predicate turns the conditional into a select,
    which fuses (and computes both branches)."""
    return compute_once(lambda t: t, tree, token=token)


def compute_once(fn, *args, token: Bool[Array, ""]):
    """``fn(*args)``, computed inside a conditional's branch: its inputs are materialised,
    ``fn``'s body cannot be re-computed by its consumers, and its output is written once
    (no copy, unlike :func:`materialize`). ``token`` as for :func:`materialize`."""
    shapes = jax.eval_shape(fn, *args)
    return jax.lax.cond(
        token, lambda a: fn(*a), lambda a: jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes), args
    )


def sum_last(x: Float[Array, "... D"], keepdims: bool = False) -> Float[Array, "..."]:
    """The sum over the last axis (a small one: D coordinates or principal values), written as
    D - 1 elementwise adds that fuse with their producers and consumers. XLA's CPU backend runs
    a reduction over a 2- or 3-wide axis as a slow loop (4x slower in the CPIC gather), and
    hands some to its YNNPACK fusions, slower still (in forward-mode Jacobians of the Hencky
    materials, a fifth of the step; docs/benchmarks.md, session 27)."""
    total = x[..., 0]
    for i in range(1, x.shape[-1]):
        total = total + x[..., i]
    return total[..., None] if keepdims else total
