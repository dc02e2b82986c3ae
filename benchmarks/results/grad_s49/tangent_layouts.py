"""Session 49's prototype (not part of the package): other ways to lay out target 6's k tangents.

    python tangent_layouts.py PARTICLES GRID STEPS MODE KS [REPEATS]

MODE: ``vmap`` (the package's way: ``jax.vmap`` of ``jax.jvp`` over the k basis tangents),
``unrollG`` (the rollout's scan carries the state and k/G groups of G tangents; each step calls
``jax.jvp`` of the step once per group, hoping XLA's CSE shares the repeated primal),
``sharedG`` (the same with the primal step written once more beside the groups), ``linvmap`` /
``linmap`` (``jax.linearize`` of the rollout, its linear map vmapped / ``lax.map``ped over k),
``steplinvmap`` / ``steplinloop`` / ``steplinmap`` (``jax.linearize`` of each step inside the
scan, its linear map vmapped over the k tangents / called once per tangent / ``lax.map``ped
over them, added in session 50).
Prints the forward's and each Jacobian's wall ms (min and median of REPEATS after a compiling
call), their ratios, and the Jacobian's largest difference from ``vmap``'s.
"""
import sys, time
import numpy as np
import jax, jax.numpy as jnp
import equinox as eqx
from jaxmpm.bench import _scene_model
from jaxmpm.bench_scene import MPMParams, grad_scene_velocity
from jaxmpm.model import initial_state
from jaxmpm.step import step

N, G, STEPS = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
mode = sys.argv[4]
ks = [int(k) for k in sys.argv[5].split(",")]
reps = int(sys.argv[6]) if len(sys.argv) > 6 else 3
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
    return step(model, prm_of(theta), s)

def final_x(theta):
    return jax.lax.scan(lambda s, _: (step_of(s, theta), None), s0_of(theta), None, length=STEPS)[0].x

def jac_vmap(k):
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    return lambda theta: jax.vmap(lambda t: jax.jvp(final_x, (theta,), (t,))[1])(basis)

def jac_unroll(k, group=1):
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    groups = [basis[i:i + group] for i in range(0, k, group)]
    def jac(theta):
        def init_t(b):
            return jax.vmap(lambda e: jax.jvp(s0_of, (theta,), (e,))[1])(b)
        s0 = s0_of(theta)
        ts0 = [init_t(b) for b in groups]
        def body(carry, _):
            s, ts = carry
            new_ts, new_s = [], None
            for b, t in zip(groups, ts):
                def one(ti, e):
                    return jax.jvp(step_of, (s, theta), (ti, e))
                ss, tt = jax.vmap(one)(t, b)
                new_ts.append(tt)
                new_s = jax.tree.map(lambda a: a[0], ss) if new_s is None else new_s
            return (new_s, new_ts), None
        (s, ts), _ = jax.lax.scan(body, (s0, ts0), None, length=STEPS)
        return jnp.concatenate([t.x for t in ts])
    return jac

def jac_unroll_shared(k, group=1):
    """primal computed once explicitly; tangents by jvp of the step (primal recomputed, CSE'd)."""
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    groups = [basis[i:i + group] for i in range(0, k, group)]
    def jac(theta):
        s0 = s0_of(theta)
        ts0 = [jax.vmap(lambda e: jax.jvp(s0_of, (theta,), (e,))[1])(b) for b in groups]
        def body(carry, _):
            s, ts = carry
            new_s = step_of(s, theta)
            new_ts = [jax.vmap(lambda ti, e: jax.jvp(step_of, (s, theta), (ti, e))[1])(t, b) for b, t in zip(groups, ts)]
            return (new_s, new_ts), None
        (s, ts), _ = jax.lax.scan(body, (s0, ts0), None, length=STEPS)
        return jnp.concatenate([t.x for t in ts])
    return jac

def timed(fn):
    fn = jax.jit(fn)
    out = jax.block_until_ready(fn(theta0))
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter(); jax.block_until_ready(fn(theta0)); ts.append(time.perf_counter() - t0)
    return out, 1e3 * np.array(ts)

def jac_lin(k, how):
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    def jac(theta):
        _, f = jax.linearize(final_x, theta)
        return jax.vmap(f)(basis) if how == "vmap" else jax.lax.map(f, basis)
    return jac


def jac_steplin(k, how):
    basis = jnp.eye(6, dtype=jnp.float32)[:k]
    def jac(theta):
        s0 = s0_of(theta)
        ts0 = jax.vmap(lambda e: jax.jvp(s0_of, (theta,), (e,))[1])(basis)
        def body(carry, _):
            s, ts = carry
            new_s, f = jax.linearize(lambda st, th: step_of(st, th), s, theta)
            if how == "vmap":
                new_ts = jax.vmap(f)(ts, basis)
            elif how == "map":
                new_ts = jax.lax.map(lambda a: f(*a), (ts, basis))
            else:
                outs = [f(jax.tree.map(lambda a: a[i], ts), basis[i]) for i in range(k)]
                new_ts = jax.tree.map(lambda *a: jnp.stack(a), *outs)
            return (new_s, new_ts), None
        (s, ts), _ = jax.lax.scan(body, (s0, ts0), None, length=STEPS)
        return ts.x
    return jac


def jacobian(k):
    """The Jacobian function of ``mode`` for k tangents."""
    for prefix, build in (("unroll", jac_unroll), ("shared", jac_unroll_shared)):
        if mode.startswith(prefix):
            return build(k, int(mode[len(prefix):] or 1))
    if mode.startswith("steplin"):
        return jac_steplin(k, mode[len("steplin"):])
    if mode.startswith("lin"):
        return jac_lin(k, mode[len("lin"):])
    return jac_vmap(k)


_, f = timed(final_x)
line = [f"forward min {f.min():.0f} med {np.median(f):.0f}"]
for k in ks:
    out, t = timed(jacobian(k))
    o2 = jax.jit(jac_vmap(k))(theta0)
    err = float(jnp.max(jnp.abs(out.reshape(o2.shape) - o2)) / jnp.max(jnp.abs(o2)))
    line.append(f"k={k} min {t.min():.0f} ({t.min()/f.min():.2f}x) med {np.median(t):.0f} "
                f"({np.median(t)/np.median(f):.2f}x) relerr {err:.1e}")
print(mode, " | ".join(line), flush=True)
