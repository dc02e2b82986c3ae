"""The infinite half-space collider (PAC-NeRF's floor)."""

from __future__ import annotations

from typing import Callable, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import SceneError
from .base import RigidCollider, init_motion

class Plane(RigidCollider):
    """An infinite half-space ``{x : (x - point)·normal <= 0}`` (the solid side).

    Planes are applied analytically to grid nodes in every collision mode (PAC-NeRF's floor):
    a half-space has a global inside, so it cannot be tunnelled through and needs no
    particle-wise treatment. A plane may move rigidly like any collider (``velocity``,
    ``angular_velocity`` about ``pivot`` = ``point`` by default, or a scripted ``motion``).

    Attributes:
        point: a point on the plane at t = 0, length D, metres.
        normal: the outward unit normal at t = 0 (normalised on construction), length D.
        velocity, angular_velocity, pivot, motion: rigid motion (see :class:`RigidCollider`).
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    point: tuple[float, ...] = eqx.field(static=True)
    normal: tuple[float, ...] = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "plane"

    def __init__(
        self,
        point,
        normal,
        contact: str = "sticky",
        name: str = "plane",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        point = tuple(float(p) for p in np.asarray(point, float).reshape(-1))
        dim = len(point)
        if dim not in (2, 3):
            raise SceneError(f"collider {name!r}: 'point' must have 2 or 3 components")
        n = np.asarray(normal, float).reshape(-1)
        if n.shape != (dim,):
            raise SceneError(f"collider {name!r}: 'normal' must have {dim} components")
        norm = float(np.linalg.norm(n))
        if not np.isfinite(norm) or norm == 0.0:
            raise SceneError(f"collider {name!r}: 'normal' must be a non-zero vector, got {n.tolist()}")
        self.point = point
        self.normal = tuple(float(c) for c in n / norm)
        init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, np.asarray(point), motion)

    def bounds(self) -> np.ndarray:
        """A plane is unbounded: ``[-inf, +inf]`` on every axis."""
        return np.stack([np.full(self.dim, -np.inf), np.full(self.dim, np.inf)])

    def signed_distance(self, x, time):
        """Signed distance (``+`` side positive) and unit normal at world points ``x (M, D)``.

        The distance to a plane is affine in the point, so a moving plane is placed once at
        ``time`` (its point and normal moved) instead of taking every query point to its rest
        frame and every normal back: on a 3D grid that is two ``(M, D) x (D, D)`` products
        fewer per substep."""
        if not self.moving:
            return self._local_signed_distance(x)
        c, r = self.rigid_transform(time, dtype=x.dtype)
        n = r @ jnp.asarray(self.normal, x.dtype)
        point = c + r @ (jnp.asarray(self.point, x.dtype) - jnp.asarray(self.pivot, x.dtype))
        return (x - point) @ n, jnp.broadcast_to(n, x.shape)

    def _local_signed_distance(self, X):
        n = jnp.asarray(self.normal, X.dtype)
        sd = (X - jnp.asarray(self.point, X.dtype)) @ n
        return sd, jnp.broadcast_to(n, X.shape)
