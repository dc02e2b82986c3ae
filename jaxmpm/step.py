"""One MLS-MPM step as a list of named stages, and ``simulate`` (nested ``lax.scan``).

Stage order follows PAC-NeRF so results are comparable:

    stencil -> F_trial = (I + dt C) F -> return map -> Kirchhoff stress -> P2G
    -> grid update (gravity, colliders, domain walls) -> G2P -> advect

Every function here is pure and dimension-generic (D = 2 or 3 from array shapes).
"""

from __future__ import annotations

import itertools
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .colliders import project_velocity
from .model import Model, Params
from .state import Grid, State

#: Grid nodes lighter than this times dx^D are treated as empty (PAC-NeRF: 1e-8 dx^3).
MASS_EPS = 1e-8


class Stencil(eqx.Module):
    """Quadratic B-spline stencil of every particle, shared by P2G and G2P.

    Attributes:
        base: index of the stencil's lowest node per axis, ``(N, D)`` int32.
        fx: particle position relative to ``base`` in cells, ``(N, D)``, in [0.5, 1.5).
        w: per-axis weights of the three nodes, ``(3, N, D)``.
    """

    base: Int[Array, "N D"]
    fx: Float[Array, "N D"]
    w: Float[Array, "3 N D"]


def stencil_offsets(dim: int) -> tuple[tuple[int, ...], ...]:
    """The 3^D node offsets of the quadratic stencil (unrolled in Python)."""
    return tuple(itertools.product(range(3), repeat=dim))


def compute_stencil(grid: Grid, x: Float[Array, "N D"]) -> Stencil:
    """Stencil of particles at ``x`` (positions are assumed inside the padded grid)."""
    origin = jnp.asarray(grid.origin, x.dtype)
    xi = (x - origin) / grid.dx
    base = jnp.floor(xi - 0.5).astype(jnp.int32)
    fx = xi - base.astype(x.dtype)
    w = jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])
    return Stencil(base=base, fx=fx, w=w)


def _strides(shape: tuple[int, ...]) -> tuple[int, ...]:
    strides, acc = [], 1
    for n in reversed(shape):
        strides.append(acc)
        acc *= n
    return tuple(reversed(strides))


def _offset_terms(grid: Grid, st: Stencil, offset: tuple[int, ...]):
    """Flat node index ``(N,)``, weight ``(N,)`` and ``(x_i - x_p)/dx`` ``(N, D)`` of one offset."""
    strides = _strides(grid.shape)
    index = sum((st.base[:, d] + o) * s for d, (o, s) in enumerate(zip(offset, strides)))
    weight = jnp.prod(jnp.stack([st.w[o, :, d] for d, o in enumerate(offset)], axis=-1), axis=-1)
    dpos = jnp.asarray(offset, st.fx.dtype) - st.fx
    return index, weight, dpos


# --------------------------------------------------------------------------- stages


def material_update(model: Model, params: Params, state: State) -> tuple[Float[Array, "N D D"], Float[Array, " N"]]:
    """``F_trial = (I + dt C) F`` followed by each body's return map."""
    dt = model.dt
    dim = state.dim
    eye = jnp.eye(dim, dtype=state.F.dtype)
    F_trial = jnp.einsum("nij,njk->nik", eye + dt * state.C, state.F)
    Fs, auxs = [], []
    for body, sl, bp in zip(model.bodies, model.body_slices(), params["bodies"]):
        F, aux = body.material.return_map(F_trial[sl], state.C[sl], state.aux[sl], bp, dt)
        Fs.append(F)
        auxs.append(aux)
    return jnp.concatenate(Fs), jnp.concatenate(auxs)


def kirchhoff_stress(
    model: Model, params: Params, F: Float[Array, "N D D"], C: Float[Array, "N D D"], aux: Float[Array, " N"]
) -> Float[Array, "N D D"]:
    """Kirchhoff stress of every particle, body by body."""
    taus = [
        body.material.kirchhoff(F[sl], C[sl], aux[sl], bp)
        for body, sl, bp in zip(model.bodies, model.body_slices(), params["bodies"])
    ]
    return jnp.concatenate(taus)


