"""Fusion boundaries for XLA's CPU compiler: values computed once and stored.

XLA's CPU fusion treats elementwise arithmetic as cheap and re-computes it inside every
consumer: inside each of P2G's 3^D row fusions, per output entry of a sum over the stencil,
and in forward mode their tangents too (5x slower steps, or 2-3x slower Jacobians, measured
in docs/benchmarks.md). ``lax.optimization_barrier`` is expanded away before fusion on CPU.
A conditional is a fusion boundary: its operands and its output are materialised once.
JAX differentiates, batches and transposes both helpers as conditionals: ``materialize`` is
the identity, and ``compute_once`` is linear wherever its function is (a tangent gather).

:func:`sum_last` keeps a sum over a small last axis out of XLA's reductions altogether, and
:func:`scale_rows` and :func:`spread` the sums reverse mode makes of a product with a
broadcast weight and of a value broadcast over a node axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
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


def spread(x: Array, count: int) -> Array:
    """``x`` repeated ``count`` times along a new leading axis, ``(count, *x.shape)``: one value
    per stencil or corner node. Written as a stack, whose transpose (reverse mode's cotangent
    of ``x``) is ``count - 1`` elementwise adds; the transpose of ``x[None]`` broadcast against
    a ``(count, ...)`` array is a reduction over the leading axis, which XLA's CPU backend
    hands to YNNPACK fusions (in the CPIC gather's backward pass, 9 ms for 8 x 25k x 3
    entries)."""
    return jnp.stack([x] * count)


def scale_rows(w: Float[Array, "... N"], x: Float[Array, "... N *T"]) -> Float[Array, "... N *T"]:
    """``w * x`` with ``w`` broadcast over ``x``'s trailing axes ``T``: row ``n`` of ``x``
    scaled by ``w[n]`` (P2G's weighted rows, momentum over mass). Leading axes broadcast.

    A JAX primitive, bilinear, with its own transpose: reverse mode's cotangent of ``w`` is a
    sum over ``T`` written as adds. JAX's rule for a broadcast ``w`` gives a reduction over
    ``T``, which XLA's CPU backend hands to YNNPACK fusions: a third of P2G's backward pass
    and most of the grid update's (docs/benchmarks.md, session 28). The value and the tangent
    are the broadcast products (forward mode as fast as before)."""
    dtype = jnp.result_type(w, x)
    return _scale_rows_p.bind(jnp.asarray(w, dtype), jnp.asarray(x, dtype))


def _trailing(w, x) -> int:
    """How many axes of ``x`` follow ``w``'s (``T``)."""
    return x.ndim - w.ndim


def _scale_rows_impl(w, x):
    return w.reshape(w.shape + (1,) * _trailing(w, x)) * x


def _scale_rows_abstract(w, x):
    t = _trailing(w, x)
    lead = jnp.broadcast_shapes(w.shape, x.shape[: x.ndim - t])
    return jax.core.ShapedArray(lead + x.shape[x.ndim - t:], x.dtype)


def _scale_rows_transpose_w(ct, w, x):
    t = _trailing(w.aval, x)
    flat = (ct * x).reshape(ct.shape[: ct.ndim - t] + (-1,))
    return sum_to_shape(sum_last(flat), w.aval.shape)


def _scale_rows_transpose_x(ct, w, x):
    return sum_to_shape(scale_rows(w, ct), x.aval.shape)


def sum_to_shape(g: Array, shape: tuple[int, ...]) -> Array:
    """``g`` summed over the leading axes that broadcasting added or stretched in ``shape``."""
    g = g.sum(axis=tuple(range(g.ndim - len(shape))))
    stretched = tuple(i for i, (n, m) in enumerate(zip(shape, g.shape)) if n == 1 and m != 1)
    return g.sum(axis=stretched, keepdims=True) if stretched else g


def _scale_rows_batch(args, dims):
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    w, x = (a[None] if d is None else batching.bdim_at_front(a, d, size) for a, d in zip(args, dims))
    return _scale_rows_p.bind(w, x), 0


_scale_rows_p = Primitive("jaxmpm_scale_rows")
_scale_rows_p.def_impl(_scale_rows_impl)
_scale_rows_p.def_abstract_eval(_scale_rows_abstract)
mlir.register_lowering(_scale_rows_p, mlir.lower_fun(_scale_rows_impl, multiple_results=False))
ad.defbilinear(_scale_rows_p, _scale_rows_transpose_w, _scale_rows_transpose_x)
batching.primitive_batchers[_scale_rows_p] = _scale_rows_batch
