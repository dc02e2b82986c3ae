"""The static simulation model (grid, bodies, colliders, time stepping) and its parameters.

A :class:`Model` holds everything that does not change during a fit; the numbers one
may fit or sweep live in a separate ``params`` pytree::

    params = {
        "gravity": (D,) m/s^2,
        "bodies": ({"velocity": (D,), "offset": (D,), "density": (), <material parameters>: ()}, ...),
        "colliders": ({"friction": (), "restitution": ()}, ...),
    }

so ``jax.grad``, ``jax.jacfwd`` and ``jax.vmap`` act on ``params`` while the model is
closed over.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .colliders import Collider, Plane
from .constitutive import Material
from .state import Grid, State, make_state

Params = dict[str, Any]



class Collision(str, enum.Enum):
    """How non-planar colliders act (the scene's ``collision`` key; see :class:`Model`).

    A ``str`` enum: ``Collision("cpic")`` parses the scene value, and a member compares equal
    to its string (``Collision.CPIC == "cpic"``), so it is a hashable ``jax.jit``-static field.
    """

    CPIC = "cpic"
    GRID = "grid"
    PARTICLES = "particles"

    def __str__(self) -> str:
        return self.value


#: The scene values of :class:`Collision`, in order.
COLLISION_MODES = tuple(mode.value for mode in Collision)


class Body(eqx.Module):
    """One body of material: its particles' reference positions and its constitutive model.

    Attributes:
        name: name used in parameter paths and messages.
        material: the constitutive model (no array fields).
        x0: reference positions, ``(n, D)``, metres.
        vol0: initial particle volumes, ``(n,)``.
    """

    name: str = eqx.field(static=True)
    material: Material
    x0: Float[Array, "n D"]
    vol0: Float[Array, " n"]

    @property
    def num_particles(self) -> int:
        return self.x0.shape[0]


class Model(eqx.Module):
    """Static structure of a simulation.

    Attributes:
        grid: the background grid.
        bodies: the bodies; particles of body k are a contiguous slice of the state.
        colliders: rigid colliders.
        frame_dt: seconds between output frames.
        substeps: MPM steps per frame (``dt = frame_dt / substeps``).
        frames: number of output frames, including the initial one at t = 0.
        collision: how non-planar colliders act (planes are analytic grid conditions in
            every mode):

            * ``"cpic"`` (default): particle-wise, Compatible Particle-in-Cell (Hu et al. 2018;
              AS-DiffMPM) — persistent side tags, compatibility-masked P2G, Coulomb-projected
              ghost nodes in G2P, penetration correction (:mod:`jaxmpm.cpic`).
            * ``"grid"``: grid-level signed-distance condition on the nodes inside the collider
              (AS-DiffMPM's GOP-DiffMPM baseline), from the precomputed field.
            * ``"particles"``: the collider is a layer of heavy rigid boundary particles that
              take part in P2G (RP-DiffMPM baseline; sticky, ignores friction/restitution).
        fields: per collider, its precomputed :class:`~jaxmpm.cpic.CollisionField` (``None``
            for planes and in ``"particles"`` mode). Built on construction when not given.
        boundary: per collider, its :class:`~jaxmpm.cpic.BoundaryParticles` (``"particles"``
            mode only; else ``None``). Built on construction when not given.
        penetration: strength in [0, 1] of the CPIC penetration correction: the fraction of a
            predicted penetration undone in the same substep.
        flip: weight ``alpha`` in [0, 1) of FLIP's velocity update blended into APIC's (0:
            APIC alone, the default and PAC-NeRF's transfer). APIC's transfers take a share of
            the kinetic energy out at every step, whatever dt, so at fixed dx a finer dt adds
            numerical viscosity; a blend of 0.95-0.99 keeps most of it (docs/materials.md,
            "Transfers"). A step costs 1.35x APIC's (25,000 particles, 3D). Works with every
            collision mode (a CPIC particle's ghost nodes count as its own affine velocity).
    """

    grid: Grid
    bodies: tuple[Body, ...]
    colliders: tuple[Collider, ...] = ()
    frame_dt: float = eqx.field(static=True, default=1.0 / 24.0)
    substeps: int = eqx.field(static=True, default=200)
    frames: int = eqx.field(static=True, default=16)
    collision: Collision = eqx.field(static=True, default=Collision.CPIC)
    fields: tuple | None = None
    boundary: tuple | None = None
    penetration: float = eqx.field(static=True, default=0.5)
    flip: float = eqx.field(static=True, default=0.0)

    def __post_init__(self):
        if self.collision not in COLLISION_MODES:
            raise ValueError(f"collision must be one of {COLLISION_MODES}, got {self.collision!r}")
        self.collision = Collision(self.collision)
        from .cpic import build_boundary, build_fields, check_planes, is_particle_wise

        check_planes(self.colliders, self.grid)

        dtype = self.bodies[0].x0.dtype if self.bodies else None
        k = len(self.colliders)
        fields = tuple(self.fields) if self.fields is not None else (None,) * k
        boundary = tuple(self.boundary) if self.boundary is not None else (None,) * k
        if len(fields) != k or len(boundary) != k:
            raise ValueError("Model.fields / Model.boundary must have one entry per collider")
        # Build (only) what the collision mode needs and is missing; NumPy, once.
        missing = [i for i, c in enumerate(self.colliders) if is_particle_wise(c)]
        if self.collision in (Collision.CPIC, Collision.GRID):
            todo = [i for i in missing if fields[i] is None]
            if todo:
                built = build_fields([self.colliders[i] for i in todo], self.grid, dtype)
                fields = tuple(built[todo.index(i)] if i in todo else f for i, f in enumerate(fields))
        else:
            todo = [i for i in missing if boundary[i] is None]
            if todo:
                built = build_boundary([self.colliders[i] for i in todo], self.grid, dtype)
                boundary = tuple(built[todo.index(i)] if i in todo else b for i, b in enumerate(boundary))
        self.fields = fields
        self.boundary = boundary

    def __check_init__(self):
        if not 0.0 <= self.penetration <= 1.0:
            raise ValueError(f"penetration must be in [0, 1], got {self.penetration}")
        if not 0.0 <= self.flip < 1.0:
            raise ValueError(f"flip must be in [0, 1) (pure FLIP, 1, is noisy and not offered), got {self.flip}")

    @property
    def dt(self) -> float:
        return self.frame_dt / self.substeps

    @property
    def dim(self) -> int:
        return self.grid.dim

    @property
    def num_particles(self) -> int:
        return sum(b.num_particles for b in self.bodies)

    def body_slices(self) -> tuple[slice, ...]:
        """The particle range of each body in the state arrays."""
        out, start = [], 0
        for body in self.bodies:
            out.append(slice(start, start + body.num_particles))
            start += body.num_particles
        return tuple(out)

    def frame_times(self):
        """Times of the output frames, ``(frames,)`` seconds (NumPy)."""
        import numpy as np

        return np.arange(self.frames) * self.frame_dt

    def with_substeps(self, substeps: int) -> "Model":
        """The same model with a different number of substeps per frame."""
        return dataclasses.replace(self, substeps=substeps)

    def with_flip(self, flip: float) -> "Model":
        """The same model with another FLIP blend in the transfers (0: APIC)."""
        return dataclasses.replace(self, flip=flip)

    def with_collision(self, collision: str) -> "Model":
        """The same model with another collision mode (builds the fields it needs)."""
        return dataclasses.replace(self, collision=collision)

    def with_colliders(self, colliders) -> "Model":
        """The same model with other colliders (their fields are rebuilt), e.g. to attach a
        scripted ``motion`` to a collider loaded from a scene."""
        return dataclasses.replace(self, colliders=tuple(colliders), fields=None, boundary=None)


def initial_state(model: Model, params: Params) -> State:
    """The state at t = 0 from the model's reference configuration and ``params``.

    Differentiable with respect to each body's ``velocity``, ``offset`` (a rigid translation of
    its reference positions; a params pytree without it places the body at its reference) and
    ``density``.
    """
    xs, vs, masses, vols, auxs = [], [], [], [], []
    for body, bp in zip(model.bodies, params["bodies"]):
        n = body.num_particles
        dtype = body.x0.dtype
        xs.append(body.x0 + jnp.asarray(bp["offset"], dtype) if "offset" in bp else body.x0)
        vs.append(jnp.broadcast_to(jnp.asarray(bp["velocity"], dtype), (n, model.dim)))
        masses.append(jnp.asarray(bp["density"], dtype) * body.vol0)
        vols.append(body.vol0)
        auxs.append(body.material.init_aux(n, dtype))
    return make_state(
        x=jnp.concatenate(xs),
        v=jnp.concatenate(vs),
        mass=jnp.concatenate(masses),
        vol0=jnp.concatenate(vols),
        aux=jnp.concatenate(auxs),
        num_colliders=len(model.colliders),
    )


#: What CPIC does with a restitution (docs/colliders.md, "Restitution in CPIC"): the law acts
#: on the ghost nodes only, which carry ~15 % of a surface particle's stencil.
CPIC_RESTITUTION_NOTE = (
    "in CPIC contact a restitution barely changes a rebound (measured: an elastic disk leaves at 0.73 of its "
    "arrival speed with e = 0 and 0.80 with e = 1; a particle without stress does not bounce): a known defect, see "
    "docs/colliders.md, 'Restitution in CPIC'. The rebound comes from the material's elasticity"
)


def inert_contact_parameter(model: Model, k: int, name: str) -> str | None:
    """Why collider ``k``'s contact parameter ``name`` (``"friction"`` or ``"restitution"``)
    has no effect in ``model``, or ``None`` when it acts.

    Boundary particles (``collision = "particles"``) are sticky whatever the collider's contact
    (planes excepted: they act on the grid in every mode); sticky contact stops all sliding and
    bouncing; slip contact is frictionless.
    """
    collider = model.colliders[k]
    if model.collision == Collision.PARTICLES and not isinstance(collider, Plane):
        return "boundary particles (collision = 'particles') are sticky and ignore friction and restitution"
    if collider.contact == "sticky":
        return "its contact is 'sticky', which stops all sliding and bouncing"
    if collider.contact == "slip" and name == "friction":
        return "its contact is 'slip' (frictionless); set contact = 'friction' to use it"
    return None


def weak_restitution(model: Model, k: int) -> bool:
    """Whether collider ``k``'s restitution acts only through CPIC's ghost nodes
    (:data:`CPIC_RESTITUTION_NOTE`): a non-planar, non-sticky collider in ``"cpic"`` mode."""
    collider = model.colliders[k]
    return model.collision == Collision.CPIC and not isinstance(collider, Plane) and collider.contact != "sticky"


def contact_notes(model: Model, params: Params) -> list[str]:
    """One line for each collider's friction or restitution that is set (non-zero) but does
    nothing (:func:`inert_contact_parameter`) or less than its name says
    (:func:`weak_restitution`). :func:`jaxmpm.load_scene` issues them as warnings."""
    notes = []
    for k, (collider, cp) in enumerate(zip(model.colliders, params["colliders"])):
        for name in ("friction", "restitution"):
            value = float(cp[name])
            if value == 0.0:
                continue
            why = inert_contact_parameter(model, k, name)
            if why is not None:
                notes.append(f"collider {collider.name!r}: {name} = {value:g} has no effect: {why}")
            elif name == "restitution" and weak_restitution(model, k):
                notes.append(f"collider {collider.name!r}: restitution = {value:g}: {CPIC_RESTITUTION_NOTE}")
    return notes
