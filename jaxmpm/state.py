"""The particle state pytree, the static background-grid specification and the particles' stencil."""

from __future__ import annotations

import functools
import itertools
import math
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.interpreters import ad, batching
from jaxtyping import Array, Bool, Float, Int

from .fusion import (
    always_true,
    compute_once,
    lowered_primitive,
    materialize,
    scale_rows,
    spread,
    sum_last,
    sum_to_shape,
)

#: Number of padding cells added around the scene's domain on every side, so that the
#: quadratic B-spline stencil of a particle anywhere in the domain (or slightly
#: outside it) stays inside the grid.
GRID_PADDING = 3


class Grid(eqx.Module):
    """Static description of the dense background grid.

    Node ``i`` (a D-tuple of ints) sits at ``origin + i * dx``. The grid covers the
    scene's domain ``[lo, hi]`` plus ``GRID_PADDING`` cells on each side; nodes outside
    the domain act as slip walls.

    Attributes:
        lo: domain lower corner, metres, length D.
        hi: domain upper corner, metres, length D.
        dx: grid spacing, metres.
    """

    lo: tuple[float, ...] = eqx.field(static=True)
    hi: tuple[float, ...] = eqx.field(static=True)
    dx: float = eqx.field(static=True)

    @property
    def dim(self) -> int:
        return len(self.lo)

    @property
    def origin(self) -> tuple[float, ...]:
        """World position of node (0, ..., 0)."""
        return tuple(lo - GRID_PADDING * self.dx for lo in self.lo)

    @property
    def shape(self) -> tuple[int, ...]:
        """Number of nodes per axis."""
        return tuple(
            int(math.ceil((hi - lo) / self.dx - 1e-9)) + 1 + 2 * GRID_PADDING
            for lo, hi in zip(self.lo, self.hi)
        )

    @property
    def num_nodes(self) -> int:
        return int(np.prod(self.shape))

    def node_positions(self) -> np.ndarray:
        """All node positions as a NumPy array of shape ``(num_nodes, D)`` (C order)."""
        axes = [o + self.dx * np.arange(n) for o, n in zip(self.origin, self.shape)]
        mesh = np.meshgrid(*axes, indexing="ij")
        return np.stack([m.reshape(-1) for m in mesh], axis=-1)


class State(eqx.Module):
    """Particle state of a simulation (a pytree; every field is an array leaf).

    Attributes:
        x: positions, ``(N, D)``, metres.
        v: velocities, ``(N, D)``, m/s.
        C: affine velocity field (APIC/MLS), ``(N, D, D)``, 1/s.
        F: elastic deformation gradient, ``(N, D, D)``.
        aux: one scalar of material internal state per particle, ``(N,)``
            (the volume ratio J for Newtonian fluids, 0 where unused).
        mass: particle masses, ``(N,)``, kg (kg/m in 2D).
        vol0: initial particle volumes, ``(N,)``, m^3 (m^2 in 2D).
        tag: per-collider side tags in {-1, 0, +1}, ``(N, K)`` int8 (K may be 0).
        time: simulated time, scalar, seconds.
    """

    x: Float[Array, "N D"]
    v: Float[Array, "N D"]
    C: Float[Array, "N D D"]
    F: Float[Array, "N D D"]
    aux: Float[Array, " N"]
    mass: Float[Array, " N"]
    vol0: Float[Array, " N"]
    tag: Int[Array, "N K"]
    time: Float[Array, ""]

    @property
    def num_particles(self) -> int:
        return self.x.shape[0]

    @property
    def dim(self) -> int:
        return self.x.shape[1]


