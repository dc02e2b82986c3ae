"""Session 50's prototype (not part of the package): the step's particle-side work in chunks of particles,
so that each chunk's k tangent rows stay in cache (target 6's forward half; see docs/benchmarks.md, session 50).

    python particle_chunks.py PARTICLES GRID STEPS NCHUNKS KS [REPEATS]
NCHUNKS=0: the package's step.
"""
import sys, time, functools
import numpy as np
import jax, jax.numpy as jnp
import equinox as eqx
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jaxmpm.bench import _scene_model
from jaxmpm.bench_scene import MPMParams, grad_scene_velocity
from jaxmpm.model import initial_state
from jaxmpm.step import step, grid_update, g2p, advect, affine_momentum
from jaxmpm import extensions as _ext
from jaxmpm.state import (State, compute_stencil, stencil_weights, stencil_offsets, stencil_index,
                          _BLOCK_SCATTER, _IN_BOUNDS, _shift_batch, _batch_at_front)
from jaxmpm.fusion import compute_once, always_true, scale_rows
from jaxmpm.constitutive.base import matmul

N, G, STEPS, NC = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
ks = [int(k) for k in sys.argv[5].split(",")]
reps = int(sys.argv[6]) if len(sys.argv) > 6 else 3


def _acc_impl(buf, *args):
    count = len(args) // 2
    out = buf
    for node, block in zip(args[:count], args[count:]):
        out = jax.lax.scatter_add(out, node[:, None], block, _BLOCK_SCATTER, mode=_IN_BOUNDS)
    return out


def _acc_jvp(primals, tangents):
    count = (len(primals) - 1) // 2
    out = _acc_p.bind(*primals)
    dbuf = ad.instantiate_zeros(tangents[0])
    drows = [ad.instantiate_zeros(t) for t in tangents[1 + count:]]
    return out, _acc_p.bind(dbuf, *primals[1:1 + count], *drows)


def _acc_batch(args, dims):
    count = (len(args) - 1) // 2
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
    args = [_batch_at_front(a, d, size) for a, d in zip(args, dims)]
    buf = args[0]
    g = buf.shape[1]
    index = [_shift_batch(i, g) for i in args[1:1 + count]]
    rows = [r.reshape((-1,) + r.shape[2:]) for r in args[1 + count:]]
    out = _acc_p.bind(buf.reshape((-1,) + buf.shape[2:]), *index, *rows)
    return out.reshape(buf.shape), 0


_acc_p = Primitive("proto_acc_scatter")
_acc_p.def_impl(_acc_impl)
_acc_p.def_abstract_eval(lambda *avals: jax.core.ShapedArray(avals[0].shape, avals[0].dtype))
mlir.register_lowering(_acc_p, mlir.lower_fun(_acc_impl, multiple_results=False))
ad.primitive_jvps[_acc_p] = _acc_jvp
batching.primitive_batchers[_acc_p] = _acc_batch


def p2g_into(buf, grid, st, state, tau, dt):
    dim = state.dim

    def momentum_terms(state, tau, fx):
        affine = affine_momentum(grid, state, tau, dt)
        columns = [grid.dx * affine[:, :, d] for d in range(dim)]
        affine_fx = sum(scale_rows(fx[d], affine[:, :, d]) for d in range(dim))
        return columns, scale_rows(state.mass, state.v) - grid.dx * affine_fx

    columns, base_momentum = compute_once(momentum_terms, state, tau, st.fx, token=always_true(st.base))
    weights = compute_once(stencil_weights, st, None, token=always_true(st.base))
    rows = []
    for weight, offset in zip(weights, stencil_offsets(dim)):
        momentum = base_momentum
        for d, od in enumerate(offset):
            if od:
                momentum = momentum + od * columns[d]
        rows.append(scale_rows(weight, jnp.concatenate([state.mass[:, None], momentum], axis=-1)))
    blocks = [jnp.stack(rows[i:i + 3], axis=1) for i in range(0, len(rows), 3)]
    return _acc_p.bind(buf, *stencil_index(grid, st)[::3], *blocks)


