"""The abstract collider, rigid motion, and the contact velocity projection all colliders share.

A collider is static geometry (``eqx.field(static=True)``) plus differentiable contact
parameters that live in ``params["colliders"][k]`` (``friction`` = Coulomb coefficient
mu_b, ``restitution`` = e), so that ``jax.grad`` reaches them.
"""

from __future__ import annotations

import abc
import copy
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..constitutive.base import matmul
from ..errors import SceneError
from ..fusion import sum_last

CONTACTS = ("sticky", "slip", "friction")
_EPS = 1e-12


def row_dot(a, b, keepdims: bool = False):
    """``sum(a * b, axis=-1)`` as explicit adds over the (small) last axis
    (:func:`jaxmpm.fusion.sum_last`)."""
    return sum_last(a * b, keepdims=keepdims)


def row_matvec(m, v):
    """``einsum("...ij,...j->...i", m, v)`` for small matrices, unrolled (see :func:`row_dot`)."""
    out = m[..., :, 0] * v[..., None, 0]
    for d in range(1, v.shape[-1]):
        out = out + m[..., :, d] * v[..., None, d]
    return out


def rows_times(x, r):
    """``x @ r`` for rows ``x (..., D)`` and a small matrix ``r (D, D)``: unrolled products
    (:func:`jaxmpm.constitutive.base.matmul`), whose reverse mode is two dot ops. The
    transposes of the unrolled broadcast products were sums over 3-wide axes and over every
    row, which XLA's CPU backend hands to YNNPACK fusions (18 of them in the backward pass of
    a moving collider's contact, 12 CPU ms per step; docs/benchmarks.md, session 30)."""
    return matmul(x[..., None, :], r)[..., 0, :]


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
    vn = row_dot(rel, normal, keepdims=True)
    if contact == "sticky":
        return jnp.zeros_like(rel) + v_collider
    approaching = vn < 0
    tangential = rel - vn * normal
    if contact == "friction":
        vt_norm = jnp.sqrt(row_dot(tangential, tangential, keepdims=True) + _EPS)
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


# =====================================================================================
# Conventions shared by every collider (Plane, Box, MeshCollider, GaussianDisks) and
# by ``jaxmpm.cpic``:
#
# * Units are metres, seconds, radians for angular velocity; ``rotate`` keys are degrees.
# * Every collider has an outward/"+" side. For closed solids (boxes, closed meshes,
#   closed polylines) "+" is outside and "-" inside. For open surfaces (a bowl, a sheet,
#   an open polyline, a set of disks) "+" is the side the face normals point to.
#   3D triangles are counter-clockwise seen from "+" (right-hand rule); a 2D segment
#   a -> b has its "+" normal on its right, ``n = (t_y, -t_x)``, so a counter-clockwise
#   closed polygon has outward normals.
# * Motion is rigid: velocity ``v`` (m/s) and angular velocity ``w`` (rad/s; a vector in
#   3D, a scalar in 2D) are constant. The collider turns about its ``pivot`` ``c0`` (by
#   default the centre of its bounding box at t = 0) which moves along
#   ``c(t) = c0 + v t``; its rotation is ``R(t) = exp(t [w]x)``. A point ``X`` of the
#   collider as placed at t = 0 (the *rest frame*, which coincides with the world frame at
#   t = 0) is at ``x = c(t) + R(t) (X - c0)`` at time t, and moves with the surface
#   velocity ``v + w x (x - c(t))`` (2D: ``w x r = w (-r_y, r_x)``).
# * Geometry is static NumPy data (:class:`StaticArray`, hashable) so colliders can be
#   jit arguments and closures alike; nothing about the geometry is traced.
# =====================================================================================