def p2g(
    grid: Grid, st: Stencil, state: State, tau: Float[Array, "N D D"], dt: float
) -> tuple[Float[Array, " G"], Float[Array, "G D"]]:
    """Scatter mass and momentum (MLS fused stress + APIC affine term) to the grid.

    ``A_p = -dt V_p^0 (4/dx^2) tau_p + m_p C_p``; node i receives
    ``w_ip [m_p, m_p v_p + A_p (x_i - x_p)]``. One packed scatter per stencil offset.

    Returns:
        node masses ``(G,)`` and momenta ``(G, D)`` (flat, C order).
    """
    dim = state.dim
    affine = (-dt * 4.0 / grid.dx**2) * state.vol0[:, None, None] * tau + state.mass[:, None, None] * state.C
    mv = state.mass[:, None] * state.v
    packed = jnp.zeros((grid.num_nodes, 1 + dim), state.x.dtype)
    for offset in stencil_offsets(dim):
        index, weight, dpos = _offset_terms(grid, st, offset)
        momentum = mv + jnp.einsum("nij,nj->ni", affine, dpos * grid.dx)
        values = weight[:, None] * jnp.concatenate([state.mass[:, None], momentum], axis=-1)
        packed = packed.at[index].add(values)
    return packed[:, 0], packed[:, 1:]


def node_coordinates(grid: Grid, dtype) -> Float[Array, "G D"]:
    """World positions of all nodes, ``(G, D)``, built from iotas (no stored constant)."""
    coords = [
        grid.origin[d] + grid.dx * jax.lax.broadcasted_iota(dtype, grid.shape, d) for d in range(grid.dim)
    ]
    return jnp.stack([c.reshape(-1) for c in coords], axis=-1)


def grid_update(
    model: Model,
    params: Params,
    mass: Float[Array, " G"],
    momentum: Float[Array, "G D"],
    time: Float[Array, ""],
) -> Float[Array, "G D"]:
    """Node velocities: momentum / mass, gravity, collider conditions, domain walls."""
    grid = model.grid
    dtype = momentum.dtype
    occupied = mass > MASS_EPS * grid.dx**grid.dim
    safe_mass = jnp.where(occupied, mass, 1.0)
    v = jnp.where(occupied[:, None], momentum / safe_mass[:, None], 0.0)
    v = v + model.dt * jnp.asarray(params["gravity"], dtype)
    nodes = node_coordinates(grid, dtype)
    v = apply_grid_colliders(model, params, nodes, v, time)
    v = apply_domain_walls(grid, nodes, v)
    return jnp.where(occupied[:, None], v, 0.0)


def apply_grid_colliders(
    model: Model, params: Params, nodes: Float[Array, "G D"], v: Float[Array, "G D"], time
) -> Float[Array, "G D"]:
    """Grid-level collider condition: nodes inside a collider get the contact projection."""
    for collider, cp in zip(model.colliders, params["colliders"]):
        sd, normal = collider.signed_distance(nodes, time)
        inside = sd <= 1e-6 * model.grid.dx
        projected = project_velocity(
            v,
            normal,
            collider.contact,
            friction=cp["friction"],
            restitution=cp["restitution"],
            v_collider=collider.velocity_at(nodes, time),
        )
        v = jnp.where(inside[:, None], projected, v)
    return v


def apply_domain_walls(grid: Grid, nodes: Float[Array, "G D"], v: Float[Array, "G D"]) -> Float[Array, "G D"]:
    """Slip walls: nodes on or beyond the domain's faces lose their outward velocity."""
    columns = []
    for d in range(grid.dim):
        vd = v[:, d]
        vd = jnp.where(nodes[:, d] <= grid.lo[d], jnp.maximum(vd, 0.0), vd)
        vd = jnp.where(nodes[:, d] >= grid.hi[d], jnp.minimum(vd, 0.0), vd)
        columns.append(vd)
    return jnp.stack(columns, axis=-1)