def make_state(
    x: Float[Array, "N D"],
    v: Float[Array, "N D"],
    mass: Float[Array, " N"],
    vol0: Float[Array, " N"],
    aux: Float[Array, " N"] | None = None,
    num_colliders: int = 0,
) -> State:
    """A state at rest in its reference configuration (``F = I``, ``C = 0``)."""
    x = jnp.asarray(x)
    n, d = x.shape
    dtype = x.dtype
    eye = jnp.broadcast_to(jnp.eye(d, dtype=dtype), (n, d, d))
    return State(
        x=x,
        v=jnp.broadcast_to(jnp.asarray(v, dtype), (n, d)),
        C=jnp.zeros((n, d, d), dtype),
        F=eye,
        aux=jnp.zeros((n,), dtype) if aux is None else jnp.asarray(aux, dtype),
        mass=jnp.asarray(mass, dtype),
        vol0=jnp.asarray(vol0, dtype),
        tag=jnp.zeros((n, num_colliders), jnp.int8),
        time=jnp.zeros((), dtype),
    )


# --------------------------------------------------------------------------- stencil


class Stencil(eqx.Module):
    """Quadratic B-spline stencil of every particle, shared by P2G and G2P.

    Stored as structure-of-arrays (one ``(N,)`` array per axis and node) rather than as
    stacked ``(3, N, D)`` tensors: in reverse mode the transpose of slicing a stacked
    tensor is a padded full-size buffer per use (27 offsets x D axes of them), which made
    the backward pass ~10x slower than the forward; per-axis arrays transpose elementwise.

    Attributes:
        base: index of the stencil's lowest node per axis, ``(N, D)`` int32.
        fx: per axis, the particle position relative to ``base`` in cells, ``D x (N,)``, in [0.5, 1.5).
        w: ``w[k][d]``, the weight of node ``k`` in {0, 1, 2} along axis ``d``, ``3 x D x (N,)``.
    """

    base: Int[Array, "N D"]
    fx: tuple[Float[Array, " N"], ...]
    w: tuple[tuple[Float[Array, " N"], ...], ...]

    @property
    def num_particles(self) -> int:
        return self.base.shape[0]

    @property
    def dim(self) -> int:
        return self.base.shape[1]


def stencil_offsets(dim: int) -> tuple[tuple[int, ...], ...]:
    """The 3^D node offsets of the quadratic stencil (unrolled in Python)."""
    return tuple(itertools.product(range(3), repeat=dim))


def compute_stencil(grid: Grid, x: Float[Array, "N D"]) -> Stencil:
    """Stencil of particles at ``x`` (positions are assumed inside the padded grid)."""
    origin = jnp.asarray(grid.origin, x.dtype)
    xi = (x - origin) / grid.dx
    # Clipped so every stencil node is a valid index even for a NaN or escaped particle
    # (the scatters and gathers then promise in-bounds indices; a NaN still propagates
    # through the weights).
    base = jnp.floor(jax.lax.stop_gradient(xi) - 0.5).astype(jnp.int32)
    base = jnp.clip(base, 0, jnp.asarray(grid.shape, jnp.int32) - 3)
    fx = tuple(xi[:, d] - base[:, d].astype(x.dtype) for d in range(x.shape[1]))
    return Stencil(base=base, fx=fx, w=tuple(zip(*(bspline_weights(f) for f in fx))))


def bspline_weights(f: Float[Array, " N"]) -> tuple[Float[Array, " N"], ...]:
    """Quadratic B-spline weights of the stencil's nodes 0, 1, 2 along one axis, for a
    particle ``f`` cells above the lowest node (``f`` in [0.5, 1.5))."""
    return 0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2


def bspline_slopes(f: Float[Array, " N"]) -> tuple[Float[Array, " N"], ...]:
    """``d/df`` of :func:`bspline_weights` (per cell)."""
    return f - 1.5, 2.0 * (1.0 - f), f - 0.5


def grid_strides(shape: tuple[int, ...]) -> tuple[int, ...]:
    strides, acc = [], 1
    for n in reversed(shape):
        strides.append(acc)
        acc *= n
    return tuple(reversed(strides))


def offset_weight(st: Stencil, offset: tuple[int, ...]) -> Float[Array, " N"]:
    """Weight ``(N,)`` of stencil node ``offset``: the product of its per-axis weights."""
    return functools.reduce(operator.mul, [st.w[o][d] for d, o in enumerate(offset)])


