"""The MLS-MPM step and rollouts: kinematics, conservation, transforms (jit/grad/vmap/checkpoint)."""

import functools
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import counting_compilations
from scenes import DIMS_3D_SLOW, block_spec, slow

from jaxmpm.errors import JaxmpmWarning
from jaxmpm.model import initial_state
from jaxmpm.scene import load_scene
from jaxmpm.state import Grid, stencil_terms
from jaxmpm.step import compute_stencil, p2g, run_frames, simulate, stencil_offsets, step


@pytest.mark.parametrize("dtype", [jnp.float32, pytest.param(jnp.float64, marks=pytest.mark.x64)])
def test_free_fall_follows_half_g_t_squared(dim, dtype):
    spec = block_spec(dim, frames=6, substeps=20, dx=0.05, lo=[0.4, 0.6, 0.4][:dim], hi=[0.6, 0.8, 0.6][:dim])
    scene = load_scene(spec, dtype=dtype)
    traj = jax.jit(lambda p: simulate(scene.model, p))(scene.params)
    assert traj.x.dtype == dtype
    t = np.asarray(traj.times)
    com_y = np.asarray(traj.x[..., 1]).mean(axis=1)
    # symplectic Euler: y_n = y_0 - g dt^2 n (n + 1) / 2  ->  1/2 g t^2 up to O(dt)
    expected = 0.7 - 0.5 * 9.8 * t * (t + scene.model.dt)
    np.testing.assert_allclose(com_y, expected, atol=2e-5 if dtype == jnp.float64 else 2e-4)
    # the fall is rigid: horizontal centre unchanged, no spreading
    np.testing.assert_allclose(np.asarray(traj.x[..., 0]).mean(axis=1), 0.5, atol=1e-5)
    assert not np.asarray(traj.nan).any()
    assert int(np.asarray(traj.left).max()) == 0


@pytest.mark.x64
def test_stencil_weights_are_a_partition_of_unity(dim):
    grid = Grid(lo=(0.0,) * dim, hi=(1.0,) * dim, dx=0.1)
    x = jax.random.uniform(jax.random.PRNGKey(0), (50, dim), jnp.float64, 0.05, 0.95)
    st = compute_stencil(grid, x)
    index, weight, dpos = stencil_terms(grid, st)
    np.testing.assert_allclose(weight.sum(axis=0), 1.0, atol=1e-12)
    # linear completeness: the weighted node offsets reproduce the particle position
    np.testing.assert_allclose((weight[..., None] * dpos).sum(axis=0), 0.0, atol=1e-12)
    # node k is base + stencil_offsets[k], weighted by the product of its per-axis weights
    for k, offset in enumerate(stencil_offsets(dim)):
        node = np.asarray(st.base) + np.asarray(offset)
        np.testing.assert_array_equal(index[k], np.ravel_multi_index(tuple(node.T), grid.shape))
        np.testing.assert_allclose(weight[k], np.prod([st.w[o][d] for d, o in enumerate(offset)], axis=0), rtol=1e-14)
        np.testing.assert_allclose(dpos[k], np.asarray(offset) - np.stack(st.fx, axis=-1), atol=1e-14)
    for f in st.fx:
        assert bool(jnp.all((f >= 0.5) & (f < 1.5)))


def _plain_stencil_moments(st, incompatible, values):
    """G2P's stencil sums written out, differentiated by JAX op by op (the reference)."""
    v, moments = 0.0, 0.0
    for o, offset in enumerate(stencil_offsets(st.dim)):
        w = jnp.prod(jnp.stack([st.w[k][d] for d, k in enumerate(offset)]), axis=0)
        w = w if incompatible is None else jnp.where(incompatible[o], 0.0, w)
        v = v + w[:, None] * values[o]
        moments = moments + w[:, None, None] * values[o][:, :, None] * jnp.asarray(offset, w.dtype)
    return v, moments


