"""The static simulation model (grid, bodies, colliders, time stepping) and its parameters.

A :class:`Model` holds everything that does not change during a fit; the numbers one
may fit or sweep live in a separate ``params`` pytree::

    params = {
        "gravity": (D,) m/s^2,
        "bodies": ({"velocity": (D,), "density": (), <material parameters>: ()}, ...),
        "colliders": ({"friction": (), "restitution": ()}, ...),
    }

so ``jax.grad``, ``jax.jacfwd`` and ``jax.vmap`` act on ``params`` while the model is
closed over.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .colliders import Collider
from .constitutive import Material
from .state import Grid, State, make_state

Params = dict[str, Any]

COLLISION_MODES = ("cpic", "grid", "particles")


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
        collision: how non-planar colliders act (``"cpic"``, ``"grid"``, ``"particles"``).
    """

    grid: Grid
    bodies: tuple[Body, ...]
    colliders: tuple[Collider, ...] = ()
    frame_dt: float = eqx.field(static=True, default=1.0 / 24.0)
    substeps: int = eqx.field(static=True, default=200)
    frames: int = eqx.field(static=True, default=16)
    collision: str = eqx.field(static=True, default="cpic")

    def __check_init__(self):
        if self.collision not in COLLISION_MODES:
            raise ValueError(f"collision must be one of {COLLISION_MODES}, got {self.collision!r}")

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


def initial_state(model: Model, params: Params) -> State:
    """The state at t = 0 from the model's reference configuration and ``params``.

    Differentiable with respect to each body's ``velocity`` and ``density``.
    """
    xs, vs, masses, vols, auxs = [], [], [], [], []
    for body, bp in zip(model.bodies, params["bodies"]):
        n = body.num_particles
        dtype = body.x0.dtype
        xs.append(body.x0)
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