def stencil_weights(st: Stencil, incompatible: Bool[Array, "K N"] | None = None) -> list[Float[Array, " N"]]:
    """The weights ``(N,)`` of all 3^D stencil nodes (the order of :func:`stencil_offsets`);
    nodes marked ``incompatible`` ``(3^D, N)`` (CPIC) get weight 0."""
    return _masked([offset_weight(st, o) for o in stencil_offsets(st.dim)], incompatible)


def flat_index(shape: tuple[int, ...], node: Int[Array, "N D"]) -> Int[Array, " N"]:
    """Flat (C-order) index of every ``node`` in a grid of ``shape``."""
    return sum(node[:, d] * s for d, s in enumerate(grid_strides(shape)))


def node_indices(shape: tuple[int, ...], base: Int[Array, "N D"], offsets: np.ndarray) -> Int[Array, "K N"]:
    """Flat (C-order) index in a grid of ``shape`` of every node ``base + offsets[k]``
    (``offsets (K, D)``, constant integers)."""
    strides = np.asarray(grid_strides(shape), np.int32)
    return flat_index(shape, base)[None, :] + jnp.asarray(np.asarray(offsets, np.int32) @ strides)[:, None]


def stencil_terms(grid: Grid, st: Stencil):
    """:func:`offset_terms` of all 3^D offsets at once, stacked offset-major (the order of
    :func:`stencil_offsets`): flat node index ``(K, N)``, weight ``(K, N)`` and
    ``(x_i - x_p)/dx`` ``(K, N, D)``. A few whole-array operations instead of 3^D
    per-offset ones: for code that treats every node alike (the CPIC side tests)."""
    dim = st.dim
    offsets = np.asarray(stencil_offsets(dim), np.int32)  # (K, D)
    index = node_indices(grid.shape, st.base, offsets)
    weight = functools.reduce(operator.mul, [jnp.stack([st.w[k][d] for k in range(3)])[offsets[:, d]]
                                             for d in range(dim)])
    fx = spread(jnp.stack(st.fx, axis=-1), len(offsets))  # (K, N, D)
    dpos = jnp.asarray(offsets, fx.dtype)[:, None, :] - fx
    return index, weight, dpos


# --------------------------------------------------------------------------- transfers
#
# G2P reads all 3^D stencil nodes of all particles in ONE gather of ``(3^D N, C)`` rows, split
# into per-offset ``(N, C)`` blocks: reverse mode transposes it into one scatter (and the
# split into one concatenation). With 3^D separate gathers, each transposes into its own
# zero-filled grid-sized buffer and the buffers are summed, which made G2P's backward pass
# ~10x the forward (docs/benchmarks.md). P2G scatters per block of 3 consecutive nodes into
# one buffer updated in place (the transpose, a gather per block, is cheap). Rows are padded to
# a power-of-two width: XLA's CPU scatter-add is 4-5x slower on 3-wide rows than on 4-wide ones
# (measured).
#
# P2G's scatter (:func:`scatter_blocks`) is a JAX primitive of its own with three rules: its
# tangent is the same scatter of the tangent rows (it is linear in them), its transpose is one
# gather per block, and under ``jax.vmap`` a batch of B is ONE scatter per block of the ``B N``
# stacked rows into a ``(B G, C)`` buffer, the indices shifted by ``b G``. JAX's own batching
# of a scatter makes the batch a window dimension, which XLA's CPU backend lays out
# particle-major, ``(N, B, C)``: forward-mode Jacobians (``vmap`` of ``jvp`` over k tangent
# directions) then transposed every tangent row on its way to the grid (docs/benchmarks.md,
# session 26). G2P's gather reaches the same layout with a conditional (:func:`gather_rows`);
# a primitive with the same batching rule was measured slower there (XLA then fused the grid
# update into it).


def stencil_index(grid: Grid, st: Stencil) -> list[Int[Array, " N"]]:
    """Flat node index of each stencil node of every particle, one ``(N,)`` array per offset
    (the order of :func:`stencil_offsets`): the lowest node's index plus a constant."""
    # stored once: each consumer (the scatters' and gathers' index operands) would otherwise
    # re-derive the node index from the positions per entry (in forward mode, per tangent)
    flat = compute_once(functools.partial(flat_index, grid.shape), st.base, token=always_true(st.base))
    return [flat + int(np.dot(offset, grid_strides(grid.shape))) for offset in stencil_offsets(st.dim)]