def g2p(grid: Grid, st: Stencil, grid_v: Float[Array, "G D"]) -> tuple[Float[Array, "N D"], Float[Array, "N D D"]]:
    """Gather particle velocities and affine matrices ``C = 4/dx^2 sum w v_i (x_i - x_p)^T``."""
    n, dim = st.fx.shape
    v = jnp.zeros((n, dim), grid_v.dtype)
    C = jnp.zeros((n, dim, dim), grid_v.dtype)
    for offset in stencil_offsets(dim):
        index, weight, dpos = _offset_terms(grid, st, offset)
        vi = grid_v[index]
        v = v + weight[:, None] * vi
        C = C + (4.0 / grid.dx) * weight[:, None, None] * vi[:, :, None] * dpos[:, None, :]
    return v, C


def advect(grid: Grid, x: Float[Array, "N D"], v: Float[Array, "N D"], dt: float) -> Float[Array, "N D"]:
    """``x + dt v``, clamped to the padded grid so every stencil stays in bounds."""
    lo = jnp.asarray(grid.origin, x.dtype) + grid.dx
    hi = jnp.asarray(grid.origin, x.dtype) + (jnp.asarray(grid.shape, x.dtype) - 2.0) * grid.dx - 1e-4 * grid.dx
    return jnp.clip(x + dt * v, lo, hi)


def step(model: Model, params: Params, state: State) -> State:
    """Advance ``state`` by one MPM step of ``model.dt`` seconds."""
    dt = model.dt
    st = compute_stencil(model.grid, state.x)
    F, aux = material_update(model, params, state)
    tau = kirchhoff_stress(model, params, F, state.C, aux)
    mass, momentum = p2g(model.grid, st, state, tau, dt)
    grid_v = grid_update(model, params, mass, momentum, state.time)
    v, C = g2p(model.grid, st, grid_v)
    x = advect(model.grid, state.x, v, dt)
    return eqx.tree_at(lambda s: (s.x, s.v, s.C, s.F, s.aux, s.time), state, (x, v, C, F, aux, state.time + dt))


# --------------------------------------------------------------------------- rollouts

CHECKPOINT_POLICIES = (None, "step", "frame", "nested")


class Trajectory(eqx.Module):
    """Per-frame outputs of :func:`simulate` (frame 0 is the initial state).

    Attributes:
        times: frame times, ``(T,)`` seconds.
        x: positions, ``(T, N, D)``.
        v: velocities, ``(T, N, D)``.
        extra: whatever ``observe(state)`` returned, stacked over frames (or None).
        cfl: max CFL number ``max|v| dt / dx`` over the substeps that led to each frame, ``(T,)``.
        nan: whether any position is NaN at each frame, ``(T,)``.
        left: number of particles outside the domain at each frame, ``(T,)``.
        final: the state after the last frame.
    """

    times: Float[Array, " T"]
    x: Float[Array, "T N D"]
    v: Float[Array, "T N D"]
    extra: Any
    cfl: Float[Array, " T"]
    nan: Bool[Array, " T"]
    left: Int[Array, " T"]
    final: State

    def first_unstable_frame(self, cfl_limit: float = 1.0) -> int | None:
        """Index of the first frame whose CFL number exceeds ``cfl_limit`` or that has NaNs."""
        import numpy as np

        bad = np.asarray(self.nan) | (np.asarray(self.cfl) > cfl_limit) | ~np.isfinite(np.asarray(self.cfl))
        return int(np.argmax(bad)) if bad.any() else None


def _left_domain(grid: Grid, x: Float[Array, "N D"]) -> Int[Array, ""]:
    lo = jnp.asarray(grid.lo, x.dtype)
    hi = jnp.asarray(grid.hi, x.dtype)
    outside = jnp.any((x < lo) | (x > hi), axis=-1)
    return jnp.sum(outside.astype(jnp.int32))