class StaticArray:
    """A read-only NumPy array that is hashable, for ``eqx.field(static=True)`` use.

    Equality is by value (shape, dtype and contents); the hash is computed once.
    ``np.asarray(static_array)`` returns the underlying (read-only) array.
    """

    __slots__ = ("array", "_hash")

    def __init__(self, array):
        a = np.array(array, copy=True)
        a.setflags(write=False)
        self.array = a
        self._hash = hash((a.shape, a.dtype.str, a.tobytes()))

    def __array__(self, dtype=None, copy=None):
        return self.array if dtype is None else self.array.astype(dtype)

    def __hash__(self):
        return self._hash

    def __eq__(self, other):
        if self is other:
            return True
        if not isinstance(other, StaticArray) or self._hash != other._hash:
            return False
        a, b = self.array, other.array
        return a.shape == b.shape and a.dtype == b.dtype and bool(np.array_equal(a, b))

    def __len__(self):
        return len(self.array)

    @property
    def shape(self):
        return self.array.shape

    def __repr__(self):
        return f"StaticArray(shape={self.array.shape}, dtype={self.array.dtype})"


def rotation_matrix(degrees, dim: int) -> np.ndarray:
    """Rotation matrix from ``rotate`` angles in degrees (NumPy, static).

    3D: angles ``(a, b, c)`` about the fixed x, y and z axes applied in that order,
    ``R = Rz(c) @ Ry(b) @ Rx(a)``. 2D: one angle, counter-clockwise.
    """
    deg = np.asarray(degrees, float).reshape(-1)
    if dim == 2:
        if deg.size != 1:
            raise ValueError("a 2D rotation is one angle in degrees")
        t = np.deg2rad(deg[0])
        return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    if deg.size != 3:
        raise ValueError("a 3D rotation is three angles (x, y, z) in degrees")
    a, b, c = np.deg2rad(deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


def rotation_after(omega, t, dim: int):
    """``exp(t [omega]x)`` in jnp: 2D angle ``omega t``; 3D Rodrigues, safe at ``omega = 0``."""
    if dim == 2:
        theta = jnp.reshape(omega, ()) * t
        c, s = jnp.cos(theta), jnp.sin(theta)
        return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])
    rv = jnp.reshape(omega, (3,)) * t
    th2 = jnp.sum(rv * rv)
    small = th2 < 1e-8
    th2_safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2_safe)
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / th2_safe)
    zero = jnp.zeros((), rv.dtype)
    k = jnp.stack(
        [
            jnp.stack([zero, -rv[2], rv[1]]),
            jnp.stack([rv[2], zero, -rv[0]]),
            jnp.stack([-rv[1], rv[0], zero]),
        ]
    )
    return jnp.eye(3, dtype=rv.dtype) + a * k + b * (k @ k)


def cross_omega(omega, r):
    """``omega x r`` for rows of ``r``; in 2D ``omega`` is a scalar."""
    if r.shape[-1] == 2:
        w = jnp.reshape(omega, ())
        return w * jnp.stack([-r[..., 1], r[..., 0]], axis=-1)
    return jnp.cross(jnp.broadcast_to(jnp.reshape(omega, (3,)), r.shape), r)


def safe_normalize_np(v, fallback=None):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = n[..., 0] > 1e-300
    out = np.where(ok[..., None], v / np.where(ok[..., None], n, 1.0), 0.0)
    if fallback is not None:
        out = np.where(ok[..., None], out, fallback)
    return out