def _padded_width(c: int) -> int:
    return 1 << max(c - 1, 0).bit_length()


def _shift_batch(index: Int[Array, "B M"], num_nodes: int) -> Int[Array, " BM"]:
    """Indices into the ``b``-th of B stacked ``num_nodes``-row tables, flattened."""
    return (index + num_nodes * jnp.arange(index.shape[0], dtype=index.dtype)[:, None]).reshape(-1)


def _batch_at_front(x: Array, dim: int | None, size: int) -> Array:
    return jnp.broadcast_to(x, (size,) + x.shape) if dim is None else batching.bdim_at_front(x, dim, size)


def _fits_int32(size: int, num_nodes: int) -> bool:
    return size * num_nodes < np.iinfo(np.int32).max


# a block of W consecutive rows per index
_BLOCK_SCATTER = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1, 2), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,)
)
_BLOCK_GATHER = jax.lax.GatherDimensionNumbers(offset_dims=(1, 2), collapsed_slice_dims=(), start_index_map=(0,))
# lax's scatter and gather, not ``.at[]``: in-bounds indices need no wrap-around of negatives
_IN_BOUNDS = jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS


def scatter_stencil(grid: Grid, st: Stencil, rows: list[Float[Array, "N C"]]) -> Float[Array, "G C"]:
    """``sum_o zeros(G, C).at[node_o].add(rows[o])`` over the stencil's 3^D nodes (``rows`` in
    the order of :func:`stencil_offsets`). The 3 nodes of a run along the last axis are
    consecutive grid rows: each run is one ``(N, 3, C)`` block of one scatter (3^(D-1)
    scatters, one index array each)."""
    blocks = [jnp.stack(rows[i:i + 3], axis=1) for i in range(0, len(rows), 3)]
    return scatter_blocks(grid.num_nodes, stencil_index(grid, st)[::3], blocks)


def scatter_blocks(
    num_nodes: int, index: list[Int[Array, " N"]], blocks: list[Float[Array, "N W C"]]
) -> Float[Array, "G C"]:
    """``sum_o sum_w zeros(G, C).at[index[o] + w].add(blocks[o][:, w])``: one grid buffer
    updated in place by one scatter per block (indices in bounds, see :func:`compute_stencil`)."""
    return _scatter_blocks_p.bind(*index, *blocks, num_nodes=num_nodes)


def _scatter_blocks_impl(*args: Array, num_nodes: int) -> Float[Array, "G C"]:
    count = len(args) // 2
    index, rows = args[:count], args[count:]
    c = rows[0].shape[-1]
    cp = _padded_width(c)
    out = jnp.zeros((num_nodes, cp), rows[0].dtype)
    for node, block in zip(index, rows):
        out = jax.lax.scatter_add(out, node[:, None], jnp.pad(block, ((0, 0), (0, 0), (0, cp - c))), _BLOCK_SCATTER,
                                  mode=_IN_BOUNDS)
    return out[:, :c]


def _scatter_blocks_jvp(primals, tangents, *, num_nodes: int):
    count = len(primals) // 2
    out = _scatter_blocks_p.bind(*primals, num_nodes=num_nodes)
    drows = tangents[count:]
    if all(type(t) is ad.Zero for t in drows):
        return out, ad.Zero.from_primal_value(out)
    drows = [ad.instantiate_zeros(t) for t in drows]
    return out, _scatter_blocks_p.bind(*primals[:count], *drows, num_nodes=num_nodes)


def _scatter_blocks_transpose(cotangent, *args, num_nodes: int):
    count = len(args) // 2
    index, rows = args[:count], args[count:]
    if any(ad.is_undefined_primal(i) for i in index):
        raise ValueError("scatter_blocks is linear in its blocks, not in its node indices")
    if type(cotangent) is ad.Zero:
        return [None] * count + [ad.Zero(r.aval) for r in rows]
    c = cotangent.shape[-1]
    padded = jnp.pad(cotangent, ((0, 0), (0, _padded_width(c) - c)))
    return [None] * count + [
        jax.lax.gather(padded, i[:, None], _BLOCK_GATHER, (r.aval.shape[1], padded.shape[1]), mode=_IN_BOUNDS)[..., :c]
        for i, r in zip(index, rows)
    ]