def simulate(
    model: Model,
    params: Params,
    state: State | None = None,
    *,
    checkpoint: str | None = "nested",
    observe: Callable[[State], Any] | None = None,
    frames: int | None = None,
) -> Trajectory:
    """Roll the model out over ``frames`` output frames (default ``model.frames``).

    A nested ``lax.scan``: frames x ``model.substeps``. Per-frame outputs are scan outputs,
    never a buffer in the carry.

    Arguments:
        model: the static model.
        params: the parameter pytree (see :mod:`jaxmpm.model`).
        state: initial state; default ``initial_state(model, params)``.
        checkpoint: rematerialisation for reverse mode: ``None`` (store everything),
            ``"step"`` (``jax.checkpoint`` per substep: stores one state per substep),
            ``"frame"`` (per frame: stores one state per frame, recomputes a frame's
            substeps with their intermediates), ``"nested"`` (both: one state per frame
            plus one per substep of the frame being differentiated).
        observe: optional function of the state whose values are stacked per frame.
        frames: number of output frames including t = 0.

    Returns:
        A :class:`Trajectory`.
    """
    from .model import initial_state

    if checkpoint not in CHECKPOINT_POLICIES:
        raise ValueError(f"checkpoint must be one of {CHECKPOINT_POLICIES}, got {checkpoint!r}")
    frames = model.frames if frames is None else frames
    if state is None:
        state = initial_state(model, params)
    frame = _frame_function(model, params, observe, checkpoint)
    first = _frame_outputs(model, state, observe, jnp.zeros((), state.x.dtype))
    final, rest = jax.lax.scan(frame, state, None, length=frames - 1)
    out = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, rest)
    return _trajectory(model, out, final)


def _trajectory(model: Model, out, final: State) -> Trajectory:
    x, v, extra, cfl, nan, left = out
    times = jnp.arange(x.shape[0], dtype=x.dtype) * model.frame_dt
    return Trajectory(times=times, x=x, v=v, extra=extra, cfl=cfl, nan=nan, left=left, final=final)


def _frame_function(model: Model, params: Params, observe, checkpoint):
    """``frame(state, _) -> (state, outputs)``: ``model.substeps`` steps and the frame's outputs."""
    dt, dx = model.dt, model.grid.dx

    def substep(carry, _):
        s, cfl = carry
        s = step(model, params, s)
        speed2 = jnp.max(jnp.sum(jax.lax.stop_gradient(s.v) ** 2, axis=-1))
        return (s, jnp.maximum(cfl, jnp.sqrt(speed2) * dt / dx)), None

    if checkpoint in ("step", "nested"):
        substep = jax.checkpoint(substep)

    def frame(s, _):
        zero = jnp.zeros((), s.x.dtype)
        (s, cfl), _ = jax.lax.scan(substep, (s, zero), None, length=model.substeps)
        return s, _frame_outputs(model, s, observe, cfl)

    if checkpoint in ("frame", "nested"):
        frame = jax.checkpoint(frame)
    return frame


def run_frames(
    model: Model,
    params: Params,
    state: State | None = None,
    *,
    observe: Callable[[State], Any] | None = None,
    on_frame: Callable[[int], None] | None = None,
    cfl_limit: float = 1.0,
) -> Trajectory:
    """Forward-only rollout frame by frame from Python, for progress output and early stops.

    Same results as :func:`simulate`, but each frame is one jitted call, ``on_frame(i)``
    is called after frame i, and the run stops with a :class:`SimulationError` naming the
    first frame whose CFL number exceeds ``cfl_limit`` or that produced NaNs.
    """
    from .errors import SimulationError
    from .model import initial_state

    if state is None:
        state = initial_state(model, params)
    frame = jax.jit(_frame_function(model, params, observe, None))
    outputs = [_frame_outputs(model, state, observe, jnp.zeros((), state.x.dtype))]
    for i in range(1, model.frames):
        state, out = frame(state, None)
        cfl, nan = float(out[3]), bool(out[4])
        if nan or not cfl <= cfl_limit:
            reason = "NaN values appeared" if nan else f"the CFL number reached {cfl:.2f} (> {cfl_limit})"
            raise SimulationError(
                f"the simulation became unstable at frame {i} (t = {i * model.frame_dt:.4g} s): {reason}; "
                f"use a smaller dt (more than {model.substeps} substeps per frame) or a coarser dx"
            )
        outputs.append(out)
        if on_frame is not None:
            on_frame(i)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *outputs)
    return _trajectory(model, stacked, state)


def _frame_outputs(model: Model, s: State, observe, cfl):
    extra = observe(s) if observe is not None else None
    nan = jnp.any(jnp.isnan(s.x)) | jnp.any(jnp.isnan(s.v))
    return s.x, s.v, extra, jax.lax.stop_gradient(cfl), nan, _left_domain(model.grid, s.x)
