"""Fusion boundaries for XLA's CPU compiler: values computed once and stored.

XLA's CPU fusion treats elementwise arithmetic as cheap and re-computes it inside every
consumer: inside each of P2G's 3^D row fusions, per output entry of a sum over the stencil,
and in forward mode their tangents too (5x slower steps, or 2-3x slower Jacobians, measured
in docs/benchmarks.md). ``lax.optimization_barrier`` is expanded away before fusion on CPU.
A conditional is a fusion boundary: its operands and its output are materialised once.
JAX differentiates, batches and transposes both helpers as conditionals: ``materialize`` is
the identity, and ``compute_once`` is linear wherever its function is (a tangent gather).

:func:`sum_last` keeps a sum over a small last axis out of XLA's reductions altogether, and
:func:`scale_rows`, :func:`spread` and :func:`symmetric_pair_sum` the sums reverse mode makes
of a product with a broadcast weight, of a value broadcast over a node axis and of a sum over
partner nodes.
"""

from __future__ import annotations

import functools

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


def lowered_primitive(name: str, impl, abstract_eval, batch, *, jvp=None, transpose=None, bilinear=None,
                      multiple_results: bool = False) -> Primitive:
    """A JAX primitive whose lowering is ``impl``'s own JAX operations, with its rules: ``batch``
    (the batching rule), and either ``jvp`` and ``transpose`` or ``bilinear``, the pair of
    transposes of a primitive bilinear in its two operands (``ad.defbilinear``)."""
    prim = Primitive(name)
    prim.multiple_results = multiple_results
    prim.def_impl(impl)
    prim.def_abstract_eval(abstract_eval)
    mlir.register_lowering(prim, mlir.lower_fun(impl, multiple_results=multiple_results))
    if bilinear is not None:
        ad.defbilinear(prim, *bilinear)
    else:
        ad.primitive_jvps[prim] = jvp
        ad.primitive_transposes[prim] = transpose
    batching.primitive_batchers[prim] = batch
    return prim


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
    added = tuple(range(g.ndim - len(shape)))
    g = g.sum(axis=added) if added else g
    stretched = tuple(i for i, (n, m) in enumerate(zip(shape, g.shape)) if n == 1 and m != 1)
    return g.sum(axis=stretched, keepdims=True) if stretched else g


def _scale_rows_batch(args, dims):
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    w, x = (a[None] if d is None else batching.bdim_at_front(a, d, size) for a, d in zip(args, dims))
    return _scale_rows_p.bind(w, x), 0


_scale_rows_p = lowered_primitive("jaxmpm_scale_rows", _scale_rows_impl, _scale_rows_abstract, _scale_rows_batch,
                                  bilinear=(_scale_rows_transpose_w, _scale_rows_transpose_x))


def symmetric_pair_sum(weights: list[Array], values: Array) -> Array:
    """``out[i] = sum_j weights[j][i] * values[j]`` over the ``K`` nodes of a node-major
    ``values (K, ...)``, for a symmetric table of pair weights given by rows (``weights[j]``,
    ``(K, ...)`` each, with ``weights[j][i] == weights[i][j]``): the CPIC surface estimate's
    sums over partner nodes. Written as ``K - 1`` elementwise adds of ``weights[j] *
    values[j:j + 1]``, which fuse.

    A JAX primitive, bilinear, with its own transpose. By symmetry the cotangent of
    ``values`` is the same sum of the cotangent, adds again; JAX's transpose of the
    broadcast ``values[j:j + 1]`` is a reduction over the ``K`` nodes per partner, which
    XLA's CPU backend hands to YNNPACK fusions (on a moving collider, 107 of them took 112
    of the contact stage's 186 CPU ms per backward step; docs/benchmarks.md, session 30)."""
    dtype = jnp.result_type(values, *weights)
    return _pair_sum_p.bind(*(jnp.asarray(w, dtype) for w in weights), jnp.asarray(values, dtype))


def _pair_sum_impl(*args):
    *weights, values = args
    total = weights[0] * values[0:1]
    for j in range(1, len(weights)):
        total = total + weights[j] * values[j:j + 1]
    return total


def _pair_sum_abstract(*avals):
    *weights, values = avals
    shape = jnp.broadcast_shapes(values.shape, *(w.shape for w in weights))
    return jax.core.ShapedArray(shape, values.dtype)


def _pair_sum_jvp(primals, tangents):
    *weights, values = primals
    *dweights, dvalues = tangents
    out = _pair_sum_p.bind(*primals)
    terms = []
    if type(dvalues) is not ad.Zero:
        terms.append(_pair_sum_p.bind(*weights, dvalues))
    if any(type(d) is not ad.Zero for d in dweights):
        terms.append(_pair_sum_p.bind(*(ad.instantiate_zeros(d) for d in dweights), values))
    if not terms:
        return out, ad.Zero.from_primal_value(out)
    return out, functools.reduce(jnp.add, terms)


def _pair_sum_transpose(ct, *args):
    *weights, values = args
    if type(ct) is ad.Zero:
        return [None if not ad.is_undefined_primal(a) else ad.Zero(a.aval) for a in args]
    if ad.is_undefined_primal(values):
        if any(ad.is_undefined_primal(w) for w in weights):
            raise ValueError("symmetric_pair_sum is bilinear: one of its operands must be known")
        # stored once: its consumers (the cotangents of the node weights, corner products, ...)
        # would otherwise each re-derive the K-term sum for every entry they write
        summed = compute_once(lambda *a: _pair_sum_p.bind(*a), *weights, ct, token=always_true(weights[0]))
        return [None] * len(weights) + [sum_to_shape(summed, values.aval.shape)]
    return [sum_to_shape(ct * values[j:j + 1], w.aval.shape) if ad.is_undefined_primal(w) else None
            for j, w in enumerate(weights)] + [None]


def _pair_sum_batch(args, dims):
    # the batch becomes axis 1, after the node axis (a weight or value without it broadcasts)
    moved = [jnp.expand_dims(a, 1) if d is None else jnp.moveaxis(a, d, 1) for a, d in zip(args, dims)]
    return _pair_sum_p.bind(*moved), 1


_pair_sum_p = lowered_primitive("jaxmpm_symmetric_pair_sum", _pair_sum_impl, _pair_sum_abstract, _pair_sum_batch,
                                jvp=_pair_sum_jvp, transpose=_pair_sum_transpose)