def _scatter_blocks_batch(args, dims, *, num_nodes: int):
    count = len(args) // 2
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    if not _fits_int32(size, num_nodes):
        return jax.vmap(functools.partial(_scatter_blocks_impl, num_nodes=num_nodes), in_axes=dims)(*args), 0
    args = [_batch_at_front(a, d, size) for a, d in zip(args, dims)]
    index = [_shift_batch(i, num_nodes) for i in args[:count]]
    rows = [r.reshape((-1,) + r.shape[2:]) for r in args[count:]]
    out = _scatter_blocks_p.bind(*index, *rows, num_nodes=size * num_nodes)
    return out.reshape((size, num_nodes) + out.shape[1:]), 0


_scatter_blocks_p = lowered_primitive(
    "jaxmpm_scatter_blocks",
    _scatter_blocks_impl,
    lambda *avals, num_nodes: jax.core.ShapedArray((num_nodes, avals[-1].shape[-1]), avals[-1].dtype),
    _scatter_blocks_batch,
    jvp=_scatter_blocks_jvp,
    transpose=_scatter_blocks_transpose,
)


def _stencil_moments(
    offsets, weights: list[Float[Array, " N"]], values: list[Float[Array, "N C"]]
) -> tuple[Float[Array, "N C"], Float[Array, "N C D"]]:
    """``sum_o w_o v_o`` and ``M[:, c, d] = sum_o w_o o_d v_o[c]`` over the stencil."""
    total = jnp.zeros_like(values[0])
    moments = [jnp.zeros_like(values[0]) for _ in offsets[0]]
    for offset, weight, vo in zip(offsets, weights, values):
        wv = weight[:, None] * vo
        total = total + wv
        moments = [m + od * wv if od else m for m, od in zip(moments, offset)]
    return total, jnp.stack(moments, axis=-1)


def moment_sums(
    offsets, weights: list[Float[Array, "... N"]], values: list[Float[Array, "... N C"]]
) -> tuple[Float[Array, "... N C"], Float[Array, "... N C D"]]:
    """:func:`_stencil_moments` as a JAX primitive, bilinear in ``weights`` and ``values``: G2P's
    tangent sums. Its value is one pass, ``sum_o (w_o v_o) ⊗ (1, o)`` into ``(..., N, C, 1 + D)``
    stored once, so that each of the k tangents' gathered rows is read once (XLA wrote the
    moments ``M`` as a concatenation of D column chains, each reading all the rows: 8 CPU ms of
    a 25,000-particle step's k = 6 Jacobian, session 51). Its transpose is written by hand, the
    per-offset cotangent ``w_o (ct_v + sum_d o_d ct_M[..., d])``: JAX's own transpose of the one
    pass sums over its ``1 + D`` axis per offset (reverse mode +44 %, session 51). Paired with
    the plain sums it made the k = 6 Jacobian 11-12 % faster (docs/benchmarks.md, session 52)."""
    return tuple(_moments_p.bind(*weights, *values, offsets=tuple(map(tuple, offsets))))


def _moments_impl(*args, offsets):
    k = len(offsets)
    weights, values = args[:k], args[k:]
    acc = None
    for offset, w, v in zip(offsets, weights, values):
        coeff = jnp.asarray((1.0,) + tuple(float(o) for o in offset), v.dtype)
        term = (w[..., None] * v)[..., None] * coeff
        acc = term if acc is None else acc + term
    acc = materialize(acc, always_true(acc[(0,) * acc.ndim]))  # a lowering: no tangent or batch here
    return [acc[..., 0], acc[..., 1:]]


def _moments_lead(args, k: int) -> tuple[int, ...]:
    """The leading axes, broadcast, of ``moment_sums``' ``k`` weights ``(..., N)`` and values
    ``(..., N, C)`` (arrays or avals)."""
    return jnp.broadcast_shapes(*(a.shape[:-1] for a in args[:k]), *(a.shape[:-2] for a in args[k:]))