class RigidCollider(Collider):
    """A collider with a shape and constant rigid motion (abstract; see the conventions above).

    Attributes (of every concrete subclass):
        velocity: pivot velocity ``v``, length D, m/s.
        angular_velocity: ``w`` in rad/s, length 3 in 3D, length 1 in 2D.
        pivot: ``c0``, the centre of rotation at t = 0, length D, metres.
        motion: optional scripted motion, a callable ``motion(t) -> (c, R)`` (jnp-traceable,
            ``t`` a scalar array) giving the pivot's world position ``c (D,)`` and the rotation
            ``R (D, D)`` at time t, so that a rest-frame point X sits at ``c + R (X - c0)``.
            It replaces ``velocity``/``angular_velocity``; the surface velocity is its time
            derivative (``jax.jvp``). ``motion(0)`` need not be the identity placement: the
            collision field lives in the rest frame (the geometry as constructed).
    """

    velocity: eqx.AbstractVar[tuple[float, ...]]
    angular_velocity: eqx.AbstractVar[tuple[float, ...]]
    pivot: eqx.AbstractVar[tuple[float, ...]]

    @property
    def dim(self) -> int:
        return len(self.pivot)

    @property
    def moving(self) -> bool:
        """True if the collider moves: a scripted ``motion``, or a non-zero (angular) velocity."""
        return getattr(self, "motion", None) is not None or any(c != 0.0 for c in self.velocity + self.angular_velocity)

    @property
    def rotating(self) -> bool:
        """True if the collider may rotate (a scripted ``motion`` or a non-zero angular velocity)."""
        return getattr(self, "motion", None) is not None or any(c != 0.0 for c in self.angular_velocity)

    def with_contact(self, contact: str | None = None, motion=None) -> "RigidCollider":
        """A copy with another contact law and/or scripted ``motion`` (validated as in the
        constructor) and the same shape, so a collision field built from this collider's
        geometry stays valid for the copy (its constructor is not run again: a mesh's
        field and pre-processing are kept).

        ``contact`` and ``motion`` are static fields, which ``eqx.tree_at`` cannot replace;
        this is the one place that sets them on a copy.
        """
        contact = self.contact if contact is None else contact
        if contact not in CONTACTS:
            raise SceneError(f"collider {self.name!r}: 'contact' must be one of {CONTACTS}, got {contact!r}")
        if motion is not None and not callable(motion):
            raise SceneError(f"collider {self.name!r}: 'motion' must be a callable t -> (c(t), R(t)), got {motion!r}")
        new = copy.copy(self)
        object.__setattr__(new, "contact", contact)
        if motion is not None:
            object.__setattr__(new, "motion", motion)
        return new

    @abc.abstractmethod
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounds of the collider at t = 0, ``(2, D)`` NumPy (lo, hi)."""

    def rigid_transform(self, time, velocity=None, angular_velocity=None, dtype=None):
        """The rigid placement at ``time``: ``(c(t), R(t))``, with ``x = c(t) + R(t)(X - c0)``.

        Arguments:
            time: seconds (scalar, may be traced).
            velocity, angular_velocity: override the static motion (e.g. with fitted,
                traced values); ``None`` uses the collider's own.
            dtype: the float dtype of the result (default: that of ``time``/the default).

        Returns:
            ``c (D,)`` and ``R (D, D)`` as jnp arrays.
        """
        dtype = dtype or jnp.result_type(float)
        t = jnp.asarray(time).astype(dtype)
        motion = getattr(self, "motion", None)
        if motion is not None and velocity is None and angular_velocity is None:
            c, r = motion(t)
            return jnp.asarray(c).astype(dtype), jnp.asarray(r).astype(dtype)
        v = jnp.asarray(self.velocity if velocity is None else velocity).astype(dtype)
        w = jnp.asarray(self.angular_velocity if angular_velocity is None else angular_velocity).astype(dtype)
        c = jnp.asarray(self.pivot, dtype) + v * t
        return c, rotation_after(w, t, self.dim)

    def to_local(self, x, time, velocity=None, angular_velocity=None):
        """Rest-frame coordinates ``X = c0 + R(t)^T (x - c(t))`` of world points ``x (M, D)``.

        The collision field of a moving collider is built in this frame (on the same grid
        nodes, as the collider sits at t = 0); query it at ``to_local(x, t)`` and rotate the
        normals back with :meth:`to_world_vectors`.
        """
        if velocity is None and angular_velocity is None and not self.moving:
            return x
        c, r = self.rigid_transform(time, velocity, angular_velocity, x.dtype)
        return jnp.asarray(self.pivot, x.dtype) + rows_times(x - c, r)

    def to_world_vectors(self, n, time, angular_velocity=None):
        """Rotate rest-frame vectors (normals) ``n (M, D)`` to the world frame at ``time``."""
        if angular_velocity is None and not self.rotating:
            return n
        _, r = self.rigid_transform(time, None, angular_velocity, n.dtype)
        return rows_times(n, r.T)

    def velocity_at(self, x, time, velocity=None, angular_velocity=None):
        """Surface velocity ``v + w x (x - c(t))`` at world points ``x (M, D)``, m/s."""
        if velocity is None and angular_velocity is None and not self.moving:
            return jnp.zeros_like(x)
        dtype = x.dtype
        t = jnp.asarray(time).astype(dtype)
        if getattr(self, "motion", None) is not None and velocity is None and angular_velocity is None:
            # Scripted motion: d/dt of x = c(t) + R(t)(X - c0) is c' + R' R^T (x - c).
            (c, r), (dc, dr) = jax.jvp(lambda s: self.rigid_transform(s, dtype=dtype), (t,), (jnp.ones_like(t),))
            return dc + rows_times(x - c, (dr @ r.T).T)
        v = jnp.asarray(self.velocity if velocity is None else velocity).astype(dtype)
        w = jnp.asarray(self.angular_velocity if angular_velocity is None else angular_velocity).astype(dtype)
        c = jnp.asarray(self.pivot, dtype) + v * t
        return v + cross_omega(w, x - c)

    def signed_distance(self, x, time):
        """Signed distance (``+`` side positive) and unit ``+``-side normal at world points."""
        sd, n = self._local_signed_distance(self.to_local(x, time))
        return sd, self.to_world_vectors(n, time)

    @abc.abstractmethod
    def _local_signed_distance(self, X):
        """Signed distance and normal at rest-frame points (jnp)."""


def rigid_transform(collider: Collider, time, dtype=None):
    """``(c(t), R(t))`` of any collider; colliders without motion give ``(0, I)``."""
    if isinstance(collider, RigidCollider):
        return collider.rigid_transform(time, dtype=dtype)
    dtype = dtype or jnp.result_type(float)
    d = len(getattr(collider, "point", (0.0, 0.0, 0.0)))
    return jnp.zeros((d,), dtype), jnp.eye(d, dtype=dtype)


def vector(value, n: int, where: str) -> np.ndarray:
    """``value`` as a finite float vector of ``n`` components (a scalar counts as one).

    Arguments:
        value: a number or a list of numbers from a scene spec.
        n: the required number of components.
        where: what the value is, for the message (e.g. ``"bodies[0].velocity"``).

    Returns:
        ``(n,)`` float64 NumPy array.

    Raises:
        SceneError: not numbers, the wrong count, or NaN/infinite entries.
    """
    try:
        a = np.asarray(value, float).reshape(-1)
    except (TypeError, ValueError):
        raise SceneError(f"{where} must be a list of {n} numbers, got {value!r}") from None
    if a.size != n or not np.all(np.isfinite(a)):
        raise SceneError(f"{where} must be a list of {n} finite numbers, got {value!r}")
    return a


def static_vector(value, n: int, name: str, key: str) -> tuple[float, ...]:
    """:func:`vector` for a collider's static field: a tuple of floats (hashable)."""
    return tuple(float(c) for c in vector(value, n, f"collider {name!r}: {key!r}"))


def init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, default_pivot, motion=None):
    """Set the fields every :class:`RigidCollider` shares (name, contact, motion), validated.

    Called from the concrete colliders' ``__init__``; ``default_pivot`` is the shape's own
    centre, used when ``pivot`` is None.
    """
    if contact not in CONTACTS:
        raise SceneError(f"collider {name!r}: 'contact' must be one of {CONTACTS}, got {contact!r}")
    if motion is not None and not callable(motion):
        raise SceneError(f"collider {name!r}: 'motion' must be a callable t -> (c(t), R(t)), got {motion!r}")
    if motion is not None and (velocity is not None or angular_velocity is not None):
        raise SceneError(f"collider {name!r}: give either 'motion' or 'velocity'/'angular_velocity', not both")
    self.motion = motion
    self.name = name
    self.contact = contact
    self.velocity = static_vector(np.zeros(dim) if velocity is None else velocity, dim, name, "velocity")
    nw = 3 if dim == 3 else 1
    self.angular_velocity = static_vector(
        np.zeros(nw) if angular_velocity is None else angular_velocity, nw, name, "angular_velocity"
    )
    self.pivot = static_vector(default_pivot if pivot is None else pivot, dim, name, "pivot")