@pytest.mark.x64
@pytest.mark.parametrize("masked", [False, True])
@DIMS_3D_SLOW
def test_stencil_moments_forward_and_reverse_rules_match_plain_autodiff_and_differences(dim, masked):
    """:func:`jaxmpm.state.stencil_moments` regroups its tangent by hand: its value, its
    Jacobian-vector products (batched over directions, as Jacobians are) and its transpose
    must equal the op-by-op derivative of the plain sums, and central differences."""
    from jaxmpm.state import stencil_moments

    grid = Grid(lo=(0.0,) * dim, hi=(1.0,) * dim, dx=0.1)
    keys = jax.random.split(jax.random.PRNGKey(3), 6)
    n, k = 40, 3
    x = jax.random.uniform(keys[0], (n, dim), jnp.float64, 0.1, 0.9)
    values = jax.random.normal(keys[1], (3**dim, n, dim), jnp.float64)
    incompatible = jax.random.bernoulli(keys[2], 0.3, (3**dim, n)) if masked else None

    def f(impl, x, values):
        return impl(compute_stencil(grid, x), incompatible, list(values))

    dx = jax.random.normal(keys[3], (k, n, dim), jnp.float64) * 1e-2
    dv = jax.random.normal(keys[4], (k, *values.shape), jnp.float64)
    cot = jax.random.normal(keys[5], (n, dim), jnp.float64), jax.random.normal(keys[5], (n, dim, dim), jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(impl, x, values, dx, dv, cot):
        """Value, batched tangents and cotangents of one implementation: one program each."""
        fn = functools.partial(f, impl)
        tangents = jax.vmap(lambda a, b: jax.jvp(fn, (x, values), (a, b))[1])(dx, dv)
        return fn(x, values), tangents, jax.vjp(fn, x, values)[1](cot)

    (value, tangents, grads), (value_p, tangents_p, grads_p) = (
        derivatives(impl, x, values, dx, dv, cot) for impl in (stencil_moments, _plain_stencil_moments))
    for a, b in zip(value, value_p):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
    for a, b in zip(tangents, tangents_p):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    # central differences along the first direction (stencils do not change: |h dx| << fx's margin)
    h = 1e-6
    mine = jax.jit(functools.partial(f, stencil_moments))
    up, down = mine(x + h * dx[0], values + h * dv[0]), mine(x - h * dx[0], values - h * dv[0])
    for t, u, d in zip(tangents, up, down):
        np.testing.assert_allclose(t[0], (u - d) / (2 * h), rtol=1e-6, atol=1e-8)
    # reverse mode transposes the rule
    for a, b in zip(grads, grads_p):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.x64
def test_sum_last_matches_jnp_sum(dim):
    """:func:`jaxmpm.fusion.sum_last` (a sum over the last axis written as adds) equals
    ``jnp.sum(x, axis=-1)`` in value, with ``keepdims``, and in forward and reverse mode."""
    from jaxmpm.fusion import sum_last

    x = jax.random.normal(jax.random.PRNGKey(11), (5, 4, dim), jnp.float64)
    dx = jax.random.normal(jax.random.PRNGKey(12), x.shape, jnp.float64)
    for keepdims in (False, True):
        def mine(x):
            return sum_last(x, keepdims=keepdims)

        def plain(x):
            return jnp.sum(x, axis=-1, keepdims=keepdims)

        (a, da), (b, db) = (jax.jvp(f, (x,), (dx,)) for f in (mine, plain))
        np.testing.assert_allclose(a, b, rtol=1e-15)
        np.testing.assert_allclose(da, db, rtol=1e-15)
        assert a.shape == b.shape
        cot = jax.random.normal(jax.random.PRNGKey(13), b.shape, jnp.float64)
        np.testing.assert_array_equal(jax.vjp(mine, x)[1](cot)[0], jax.vjp(plain, x)[1](cot)[0])


@pytest.mark.x64
@pytest.mark.parametrize("count", [4, 27])
def test_spread_transposes_into_adds(dim, count):
    """:func:`jaxmpm.fusion.spread` equals ``x[None]`` broadcast over ``count`` nodes in value,
    tangent and cotangent, and its cotangent is computed without a reduction (the YNNPACK
    fusions it exists to avoid)."""
    from jaxmpm.fusion import spread

    x = jax.random.normal(jax.random.PRNGKey(15), (7, dim), jnp.float64)
    dx = jax.random.normal(jax.random.PRNGKey(16), x.shape, jnp.float64)
    cot = jax.random.normal(jax.random.PRNGKey(17), (count, *x.shape), jnp.float64)

    def plain(x):
        return jnp.broadcast_to(x[None], (count, *x.shape))

    mine = functools.partial(spread, count=count)
    np.testing.assert_array_equal(mine(x), plain(x))
    np.testing.assert_array_equal(jax.jvp(mine, (x,), (dx,))[1], jax.jvp(plain, (x,), (dx,))[1])
    np.testing.assert_allclose(jax.vjp(mine, x)[1](cot)[0], jax.vjp(plain, x)[1](cot)[0], rtol=1e-14)
    vjp_text = str(jax.make_jaxpr(lambda c: jax.vjp(mine, x)[1](c))(cot))
    assert "reduce_sum" not in vjp_text and "reduce_sum" in str(jax.make_jaxpr(lambda c: jax.vjp(plain, x)[1](c))(cot))


@pytest.mark.x64
@pytest.mark.parametrize("trailing", [(), (3,)])
@DIMS_3D_SLOW
def test_symmetric_pair_sum_matches_the_broadcast_sum(dim, trailing):
    """:func:`jaxmpm.fusion.symmetric_pair_sum` over the 3^D stencil nodes (a primitive whose
    transpose uses the pair weights' symmetry): value, forward mode batched over tangents,
    reverse mode for the values and for the weights, and the gradient of a batch, against
    the plain sum of broadcast products; its cotangent has no reduction, and a non-symmetric
    table gives a wrong one (the rule relies on the symmetry)."""
    from jaxmpm.fusion import symmetric_pair_sum

    k = 3**dim
    keys = jax.random.split(jax.random.PRNGKey(23), 6)
    half = jax.random.normal(keys[0], (k, k, 5), jnp.float64)
    table = half + jnp.swapaxes(half, 0, 1)  # table[j, i] == table[i, j]
    weights = list(table)
    values = jax.random.normal(keys[1], (k, 5, *trailing), jnp.float64)
    if trailing:
        weights = [w[..., None] for w in weights]

    def plain(ws, v):
        return sum(w * v[j][None] for j, w in enumerate(ws))

    dv = jax.random.normal(keys[2], (4, *values.shape), jnp.float64)
    dw = [jax.random.normal(kk, (4, *w.shape), jnp.float64) for kk, w in zip(jax.random.split(keys[3], k), weights)]
    cot = jax.random.normal(keys[4], values.shape, jnp.float64)
    batch = jax.random.normal(keys[5], (3, *values.shape), jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, weights, values, dv, dw, cot, batch):
        """Value, batched tangents, cotangents and a batch's gradient: one program each."""
        tangents = jax.vmap(lambda t, tw: jax.jvp(fn, (weights, values), (tw, t))[1])(dv, dw)
        loss = lambda b: jnp.sum(jax.vmap(lambda v: fn(weights, v))(b) ** 2)  # noqa: E731
        return fn(weights, values), tangents, jax.vjp(fn, weights, values)[1](cot), jax.grad(loss)(batch)

    mine, theirs = (derivatives(fn, weights, values, dv, dw, cot, batch) for fn in (symmetric_pair_sum, plain))
    np.testing.assert_allclose(mine[0], theirs[0], rtol=1e-13)
    np.testing.assert_allclose(mine[1], theirs[1], rtol=1e-12, atol=1e-13)
    for a, b in zip(jax.tree.leaves(mine[2]), jax.tree.leaves(theirs[2])):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(mine[3], theirs[3], rtol=1e-12)
    vjp_text = str(jax.make_jaxpr(lambda c: jax.vjp(lambda v: symmetric_pair_sum(weights, v), values)[1](c))(cot))
    assert not re.search(r"f64\[[^\]]*\] = reduce_sum", vjp_text)  # (an integer one makes the conditional's token)
    skewed = [w + 0.1 * jnp.arange(k, dtype=w.dtype).reshape((k,) + (1,) * (w.ndim - 1)) for w in weights]
    bad, right = (derivatives(fn, skewed, values, dv, dw, cot, batch)[2][1] for fn in (symmetric_pair_sum, plain))
    assert not np.allclose(bad, right)


@pytest.mark.x64
@pytest.mark.parametrize("trailing", [(), (4,), (3, 3)])
@DIMS_3D_SLOW
def test_scale_rows_matches_the_broadcast_product(dim, trailing):
    """:func:`jaxmpm.fusion.scale_rows` (a primitive whose transpose sums a row's products
    with adds): its value, batched Jacobian-vector products, vector-Jacobian products, second
    derivatives and batches with one operand shared equal the plain broadcast product's."""
    from jaxmpm.fusion import scale_rows

    def plain(w, x):
        return w.reshape(w.shape + (1,) * len(trailing)) * x

    keys = jax.random.split(jax.random.PRNGKey(14), 6)
    n = 5 * dim
    w, dw = jax.random.normal(keys[0], (n,), jnp.float64), jax.random.normal(keys[1], (3, n), jnp.float64)
    x, dx = (jax.random.normal(k, s + (n, *trailing), jnp.float64) for k, s in ((keys[2], ()), (keys[3], (3,))))

    def close(a, b):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)

    cot = jax.random.normal(keys[4], x.shape, jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(f, w, x, dw, dx, cot):
        """Value, batched tangents, cotangents, second derivatives, the grad of a vmap (the
        transpose batched) and grads with one operand shared by a batch: one program each."""
        loss = lambda a, b: jnp.sum(jnp.sin(f(a, b)) * cot)  # noqa: E731
        return (
            f(w, x),
            jax.vmap(lambda s, t: jax.jvp(f, (w, x), (s, t))[1])(dw, dx),
            jax.vjp(f, w, x)[1](cot),
            jax.hessian(loss, argnums=(0, 1))(w, x),
            jax.grad(lambda a: jnp.sum(jax.vmap(f, (None, 0))(a, dx) * cot))(w),
            jax.grad(lambda b: jnp.sum(jax.vmap(f, (0, None))(dw, b) * cot))(x),
        )

    mine, theirs = (derivatives(f, w, x, dw, dx, cot) for f in (scale_rows, plain))
    np.testing.assert_array_equal(mine[0], theirs[0])
    for a, b in zip(jax.tree.leaves(mine[1:]), jax.tree.leaves(theirs[1:]), strict=True):
        close(a, b)


@pytest.mark.x64
@DIMS_3D_SLOW
def test_small_matmul_matches_jnp_matmul_in_value_and_derivatives(dim):
    """:func:`jaxmpm.constitutive.base.matmul` (a primitive: elementwise value and tangents,
    dot-based transpose): its value, Jacobian-vector products batched over directions,
    vector-Jacobian products, second derivatives and batches in which one operand is shared
    or broadcast equal ``jnp.matmul``'s."""
    from jaxmpm.constitutive.base import matmul

    keys = jax.random.split(jax.random.PRNGKey(4), 5)
    a, b = (jax.random.normal(key, (7, dim, dim), jnp.float64) for key in keys[:2])
    da, db = (jax.random.normal(key, (4, 7, dim, dim), jnp.float64) for key in keys[2:4])

    def close(x, y):
        np.testing.assert_allclose(x, y, rtol=1e-13, atol=1e-14)

    cot = jax.random.normal(keys[4], (7, dim, dim), jnp.float64)
    eye = jnp.eye(dim, dtype=jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, a, b, da, db, cot, eye):
        """Value, batched tangents, cotangents, a second derivative (the transpose's dots
        differentiated again), the grad of a vmap, batches with one operand shared
        (vmap) or broadcast over the other's batch, and a cotangent with a constant
        operand: one program each."""
        loss = lambda x, y: jnp.sum(jnp.sin(fn(x, y)))  # noqa: E731
        return (
            fn(a, b),
            jax.vmap(lambda s, t: jax.jvp(fn, (a, b), (s, t))[1])(da, db),
            jax.vjp(fn, a, b)[1](cot),
            jax.hessian(loss, argnums=(0, 1))(a[0], b[0])[0][1],
            jax.grad(lambda x: jnp.sum(jax.vmap(loss, (None, 0))(x, da)))(a),
            jax.vmap(fn, (0, None))(da, b),
            jax.vmap(fn, (None, 0))(a, db),
            jax.vmap(fn, (0, None))(da[:, 0], b),  # (D, D) @ (7, D, D)
            jax.vjp(fn, eye, b)[1](cot),
        )

    mine, theirs = (derivatives(fn, a, b, da, db, cot, eye) for fn in (matmul, jnp.matmul))
    np.testing.assert_allclose(mine[0], theirs[0], rtol=1e-14)
    for x, y in zip(jax.tree.leaves(mine[1:]), jax.tree.leaves(theirs[1:]), strict=True):
        close(x, y)


@pytest.mark.x64
@DIMS_3D_SLOW
def test_gather_rows_rule_matches_plain_indexing(dim):
    """:func:`jaxmpm.state.gather_rows` gathers tangents in a conditional of its own (a fusion
    boundary): its value, batched Jacobian-vector products and transpose equal plain
    indexing's, with a table narrower than its padded rows."""
    from jaxmpm.state import gather_rows, stencil_index

    grid = Grid(lo=(0.0,) * dim, hi=(1.0,) * dim, dx=0.1)
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    x = jax.random.uniform(keys[0], (30, dim), jnp.float64, 0.1, 0.9)
    index = stencil_index(grid, compute_stencil(grid, x))
    table = jax.random.normal(keys[1], (grid.num_nodes, 3), jnp.float64)

    def plain(t):
        return [t[i] for i in index]

    def mine(t):
        return gather_rows(t, index)

    dt = jax.random.normal(keys[2], (4, *table.shape), jnp.float64)
    cot = list(jax.random.normal(keys[3], (len(index), 30, 3), jnp.float64))

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, table, dt, cot):
        """Value, batched tangents and cotangent: one program each."""
        return fn(table), jax.vmap(lambda d: jax.jvp(fn, (table,), (d,))[1])(dt), jax.vjp(fn, table)[1](cot)[0]

    ours, theirs = (derivatives(fn, table, dt, cot) for fn in (mine, plain))
    for a, b in zip(jax.tree.leaves(ours[:2]), jax.tree.leaves(theirs[:2]), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(ours[2], theirs[2], rtol=1e-14, atol=1e-14)


@pytest.mark.x64
def test_faces_and_planes_on_node_rows_hold_whole_rows_in_every_dtype_jitted_or_not(dim):
    """A node on a domain face, or on a plane through a node row, is on it whatever the
    rounding. Before session 50 both were decided on rounded node coordinates: in float32 the
    upper faces' rows of this grid were not walls, and under ``jax.jit`` in float64 (whose
    fused multiply-adds round otherwise) neither was the floor's; of planes through node rows
    at dx = 12.5 mm, 17 of 71 heights lost or gained their row in float32."""
    from jaxmpm.state import GRID_PADDING
    from jaxmpm.step import apply_grid_colliders, domain_wall_nodes, node_coordinates

    dx, rows = 0.0125, 64  # the domain [0, 0.8]: its faces lie on node rows 3 and 67
    index = np.stack(np.meshgrid(*[np.arange(rows + 1 + 2 * GRID_PADDING)] * dim, indexing="ij"), -1).reshape(-1, dim)
    for dtype in (jnp.float32, jnp.float64):
        for heights in ([0.175, 0.2375, 0.525], [0.225, 0.45, 0.7125]):  # rows 14, 19, 42 and 18, 36, 57
            spec = block_spec(dim, dx=dx, lo=[0.3] * dim, hi=[0.32] * dim, domain_hi=rows * dx)
            spec["colliders"] = [{"type": "plane", "name": f"p{k}", "point": [0.0] * (dim - 1) + [h],
                                  "normal": [0.0] * (dim - 1) + [1.0], "contact": "slip"} for k, h in enumerate(heights)]
            scene = load_scene(spec, dtype=dtype)
            grid = scene.model.grid
            assert grid.shape == (rows + 1 + 2 * GRID_PADDING,) * dim

            def inside_planes_and_walls(v):
                nodes = node_coordinates(grid, dtype)
                up = apply_grid_colliders(scene.model, scene.params, nodes, v, jnp.zeros((), dtype))[:, -1]
                return up == 0.0, domain_wall_nodes(grid)

            falling = jnp.zeros((grid.num_nodes, dim), dtype).at[:, -1].set(-1.0)
            for run in (inside_planes_and_walls, jax.jit(inside_planes_and_walls)):
                stopped, walls = run(falling)
                # slip planes stop the fall at and below the highest plane's row, and only there
                highest = GRID_PADDING + round(max(heights) / dx)
                np.testing.assert_array_equal(np.asarray(stopped), index[:, -1] <= highest)
                for d, (below, beyond) in enumerate(walls):
                    np.testing.assert_array_equal(np.asarray(below), index[:, d] <= GRID_PADDING)
                    np.testing.assert_array_equal(np.asarray(beyond), index[:, d] >= GRID_PADDING + rows)


def _dam_break_spec(substeps: int, frames: int) -> dict:
    """A 0.4 m water column at dx = 0.02 m collapsing onto the floor (a domain face)."""
    u = np.sqrt(9.81 * 0.4)
    return {"dim": 2, "dx": 0.02, "domain": {"lo": [0, 0], "hi": [1.6, 0.8]}, "frames": frames, "frame_dt": 0.02,
            "substeps": substeps, "gravity": [0, -9.81],
            "bodies": [{"shape": "box", "lo": [0.0, 0.0], "hi": [0.4, 0.4],
                        "material": {"model": "newtonian", "mu": 0.002, "kappa": 1000 * (6 * u) ** 2}}]}


@pytest.mark.x64
def test_the_transfers_alone_take_a_fixed_share_of_kinetic_energy_per_step_whatever_dt():
    """As dt -> 0 the work of gravity and stress in a step vanishes and what is left of the
    step's change in kinetic energy (APIC's: ``m |v|^2 / 2 + m (dx^2 / 4) |C|^2 / 2``) is the
    transfers' own. It must never be a gain, and it does not shrink with dt: why a rollout at
    fixed dx does not converge as dt alone falls (measured: -2.20e-5 and -2.22e-5 of the
    kinetic energy per step at dt = 1e-8 and 1e-9 s from this collapsing column at 0.1 s;
    docs/case_studies/dam_break_3d_obstacle.md)."""
    scene = load_scene(_dam_break_spec(80, 6), dtype=jnp.float64)
    start = simulate(scene.model, scene.params).final
    m, dx = np.asarray(start.mass), 0.02

    def kinetic(s):
        v, C = np.asarray(s.v), np.asarray(s.C)
        return 0.5 * (m * (v**2).sum(-1)).sum() + 0.5 * (m * dx**2 / 4 * (C**2).sum((-1, -2))).sum()

    shares = []
    for substeps in (2_000_000, 20_000_000):  # dt = 1e-8 s and 1e-9 s
        tiny = load_scene(_dam_break_spec(substeps, 2), dtype=jnp.float64)
        ten = jax.jit(lambda s: jax.lax.scan(lambda q, _: (step(tiny.model, tiny.params, q), None), s, None,
                                             length=10)[0])
        shares.append((kinetic(ten(start)) - kinetic(start)) / 10 / kinetic(start))
    assert shares[0] < -1e-6, shares  # a loss, not a gain ...
    np.testing.assert_allclose(shares[1], shares[0], rtol=0.05)  # ... that does not fall with dt


def test_a_flip_blend_keeps_the_energy_apic_transfers_lose_and_converges_as_dt_falls():
    """What a user of ``flip`` sees (``Model.flip``): the 2D dam break of the test above,
    0.58 s, at 80 and 320 substeps a frame. With APIC alone the flow loses more mechanical
    energy the finer dt (measured: 24.3 and 30.0 J/m); with a FLIP share of 0.99 it loses
    about half as much and a finer dt changes it less and the other way (13.1 and 11.6 J/m;
    ``benchmarks/transfer_dissipation.py``). No run gains energy (the health check's
    ``energy_gain``) or goes NaN, and the front travels as far."""
    def lost(flip, substeps):
        scene = load_scene({**_dam_break_spec(substeps, 30), "flip": flip})
        traj = simulate(scene.model, scene.params, observe=lambda s: s)
        assert not np.asarray(traj.nan).any()
        assert np.asarray(traj.energy_gain).max() <= 1e-3
        s0, s1 = (jax.tree.map(lambda a, i=i: np.asarray(a[i], np.float64), traj.extra) for i in (0, -1))

        def mechanical(s):
            return float((s.mass * (0.5 * (s.v**2).sum(-1) + 9.81 * s.x[:, 1])).sum())
        return mechanical(s0) - mechanical(s1), float(np.asarray(traj.x)[-1, :, 0].max())

    apic = [lost(0.0, n) for n in (80, 320)]
    flip = [lost(0.99, n) for n in (80, 320)]
    assert apic[1][0] > apic[0][0] * 1.1  # APIC: a finer dt loses more
    for (f, _), (a, _) in zip(flip, apic):
        assert 0.0 < f < 0.65 * a  # the blend keeps most of what APIC loses
    assert abs(flip[1][0] - flip[0][0]) < 0.5 * (apic[1][0] - apic[0][0])  # and depends less on dt
    for (_, front_f), (_, front_a) in zip(flip, apic):
        assert abs(front_f - front_a) < 2 * 0.02  # the surge reaches as far (within 2 dx)


@pytest.mark.x64
# the landing on a box takes the free-flight cases' path before it lands; APIC's gradients are
# tested against central differences for every material in tests/test_gradients.py
@pytest.mark.parametrize("flip, box", [slow(0.0, False), slow(0.95, False), (0.95, True)])
def test_flip_blend_gradient_matches_central_differences(flip, box):
    """The blend's extra transfer is differentiable like the rest of the step: the gradient of
    a 2D elastic block's final centre of mass with respect to E and its initial velocity
    matches central differences (float64), in free flight and landing on a CPIC box (its
    ghost nodes' share)."""
    spec = block_spec(2, {"model": "elastic", "E": 2e3, "nu": 0.3}, frames=3, substeps=20, velocity=[0.5, -1.0])
    if box:
        spec["colliders"] = [{"type": "box", "lo": [0.0, 0.0], "hi": [1.0, 0.2], "contact": "slip"}]
    scene = load_scene({**spec, "flip": flip}, dtype=jnp.float64)

    def com(theta):
        p = jax.tree.map(lambda a: a, scene.params)
        p["bodies"][0]["E"] = jnp.exp(theta[0])
        p["bodies"][0]["velocity"] = jnp.asarray([theta[1], -1.0])
        return simulate(scene.model, p, checkpoint=None).x[-1].mean(0).sum()

    theta = jnp.asarray([np.log(2e3), 0.5])
    grad = jax.jit(jax.grad(com))(theta)
    h, com = 1e-5, jax.jit(com)
    fd = [(com(theta.at[i].add(h)) - com(theta.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.x64
def test_a_water_column_collapses_alike_in_float32_and_float64():
    """What a user sees of the walls' rounding: a 2D dam break (a 0.4 m water column on a
    floor at a domain face, 80 substeps a frame) follows the same path in float32 and float64.
    Measured after 0.1 s: particles under 1e-6 m apart; before session 50 the float64 run
    (jitted: the floor's node row was not a wall) was 36 mm ahead."""
    spec = _dam_break_spec(80, 6)
    runs = [np.asarray(simulate(scene.model, scene.params).x, np.float64)
            for scene in (load_scene(spec, dtype=dtype) for dtype in (jnp.float32, jnp.float64))]
    assert runs[1][-1, :, 0].max() > 0.48  # the front left the column (0.4 m) ...
    assert np.abs(runs[0] - runs[1]).max() < 1e-3 * spec["dx"]  # ... by the same path in both


@pytest.mark.x64
@pytest.mark.parametrize("dim, collision", [(2, "cpic"), (2, "grid"), (2, "particles"), slow(3, "cpic")])
def test_sand_lands_on_a_box_alike_in_float32_and_float64(dim, collision):
    """A sand block dropped onto a box collider (friction contact, a slip floor below) follows
    the same path in both precisions in every collision mode: nothing decides on rounding.
    Measured over 8 frames: at most 2e-5 dx apart in 2D and 5e-5 dx in 3D."""
    sand = {"model": "sand", "friction_angle": 30.0, "E": 1e5, "nu": 0.3}
    spec = block_spec(dim, sand, dx=0.05, frames=8, substeps=40, lo=[0.4, 0.45, 0.4][:dim], hi=[0.6, 0.6, 0.6][:dim],
                      floor={"point": [0.0] * dim, "normal": [0.0, 1.0, 0.0][:dim], "contact": "slip"})
    spec["collision"] = collision
    spec["colliders"].append({"type": "box", "name": "box", "lo": [0.3, 0.2, 0.3][:dim], "hi": [0.7, 0.3, 0.7][:dim],
                              "contact": "friction", "friction": 0.3})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", JaxmpmWarning)  # the particles mode ignores the friction, and says so
        runs = [np.asarray(simulate(scene.model, scene.params).x, np.float64)
                for scene in (load_scene(spec, dtype=dtype) for dtype in (jnp.float32, jnp.float64))]
    assert runs[1][-1, :, 1].min() < 0.3 + 2 * spec["dx"]  # the sand came down on the box (boundary particles
    # hold it about a cell up) ...
    assert np.abs(runs[0] - runs[1]).max() < 1e-3 * spec["dx"]  # ... by the same path in both


@pytest.mark.x64
def test_domain_walls_rule_matches_autodiff_of_the_walls(dim):
    """:func:`jaxmpm.step.apply_domain_walls` has a hand-written tangent (a select): its value,
    batched Jacobian-vector products and vector-Jacobian products equal JAX's derivatives of
    the same function, on nodes inside, on and beyond the walls, with inward and outward
    velocities (none exactly zero, where ``maximum``'s tie rule would differ)."""
    from jaxmpm.step import apply_domain_walls, domain_wall_nodes

    grid = Grid(lo=(0.2,) * dim, hi=(0.8,) * dim, dx=0.1)
    keys = jax.random.split(jax.random.PRNGKey(7), 3)
    v = jax.random.normal(keys[0], (grid.num_nodes, dim), jnp.float64)
    walled = jnp.stack([below | beyond for below, beyond in domain_wall_nodes(grid)], axis=-1)
    assert bool(jnp.any(walled & (v < 0))) and bool(jnp.any(walled & (v > 0)))
    # the rule's mask reads the walls on the grid's shape: the same nodes, unflattened
    for flat, shaped in zip(domain_wall_nodes(grid), domain_wall_nodes(grid, flat=False), strict=True):
        for a, b in zip(flat, shaped, strict=True):
            assert b.shape == grid.shape
            np.testing.assert_array_equal(a, b.reshape(-1))

    def mine(u):
        return apply_domain_walls(grid, u)

    def plain(u):
        return apply_domain_walls.fun(grid, u)

    dv = jax.random.normal(keys[1], (3, *v.shape), jnp.float64)
    cot = jax.random.normal(keys[2], v.shape, jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, v, dv, cot):
        """Value, batched tangents and cotangent: one program each."""
        return fn(v), jax.vmap(lambda d: jax.jvp(fn, (v,), (d,))[1])(dv), jax.vjp(fn, v)[1](cot)[0]

    for a, b in zip(*(derivatives(fn, v, dv, cot) for fn in (mine, plain)), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.x64
@pytest.mark.parametrize("batching", ["shifted", "jax"])
@DIMS_3D_SLOW
def test_scatter_stencil_rules_match_plain_scatter(dim, batching, monkeypatch):
    """:func:`jaxmpm.state.scatter_stencil` (P2G's scatter, a primitive with its own rules):
    value, batched Jacobian-vector products, transpose, a batch of stencils and a batch of
    batches equal plain per-node ``.at[].add``; with 3-wide rows (padded inside), in and out of
    ``jax.jit``, with the batching rule's shifted indices and with its fallback to JAX's own
    batching (taken when the shifted indices would overflow int32)."""
    from jaxmpm import state as state_module
    from jaxmpm.state import scatter_stencil, stencil_index

    if batching == "jax":
        monkeypatch.setattr(state_module, "_fits_int32", lambda size, num_nodes: False)
    grid = Grid(lo=(0.0,) * dim, hi=(1.0,) * dim, dx=0.1)
    keys = jax.random.split(jax.random.PRNGKey(6), 6)
    n, c, k = 30, 3, 4
    xs = jax.random.uniform(keys[0], (2, n, dim), jnp.float64, 0.1, 0.9)  # two stencils
    rows = jax.random.normal(keys[1], (3**dim, n, c), jnp.float64)

    def plain(x, r):
        index = stencil_index(grid, compute_stencil(grid, x))
        out = jnp.zeros((grid.num_nodes, c), r.dtype)
        for node, row in zip(index, r):
            out = out.at[node].add(row)
        return out

    def mine(x, r):
        return scatter_stencil(grid, compute_stencil(grid, x), list(r))

    def close(a, b):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)

    drows = jax.random.normal(keys[2], (k, *rows.shape), jnp.float64)
    cot = jax.random.normal(keys[3], (grid.num_nodes, c), jnp.float64)
    batch_rows = jax.random.normal(keys[4], (2, *rows.shape), jnp.float64)

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, xs, rows, drows, cot, batch_rows):
        """Value, batched tangents, transpose, a batch of stencils (index and rows batched, or
        the index only) and a batch of batches: one program each."""
        scatter = functools.partial(fn, xs[0])
        nested = jax.vmap(lambda x, r: jax.vmap(lambda d: jax.jvp(lambda q: fn(x, q), (r,), (d,))[1])(drows))
        return (
            scatter(rows),
            jax.vmap(lambda d: jax.jvp(scatter, (rows,), (d,))[1])(drows),
            jax.vjp(scatter, rows)[1](cot)[0],
            jax.vmap(fn)(xs, batch_rows),
            jax.vmap(fn, in_axes=(0, None))(xs, rows),
            nested(xs, batch_rows),
        )

    ours, theirs = (derivatives(fn, xs, rows, drows, cot, batch_rows) for fn in (mine, plain))
    close(mine(xs[0], rows), theirs[0])  # outside jit too
    for a, b in zip(ours, theirs, strict=True):
        close(a, b)


@pytest.mark.x64
@pytest.mark.parametrize("dim", [2, 3])
def test_moment_sums_rules_match_plain_sums(dim):
    """:func:`jaxmpm.state.moment_sums` (G2P's tangent sums, a primitive with its own rules):
    value, Jacobian-vector products in the weights and the values together, the transpose in
    each, batches of values (the Jacobians' case), of weights, and of both nested, and reverse
    mode through a Jacobian-vector product, under ``jax.jit``, equal the plain sums."""
    from jaxmpm.state import _stencil_moments, moment_sums, stencil_offsets

    offsets = stencil_offsets(dim)
    k, n, c = len(offsets), 11, 3
    keys = jax.random.split(jax.random.PRNGKey(9), 6)
    w, dw = (list(jax.random.normal(key, (k, n), jnp.float64)) for key in keys[:2])
    v, dv = (list(jax.random.normal(key, (k, n, c), jnp.float64)) for key in keys[2:4])
    cot = (jax.random.normal(keys[4], (n, c), jnp.float64), jax.random.normal(keys[5], (n, c, dim), jnp.float64))
    batch_v, batch_w = [jnp.stack([x, 2.0 * x, -x]) for x in v], [jnp.stack([x, 0.5 * x]) for x in w]

    @functools.partial(jax.jit, static_argnums=0)
    def derivatives(fn, w, v, dw, dv, cot, batch_w, batch_v):
        sums = functools.partial(fn, offsets)
        return (
            sums(w, v),
            jax.jvp(sums, (w, v), (dw, dv))[1],
            jax.vjp(lambda a: sums(a, v), w)[1](cot)[0],
            jax.vjp(lambda b: sums(w, b), v)[1](cot)[0],
            jax.vmap(lambda b: sums(w, b))(batch_v),
            jax.vmap(lambda a: sums(a, v))(batch_w),
            jax.vmap(lambda a: jax.vmap(lambda b: sums(a, b))(batch_v))(batch_w),
            jax.grad(lambda a, b: jnp.sum(jax.jvp(lambda q: sums(a, q), (b,), (dv,))[1][1] ** 2))(w, v),
        )

    ours = derivatives(moment_sums, w, v, dw, dv, cot, batch_w, batch_v)
    theirs = derivatives(_stencil_moments, w, v, dw, dv, cot, batch_w, batch_v)
    for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(theirs), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.x64
@pytest.mark.parametrize("model_name", ["elastic", "newtonian"])
@pytest.mark.parametrize("flip", [0.0, 0.95])
def test_mass_and_momentum_are_conserved_without_boundaries(dim, model_name, flip):
    material = {"elastic": {"model": "elastic", "E": 1e4, "nu": 0.3}, "newtonian": {"model": "newtonian", "mu": 1.0, "kappa": 1e4}}[model_name]
    spec = block_spec(dim, material, gravity=[0.0] * dim, frames=4, substeps=20, dx=0.05)
    scene = load_scene({**spec, "flip": flip}, dtype=jnp.float64)
    state = initial_state(scene.model, scene.params)
    key = jax.random.PRNGKey(1)
    v = 0.3 * jax.random.normal(key, state.v.shape, jnp.float64)
    state = state.__class__(**{**{f: getattr(state, f) for f in state.__dataclass_fields__}, "v": v})
    # P2G conserves mass and momentum exactly
    grid = scene.model.grid
    m_grid, mv_grid = (np.asarray(a) for a in jax.jit(
        lambda s: p2g(grid, compute_stencil(grid, s.x), s, jnp.zeros_like(s.F), scene.model.dt))(state))
    mass, v = np.asarray(state.mass), np.asarray(state.v)
    np.testing.assert_allclose(m_grid.sum(), mass.sum(), rtol=1e-12)
    np.testing.assert_allclose(mv_grid.sum(0), (mass[:, None] * v).sum(0), rtol=1e-10, atol=1e-14)
    # and a rollout with internal stresses keeps the total momentum
    traj = simulate(scene.model, scene.params, state)
    p0 = (mass[:, None] * v).sum(0)
    for k in range(traj.x.shape[0]):
        p = (mass[:, None] * np.asarray(traj.v[k])).sum(0)
        np.testing.assert_allclose(p, p0, atol=1e-10 * float(mass.sum()))


@pytest.mark.parametrize("rollout", ["simulate", "run_frames"])
def test_a_rollout_called_outside_jit_is_one_program_reused_for_other_parameters(rollout):
    """``simulate`` and ``run_frames`` outside a jitted function compile once per scene layout
    and frame count: a second rollout with another viscosity compiles nothing, and equals the
    jitted ``simulate``. The block rests on the domain's floor, where it spreads and the
    viscosity acts (falling freely it has no velocity gradient, and the two viscosities gave
    positions 3e-8 m apart: rounding; here 1.6e-4 m)."""
    scene = load_scene(block_spec(2, {"model": "newtonian", "mu": 1.0, "kappa": 1e3}, lo=[0.4, 0.05], hi=[0.6, 0.25],
                                  frames=3, substeps=5))
    body = dict(scene.params["bodies"][0], mu=jnp.asarray(5.0, jnp.float32))
    other = dict(scene.params, bodies=(body,))
    run = (lambda p: simulate(scene.model, p, checkpoint=None)) if rollout == "simulate" else (
        lambda p: run_frames(scene.model, p))
    with counting_compilations() as compiles:
        first = run(scene.params)
        compiled = len(compiles)
        second = run(other)
    assert compiled > 0 and len(compiles) == compiled
    assert float(jnp.max(jnp.abs(first.x[-1] - second.x[-1]))) > 1e-5  # the viscosity acted, beyond rounding
    np.testing.assert_array_equal(second.x, jax.jit(lambda p: simulate(scene.model, p, checkpoint=None).x)(other))


@DIMS_3D_SLOW
def test_single_step_is_pure_and_advances_time(dim):
    """Run operation by operation (no ``jit``, which would trace a Python side effect once
    and hide it), two steps from one state agree and advance the time by ``dt``."""
    scene = load_scene(block_spec(dim))
    state = initial_state(scene.model, scene.params)
    a = step(scene.model, scene.params, state)
    b = step(scene.model, scene.params, state)
    np.testing.assert_array_equal(a.x, b.x)
    assert float(a.time) == pytest.approx(scene.model.dt)


@pytest.mark.x64
def test_a_rollout_of_its_first_active_frames_holds_the_rest_and_differentiates_like_the_short_one():
    """``simulate(frames=5, active=k)`` (k traced) equals the k-frame rollout on its first k
    frames and holds the last state after them; its gradient and JVP through a loss of the
    first k frames equal the short rollout's."""
    spec = block_spec(2, {"model": "newtonian", "mu": 10.0, "kappa": 1e4}, frames=5, substeps=6,
                      floor={"point": [0, 0.28], "normal": [0, 1], "contact": "slip"})
    scene = load_scene(spec, dtype=jnp.float64)
    long = jax.jit(lambda p, k: simulate(scene.model, p, checkpoint="nested", frames=5, active=k))
    for k in (2, 5):
        short = simulate(scene.model, scene.params, frames=k)
        held = long(scene.params, k)
        np.testing.assert_array_equal(held.x[:k], short.x)
        np.testing.assert_array_equal(held.x[k:], np.broadcast_to(short.x[-1], held.x[k:].shape))
        np.testing.assert_array_equal(held.final.x, short.final.x)
    assert float(jnp.max(jnp.abs(long(scene.params, 5).x[-1] - long(scene.params, 4).x[-1]))) > 0

    from jaxmpm.identify.parameters import set_param

    def head_loss(mu, rollout):
        return jnp.mean(rollout(set_param(scene.params, ("bodies", 0, "mu"), mu)).x[:3, :, 1] ** 2)

    short = lambda p: simulate(scene.model, p, frames=3)  # noqa: E731
    mu = jnp.asarray(10.0)
    g_short, g_long = (jax.grad(head_loss)(mu, r) for r in (short, lambda p: long(p, 3)))
    t_short, t_long = (jax.jvp(lambda m: head_loss(m, r), (mu,), (jnp.ones(()),))[1] for r in (short, lambda p: long(p, 3)))
    np.testing.assert_allclose(g_long, g_short, rtol=1e-10)
    np.testing.assert_allclose(t_long, t_short, rtol=1e-10)
    assert abs(float(g_short)) > 0


def _loss(model, checkpoint):
    def loss(params):
        traj = simulate(model, params, checkpoint=checkpoint)
        return jnp.mean(traj.x[-1, :, 0] ** 2 + 2 * traj.x[-1, :, 1] ** 2)

    return loss


@pytest.mark.x64
@pytest.mark.parametrize("policy", ["nested", slow("step"), slow("frame")])  # "nested": the fits' default
def test_checkpoint_policies_give_identical_gradients(policy):
    spec = block_spec(2, {"model": "elastic", "E": 3e4, "nu": 0.3}, frames=3, substeps=4, floor={"point": [0, 0.28], "normal": [0, 1], "contact": "slip"})
    scene = load_scene(spec, dtype=jnp.float64)
    plain, checkpointed = (jax.tree_util.tree_leaves(jax.grad(_loss(scene.model, c))(scene.params)) for c in (None, policy))
    for a, b in zip(plain, checkpointed):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.x64
def test_vmap_over_parameter_sets_equals_a_loop():
    spec = block_spec(2, {"model": "newtonian", "mu": 10.0, "kappa": 1e4}, frames=3, substeps=10, floor={"point": [0, 0.28], "normal": [0, 1]})
    scene = load_scene(spec, dtype=jnp.float64)
    # stable parameter sets only: an exploding rollout (kappa >= 3e4 at this dt) amplifies the
    # round-off of a different summation order in the scatter to O(1), so comparing it is moot
    mus = jnp.array([1.0, 10.0, 100.0, 300.0])
    kappas = jnp.array([1e3, 2e3, 5e3, 1e4])

    def rollout(mu, kappa):
        body = dict(scene.params["bodies"][0], mu=mu, kappa=kappa)
        return simulate(scene.model, dict(scene.params, bodies=(body,)))

    batched = jax.jit(jax.vmap(lambda mu, kappa: rollout(mu, kappa).x[-1]))(mus, kappas)
    for i in range(4):
        single = rollout(mus[i], kappas[i])
        assert single.first_unstable_frame() is None
        np.testing.assert_allclose(batched[i], single.x[-1], rtol=1e-10, atol=1e-12)
    assert float(jnp.max(jnp.abs(batched[0] - batched[3]))) > 1e-3  # the parameter sets differ in outcome


@pytest.mark.x64
def test_forward_and_reverse_mode_agree_for_velocity_and_gravity():
    spec = block_spec(2, {"model": "newtonian", "mu": 10.0, "kappa": 1e4}, frames=3, substeps=4, floor={"point": [0, 0.28], "normal": [0, 1]})
    scene = load_scene(spec, dtype=jnp.float64)

    def loss(v0, g):
        body = dict(scene.params["bodies"][0], velocity=v0)
        traj = simulate(scene.model, dict(scene.params, bodies=(body,), gravity=g))
        return jnp.mean(traj.x[-1] ** 2)

    v0, g = scene.params["bodies"][0]["velocity"], scene.params["gravity"]
    rev = jax.grad(loss, argnums=(0, 1))(v0, g)
    fwd = jax.jacfwd(loss, argnums=(0, 1))(v0, g)
    for a, b in zip(rev, fwd):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=1e-8)


def _saved_residuals(fn, *args, capsys) -> list[tuple[tuple[int, ...], str]]:
    """``(shape, origin)`` of each residual reverse mode keeps for ``fn(*args)`` (JAX's own listing)."""
    import re

    from jax.ad_checkpoint import print_saved_residuals

    capsys.readouterr()
    print_saved_residuals(fn, *args)
    lines = capsys.readouterr().out.splitlines()
    pattern = re.compile(r"^\w+\[([\d,]*)\] (.*)$")
    found = [(tuple(int(n) for n in m.group(1).split(",") if n), m.group(2)) for m in map(pattern.match, lines) if m]
    assert len(found) == len(lines) and found, lines
    return found


@pytest.mark.parametrize("collider", [None, "box"])
@DIMS_3D_SLOW
def test_checkpointed_rollout_saves_particle_state_per_step_never_grid_arrays(dim, collider, capsys):
    """Memory guard: under ``checkpoint="step"``/``"nested"`` reverse mode keeps, per substep,
    one particle state (x, v, C, F, aux, tags: O(N D^2)) and nothing grid sized (constants such
    as a collider's precomputed field are kept once, not per step). Without checkpointing it
    keeps grid arrays per step, so the guard can fail."""
    spec = block_spec(dim, {"model": "elastic", "E": 3e4, "nu": 0.3}, frames=3, substeps=4)
    if collider == "box":  # a CPIC collider right under the block: tags and contact terms in the step
        spec["colliders"] = [{"type": "box", "name": "box", "lo": [0.3] + [0.2] * (dim - 1), "hi": [0.7] + [0.29] * (dim - 1)}]
    scene = load_scene(spec)
    model = scene.model
    n, nodes, steps = model.num_particles, model.grid.num_nodes, (model.frames - 1) * model.substeps
    assert nodes > 4 * n  # grid-sized and particle-sized arrays are told apart by size

    def loss(checkpoint):
        return lambda p: jnp.sum(simulate(model, p, checkpoint=checkpoint).x[-1])

    def per_step(checkpoint):
        saved = _saved_residuals(loss(checkpoint), scene.params, capsys=capsys)
        return [shape for shape, origin in saved if "from a constant" not in origin and "argument" not in origin]

    per_step_state = n * (2 * dim + 2 * dim * dim + 1 + len(model.colliders))  # x, v, C, F, aux, tags
    for policy in ("step", "nested"):
        shapes = per_step(policy)
        assert all(nodes not in s for s in shapes), (policy, shapes)
        total = sum(int(np.prod(s)) for s in shapes)
        assert total <= 1.5 * steps * per_step_state, (policy, total, steps * per_step_state)
    assert any(nodes in s for s in per_step(None))