def _moments_abstract(*avals, offsets):
    k = len(offsets)
    lead = _moments_lead(avals, k)
    (n, c), dtype, dim = avals[k].shape[-2:], avals[k].dtype, len(offsets[0])
    return [jax.core.ShapedArray(lead + (n, c), dtype), jax.core.ShapedArray(lead + (n, c, dim), dtype)]


def _moments_jvp(primals, tangents, *, offsets):
    k = len(offsets)
    out = _moments_p.bind(*primals, offsets=offsets)
    dw, dv = tangents[:k], tangents[k:]
    terms = []
    if not all(type(t) is ad.Zero for t in dw):
        terms.append(_moments_p.bind(*map(ad.instantiate_zeros, dw), *primals[k:], offsets=offsets))
    if not all(type(t) is ad.Zero for t in dv):
        terms.append(_moments_p.bind(*primals[:k], *map(ad.instantiate_zeros, dv), offsets=offsets))
    if not terms:
        return out, [ad.Zero.from_primal_value(o) for o in out]
    return out, [sum(t[i] for t in terms) for i in range(2)]


def _moments_transpose(cotangents, *args, offsets):
    k = len(offsets)
    weights, values = args[:k], args[k:]
    ct_v, ct_M = (ad.instantiate_zeros(c) for c in cotangents)
    if any(ad.is_undefined_primal(w) for w in weights) == any(ad.is_undefined_primal(v) for v in values):
        raise ValueError("moment_sums is linear in its weights or in its values, one at a time")
    per_offset = []
    for offset in offsets:  # ct_v + sum_d o_d ct_M[..., d]
        ct = ct_v
        for d, od in enumerate(offset):
            if od:
                ct = ct + od * ct_M[..., d]
        per_offset.append(ct)
    if any(ad.is_undefined_primal(v) for v in values):
        return [None] * k + [sum_to_shape(scale_rows(w, ct), v.aval.shape)
                             for w, ct, v in zip(weights, per_offset, values)]
    return [sum_to_shape(sum_last(ct * v), w.aval.shape) for w, ct, v in zip(weights, per_offset, values)] + [None] * k


def _moments_batch(args, dims, *, offsets):
    # the batch is folded into the particle rows, (B N, ...): XLA's CPU backend splits a
    # fusion's leading axis among its threads, and k = 3 tangents on 2 threads split 1 + 2
    k = len(offsets)
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    args = [_batch_at_front(a, d, size) for a, d in zip(args, dims)]
    n, c = args[k].shape[-2:]
    lead = _moments_lead(args, k)
    weights = [jnp.broadcast_to(w, lead + (n,)).reshape(-1) for w in args[:k]]
    values = [jnp.broadcast_to(v, lead + (n, c)).reshape(-1, c) for v in args[k:]]
    v, M = _moments_p.bind(*weights, *values, offsets=offsets)
    return (v.reshape(lead + (n, c)), M.reshape(lead + (n,) + M.shape[1:])), [0, 0]


_moments_p = lowered_primitive("jaxmpm_moment_sums", _moments_impl, _moments_abstract, _moments_batch,
                               jvp=_moments_jvp, transpose=_moments_transpose, multiple_results=True)


def _masked(weights, incompatible):
    return weights if incompatible is None else [jnp.where(incompatible[o], 0.0, w) for o, w in enumerate(weights)]


def _weight_partials(st: Stencil, offsets, incompatible):
    """``d w_o / d fx_e`` for every axis ``e`` and offset ``o``: ``D x 3^D x (N,)``."""
    slope = [bspline_slopes(f) for f in st.fx]  # slope[d][k]
    return [
        _masked([functools.reduce(operator.mul, [slope[d][k] if d == e else st.w[k][d] for d, k in enumerate(offset)])
                 for offset in offsets], incompatible)
        for e in range(st.dim)
    ]