def chunked_step(model, params, state, nc):
    grid, dt = model.grid, model.dt
    n = state.x.shape[0] // nc
    split = lambda a: a.reshape((nc, n) + a.shape[1:])
    parts = jax.tree.map(split, (state.x, state.v, state.C, state.F, state.aux, state.mass, state.vol0, state.tag))
    body, bp = model.bodies[0], params["bodies"][0]
    eye = jnp.eye(3, dtype=state.F.dtype)

    def chunk_state(part):
        x, v, C, F, aux, mass, vol0, tag = part
        return State(x=x, v=v, C=C, F=F, aux=aux, mass=mass, vol0=vol0, tag=tag, time=state.time)

    def scatter_chunk(buf, part):
        s = chunk_state(part)
        st = compute_stencil(grid, s.x)
        F_trial = matmul(eye + dt * s.C, s.F)
        F, aux, tau = _ext.material_update(body.material, F_trial, s.C, s.aux, bp, dt, params)
        return p2g_into(buf, grid, st, s, tau, dt), (F, aux)

    buf = jnp.zeros((grid.num_nodes, 4), state.x.dtype)
    buf, (F, aux) = jax.lax.scan(scatter_chunk, buf, parts)
    grid_v = grid_update(model, params, buf[:, 0], buf[:, 1:], state.time)

    def gather_chunk(_, x):
        st = compute_stencil(grid, x)
        v, C = g2p(grid, st, grid_v)
        return None, (advect(grid, x, v, dt), v, C)

    _, (x, v, C) = jax.lax.scan(gather_chunk, None, parts[0])
    join = lambda a: a.reshape((-1,) + a.shape[2:])
    x, v, C, F, aux = map(join, (x, v, C, F, aux))
    return eqx.tree_at(lambda s: (s.x, s.v, s.C, s.F, s.aux, s.time), state, (x, v, C, F, aux, state.time + dt))


model, params = _scene_model(N, G, "corotated", jnp.float32)
v_field = jnp.asarray(grad_scene_velocity(np.asarray(model.bodies[0].x0)), jnp.float32)
p = MPMParams(grid_n=G)
theta0 = jnp.asarray([p.E, p.nu, p.rho, 0.0, 0.0, 0.0], jnp.float32)


def prm_of(theta):
    body = {**params["bodies"][0], "E": theta[0], "nu": theta[1], "density": theta[2], "velocity": theta[3:6]}
    return {**params, "bodies": (body,)}


def s0_of(theta):
    s0 = initial_state(model, prm_of(theta))
    return eqx.tree_at(lambda s: s.v, s0, s0.v + v_field)


def step_of(s, theta):
    return step(model, prm_of(theta), s) if NC == 0 else chunked_step(model, prm_of(theta), s, NC)


def final_x(theta):
    return jax.lax.scan(lambda s, _: (step_of(s, theta), None), s0_of(theta), None, length=STEPS)[0].x


def jac(k):
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    return lambda theta: jax.vmap(lambda t: jax.jvp(final_x, (theta,), (t,))[1])(basis)


def timed(fn):
    fn = jax.jit(fn)
    out = jax.block_until_ready(fn(theta0))
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter(); jax.block_until_ready(fn(theta0)); ts.append(time.perf_counter() - t0)
    return out, 1e3 * np.array(ts)


xf, f = timed(final_x)
line = [f"NC={NC} forward min {f.min():.0f} med {np.median(f):.0f} x[0]={np.asarray(xf[0])}"]
for k in ks:
    out, t = timed(jac(k))
    line.append(f"k={k} min {t.min():.0f} ({t.min()/f.min():.2f}x) med {np.median(t):.0f} "
                f"({np.median(t)/np.median(f):.2f}x) |J|={float(jnp.abs(out).max()):.4e}")
print(" | ".join(line), flush=True)
