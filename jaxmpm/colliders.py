"""Rigid colliders and the contact velocity projection they share.

A collider is static geometry (``eqx.field(static=True)``) plus differentiable contact
parameters that live in ``params["colliders"][k]`` (``friction`` = Coulomb coefficient
mu_b, ``restitution`` = e), so that ``jax.grad`` reaches them.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .errors import SceneError

CONTACTS = ("sticky", "slip", "friction")
_EPS = 1e-12


def project_velocity(
    v: Float[Array, "... D"],
    normal: Float[Array, "... D"],
    contact: str,
    friction: Float[Array, ""] | float = 0.0,
    restitution: Float[Array, ""] | float = 0.0,
    v_collider: Float[Array, "... D"] | float = 0.0,
) -> Float[Array, "... D"]:
    """Project a velocity against a rigid surface moving with ``v_collider``.

    Only approaching motion (``(v - v_c)·n < 0``) is changed. ``sticky`` returns the
    collider velocity; ``slip`` removes the approaching normal part; ``friction``
    removes it and shrinks the tangential part by ``mu·|v_n|`` (Coulomb, never
    reversing it); a restitution ``e`` sends back ``-e·v_n`` along the normal.

    Arguments:
        v: velocities, ``(..., D)``, m/s.
        normal: unit outward normals of the surface, ``(..., D)``.
        contact: ``"sticky"``, ``"slip"`` or ``"friction"`` (static).
        friction: Coulomb coefficient (used by ``"friction"``).
        restitution: normal restitution coefficient in [0, 1].
        v_collider: the surface's velocity at the same points, m/s.

    Returns:
        The projected velocities, ``(..., D)``.
    """
    if contact not in CONTACTS:
        raise ValueError(f"unknown contact {contact!r}; expected one of {CONTACTS}")
    rel = v - v_collider
    vn = jnp.sum(rel * normal, axis=-1, keepdims=True)
    if contact == "sticky":
        return jnp.zeros_like(rel) + v_collider
    approaching = vn < 0
    tangential = rel - vn * normal
    if contact == "friction":
        vt_norm = jnp.sqrt(jnp.sum(tangential * tangential, axis=-1, keepdims=True) + _EPS)
        scale = jnp.maximum(vt_norm + friction * vn, 0.0) / vt_norm
        tangential = tangential * scale
    projected = tangential - restitution * vn * normal
    return jnp.where(approaching, projected, rel) + v_collider


class Collider(eqx.Module):
    """A rigid collider. Concrete colliders are final subclasses.

    Attributes:
        name: a name used in messages and parameter paths.
        contact: ``"sticky"``, ``"slip"`` or ``"friction"``.
    """

    name: eqx.AbstractVar[str]
    contact: eqx.AbstractVar[str]

    #: The scene ``type`` string of this collider.
    kind: ClassVar[str]

    @abc.abstractmethod
    def signed_distance(
        self, x: Float[Array, "M D"], time: Float[Array, ""]
    ) -> tuple[Float[Array, " M"], Float[Array, "M D"]]:
        """Signed distance (positive outside the solid) and unit normal at points ``x``."""

    def velocity_at(self, x: Float[Array, "M D"], time: Float[Array, ""]) -> Float[Array, "M D"]:
        """Velocity of the collider surface at points ``x`` (m/s); static by default."""
        return jnp.zeros_like(x)


class Plane(Collider):
    """An infinite half-space ``{x : (x - point)·normal <= 0}`` (the solid side).

    Attributes:
        point: a point on the plane, length D, metres.
        normal: the outward unit normal (normalised on construction), length D.
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    point: tuple[float, ...] = eqx.field(static=True)
    normal: tuple[float, ...] = eqx.field(static=True)

    kind: ClassVar[str] = "plane"

    def __init__(self, point, normal, contact: str = "sticky", name: str = "plane"):
        point = tuple(float(p) for p in np.asarray(point, float).reshape(-1))
        n = np.asarray(normal, float).reshape(-1)
        if n.shape != (len(point),):
            raise SceneError(f"collider {name!r}: 'normal' must have {len(point)} components")
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            raise SceneError(f"collider {name!r}: 'normal' must be a non-zero vector, got {n.tolist()}")
        if contact not in CONTACTS:
            raise SceneError(f"collider {name!r}: 'contact' must be one of {CONTACTS}, got {contact!r}")
        self.point = point
        self.normal = tuple(float(c) for c in n / norm)
        self.contact = contact
        self.name = name

    def signed_distance(self, x, time):
        n = jnp.asarray(self.normal, x.dtype)
        sd = (x - jnp.asarray(self.point, x.dtype)) @ n
        return sd, jnp.broadcast_to(n, x.shape)


def plane_from_spec(spec: dict, name: str, dim: int, base_dir) -> Plane:
    point, normal = spec["point"], spec["normal"]
    if len(point) != dim:
        raise SceneError(f"collider {name!r}: 'point' must have {dim} components")
    return Plane(point, normal, contact=spec.get("contact", "sticky"), name=name)


#: Scene ``type`` -> (constructor from a spec dict, required keys, optional keys).
#: Every collider spec may also have ``contact``, ``friction``, ``restitution``, ``name``.
COLLIDER_TYPES: dict[str, tuple] = {
    "plane": (plane_from_spec, ("point", "normal"), ()),
}