@jax.custom_jvp
def stencil_moments(
    st: Stencil, incompatible: Bool[Array, "K N"] | None, values: list[Float[Array, "N C"]]
) -> tuple[Float[Array, "N C"], Float[Array, "N C D"]]:
    """G2P's sums over the stencil: ``v = sum_o w_o v_o`` ``(N, C)`` and the first moments
    ``M[:, c, d] = sum_o w_o o_d v_o[c]`` ``(N, C, D)`` of the per-offset values ``v_o``
    (``(N, C)`` each, in the order of :func:`stencil_offsets`); nodes marked ``incompatible``
    ``(3^D, N)`` get weight 0.

    Forward mode: the weights' tangent ``dw_o = sum_e dw_o/dfx_e dfx_e`` is regrouped as
    ``sum_e dfx_e (sum_o dw_o/dfx_e v_o)``: the sums in brackets depend on the primal only and
    are computed once, not per tangent direction and output entry (XLA's fused tangent
    recomputed every weight's derivative for each of the ``k x C x D`` entries: 3x slower
    Jacobians). The sums of the values' tangents are :func:`moment_sums`, one pass over the
    gathered tangent rows with its own transpose. The rule is linear in the tangents, so
    reverse mode transposes it. ``st.w`` must be :func:`bspline_weights` of ``st.fx`` (as
    :func:`compute_stencil` makes it).
    """
    offsets = stencil_offsets(st.dim)
    if incompatible is None:
        return _stencil_moments(offsets, stencil_weights(st), values)
    # stored once: each output entry of the sums would otherwise re-derive the 3^D masked weights
    weights = compute_once(stencil_weights, st, incompatible, token=always_true(st.base))
    return _stencil_moments(offsets, weights, values)


@stencil_moments.defjvp
def _stencil_moments_jvp(primals, tangents):
    st, incompatible, values = primals
    dst, _, dvalues = tangents
    offsets = stencil_offsets(st.dim)
    # stored once: the tangent's sums (and in reverse mode their transposes, one per offset)
    # would otherwise each re-derive the weights from the positions for every entry they write
    weights = compute_once(stencil_weights, st, incompatible, token=always_true(st.base))
    out = _stencil_moments(offsets, weights, values)
    # d/dfx_e of (v, M), e = 0 .. D-1: primal only
    by_axis = [_stencil_moments(offsets, p, values) for p in _weight_partials(st, offsets, incompatible)]
    by_axis = materialize(by_axis, always_true(st.base))
    dv, dM = moment_sums(offsets, weights, dvalues)
    for dfx, (P, Q) in zip(dst.fx, by_axis):
        dv = dv + scale_rows(dfx, P)
        dM = dM + scale_rows(dfx, Q)
    # stored: G2P's affine-matrix tangent reads dv for each of its D x D entries
    return out, materialize((dv, dM), always_true(st.base))


def gather_rows(table: Float[Array, "G C"], index: list[Int[Array, " N"]]) -> list[Float[Array, "N C"]]:
    """``table[index[o]]`` for every offset ``o`` in one gather (of the concatenated indices),
    split into per-offset ``(N, C)`` blocks.

    Forward mode gathers the tangent table inside a conditional (:func:`jaxmpm.fusion.compute_once`):
    under ``jax.vmap`` over k tangent directions XLA otherwise lays the gathered rows out
    particle-major, ``(3^D N, k, C)``, and the stencil sums that read them run 3x slower
    (docs/benchmarks.md, session 25). The rule is the plain gather, transposed as before."""
    c = table.shape[-1]
    return [block[:, :c] for block in jnp.split(_gather(table, jnp.concatenate(index)), len(index))]


@jax.custom_jvp
def _gather(table: Float[Array, "G C"], index: Int[Array, " M"]) -> Float[Array, "M P"]:
    """``table[index]`` with rows padded to ``P``, a power of two."""
    c = table.shape[-1]
    return jnp.pad(table, ((0, 0), (0, _padded_width(c) - c))).at[index].get(mode="promise_in_bounds")


@_gather.defjvp
def _gather_jvp(primals, tangents):
    table, index = primals
    dtable, _ = tangents
    return _gather(table, index), compute_once(_gather, dtable, index, token=always_true(index))
