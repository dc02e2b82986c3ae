"""One MLS-MPM step as a list of named stages, and ``simulate`` (nested ``lax.scan``).

Stage order follows PAC-NeRF so results are comparable; the collider stages are CPIC's
(Hu et al. 2018, as adapted by AS-DiffMPM):

    stencil -> gather collision field (CPIC: signed distance, normal, persistent side tags,
    compatibility bits) -> F_trial = (I + dt C) F -> return map -> Kirchhoff stress
    -> P2G (compatibility-masked; rigid boundary particles in "particles" mode)
    -> grid update (gravity, planes, grid-level colliders in "grid" mode, domain walls)
    -> G2P (incompatible nodes read the particle's own Coulomb-projected velocity)
    -> advect (+ penetration correction)

Every function here is pure and dimension-generic (D = 2 or 3 from array shapes).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import cpic
from . import extensions as _ext
from .colliders import Plane, project_velocity, row_matvec
from .constitutive.base import matmul
from .fusion import always_true, compute_once, scale_rows
from .model import Collision, Model, Params
from .precision import compiled_entry, full_precision
from .state import (
    GRID_PADDING,
    Grid,
    State,
    Stencil,
    compute_stencil,
    gather_rows,
    offset_weight,
    scatter_stencil,
    stencil_index,
    stencil_moments,
    stencil_offsets,
    stencil_weights,
)

__all__ = [
    "Stencil",
    "compute_stencil",
    "stencil_offsets",
    "gather_contact",
    "material_update",
    "affine_momentum",
    "p2g",
    "p2g_boundary",
    "grid_update",
    "apply_grid_colliders",
    "apply_domain_walls",
    "domain_wall_nodes",
    "node_tolerance",
    "g2p",
    "advect",
    "step",
    "simulate",
    "simulate_healthy",
    "run_frames",
    "Trajectory",
    "unhealthy",
    "health_message",
    "step_with_speed",
    "mechanical_energy",
    "energy_scale",
    "ENERGY_GAIN_LIMIT",
    "wave_cfl",
    "WAVE_CFL_LIMIT",
    "stable_substeps",
]

#: Grid nodes lighter than this times dx^D are treated as empty (PAC-NeRF: 1e-8 dx^3).
MASS_EPS = 1e-8


# --------------------------------------------------------------------------- stages


def material_update(
    model: Model, params: Params, state: State
) -> tuple[Float[Array, "N D D"], Float[Array, " N"], Float[Array, "N D D"]]:
    """``F_trial = (I + dt C) F``, then each body's return map and Kirchhoff stress
    (:meth:`jaxmpm.constitutive.Material.update`): the new ``F``, ``aux`` and ``tau``."""
    dt = model.dt
    dim = state.dim
    eye = jnp.eye(dim, dtype=state.F.dtype)
    F_trial = matmul(eye + dt * state.C, state.F)
    Fs, auxs, taus = [], [], []
    for body, sl, bp in zip(model.bodies, model.body_slices(), params["bodies"]):
        F, aux, tau = _ext.material_update(body.material, F_trial[sl], state.C[sl], state.aux[sl], bp, dt, params)
        Fs.append(F)
        auxs.append(aux)
        taus.append(tau)
    return jnp.concatenate(Fs), jnp.concatenate(auxs), jnp.concatenate(taus)


def gather_contact(model: Model, st: Stencil, state: State) -> cpic.Contact | None:
    """CPIC gather: per particle and particle-wise collider, the signed distance and normal
    from the stencil's affine nodes, the updated persistent side tags and the bits of the
    stencil nodes on the other side (see :func:`jaxmpm.cpic.gather_contact`).

    ``None`` unless ``model.collision == "cpic"`` and some collider is not a plane.
    """
    if model.collision != Collision.CPIC:
        return None
    return cpic.gather_contact(model.grid, st, state.x, state.tag, state.time, model.colliders, model.fields)


def affine_momentum(grid: Grid, state: State, tau: Float[Array, "N D D"], dt: float) -> Float[Array, "N D D"]:
    """MLS fused stress + APIC matrix ``A_p = -dt V_p^0 (4/dx^2) tau_p + m_p C_p``."""
    return scale_rows((-dt * 4.0 / grid.dx**2) * state.vol0, tau) + scale_rows(state.mass, state.C)


def p2g(
    grid: Grid,
    st: Stencil,
    state: State,
    tau: Float[Array, "N D D"],
    dt: float,
    contact: cpic.Contact | None = None,
    unforced: bool = False,
) -> tuple[Float[Array, " G"], Float[Array, "G D"]] | tuple[Float[Array, " G"], Float[Array, "G D"], ...]:
    """Scatter mass and momentum (MLS fused stress + APIC affine term) to the grid.

    ``A_p = -dt V_p^0 (4/dx^2) tau_p + m_p C_p``; node i receives
    ``w_ip [m_p, m_p v_p + A_p (x_i - x_p)]``: packed ``[mass, momentum]`` rows scattered into
    one grid buffer, one scatter per run of 3 stencil nodes (:func:`jaxmpm.state.scatter_stencil`).
    With a CPIC ``contact``, nodes on the other side of a collider from the particle receive
    nothing (no mass, momentum or stress): that share goes to the collider.

    With ``unforced``, the momenta without the stress, ``w_ip m_p (v_p + C_p (x_i - x_p))``
    ``(G, D)``, are scattered in the same rows (for :func:`flip_correction`).

    Returns:
        node masses ``(G,)`` and momenta ``(G, D)`` (flat, C order), and with ``unforced``
        the unforced momenta.
    """
    dim = state.dim

    def terms(state, affine, fx):
        # ``m v + A (x_i - x_p) = m v - dx A fx + dx A o``: ``A fx`` once, then per offset a sum
        # of A's columns.
        columns = [grid.dx * affine[:, :, d] for d in range(dim)]
        affine_fx = sum(scale_rows(fx[d], affine[:, :, d]) for d in range(dim))
        return columns, scale_rows(state.mass, state.v) - grid.dx * affine_fx

    def at_offset(base, columns, offset):  # base + sum_d o_d columns[d], skipping the zeros
        for d, od in enumerate(offset):
            if od:
                base = base + od * columns[d]
        return base

    # Computed once: XLA's CPU fusion would otherwise recompute them (and in forward mode their
    # tangents, back through the material's stress) inside each of the 3^D row fusions.
    columns, base_momentum = compute_once(
        lambda state, tau, fx: terms(state, affine_momentum(grid, state, tau, dt), fx),
        state, tau, st.fx, token=always_true(st.base))
    if unforced:  # the momentum without the stress, m_p (v_p + C_p (x_i - x_p)), the same way
        free_columns, free_base = compute_once(
            lambda state, fx: terms(state, scale_rows(state.mass, state.C), fx), state, st.fx,
            token=always_true(st.base))
    incompatible = None if contact is None else contact.incompatible_mask()
    # Stored once, and in forward mode their k tangents per offset: each row fusion would
    # otherwise re-derive its weight's tangent from the positions' for every entry it writes.
    weights = compute_once(stencil_weights, st, incompatible, token=always_true(st.base))
    rows = []
    for weight, offset in zip(weights, stencil_offsets(dim)):
        cols = [state.mass[:, None], at_offset(base_momentum, columns, offset)]
        if unforced:
            cols.append(at_offset(free_base, free_columns, offset))
        rows.append(scale_rows(weight, jnp.concatenate(cols, axis=-1)))
    packed = scatter_stencil(grid, st, rows)
    if unforced:
        return packed[:, 0], packed[:, 1:1 + dim], packed[:, 1 + dim:]
    return packed[:, 0], packed[:, 1:]


#: Mass of one rigid boundary particle ("particles" mode), in units of the heaviest material particle.
BOUNDARY_MASS_RATIO = 1000.0


def p2g_boundary(
    model: Model, state: State, time: Float[Array, ""]
) -> tuple[Float[Array, " G"], Float[Array, "G D"]] | None:
    """RP-DiffMPM: scatter the colliders' heavy boundary particles (``"particles"`` mode).

    Each boundary particle carries ``BOUNDARY_MASS_RATIO`` times the heaviest material
    particle's mass and the collider's velocity at its position; it has no stress. Returns
    their node masses and momenta (kept apart so gravity acts on the material only), or
    ``None`` in the other modes.
    """
    if model.collision != Collision.PARTICLES or all(b is None for b in model.boundary):
        return None
    grid = model.grid
    dtype = state.x.dtype
    m_b = BOUNDARY_MASS_RATIO * jax.lax.stop_gradient(jnp.max(state.mass))
    lo = jnp.asarray(grid.origin, dtype) + grid.dx
    hi = jnp.asarray(grid.origin, dtype) + (jnp.asarray(grid.shape, dtype) - 2.0) * grid.dx - 1e-4 * grid.dx
    packed = jnp.zeros((grid.num_nodes, 1 + grid.dim), dtype)
    for boundary, collider in zip(model.boundary, model.colliders):
        if boundary is None:
            continue
        xb, vb = cpic.boundary_positions(boundary, collider, time)
        inside = jnp.all((xb >= lo) & (xb <= hi), axis=-1)
        st = compute_stencil(grid, jnp.clip(xb, lo, hi))
        mass = jnp.where(inside, m_b, 0.0)
        values = mass[:, None] * jnp.concatenate([jnp.ones_like(mass)[:, None], vb], axis=-1)
        rows = [offset_weight(st, offset)[:, None] * values for offset in stencil_offsets(grid.dim)]
        packed = packed + scatter_stencil(grid, st, rows)
    return packed[:, 0], packed[:, 1:]


def node_coordinates(grid: Grid, dtype) -> Float[Array, "G D"]:
    """World positions of all nodes, ``(G, D)``, built from iotas (no stored constant)."""
    coords = [
        grid.origin[d] + grid.dx * jax.lax.broadcasted_iota(dtype, grid.shape, d) for d in range(grid.dim)
    ]
    return jnp.stack([c.reshape(-1) for c in coords], axis=-1)


def node_tolerance(grid: Grid, dtype, reach: float = 0.0) -> float:
    """How close (metres) to a surface a node counts as on it: ``1e-6 dx``, or 32 rounding
    units of the node coordinates (and of a surface point ``reach`` metres from the
    origin) in ``dtype`` where that is more.

    :func:`node_coordinates` rounds: in float32, or in float64 under ``jax.jit`` (which fuses
    the product and the sum), a node on a plane through a node row lands a few units of
    the last place on either side of it, and a plain ``<= 1e-6 dx`` test then decided by
    round-off whether the whole row was inside the collider."""
    extent = max(abs(o) for o in grid.origin) + max(grid.shape) * grid.dx + abs(reach)
    return max(1e-6 * grid.dx, 32.0 * float(jnp.finfo(dtype).eps) * extent)


def node_inverse_mass(grid: Grid, mass: Float[Array, " G"]) -> tuple[Bool[Array, " G"], Float[Array, " G"]]:
    """Which nodes hold mass (above ``MASS_EPS`` per unit cell volume), and ``1 / mass`` there
    (0 on empty nodes). One reciprocal per node: 3x cheaper forward and backward than dividing
    each component under a mask (measured)."""
    occupied = mass > MASS_EPS * grid.dx**grid.dim
    return occupied, jnp.where(occupied, 1.0 / jnp.where(occupied, mass, 1.0), 0.0)


def grid_update(
    model: Model,
    params: Params,
    mass: Float[Array, " G"],
    momentum: Float[Array, "G D"],
    time: Float[Array, ""],
    rigid: tuple[Float[Array, " G"], Float[Array, "G D"]] | None = None,
) -> Float[Array, "G D"]:
    """Node velocities: momentum / mass, gravity, collider conditions, domain walls.

    ``rigid``: boundary-particle masses and momenta (``"particles"`` mode); gravity acts on
    the material's share of a node's mass only.
    """
    grid = model.grid
    dtype = momentum.dtype
    gravity = model.dt * jnp.asarray(params["gravity"], dtype)
    if rigid is None:
        total, material_share = mass, 1.0
    else:
        total = mass + rigid[0]
        momentum = momentum + rigid[1]
    occupied, inverse_mass = node_inverse_mass(grid, total)
    v = scale_rows(inverse_mass, momentum)
    if rigid is not None:
        material_share = (mass * inverse_mass)[:, None]
    v = v + material_share * gravity
    v = _ext.grid_velocity(model, params, v)  # extensions: drag (no-op unless enabled)
    nodes = node_coordinates(grid, dtype)
    v = apply_grid_colliders(model, params, nodes, v, time)
    v = apply_domain_walls(grid, v)
    return jnp.where(occupied[:, None], v, 0.0)


def apply_grid_colliders(
    model: Model, params: Params, nodes: Float[Array, "G D"], v: Float[Array, "G D"], time
) -> Float[Array, "G D"]:
    """Grid-level collider condition: nodes inside a collider get the contact projection.

    Planes are analytic and applied in every mode. Other colliders are applied here only in
    ``"grid"`` mode (GOP-DiffMPM), from their precomputed field (``side * distance`` on the
    nodes; moving colliders looked up in their rest frame); in ``"cpic"`` mode they act
    particle-wise in P2G/G2P, in ``"particles"`` mode through boundary particles.
    """
    for collider, field, cp in zip(model.colliders, model.fields, params["colliders"]):
        if isinstance(collider, Plane):
            sd, normal = collider.signed_distance(nodes, time)
            reach = float(np.linalg.norm(collider.point))
        elif model.collision == Collision.GRID:
            sd, normal = cpic.node_signed_distance(field, collider, model.grid, nodes, time)
            reach = 0.0
        else:
            continue
        inside = sd <= node_tolerance(model.grid, v.dtype, reach)
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


def domain_wall_nodes(grid: Grid, flat: bool = True) -> tuple[tuple[Bool[Array, "..."], Bool[Array, "..."]], ...]:
    """Per axis, the nodes on or below the domain's lower face and those on or beyond its
    upper face, ``(G,)`` each (``grid.shape`` each with ``flat=False``), decided on node
    indices (exact, whatever the dtype): the lower face's node is ``GRID_PADDING`` and the
    first node on or beyond the upper face is ``GRID_PADDING`` from the grid's end
    (:class:`jaxmpm.state.Grid`)."""
    walls = []
    for d in range(grid.dim):
        index = jax.lax.broadcasted_iota(jnp.int32, grid.shape, d)
        index = index.reshape(-1) if flat else index
        walls.append((index <= GRID_PADDING, index >= grid.shape[d] - 1 - GRID_PADDING))
    return tuple(walls)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def apply_domain_walls(grid: Grid, v: Float[Array, "G D"]) -> Float[Array, "G D"]:
    """Slip walls: nodes on or beyond the domain's faces (:func:`domain_wall_nodes`) lose
    their outward velocity.

    The tangent is a select on the primal's signs: JAX's derivative of ``maximum``/``minimum``
    re-derived the primal and a tie rule per tangent entry (the forward-mode grid update cost
    20x the primal one). The value keeps ``maximum``/``minimum``: programs with and without a
    null extension must round alike (``test_each_extension_alone_is_bitwise_null``)."""
    columns = []
    for d, (below, beyond) in enumerate(domain_wall_nodes(grid)):
        vd = v[:, d]
        vd = jnp.where(below, jnp.maximum(vd, 0.0), vd)
        vd = jnp.where(beyond, jnp.minimum(vd, 0.0), vd)
        columns.append(vd)
    return jnp.stack(columns, axis=-1)


@apply_domain_walls.defjvp
def _domain_walls_jvp(grid: Grid, primals, tangents):
    (v,), (dv,) = primals, tangents

    def outward_mask(v):
        # on the grid's shape XLA reads each node's index from its loop nest; on flat (G,) rows
        # it divides the flat index per entry (25,000 particles, 64^3 grid: 1.40 against 0.55
        # CPU ms per step; docs/benchmarks.md, session 53)
        cells = v.reshape(grid.shape + (grid.dim,))
        return jnp.stack([(below & (cells[..., d] < 0.0)) | (beyond & (cells[..., d] > 0.0))
                          for d, (below, beyond) in enumerate(domain_wall_nodes(grid, flat=False))],
                         axis=-1).reshape(v.shape)

    # stored once: XLA otherwise fuses the mask, and the primal velocity it reads, into the
    # tangent's select and re-derives both per tangent entry
    outward = compute_once(outward_mask, v, token=always_true(v))
    return apply_domain_walls(grid, v), jnp.where(outward, 0.0, dv)


def g2p(
    grid: Grid, st: Stencil, grid_v: Float[Array, "G D"], ghost: cpic.GhostNodes | None = None,
    also: Float[Array, "G E"] | None = None,
) -> tuple[Float[Array, "N D"], Float[Array, "N D D"]] | tuple[Float[Array, "N D"], Float[Array, "N D D"], Array]:
    """Gather particle velocities and affine matrices ``C = 4/dx^2 sum w v_i (x_i - x_p)^T``.

    Moment form: with ``x_i - x_p = dx (o - fx)``, ``C = 4/dx (M - v fx^T)`` where
    ``M = sum_o w_o v_o o^T``; no per-offset ``(N, D, D)`` outer product depends on the
    positions. All stencil nodes are read in one gather (:func:`jaxmpm.state.gather_rows`).

    With CPIC ``ghost`` nodes, the nodes incompatible with collider ``c`` read the particle's
    own projected velocity ``P_c`` (:class:`jaxmpm.cpic.GhostNodes`) instead of the grid: the
    loop skips them and their share is added at the end from their total weight ``W_c`` and
    moment ``M_c`` (:func:`jaxmpm.cpic.incompatible_moments`): ``v += W_c P_c``,
    ``C += 4/dx^2 P_c M_c^T``.

    ``also``: a second node table ``(G, E)`` read in the same gather; its plain weighted sum
    over the compatible nodes ``(N, E)`` is returned third.
    """
    dim = grid.dim
    table = grid_v if also is None else jnp.concatenate([grid_v, also], axis=-1)
    values = gather_rows(table, stencil_index(grid, st))
    incompatible = None if ghost is None else ghost.contact.incompatible_mask()
    v, moments = stencil_moments(st, incompatible, values)
    if also is not None:
        v, extra, moments = v[:, :dim], v[:, dim:], moments[:, :dim]
    fx = jnp.stack(st.fx, axis=-1)
    C = (4.0 / grid.dx) * (moments - matmul(v[:, :, None], fx[:, None, :]))
    for c in range(0 if ghost is None else len(ghost.kinds)):
        # stored once: each of C's D x D entries would otherwise re-derive the projection
        P = compute_once(lambda g, c=c: g.projected(c, grid.dx), ghost, token=always_true(st.base))
        v = v + scale_rows(ghost.weight[c], P)
        C = C + matmul((4.0 / grid.dx) * P[:, :, None], ghost.moment[c][:, None, :])
    return (v, C) if also is None else (v, C, extra)


def unforced_velocity(grid: Grid, mass: Float[Array, " G"], free_momentum: Float[Array, "G D"]) -> Float[Array, "G D"]:
    """``v*_i``: the node velocities of the APIC momentum alone, before any force, ``(G, D)``
    m/s (zero on empty nodes)."""
    return scale_rows(node_inverse_mass(grid, mass)[1], free_momentum)


def flip_correction(
    state: State, back: Float[Array, "N D"], ghost: cpic.GhostNodes | None, dx: float
) -> Float[Array, "N D"]:
    """What one transfer filtered out of the particles' own velocities, ``v_p - sum_i w_ip v*_i``
    ``(N, D)`` m/s, from ``back = sum_i w_ip v*_i`` over the compatible nodes
    (:func:`unforced_velocity`, read by :func:`g2p`). APIC's velocity plus ``alpha`` times this
    is the FLIP/APIC blend ``(1 - alpha) v_APIC + alpha (v_p + sum w (v_i - v*_i))``
    (:attr:`jaxmpm.Model.flip`).

    A particle's incompatible (CPIC ghost) nodes hold, before any force, its own affine
    velocity ``v_p + C_p (x_i - x_p)`` (:class:`jaxmpm.cpic.GhostNodes`): their share of
    ``sum w v*`` is ``W_c v_p + C_p M_c``. (Counting them as ``v_p`` alone fed the particle's
    velocity gradient back into its velocity at every substep; an elastic block dropped on a
    CPIC box then went NaN within 22-42 frames, measured in session 55.)
    """
    out = state.v - back
    for c in range(0 if ghost is None else len(ghost.kinds)):
        out = out - scale_rows(ghost.weight[c], state.v) - dx * row_matvec(state.C, ghost.moment[c])
    return out


def ghost_nodes(
    model: Model, params: Params, state: State, st: Stencil, tau: Float[Array, "N D D"], contact: cpic.Contact | None
) -> cpic.GhostNodes | None:
    """The CPIC ghost-node data of this substep (``None`` without particle-wise colliders)."""
    if contact is None:
        return None
    dt = model.dt
    affine = affine_momentum(model.grid, state, tau, dt)
    u = state.v + dt * jnp.asarray(params["gravity"], state.v.dtype)
    cps = [params["colliders"][k] for k in contact.index]
    weight, moment = cpic.incompatible_moments(st, contact)
    return cpic.GhostNodes(
        contact=contact,
        u=u,
        B=affine / state.mass[:, None, None],
        weight=weight,
        moment=moment,
        friction=tuple(jnp.asarray(cp["friction"], u.dtype) for cp in cps),
        restitution=tuple(jnp.asarray(cp["restitution"], u.dtype) for cp in cps),
        kinds=tuple(model.colliders[k].contact for k in contact.index),
    )


def advect(
    grid: Grid, x: Float[Array, "N D"], v: Float[Array, "N D"], dt: float, correction: Float[Array, "N D"] | None = None
) -> Float[Array, "N D"]:
    """``x + dt v`` (+ the penetration ``correction``), clamped to the padded grid so every
    stencil stays in bounds."""
    lo = jnp.asarray(grid.origin, x.dtype) + grid.dx
    hi = jnp.asarray(grid.origin, x.dtype) + (jnp.asarray(grid.shape, x.dtype) - 2.0) * grid.dx - 1e-4 * grid.dx
    moved = x + dt * v
    if correction is not None:
        moved = moved + correction
    return jnp.clip(moved, lo, hi)


def penetration_correction(model: Model, contact: cpic.Contact | None, v: Float[Array, "N D"]):
    """CPIC penetration correction (a smooth push back to the particle's own side), or ``None``."""
    if contact is None or model.penetration == 0.0:
        return None
    return cpic.penetration_correction(contact, v, model.dt, model.grid.dx, model.penetration)


@full_precision
def step(model: Model, params: Params, state: State) -> State:
    """Advance ``state`` by one MPM step of ``model.dt`` seconds.

    Each stage runs under a :func:`jax.named_scope` of its name, so profiles (and their
    backward passes, ``transpose(jvp(<stage>))``) are attributed per stage
    (``benchmarks/profile_step.py``).
    """
    return step_with_speed(model, params, state)[0]


def projected_speed2(
    grid_v: Float[Array, "G D"], v: Float[Array, "N D"], ghost: cpic.GhostNodes | None, dx: float
) -> Float[Array, ""]:
    """The largest squared speed (m^2/s^2) any projection of a substep produced: the grid
    nodes after the grid update (planes, grid-level colliders, walls), the particles after
    G2P, and the CPIC ghost velocities ``P`` of particles touching a collider (each counted
    where its incompatible nodes carry weight). Gradient-free (a health diagnostic)."""
    stop = jax.lax.stop_gradient
    speed2 = jnp.maximum(jnp.max(_row_norm2(stop(grid_v))), jnp.max(_row_norm2(stop(v))))
    for c in range(0 if ghost is None else len(ghost.kinds)):
        touching = stop(ghost.weight[c]) > cpic.GHOST_WEIGHT_MIN
        speed2 = jnp.maximum(speed2, jnp.max(jnp.where(touching, _row_norm2(stop(ghost.projected(c, dx))), 0.0)))
    return speed2


def _row_norm2(v):
    # (a reduction, not colliders.row_dot's unrolled form: under the max over the grid that
    # made a 3D step over a floor 1.5x slower, measured in session 22)
    return jnp.sum(v * v, axis=-1)


@full_precision
def step_with_speed(model: Model, params: Params, state: State) -> tuple[State, Float[Array, ""]]:
    """:func:`step`, and the largest squared speed its projections produced
    (:func:`projected_speed2`; the CFL number of the substep is ``sqrt(speed2) dt / dx``)."""
    dt, grid = model.dt, model.grid
    with jax.named_scope("stencil"):
        st = compute_stencil(grid, state.x)
    with jax.named_scope("contact"):
        contact = gather_contact(model, st, state)
    with jax.named_scope("material"):
        F, aux, tau = material_update(model, params, state)
        tau = _ext.stress(model, params, state, F, aux, tau)  # extensions: rate_dependence, heterogeneity
    with jax.named_scope("p2g"):
        if model.flip:
            mass, momentum, free_momentum = p2g(grid, st, state, tau, dt, contact, unforced=True)
        else:
            mass, momentum = p2g(grid, st, state, tau, dt, contact)
        rigid = p2g_boundary(model, state, state.time)
    with jax.named_scope("grid_update"):
        grid_v = grid_update(model, params, mass, momentum, state.time, rigid)
    with jax.named_scope("g2p"):
        ghost = ghost_nodes(model, params, state, st, tau, contact)
        if model.flip:
            v, C, back = g2p(grid, st, grid_v, ghost, also=unforced_velocity(grid, mass, free_momentum))
            v = v + model.flip * flip_correction(state, back, ghost, grid.dx)
        else:
            v, C = g2p(grid, st, grid_v, ghost)
        C = _ext.affine(model, params, C)  # extensions: damping
    with jax.named_scope("advect"):
        x = advect(grid, state.x, v, dt, penetration_correction(model, contact, v))
    tag = state.tag if contact is None else contact.tag
    new = eqx.tree_at(
        lambda s: (s.x, s.v, s.C, s.F, s.aux, s.tag, s.time), state, (x, v, C, F, aux, tag, state.time + dt)
    )
    return new, projected_speed2(grid_v, v, ghost, grid.dx)


# --------------------------------------------------------------------------- rollouts

CHECKPOINT_POLICIES = (None, "step", "frame", "nested")


class Trajectory(eqx.Module):
    """Per-frame outputs of :func:`simulate` (frame 0 is the initial state).

    Attributes:
        times: frame times, ``(T,)`` seconds.
        x: positions, ``(T, N, D)``.
        v: velocities, ``(T, N, D)``.
        extra: whatever ``observe(state)`` returned, stacked over frames (or None).
        cfl: max CFL number ``max|v| dt / dx`` over the substeps that led to each frame, the
            speeds read after every projection (:func:`projected_speed2`), ``(T,)``.
        nan: whether any position is NaN at each frame, ``(T,)``.
        left: number of particles outside the domain at each frame, ``(T,)``.
        energy_gain: kinetic plus potential energy above its value at t = 0, in units of
            :func:`energy_scale` (0 when a collider moves: energy is not conserved then), ``(T,)``.
        wave_cfl: the stress-wave CFL number of the stiffest body (:func:`wave_cfl`; the same
            at every frame), ``(T,)``.
        final: the state after the last frame.
    """

    times: Float[Array, " T"]
    x: Float[Array, "T N D"]
    v: Float[Array, "T N D"]
    extra: Any
    cfl: Float[Array, " T"]
    nan: Bool[Array, " T"]
    left: Int[Array, " T"]
    energy_gain: Float[Array, " T"]
    wave_cfl: Float[Array, " T"]
    final: State

    def head(self, frames: int) -> "Trajectory":
        """The first ``frames`` frames (``final`` unchanged)."""
        cut = lambda a: None if a is None else jax.tree_util.tree_map(lambda b: b[:frames], a)  # noqa: E731
        return Trajectory(times=self.times[:frames], x=self.x[:frames], v=self.v[:frames], extra=cut(self.extra),
                          cfl=self.cfl[:frames], nan=self.nan[:frames], left=self.left[:frames],
                          energy_gain=self.energy_gain[:frames], wave_cfl=self.wave_cfl[:frames], final=self.final)

    def first_unstable_frame(self, cfl_limit: float = 1.0) -> int | None:
        """Index of the first frame that :func:`unhealthy` flags, or None."""
        bad = np.asarray(unhealthy(self, cfl_limit))
        return int(np.argmax(bad)) if bad.any() else None


# --------------------------------------------------------------------------- health
#
# The one health check: every rollout (simulate, run_frames, the CLI, the fitting and
# discovery loops) judges a frame with ``unhealthy`` and words it with ``health_message``.

#: A frame is unhealthy when its kinetic plus potential energy exceeds the initial value by
#: more than this many :func:`energy_scale` units. Material and contact only dissipate energy
#: (elastic energy starts at zero and is never negative); the penetration correction lifts a
#: few particles by a fraction of a cell (far below one unit); an exploding run gains tens.
ENERGY_GAIN_LIMIT = 1.0


def mechanical_energy(state: State, gravity: Float[Array, " D"]) -> Float[Array, ""]:
    """Kinetic plus potential energy ``sum m (|v|^2 / 2 - g·x)`` (J; J per metre of depth in 2D)."""
    g = jnp.asarray(gravity, state.x.dtype)
    return jnp.sum(state.mass * (0.5 * _row_norm2(state.v) - state.x @ g))


def energy_scale(model: Model, state: State, gravity: Float[Array, " D"]) -> Float[Array, ""]:
    """The unit of :attr:`Trajectory.energy_gain` (J): the energy of lifting the whole body by
    one cell, ``M |g| dx``, plus that of moving it at one cell per frame, ``M (dx / frame_dt)^2
    / 2``, plus 1 % of the initial kinetic energy (so it is positive without gravity)."""
    g = jnp.asarray(gravity, state.x.dtype)
    total = jnp.sum(state.mass)
    dx = model.grid.dx
    kinetic = jnp.sum(state.mass * 0.5 * _row_norm2(state.v))
    return total * (jnp.sqrt(jnp.sum(g * g)) * dx + 0.5 * (dx / model.frame_dt) ** 2) + 0.01 * kinetic


#: Explicit MPM is unstable when a stress wave crosses more than about a cell per step. Measured
#: on issue 14's sand drop (dx = 0.01 m): stable at ``c dt/dx = 1.04``, sand thrown upward at
#: 1.27 (with no speed above 0.25 dx/dt and kinetic plus potential energy below its start).
WAVE_CFL_LIMIT = 1.0

#: Uniaxial compression with which :func:`wave_cfl` probes a material (small enough to stay
#: elastic, large enough for float32).
PROBE_STRAIN = 1e-4


def wave_cfl(model: Model, params: Params) -> Float[Array, ""]:
    """The stress-wave CFL number ``c dt / dx`` of the stiffest body (dimensionless).

    ``c = sqrt(M / rho)``, with ``M = -tau_xx / eps`` the stiffness a body's own update
    (return map and Kirchhoff stress) shows after one step of uniaxial compression ``eps``
    (:data:`PROBE_STRAIN`) from rest: the P-wave modulus ``lambda + 2 mu`` of the solids,
    ``7 kappa`` plus ``mu / dt`` (the explicit viscous limit) of the Newtonian fluid.
    Traceable: differentiable in the material parameters and the density.
    """
    dim, dt = model.dim, model.dt
    out = jnp.zeros((), model.bodies[0].x0.dtype)
    for body, bp in zip(model.bodies, params["bodies"]):
        dtype = body.x0.dtype
        e11 = jnp.zeros((1, dim, dim), dtype).at[0, 0, 0].set(1.0)
        F_trial = jnp.eye(dim, dtype=dtype)[None] - PROBE_STRAIN * e11
        aux0 = body.material.init_aux(1, dtype)
        _, _, tau = body.material.update(F_trial, (-PROBE_STRAIN / dt) * e11, aux0, bp, dt)
        modulus = jnp.maximum(-tau[0, 0, 0] / PROBE_STRAIN, 0.0)
        speed = jnp.sqrt(modulus / jnp.asarray(bp["density"], dtype))
        out = jnp.maximum(out, speed * dt / model.grid.dx)
    return out


def stable_substeps(model: Model, params: Params, limit: float = WAVE_CFL_LIMIT) -> int:
    """The fewest substeps per frame whose stress-wave CFL number (:func:`wave_cfl`) is at
    most ``limit``: the explicit step's stability limit from the material alone.

    Particle speeds limit the step too (``|v| dt / dx``, checked every frame by the health
    check), and accuracy may need more substeps than stability (rerun at ``dt / 2`` to see):
    this is the floor below which a run is unstable, not a recommendation.

    The CFL number grows with dt (``c`` is constant for solids; for the Newtonian fluid
    ``c dt = sqrt((7 kappa dt^2 + mu dt) / rho)``), so a bisection over the substep count finds
    it; about ``2 log2(substeps)`` evaluations of one particle's update (NumPy-speed, eager).
    """

    def stable(n: int) -> bool:
        return float(wave_cfl(model.with_substeps(n), params)) <= limit

    hi = model.substeps
    while not stable(hi):
        if hi > 2**24:
            raise ValueError("no substep count up to 2^24 keeps the stress-wave CFL number below the limit")
        hi *= 2
    lo = 0  # unstable (or none)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if stable(mid) else (mid, hi)
    return hi


def _energy_checked(model: Model) -> bool:
    """Whether energy must not grow: no collider moves (a moving one may do work)."""
    return not any(getattr(c, "moving", False) for c in model.colliders)


def _frame_unhealthy(cfl, nan, energy_gain, wave, cfl_limit: float, energy_limit: float):
    return nan | ~(cfl <= cfl_limit) | ~(energy_gain <= energy_limit) | ~(wave <= WAVE_CFL_LIMIT)


def unhealthy(traj: Trajectory, cfl_limit: float = 1.0, energy_limit: float = ENERGY_GAIN_LIMIT) -> Bool[Array, " T"]:
    """Per frame, whether the rollout is unhealthy there: NaN values, a CFL number above
    ``cfl_limit`` (speeds read after every projection: grid, particles, collider ghosts),
    kinetic plus potential energy grown by more than ``energy_limit`` units of
    :func:`energy_scale`, or a stress-wave CFL number above :data:`WAVE_CFL_LIMIT` (every
    frame then). Traceable (use ``~jnp.any(unhealthy(traj))`` inside ``jit``)."""
    return _frame_unhealthy(traj.cfl, traj.nan, traj.energy_gain, traj.wave_cfl, cfl_limit, energy_limit)


#: A CFL number above this many times the limit is a blow-up, not a flow too fast for dt:
#: ``health_message`` then asks for half the dt instead of scaling dt by the speed.
EXPLOSION_CFL = 10.0


def health_message(
    model: Model, traj: Trajectory, cfl_limit: float = 1.0, energy_limit: float = ENERGY_GAIN_LIMIT
) -> str | None:
    """``None`` for a healthy rollout, else one line naming the first unhealthy frame
    (:func:`unhealthy`), why, and a dt that should be stable (host side, not traceable)."""
    bad = np.asarray(unhealthy(traj, cfl_limit, energy_limit))
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    values = (float(traj.cfl[i]), bool(traj.nan[i]), float(traj.energy_gain[i]), float(traj.wave_cfl[i]))
    return _unstable_message(model, i, *values, cfl_limit, energy_limit)


def _unstable_message(
    model: Model, frame: int, cfl: float, nan: bool, gain: float, wave: float, cfl_limit: float, energy_limit: float
) -> str:
    """One line: the frame, why it is unhealthy (the first criterion it fails), and a dt that
    should be stable (the present one divided by a safety factor of the excess, at least 2)."""
    if not wave <= WAVE_CFL_LIMIT:
        why = (f"the time step is too large for the stiffest material (a stress wave crosses {wave:.3g} cells "
               f"per step, > {WAVE_CFL_LIMIT:g})")
        factor = 1.25 * wave / WAVE_CFL_LIMIT if math.isfinite(wave) else 2.0
    elif nan:
        why, factor = "NaN values appeared", 2.0
    elif not cfl <= cfl_limit:
        why = f"the CFL number max|v| dt/dx reached {cfl:.3g} (> {cfl_limit:g})"
        # a flow too fast for dt shows its speed; a blow-up's speed says nothing of the dt it needs
        blew_up = not cfl <= EXPLOSION_CFL * cfl_limit
        factor = 2.0 if blew_up else 2.0 * cfl / cfl_limit
        why += ": the run blew up" if blew_up else ""
    else:
        why = (f"kinetic plus potential energy grew {gain:.3g} units (about the energy of lifting the body by "
               f"one cell) above its initial value (> {energy_limit:g}: energy was created)")
        factor = 2.0
    dt = model.dt / max(factor, 2.0)
    return (
        f"the simulation became unstable at frame {frame} (t = {frame * model.frame_dt:.4g} s): {why}; "
        f"use a smaller dt (dt <= {dt:.3g} s, i.e. substeps >= {math.ceil(model.frame_dt / dt)} per frame "
        f"instead of {model.substeps}) or a coarser dx"
    )


def _left_domain(grid: Grid, x: Float[Array, "N D"]) -> Int[Array, ""]:
    lo = jnp.asarray(grid.lo, x.dtype)
    hi = jnp.asarray(grid.hi, x.dtype)
    outside = jnp.any((x < lo) | (x > hi), axis=-1)
    return jnp.sum(outside.astype(jnp.int32))


@compiled_entry
def simulate(
    model: Model,
    params: Params,
    state: State | None = None,
    *,
    checkpoint: str | None = "nested",
    observe: Callable[[State], Any] | None = None,
    frames: int | None = None,
    active: int | Int[Array, ""] | None = None,
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
        active: simulate only the first ``active`` frames (a traced integer may be given);
            the later ones hold the last simulated state (same outputs, CFL 0). The shapes
            stay those of ``frames``, so windows of one observation share a compilation
            while their cost follows the window (``fit``'s stages). Default: all.

    Returns:
        A :class:`Trajectory` (judge its health with :func:`unhealthy`).
    """
    if checkpoint not in CHECKPOINT_POLICIES:
        raise ValueError(f"checkpoint must be one of {CHECKPOINT_POLICIES}, got {checkpoint!r}")
    frames = model.frames if frames is None else frames
    model, params, state, base, first = _prologue(model, params, state, observe)
    frame = _frame_function(model, params, observe, checkpoint, base)
    zero = jnp.zeros((), state.x.dtype)
    if active is None:
        final, rest = jax.lax.scan(frame, state, None, length=frames - 1)
    else:
        def frame_or_hold(s, i):
            hold = lambda s: (s, _frame_outputs(model, params, s, observe, zero, base))  # noqa: E731
            return jax.lax.cond(i < active, lambda s: frame(s, None), hold, s)

        final, rest = jax.lax.scan(frame_or_hold, state, jnp.arange(1, frames))
    out = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a[None], b]), first, rest)
    return _trajectory(model, out, final)


def _start(model: Model, params: Params, state: State | None):
    """The model and params with extensions prepared, and the initial state."""
    from .model import initial_state

    model, params = _ext.prepare(model, params)  # extensions: gravity, colliders (no-op unless enabled)
    if state is None:
        state = _ext.initial_velocity(model, params, initial_state(model, params))
    return model, params, state


def _trajectory(model: Model, out, final: State) -> Trajectory:
    x, v, extra, cfl, nan, left, gain, wave = out
    times = jnp.arange(x.shape[0], dtype=x.dtype) * model.frame_dt
    return Trajectory(
        times=times, x=x, v=v, extra=extra, cfl=cfl, nan=nan, left=left, energy_gain=gain, wave_cfl=wave, final=final
    )


class _HealthBaseline(NamedTuple):
    """What a rollout's per-frame health is measured against, computed once from its start:
    the initial kinetic plus potential energy and its unit (None when energy is not checked),
    and the stress-wave CFL number (constant over the rollout)."""

    energy: Any
    scale: Any
    wave: Any


def _health_baseline(model: Model, params: Params, start: State) -> _HealthBaseline:
    stop = jax.lax.stop_gradient
    wave = stop(wave_cfl(model, params))
    if not _energy_checked(model):
        return _HealthBaseline(None, None, wave)
    g = params["gravity"]
    return _HealthBaseline(stop(mechanical_energy(start, g)), stop(energy_scale(model, start, g)), wave)


def _frame_function(model: Model, params: Params, observe, checkpoint, base: _HealthBaseline):
    """``frame(state, _) -> (state, outputs)``: ``model.substeps`` steps and the frame's
    outputs (health measured against ``base``)."""
    dt, dx = model.dt, model.grid.dx

    def substep(carry, _):
        s, cfl = carry
        s, speed2 = step_with_speed(model, params, s)
        return (s, jnp.maximum(cfl, jnp.sqrt(speed2) * dt / dx)), None

    if checkpoint in ("step", "nested"):
        substep = jax.checkpoint(substep)

    def frame(s, _):
        zero = jnp.zeros((), s.x.dtype)
        (s, cfl), _ = jax.lax.scan(substep, (s, zero), None, length=model.substeps)
        return s, _frame_outputs(model, params, s, observe, cfl, base)

    if checkpoint in ("frame", "nested"):
        frame = jax.checkpoint(frame)
    return frame


def simulate_healthy(
    model: Model,
    params: Params,
    *,
    halvings: int = 2,
    frames: int | None = None,
    checkpoint: str | None = None,
) -> tuple[Trajectory, Model, list[str]]:
    """:func:`simulate`, repeated with dt halved (substeps doubled) while :func:`health_message`
    finds the rollout unhealthy, at most ``halvings`` times: an evaluation rollout that must
    not be read off an exploded run (a gauge, a mask, a plot).

    Returns:
        ``(trajectory, the model that ran it (its substeps), one line per rollout discarded)``.

    Raises:
        SimulationError: the last rollout is unhealthy too (its message).
    """
    from .errors import SimulationError

    discarded: list[str] = []
    while True:
        traj = simulate(model, params, checkpoint=checkpoint, frames=frames)
        why = health_message(model, traj)
        if why is None:
            return traj, model, discarded
        if len(discarded) == halvings:
            raise SimulationError(f"{why} (after {halvings} halvings of dt)" if halvings else why)
        discarded.append(f"{model.substeps} substeps per frame: {why}")
        model = model.with_substeps(2 * model.substeps)


@full_precision
def run_frames(
    model: Model,
    params: Params,
    state: State | None = None,
    *,
    observe: Callable[[State], Any] | None = None,
    on_frame: Callable[[int], None] | None = None,
    cfl_limit: float = 1.0,
    energy_limit: float = ENERGY_GAIN_LIMIT,
) -> Trajectory:
    """Forward-only rollout frame by frame from Python, for progress output and early stops.

    Same results as :func:`simulate`, but each frame is one jitted call, ``on_frame(i)``
    is called after frame i, and the run stops with a :class:`SimulationError` naming the
    first unhealthy frame (:func:`unhealthy`: NaN, CFL number above ``cfl_limit``, energy
    grown by more than ``energy_limit``) and suggesting a dt.
    """
    from .errors import SimulationError

    model, params, state, base, out = _first_frame(model, params, state, observe)  # one program, not op by op
    outputs = []
    for i in range(model.frames):
        if i > 0:
            state, out = _next_frame(model, params, state, observe, base)
        values = (float(out[3]), bool(out[4]), float(out[6]), float(out[7]))
        if _frame_unhealthy(*(np.asarray(v) for v in values), cfl_limit, energy_limit):
            raise SimulationError(_unstable_message(model, i, *values, cfl_limit, energy_limit))
        outputs.append(out)
        if on_frame is not None and i > 0:
            on_frame(i)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.asarray(np.stack(a)), *outputs)  # on the host: nothing to compile
    return _trajectory(model, stacked, state)


def _prologue(model: Model, params: Params, state: State | None, observe):
    """A rollout's start: the prepared model and params, the initial state, the health
    baseline and frame 0's outputs."""
    model, params, state = _start(model, params, state)
    base = _health_baseline(model, params, state)
    return model, params, state, base, _frame_outputs(model, params, state, observe, jnp.zeros((), state.x.dtype), base)


#: :func:`run_frames`' start as one compiled program (run operation by operation it compiled
#: dozens of small ones).
_first_frame = compiled_entry(_prologue)


@compiled_entry
def _next_frame(model: Model, params: Params, state: State, observe, base: _HealthBaseline):
    """:func:`run_frames`' frame: one compiled program per model layout and ``observe``,
    reused by later runs with other parameters."""
    return _frame_function(model, params, observe, None, base)(state, None)


def _frame_outputs(model: Model, params: Params, s: State, observe, cfl, base: _HealthBaseline):
    stop = jax.lax.stop_gradient
    extra = observe(s) if observe is not None else None
    nan = jnp.any(jnp.isnan(s.x)) | jnp.any(jnp.isnan(s.v))
    gain = jnp.zeros((), s.x.dtype)
    if base.energy is not None:
        gain = stop((mechanical_energy(stop(s), params["gravity"]) - base.energy) / base.scale)
    return s.x, s.v, extra, stop(cfl), nan, _left_domain(model.grid, s.x), gain, base.wave
