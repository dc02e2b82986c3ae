"""Rigid colliders and the contact velocity projection they share.

A collider is static geometry (``eqx.field(static=True)``) plus differentiable contact
parameters that live in ``params["colliders"][k]`` (``friction`` = Coulomb coefficient
mu_b, ``restitution`` = e), so that ``jax.grad`` reaches them.
"""

from __future__ import annotations

import abc
import functools
from typing import Callable, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .errors import SceneError

CONTACTS = ("sticky", "slip", "friction")
_EPS = 1e-12


def row_dot(a, b, keepdims: bool = False):
    """``sum(a * b, axis=-1)`` written as explicit adds over the (small) last axis.

    XLA's CPU backend emits slow loops for reductions over a last axis of size 2 or 3; the
    unrolled form fuses with its producers (4x faster in the CPIC gather).
    """
    out = a[..., 0] * b[..., 0]
    for d in range(1, a.shape[-1]):
        out = out + a[..., d] * b[..., d]
    return out[..., None] if keepdims else out


def row_matvec(m, v):
    """``einsum("...ij,...j->...i", m, v)`` for small matrices, unrolled (see :func:`row_dot`)."""
    out = m[..., :, 0] * v[..., None, 0]
    for d in range(1, v.shape[-1]):
        out = out + m[..., :, d] * v[..., None, d]
    return out


def rows_times(x, r):
    """``x @ r`` for rows ``x (..., D)`` and a small constant ``r (D, D)``, unrolled."""
    out = x[..., 0:1] * r[0]
    for d in range(1, x.shape[-1]):
        out = out + x[..., d : d + 1] * r[d]
    return out


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


#: Scene ``type`` -> (constructor from a spec dict, required keys, optional keys).
#: Every collider spec may also have ``contact``, ``friction``, ``restitution``, ``name``.
COLLIDER_TYPES: dict[str, tuple] = {}


# =====================================================================================
# Shaped colliders: Box, MeshCollider, GaussianDisks.
#
# Conventions shared by the three (and by ``jaxmpm.cpic``):
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


def asset_path(name: str) -> str:
    """Path of a file shipped in ``jaxmpm/assets`` (``"bunny.obj"`` or ``"meshes/bunny.obj"``).

    Shipped meshes: ``bunny.obj``, ``armadillo.obj`` (Stanford 3D Scanning Repository,
    research use with acknowledgement) and ``bowl.obj`` (open hemisphere, normals into the
    bowl); see ``jaxmpm/assets/meshes/SOURCE.md``.

    Raises:
        FileNotFoundError: no such asset.
    """
    import importlib.resources

    root = importlib.resources.files("jaxmpm") / "assets"
    for candidate in (root / name, root / "meshes" / name):
        if candidate.is_file():
            return str(candidate)
    raise FileNotFoundError(f"no asset named {name!r} in {root}")


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


def _rotation_after(omega, t, dim: int):
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


def _cross_omega(omega, r):
    """``omega x r`` for rows of ``r``; in 2D ``omega`` is a scalar."""
    if r.shape[-1] == 2:
        w = jnp.reshape(omega, ())
        return w * jnp.stack([-r[..., 1], r[..., 0]], axis=-1)
    return jnp.cross(jnp.broadcast_to(jnp.reshape(omega, (3,)), r.shape), r)


def _safe_normalize_np(v, fallback=None):
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
        return c, _rotation_after(w, t, self.dim)

    def to_local(self, x, time, velocity=None, angular_velocity=None):
        """Rest-frame coordinates ``X = c0 + R(t)^T (x - c(t))`` of world points ``x (M, D)``.

        The collision field of a moving collider is built in this frame (on the same grid
        nodes, as the collider sits at t = 0); query it at ``to_local(x, t)`` and rotate the
        normals back with :meth:`to_world_vectors`.
        """
        if velocity is None and angular_velocity is None and not self.moving:
            return x
        c, r = self.rigid_transform(time, velocity, angular_velocity, x.dtype)
        return jnp.asarray(self.pivot, x.dtype) + (x - c) @ r

    def to_world_vectors(self, n, time, angular_velocity=None):
        """Rotate rest-frame vectors (normals) ``n (M, D)`` to the world frame at ``time``."""
        if angular_velocity is None and not self.rotating:
            return n
        _, r = self.rigid_transform(time, None, angular_velocity, n.dtype)
        return n @ r.T

    def velocity_at(self, x, time, velocity=None, angular_velocity=None):
        """Surface velocity ``v + w x (x - c(t))`` at world points ``x (M, D)``, m/s."""
        if velocity is None and angular_velocity is None and not self.moving:
            return jnp.zeros_like(x)
        dtype = x.dtype
        t = jnp.asarray(time).astype(dtype)
        if getattr(self, "motion", None) is not None and velocity is None and angular_velocity is None:
            # Scripted motion: d/dt of x = c(t) + R(t)(X - c0) is c' + R' R^T (x - c).
            (c, r), (dc, dr) = jax.jvp(lambda s: self.rigid_transform(s, dtype=dtype), (t,), (jnp.ones_like(t),))
            return dc + (x - c) @ (dr @ r.T).T
        v = jnp.asarray(self.velocity if velocity is None else velocity).astype(dtype)
        w = jnp.asarray(self.angular_velocity if angular_velocity is None else angular_velocity).astype(dtype)
        c = jnp.asarray(self.pivot, dtype) + v * t
        return v + _cross_omega(w, x - c)

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


def _motion_args(spec: dict, name: str, dim: int) -> dict:
    """Parse ``velocity``, ``angular_velocity`` and ``pivot`` from a collider spec."""
    out = {}
    if "velocity" in spec:
        out["velocity"] = _vector(spec["velocity"], dim, name, "velocity")
    if "angular_velocity" in spec:
        out["angular_velocity"] = _vector(spec["angular_velocity"], 3 if dim == 3 else 1, name, "angular_velocity")
    if "pivot" in spec:
        out["pivot"] = _vector(spec["pivot"], dim, name, "pivot")
    return out


def _vector(value, n: int, name: str, key: str) -> tuple[float, ...]:
    try:
        a = np.asarray(value, float).reshape(-1)
    except (TypeError, ValueError):
        raise SceneError(f"collider {name!r}: {key!r} must be numbers, got {value!r}") from None
    if a.size != n:
        raise SceneError(f"collider {name!r}: {key!r} must have {n} component(s), got {a.size}")
    if not np.all(np.isfinite(a)):
        raise SceneError(f"collider {name!r}: {key!r} must be finite, got {a.tolist()}")
    return tuple(float(c) for c in a)


def _init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, default_pivot, motion=None):
    if contact not in CONTACTS:
        raise SceneError(f"collider {name!r}: 'contact' must be one of {CONTACTS}, got {contact!r}")
    if motion is not None and not callable(motion):
        raise SceneError(f"collider {name!r}: 'motion' must be a callable t -> (c(t), R(t)), got {motion!r}")
    if motion is not None and (velocity is not None or angular_velocity is not None):
        raise SceneError(f"collider {name!r}: give either 'motion' or 'velocity'/'angular_velocity', not both")
    self.motion = motion
    self.name = name
    self.contact = contact
    self.velocity = _vector(np.zeros(dim) if velocity is None else velocity, dim, name, "velocity")
    nw = 3 if dim == 3 else 1
    self.angular_velocity = _vector(
        np.zeros(nw) if angular_velocity is None else angular_velocity, nw, name, "angular_velocity"
    )
    self.pivot = _vector(default_pivot if pivot is None else pivot, dim, name, "pivot")


def _placement(spec: dict, name: str, dim: int):
    """``scale`` (scalar or D-vector, > 0), ``translate`` (D) and ``rotate`` (degrees) keys."""
    scale = np.asarray(spec.get("scale", 1.0), float).reshape(-1)
    if scale.size not in (1, dim) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
        raise SceneError(f"collider {name!r}: 'scale' must be a positive number or {dim} positive numbers")
    translate = np.asarray(_vector(spec.get("translate", np.zeros(dim)), dim, name, "translate"))
    rot = spec.get("rotate", np.zeros(3 if dim == 3 else 1))
    rot = _vector(rot, 3 if dim == 3 else 1, name, "rotate")
    return np.broadcast_to(scale, (dim,)).astype(float), translate, rotation_matrix(rot, dim)


# ------------------------------------------------------------------------------------
# Plane
# ------------------------------------------------------------------------------------


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
        _init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, np.asarray(point), motion)

    def bounds(self) -> np.ndarray:
        """A plane is unbounded: ``[-inf, +inf]`` on every axis."""
        return np.stack([np.full(self.dim, -np.inf), np.full(self.dim, np.inf)])

    def _local_signed_distance(self, X):
        n = jnp.asarray(self.normal, X.dtype)
        sd = (X - jnp.asarray(self.point, X.dtype)) @ n
        return sd, jnp.broadcast_to(n, X.shape)


def plane_from_spec(spec: dict, name: str, dim: int, base_dir) -> Plane:
    """``type = "plane"``: ``point``, ``normal``; optional ``velocity``, ``angular_velocity``, ``pivot``."""
    point, normal = spec["point"], spec["normal"]
    if len(point) != dim:
        raise SceneError(f"collider {name!r}: 'point' must have {dim} components")
    return Plane(point, normal, contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


# ------------------------------------------------------------------------------------
# Box
# ------------------------------------------------------------------------------------


class Box(RigidCollider):
    """A closed solid box: ``[lo, hi]`` rotated by ``rotate`` (degrees) about its centre.

    Attributes:
        lo, hi: corners of the box before rotation, length D, metres.
        rotation: the static rotation ``R0`` (``rotate`` degrees), ``D x D`` nested tuples.
        velocity, angular_velocity, pivot: rigid motion (pivot defaults to the box centre).
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    lo: tuple[float, ...] = eqx.field(static=True)
    hi: tuple[float, ...] = eqx.field(static=True)
    rotation: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "box"

    def __init__(
        self,
        lo,
        hi,
        rotate=None,
        contact: str = "sticky",
        name: str = "box",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        lo_a = np.asarray(lo, float).reshape(-1)
        dim = lo_a.size
        if dim not in (2, 3):
            raise SceneError(f"collider {name!r}: 'lo' must have 2 or 3 components")
        lo_t = _vector(lo_a, dim, name, "lo")
        hi_t = _vector(hi, dim, name, "hi")
        if not all(h > l for l, h in zip(lo_t, hi_t)):
            raise SceneError(f"collider {name!r}: need lo < hi on every axis, got lo={list(lo_t)}, hi={list(hi_t)}")
        nrot = 3 if dim == 3 else 1
        rot = np.zeros(nrot) if rotate is None else _vector(rotate, nrot, name, "rotate")
        self.lo, self.hi = lo_t, hi_t
        self.rotation = tuple(tuple(float(c) for c in row) for row in rotation_matrix(rot, dim))
        centre = 0.5 * (np.asarray(lo_t) + np.asarray(hi_t))
        _init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, centre, motion)

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.lo) + np.asarray(self.hi))

    @property
    def half_extent(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.hi) - np.asarray(self.lo))

    def bounds(self) -> np.ndarray:
        r = np.asarray(self.rotation)
        ext = np.abs(r) @ self.half_extent
        return np.stack([self.center - ext, self.center + ext])

    def _local_signed_distance(self, X):
        dtype = X.dtype
        r = jnp.asarray(self.rotation, dtype)
        y = (X - jnp.asarray(self.center, dtype)) @ r  # box axes coordinates
        q = jnp.abs(y) - jnp.asarray(self.half_extent, dtype)
        qp = jnp.maximum(q, 0.0)
        out2 = jnp.sum(qp * qp, axis=-1)
        outside = out2 > 0
        out_len = jnp.sqrt(jnp.where(outside, out2, 1.0))
        qmax = jnp.max(q, axis=-1)
        sd = jnp.where(outside, out_len, 0.0) + jnp.minimum(qmax, 0.0)
        sgn = jnp.where(y >= 0, 1.0, -1.0).astype(dtype)
        n_out = sgn * qp / out_len[:, None]
        face = _one_hot(jnp.argmax(q, axis=-1), y.shape[-1], dtype)
        n_loc = jnp.where(outside[:, None], n_out, sgn * face)
        return sd, n_loc @ r.T


def _one_hot(index, n, dtype):
    """One-hot rows of ``index`` over ``n`` classes."""
    return (index[..., None] == jnp.arange(n)).astype(dtype)


def box_from_spec(spec: dict, name: str, dim: int, base_dir) -> Box:
    lo = _vector(spec["lo"], dim, name, "lo")
    hi = _vector(spec["hi"], dim, name, "hi")
    rot = spec.get("rotate")
    return Box(lo, hi, rotate=rot, contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


# ------------------------------------------------------------------------------------
# Triangle meshes (3D) and segment sets (2D)
# ------------------------------------------------------------------------------------


def closest_on_simplices(p, a, b, c=None, xp=np):
    """Closest points on triangles ``(a, b, c)`` (3D) or segments ``(a, b)`` (2D), row-wise.

    Works with ``xp = numpy`` or ``xp = jax.numpy`` (only elementwise ops and ``where``).

    Returns:
        ``q`` the closest points, ``region`` (int: 0 inside the face, 1..3 vertex a/b/c,
        4..6 edge ab/bc/ca; 2D: 0 inside, 1 vertex a, 2 vertex b) and ``inside`` — whether
        the orthogonal projection of ``p`` onto the face's plane/line lies in the closed
        face (tolerance 1e-7 in barycentric units).
    """
    dot = lambda u, v: xp.sum(u * v, axis=-1)  # noqa: E731
    tol = 1e-7
    if c is None:
        ab = b - a
        den = dot(ab, ab)
        t = dot(p - a, ab) / xp.where(den > 0, den, 1.0)
        tc = xp.clip(t, 0.0, 1.0)
        q = a + tc[..., None] * ab
        region = xp.where(t <= 0, 1, xp.where(t >= 1, 2, 0))
        inside = (t >= -tol) & (t <= 1 + tol)
        return q, region, inside
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    def safe_div(num, den):
        return num / xp.where(den != 0, den, 1.0)

    # Barycentric coordinates of the plane projection (interior formula).
    s = va + vb + vc
    bv, bw = safe_div(vb, s), safe_div(vc, s)
    q = a + bv[..., None] * ab + bw[..., None] * ac
    region = xp.zeros(d1.shape, dtype=np.int8 if xp is np else jnp.int8)
    # Edges and vertices, in reverse order of Ericson's precedence so the first test wins.
    bc_mask = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t_bc = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    q = xp.where(bc_mask[..., None], b + t_bc[..., None] * (c - b), q)
    region = xp.where(bc_mask, 5, region)
    ac_mask = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t_ac = safe_div(d2, d2 - d6)
    q = xp.where(ac_mask[..., None], a + t_ac[..., None] * ac, q)
    region = xp.where(ac_mask, 6, region)
    c_mask = (d6 >= 0) & (d5 <= d6)
    q = xp.where(c_mask[..., None], c, q)
    region = xp.where(c_mask, 3, region)
    ab_mask = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t_ab = safe_div(d1, d1 - d3)
    q = xp.where(ab_mask[..., None], a + t_ab[..., None] * ab, q)
    region = xp.where(ab_mask, 4, region)
    b_mask = (d3 >= 0) & (d4 <= d3)
    q = xp.where(b_mask[..., None], b, q)
    region = xp.where(b_mask, 2, region)
    a_mask = (d1 <= 0) & (d2 <= 0)
    q = xp.where(a_mask[..., None], a, q)
    region = xp.where(a_mask, 1, region)
    bu = 1.0 - bv - bw
    inside = (s != 0) & (bu >= -tol) & (bv >= -tol) & (bw >= -tol)
    return q, region, inside


def _simplex_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit "+" normals and areas (lengths in 2D) of triangles / segments."""
    if vertices.shape[1] == 3:
        tri = vertices[faces]
        cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        size = 0.5 * np.linalg.norm(cr, axis=-1)
        return _safe_normalize_np(cr), size
    seg = vertices[faces]
    t = seg[:, 1] - seg[:, 0]
    size = np.linalg.norm(t, axis=-1)
    return _safe_normalize_np(np.stack([t[:, 1], -t[:, 0]], axis=-1)), size


def _mesh_topology(vertices: np.ndarray, faces: np.ndarray, name: str) -> dict:
    """Consistency, closedness and feature pseudo-normals of a triangle mesh or segment set.

    Returns a dict with ``face_normals``, ``vertex_normals`` (angle-weighted pseudo-normals),
    ``vertex_boundary``; in 3D also ``edges (E, 2)``, ``face_edges (F, 3)`` (edge k of a
    face joins its corners k and k+1), ``edge_normals``, ``edge_boundary``; and ``closed``.

    Raises:
        SceneError: inconsistent winding (a directed edge used twice, or in 2D a vertex
            where two segments both start or both end).
    """
    nv, dim = vertices.shape
    fn, _ = _simplex_normals(vertices, faces)
    out: dict = {"face_normals": fn}
    if dim == 2:
        outdeg = np.bincount(faces[:, 0], minlength=nv)
        indeg = np.bincount(faces[:, 1], minlength=nv)
        if np.any(outdeg > 1) or np.any(indeg > 1):
            raise SceneError(
                f"collider {name!r}: inconsistent winding — segments must form chains a->b->c "
                "(a vertex is the start, or the end, of two segments)"
            )
        deg = outdeg + indeg
        vn = np.zeros((nv, 2))
        np.add.at(vn, faces[:, 0], fn)
        np.add.at(vn, faces[:, 1], fn)
        out["vertex_normals"] = _safe_normalize_np(vn)
        out["vertex_boundary"] = deg == 1
        out["closed"] = bool(np.all(deg[deg > 0] == 2))
        return out
    f = faces
    directed = np.stack([f, np.roll(f, -1, axis=1)], axis=-1).reshape(-1, 2)  # (3F, 2)
    key = directed[:, 0].astype(np.int64) * nv + directed[:, 1]
    if np.unique(key).size != key.size:
        raise SceneError(
            f"collider {name!r}: inconsistent winding — some edge is used twice in the same "
            "direction (flipped faces or a non-manifold edge); trimesh.repair.fix_winding may fix it"
        )
    und = np.sort(directed, axis=1)
    edges, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    face_edges = inverse.reshape(-1, 3)
    en = np.zeros((len(edges), 3))
    np.add.at(en, inverse, np.repeat(fn, 3, axis=0))
    fallback = np.zeros((len(edges), 3))
    fallback[inverse] = np.repeat(fn, 3, axis=0)
    out["edges"] = edges
    out["face_edges"] = face_edges
    out["edge_normals"] = _safe_normalize_np(en, fallback)
    out["edge_boundary"] = counts == 1
    # Angle-weighted vertex pseudo-normals (Baerentzen & Aanaes 2005).
    tri = vertices[f]
    vn = np.zeros((nv, 3))
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        cosang = np.sum(_safe_normalize_np(e1) * _safe_normalize_np(e2), axis=-1)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        np.add.at(vn, f[:, k], ang[:, None] * fn)
    out["vertex_normals"] = _safe_normalize_np(vn)
    vb = np.zeros(nv, bool)
    vb[edges[counts == 1].reshape(-1)] = True
    out["vertex_boundary"] = vb
    out["closed"] = bool(np.all(counts == 2))
    return out


class MeshCollider(RigidCollider):
    """A triangle mesh (3D) or a set of segments (2D) placed in the world at t = 0.

    Open surfaces are fine (a bowl, a sheet): the side of a point comes from the normal of
    its nearest face (or the pseudo-normal of the nearest edge/vertex), never from ray
    parity. Closed meshes/polygons are re-oriented on construction so that their normals
    point outward (``+`` = outside).

    Attributes:
        vertices: ``(V, D)`` metres (rest frame = world at t = 0), :class:`StaticArray`.
        faces: ``(F, D)`` int vertex indices (triangles in 3D, segments in 2D).
        face_normals: ``(F, D)`` unit ``+`` normals.
        vertex_normals, vertex_boundary: angle-weighted pseudo-normals, and whether the
            vertex lies on the boundary of an open surface.
        edges, face_edges, edge_normals, edge_boundary: 3D only (``None`` in 2D).
        closed: whether the surface is closed (watertight / closed polygons).
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    vertices: StaticArray = eqx.field(static=True)
    faces: StaticArray = eqx.field(static=True)
    face_normals: StaticArray = eqx.field(static=True)
    vertex_normals: StaticArray = eqx.field(static=True)
    vertex_boundary: StaticArray = eqx.field(static=True)
    edges: StaticArray | None = eqx.field(static=True)
    face_edges: StaticArray | None = eqx.field(static=True)
    edge_normals: StaticArray | None = eqx.field(static=True)
    edge_boundary: StaticArray | None = eqx.field(static=True)
    closed: bool = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "mesh"

    def __init__(
        self,
        vertices,
        faces,
        contact: str = "sticky",
        name: str = "mesh",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        v = np.asarray(vertices, float)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] not in (2, 3) or len(v) == 0:
            raise SceneError(f"collider {name!r}: vertices must be an (V, 2) or (V, 3) array, got shape {v.shape}")
        dim = v.shape[1]
        if f.size == 0:
            raise SceneError(f"collider {name!r}: the mesh has no faces")
        if f.ndim != 2 or f.shape[1] != dim or not np.issubdtype(f.dtype, np.integer):
            raise SceneError(
                f"collider {name!r}: faces must be an integer (F, {dim}) array "
                f"({'triangles' if dim == 3 else 'segments'}), got shape {f.shape}"
            )
        if f.min() < 0 or f.max() >= len(v):
            raise SceneError(f"collider {name!r}: face indices out of range [0, {len(v)})")
        if not np.all(np.isfinite(v)):
            raise SceneError(f"collider {name!r}: vertices contain NaN or infinite values")
        f = f.astype(np.int64)
        # Drop degenerate faces (repeated vertices or zero area/length): no normal.
        scale = float(np.max(np.ptp(v, axis=0))) or 1.0
        _, size = _simplex_normals(v, f)
        distinct = np.all(f != np.roll(f, 1, axis=1), axis=1)
        keep = distinct & (size > (1e-12 * scale ** (dim - 1)))
        f = f[keep]
        if len(f) == 0:
            raise SceneError(f"collider {name!r}: the mesh has no faces (all are degenerate)")
        topo = _mesh_topology(v, f, name)
        if topo["closed"]:
            fn, size = _simplex_normals(v, f)
            centroid = np.mean(v[f], axis=1)
            signed = np.sum(size * np.sum(centroid * fn, axis=-1)) / dim  # volume / area
            if signed < 0:  # inward-facing closed surface: flip so that "+" is outside
                f = f[:, ::-1].copy()
                topo = _mesh_topology(v, f, name)
        self.vertices = StaticArray(v)
        self.faces = StaticArray(f)
        self.face_normals = StaticArray(topo["face_normals"])
        self.vertex_normals = StaticArray(topo["vertex_normals"])
        self.vertex_boundary = StaticArray(topo["vertex_boundary"])
        if dim == 3:
            self.edges = StaticArray(topo["edges"])
            self.face_edges = StaticArray(topo["face_edges"])
            self.edge_normals = StaticArray(topo["edge_normals"])
            self.edge_boundary = StaticArray(topo["edge_boundary"])
        else:
            self.edges = self.face_edges = self.edge_normals = self.edge_boundary = None
        self.closed = topo["closed"]
        used = v[np.unique(f)]
        default_pivot = 0.5 * (used.min(axis=0) + used.max(axis=0))
        _init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, default_pivot, motion)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> np.ndarray:
        v = np.asarray(self.vertices)[np.unique(np.asarray(self.faces))]
        return np.stack([v.min(axis=0), v.max(axis=0)])

    def to_trimesh(self):
        """The (3D) mesh as a ``trimesh.Trimesh`` (rest frame), e.g. for rendering."""
        import trimesh

        return trimesh.Trimesh(np.asarray(self.vertices), np.asarray(self.faces), process=False)

    def region_normals(self) -> np.ndarray:
        """Per face, the pseudo-normal of each closest-point region, ``(F, 7, 3)`` (2D: ``(F, 3, 2)``).

        Region codes as in :func:`closest_on_simplices`: 0 face, 1..3 vertices,
        4..6 edges ab, bc, ca.
        """
        f = np.asarray(self.faces)
        fn = np.asarray(self.face_normals)
        vn = np.asarray(self.vertex_normals)[f]  # (F, D, D)
        if self.dim == 2:
            return np.concatenate([fn[:, None], vn], axis=1)
        en = np.asarray(self.edge_normals)[np.asarray(self.face_edges)]  # (F, 3, 3)
        return np.concatenate([fn[:, None], vn, en], axis=1)

    def _local_signed_distance(self, X):
        """Exact brute-force signed distance over all faces (O(M F)); sign from the nearest
        feature's pseudo-normal. Meant for checks, small meshes and few points — the
        simulator uses the precomputed collision field (``jaxmpm.cpic``)."""
        corners, rn, valid = _mesh_tables(self)
        return _brute_mesh_sdf(
            X, jnp.asarray(corners, X.dtype), jnp.asarray(rn, X.dtype), jnp.asarray(valid)
        )


_SDF_CHUNK = 256


@functools.lru_cache(maxsize=16)
def _mesh_tables(mesh: MeshCollider):
    """Face corners, region pseudo-normals and a validity mask, padded to whole chunks."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    rn = mesh.region_normals()
    nf, dim = f.shape
    nchunk = -(-nf // _SDF_CHUNK)
    pad = nchunk * _SDF_CHUNK - nf
    corners = np.concatenate([v[f], np.repeat(v[f[:1]], pad, axis=0)])
    rn = np.concatenate([rn, np.repeat(rn[:1], pad, axis=0)])
    valid = np.arange(nchunk * _SDF_CHUNK) < nf
    return (
        corners.reshape(nchunk, _SDF_CHUNK, dim, dim),
        rn.reshape(nchunk, _SDF_CHUNK, *rn.shape[1:]),
        valid.reshape(nchunk, _SDF_CHUNK),
    )


@jax.jit
def _brute_mesh_sdf(X, corners, rn, valid):
    """Scan over face chunks keeping, per point, the nearest face's signed distance/normal."""
    dtype = X.dtype
    m, dim = X.shape

    def body(carry, inp):
        best_d2, best_s, best_n = carry
        cor, reg_n, ok = inp
        p = X[:, None, :]
        a, b = cor[None, :, 0], cor[None, :, 1]
        c = cor[None, :, 2] if dim == 3 else None
        q, region, _ = closest_on_simplices(p, a, b, c, xp=jnp)
        diff = p - q
        d2 = jnp.where(ok[None, :], jnp.sum(diff * diff, axis=-1), jnp.inf)
        j = jnp.argmin(d2, axis=1)
        d2j = jnp.take_along_axis(d2, j[:, None], axis=1)[:, 0]
        regj = jnp.take_along_axis(region, j[:, None], axis=1)[:, 0].astype(jnp.int32)
        pn = reg_n[j, regj]  # (M, D) pseudo-normal of the nearest feature
        dj = jnp.take_along_axis(diff, j[:, None, None], axis=1)[:, 0]
        sgn = jnp.where(jnp.sum(dj * pn, axis=-1) >= 0, 1.0, -1.0).astype(dtype)
        has_len = d2j > 0
        dirn = dj / jnp.sqrt(jnp.where(has_len, d2j, 1.0))[:, None]
        use_pn = ((regj == 0) | ~has_len)[:, None]
        nrm = jnp.where(use_pn, pn, sgn[:, None] * dirn)
        better = d2j < best_d2
        return (
            jnp.where(better, d2j, best_d2),
            jnp.where(better, sgn, best_s),
            jnp.where(better[:, None], nrm, best_n),
        ), None

    init = (jnp.full((m,), jnp.inf, dtype), jnp.ones((m,), dtype), jnp.zeros((m, dim), dtype))
    (d2, s, n), _ = jax.lax.scan(body, init, (corners, rn, valid))
    pos = d2 > 0
    dist = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
    return s * dist, n


def _resolve_path(path, base_dir, name: str) -> str:
    import os

    p = os.path.expanduser(str(path))
    candidates = [p] if os.path.isabs(p) else [os.path.join(str(base_dir or "."), p), p]
    for c in candidates:
        if os.path.isfile(c):
            return c
    try:
        return asset_path(p)
    except FileNotFoundError:
        pass
    raise SceneError(
        f"collider {name!r}: file {str(path)!r} not found (looked in {candidates[0]!r} and in the shipped assets)"
    )


def load_mesh(path, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a 3D mesh file (any format trimesh reads; scenes are merged).

    Raises:
        SceneError: the file cannot be read as a triangle mesh, or has no faces.
    """
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # noqa: BLE001 - any loader failure is a scene error
        raise SceneError(f"collider {name!r}: cannot load mesh {str(path)!r}: {exc}") from exc
    faces = getattr(mesh, "faces", None)
    if faces is None or len(faces) == 0:
        raise SceneError(f"collider {name!r}: mesh {str(path)!r} has no faces")
    return np.asarray(mesh.vertices, float), np.asarray(faces, np.int64)


def _polyline(points, segments, closed: bool, name: str) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise SceneError(f"collider {name!r}: 'points' must be a list of at least two [x, y] points")
    if segments is None:
        n = len(pts)
        seg = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
        if closed:
            seg = np.concatenate([seg, [[n - 1, 0]]])
    else:
        seg = np.asarray(segments)
        if seg.ndim != 2 or seg.shape[1] != 2 or not np.issubdtype(seg.dtype, np.integer):
            raise SceneError(f"collider {name!r}: 'segments' must be pairs of point indices")
    return pts, seg


def load_polyline_npz(path, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """A 2D segment set from an ``.npz``: ``points (P, 2)``; optional ``segments (S, 2)`` int
    (default: the chain 0-1-2-...), optional ``closed`` (bool, default False: the chain is
    closed back to point 0 when True)."""
    try:
        with np.load(str(path)) as data:
            if "points" not in data:
                raise SceneError(f"collider {name!r}: {str(path)!r} has no 'points' array")
            pts = data["points"]
            seg = data["segments"] if "segments" in data else None
            closed = bool(data["closed"]) if "closed" in data else False
    except SceneError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise SceneError(f"collider {name!r}: cannot read {str(path)!r}: {exc}") from exc
    return _polyline(pts, seg, closed, name)


def mesh_from_spec(spec: dict, name: str, dim: int, base_dir) -> MeshCollider:
    """``type = "mesh"``: ``path`` (3D: any trimesh format, resolved against the scene folder,
    then the shipped assets; 2D: an ``.npz`` polyline) or, in 2D, inline ``points`` (+
    ``segments``, ``closed``); then ``scale`` (about the file's origin), ``rotate`` (degrees),
    ``translate``, in that order."""
    if ("path" in spec) == ("points" in spec):
        raise SceneError(
            f"collider {name!r}: give 'path'" + (" or 'points' (not both)" if dim == 2 else "")
        )
    if "points" in spec:
        if dim != 2:
            raise SceneError(f"collider {name!r}: inline 'points' are for 2D scenes; use 'path' in 3D")
        v, f = _polyline(spec["points"], spec.get("segments"), bool(spec.get("closed", False)), name)
    else:
        for key in ("segments", "closed"):
            if key in spec:
                raise SceneError(f"collider {name!r}: {key!r} goes with inline 'points', not with 'path'")
        path = _resolve_path(spec["path"], base_dir, name)
        if dim == 2:
            if not path.endswith(".npz"):
                raise SceneError(f"collider {name!r}: a 2D mesh collider needs an .npz polyline, got {path!r}")
            v, f = load_polyline_npz(path, name)
        else:
            v, f = load_mesh(path, name)
    scale, translate, rot = _placement(spec, name, dim)
    v = (v * scale) @ rot.T + translate
    return MeshCollider(v, f, contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


# ------------------------------------------------------------------------------------
# Gaussian disks (2D Gaussian surfels)
# ------------------------------------------------------------------------------------


def _quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices from quaternions ``(w, x, y, z)`` (normalised here), ``(K, 3, 3)``."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def _any_perpendicular(n: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each unit row of ``n`` (3D)."""
    ref = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    return _safe_normalize_np(np.cross(n, ref))


def orient_normals(centers, normals, k: int = 10, weights=None) -> np.ndarray:
    """Make sign-ambiguous surfel normals consistent (Hoppe et al. 1992 style).

    Builds a symmetric k-nearest-neighbour graph on the centres with edge cost
    ``1 - |n_i . n_j| + |e_ij . n_i| + |e_ij . n_j|`` (``e_ij`` the unit vector between the
    centres: the last two terms steer the propagation along the surface rather than across
    two close sheets), takes its minimum spanning tree, and propagates the sign along it so
    that neighbours agree (``n_i . n_j >= 0``). Each connected piece is then flipped as a
    whole if needed so that ``sum_k w_k (c_k - c) . n_k >= 0`` (``c`` the piece's centroid,
    ``w`` the weights, e.g. disk areas) — outward for closed shapes (the sum is 3x the enclosed
    volume); for an open piece this picks the side facing away from its centroid.

    Returns:
        The re-signed normals, ``(K, D)`` (NumPy).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
    from scipy.spatial import cKDTree

    x = np.asarray(centers, float)
    n = _safe_normalize_np(np.asarray(normals, float))
    kk = len(x)
    w = np.ones(kk) if weights is None else np.asarray(weights, float)
    sign = np.ones(kk)
    if kk > 1:
        nb = min(k + 1, kk)
        _, idx = cKDTree(x).query(x, nb)
        rows = np.repeat(np.arange(kk), nb - 1)
        cols = idx[:, 1:].reshape(-1)
        keep = rows != cols
        rows, cols = rows[keep], cols[keep]
        lo_, hi_ = np.minimum(rows, cols), np.maximum(rows, cols)
        pairs = np.unique(np.stack([lo_, hi_], axis=1), axis=0)
        i, j = pairs[:, 0], pairs[:, 1]
        e = _safe_normalize_np(x[j] - x[i])
        cost = (
            1.0
            - np.abs(np.sum(n[i] * n[j], -1))
            + np.abs(np.sum(e * n[i], -1))
            + np.abs(np.sum(e * n[j], -1))
            + 1e-6
        )
        graph = coo_matrix((cost, (i, j)), shape=(kk, kk)).tocsr()
        tree = minimum_spanning_tree(graph)
        tree = tree + tree.T
        ncomp, labels = connected_components(tree, directed=False)
        parent = np.arange(kk)
        for comp in range(ncomp):
            root = int(np.flatnonzero(labels == comp)[0])
            _, pred = breadth_first_order(tree, root, directed=False, return_predecessors=True)
            members = pred >= 0
            parent[members] = pred[members]
        rel = np.where(np.sum(n * n[parent], -1) >= 0, 1.0, -1.0)
        rel[parent == np.arange(kk)] = 1.0
        # Product of relative signs up to the root, by pointer jumping.
        acc, anc = rel.copy(), parent.copy()
        while np.any(anc[anc] != anc):
            acc = acc * acc[anc]
            anc = anc[anc]
        sign = acc
    else:
        labels = np.zeros(1, int)
        ncomp = 1
    n = n * sign[:, None]
    for comp in range(int(np.max(labels)) + 1):
        sel = labels == comp
        c = np.average(x[sel], axis=0, weights=w[sel])
        if np.sum(w[sel] * np.sum((x[sel] - c) * n[sel], -1)) < 0:
            n[sel] = -n[sel]
    return n


def _read_ply_vertices(path) -> dict[str, np.ndarray]:
    """The ``vertex`` element of a PLY file (ascii or binary) as ``{property: (K,) array}``."""
    types = {
        "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
        "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
        "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
        "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
    }  # fmt: skip
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError("not a PLY file")
        fmt, elements = None, []
        while True:
            line = fh.readline()
            if not line:
                raise ValueError("PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property":
                if words[1] == "list":
                    elements[-1][2].append((words[-1], None))
                else:
                    elements[-1][2].append((words[-1], types[words[1]]))
            elif words[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise ValueError("the first PLY element must be 'vertex'")
        _, count, props = elements[0]
        if any(t is None for _, t in props):
            raise ValueError("list properties on vertices are not supported")
        if fmt == "ascii":
            rows = [fh.readline().split() for _ in range(count)]
            table = np.asarray(rows, float).reshape(count, len(props))
            return {p: table[:, i] for i, (p, _) in enumerate(props)}
        endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if endian is None:
            raise ValueError(f"unknown PLY format {fmt!r}")
        dt = np.dtype([(p, endian + t) for p, t in props])
        data = np.frombuffer(fh.read(dt.itemsize * count), dtype=dt, count=count)
        return {p: data[p].astype(float) for p, _ in props}


def load_disks(path, name: str = "disks") -> dict[str, np.ndarray]:
    """Surfels from an ``.npz`` or a 2DGS-style ``.ply``.

    ``.npz`` keys: ``centers (K, D)``; ``normals (K, D)`` or (3D) ``rotations (K, 4)``
    quaternions ``(w, x, y, z)`` whose third column is the normal and first two the tangent
    axes; ``scales`` — standard deviations along the tangent axes, ``(K, D-1)`` or ``(K,)``
    (isotropic), linear metres; optional ``tangents (K, 3)`` (the first tangent axis, 3D;
    default any perpendicular), optional ``opacity (K,)`` in [0, 1] (default 1).

    ``.ply`` (2DGS export): ``x, y, z``; ``rot_0..rot_3`` (quaternion w, x, y, z; the normal is
    the rotation's third column) or ``nx, ny, nz``; ``scale_0, scale_1`` log standard
    deviations; ``opacity`` as a logit. Returns a dict with the npz keys.
    """
    p = str(path)
    try:
        if p.endswith(".npz"):
            with np.load(p) as data:
                out = {k: np.asarray(data[k]) for k in data.files}
        else:
            props = _read_ply_vertices(p)
            if not all(k in props for k in ("x", "y", "z")):
                raise ValueError("PLY vertices need x, y, z")
            out = {"centers": np.stack([props["x"], props["y"], props["z"]], axis=1)}
            if all(f"rot_{i}" in props for i in range(4)):
                out["rotations"] = np.stack([props[f"rot_{i}"] for i in range(4)], axis=1)
            elif all(k in props for k in ("nx", "ny", "nz")):
                out["normals"] = np.stack([props["nx"], props["ny"], props["nz"]], axis=1)
            if "scale_0" in props:
                s1 = props.get("scale_1", props["scale_0"])
                out["scales"] = np.exp(np.stack([props["scale_0"], s1], axis=1))
            if "opacity" in props:
                out["opacity"] = 1.0 / (1.0 + np.exp(-props["opacity"]))
    except Exception as exc:  # noqa: BLE001
        raise SceneError(f"collider {name!r}: cannot read disks from {p!r}: {exc}") from exc
    if "centers" not in out:
        raise SceneError(f"collider {name!r}: {p!r} has no 'centers'")
    if "scales" not in out:
        raise SceneError(f"collider {name!r}: {p!r} has no 'scales' (scale_0/scale_1 in a PLY)")
    return out


class GaussianDisks(RigidCollider):
    """A set of 2D Gaussian surfels (planar elliptical disks) used as a collision surface.

    Disk k has centre ``c_k``, unit normal ``n_k`` (its ``+`` side), tangent axes
    ``t_k1, t_k2`` with standard deviations ``s_k1, s_k2`` (2D: one tangent), and opacity
    ``o_k``. A point belongs to the disk's footprint when
    ``sum_j ((x - c_k) . t_kj / s_kj)^2 <= cutoff^2``. Disks with ``o_k < min_opacity`` are
    dropped. Normals are made consistent on construction (``orient``): ``"knn"`` (default,
    :func:`orient_normals`: minimum-spanning-tree propagation over a k-NN graph, each piece then
    facing away from its centroid, i.e. outward for closed shapes), ``"centroid"`` (each disk
    independently faces away from the centroid of all centres; for star-shaped closed shapes)
    or ``"none"`` (trust the given signs). ``flip`` reverses all normals afterwards.

    Attributes:
        centers ``(K, D)``, normals ``(K, D)``, tangents ``(K, D-1, D)``, scales ``(K, D-1)``,
        opacity ``(K,)``: :class:`StaticArray`.
        cutoff: footprint radius in standard deviations.
    """

    name: str = eqx.field(static=True)
    contact: str = eqx.field(static=True)
    centers: StaticArray = eqx.field(static=True)
    normals: StaticArray = eqx.field(static=True)
    tangents: StaticArray = eqx.field(static=True)
    scales: StaticArray = eqx.field(static=True)
    opacity: StaticArray = eqx.field(static=True)
    cutoff: float = eqx.field(static=True)
    velocity: tuple[float, ...] = eqx.field(static=True)
    angular_velocity: tuple[float, ...] = eqx.field(static=True)
    pivot: tuple[float, ...] = eqx.field(static=True)
    motion: Callable | None = eqx.field(static=True)

    kind: ClassVar[str] = "disks"

    def __init__(
        self,
        centers,
        normals=None,
        scales=None,
        tangents=None,
        opacity=None,
        rotations=None,
        cutoff: float = 3.0,
        min_opacity: float = 0.05,
        orient: str = "knn",
        flip: bool = False,
        contact: str = "sticky",
        name: str = "disks",
        velocity=None,
        angular_velocity=None,
        pivot=None,
        motion=None,
    ):
        c = np.asarray(centers, float)
        if c.ndim != 2 or c.shape[1] not in (2, 3) or len(c) == 0:
            raise SceneError(f"collider {name!r}: 'centers' must be a non-empty (K, 2) or (K, 3) array, got {c.shape}")
        kk, dim = c.shape
        if not np.all(np.isfinite(c)):
            raise SceneError(f"collider {name!r}: disk centres contain NaN or infinite values")
        if rotations is not None:
            if dim != 3:
                raise SceneError(f"collider {name!r}: 'rotations' are for 3D disks")
            q = np.asarray(rotations, float).reshape(kk, 4)
            qn = np.linalg.norm(q, axis=-1)
            if not np.all(np.isfinite(qn)) or np.any(qn < 1e-12):
                bad = int(np.flatnonzero(~(qn >= 1e-12))[0])
                raise SceneError(f"collider {name!r}: disk {bad} has a zero rotation quaternion (no normal)")
            r = _quaternion_to_matrix(q)
            n, t1 = r[:, :, 2], r[:, :, 0]
        else:
            if normals is None:
                raise SceneError(f"collider {name!r}: disks need 'normals' (or 'rotations')")
            n = np.asarray(normals, float).reshape(kk, dim)
            t1 = None if tangents is None else np.asarray(tangents, float).reshape(kk, dim)
        nn = np.linalg.norm(n, axis=-1)
        bad = ~(np.isfinite(nn) & (nn > 1e-12))
        if np.any(bad):
            first = int(np.flatnonzero(bad)[0])
            raise SceneError(
                f"collider {name!r}: {int(bad.sum())} disk(s) have zero or invalid normals (first: disk {first})"
            )
        n = n / nn[:, None]
        if scales is None:
            raise SceneError(f"collider {name!r}: disks need 'scales'")
        s = np.asarray(scales, float)
        s = s.reshape(kk, -1)
        if s.shape[1] == 1:
            s = np.repeat(s, dim - 1, axis=1)
        if s.shape[1] != dim - 1:
            raise SceneError(f"collider {name!r}: 'scales' must be (K,) or (K, {dim - 1}), got {np.shape(scales)}")
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise SceneError(f"collider {name!r}: disk scales must be positive and finite")
        o = np.ones(kk) if opacity is None else np.asarray(opacity, float).reshape(kk)
        if not np.all(np.isfinite(o)):
            raise SceneError(f"collider {name!r}: disk opacity contains NaN")
        if not (np.isfinite(cutoff) and cutoff > 0):
            raise SceneError(f"collider {name!r}: 'cutoff' must be positive, got {cutoff}")
        keep = o >= min_opacity
        if not np.any(keep):
            raise SceneError(f"collider {name!r}: every disk has opacity below min_opacity={min_opacity}")
        c, n, s, o = c[keep], n[keep], s[keep], o[keep]
        t1 = None if t1 is None else t1[keep]
        if orient == "knn":
            n = orient_normals(c, n, weights=np.prod(s, axis=1))
        elif orient == "centroid":
            n = n * np.where(np.sum((c - c.mean(axis=0)) * n, -1) >= 0, 1.0, -1.0)[:, None]
        elif orient != "none":
            raise SceneError(f"collider {name!r}: 'orient' must be 'knn', 'centroid' or 'none', got {orient!r}")
        if flip:
            n = -n
        if dim == 2:
            tan = np.stack([-n[:, 1], n[:, 0]], axis=-1)[:, None, :]
        else:
            if t1 is None:
                if np.any(np.abs(s[:, 0] - s[:, 1]) > 1e-12 * np.maximum(s[:, 0], s[:, 1])):
                    raise SceneError(f"collider {name!r}: anisotropic disk scales need 'tangents' or 'rotations'")
                u = _any_perpendicular(n)
            else:
                u = t1 - np.sum(t1 * n, -1, keepdims=True) * n
                u = _safe_normalize_np(u, _any_perpendicular(n))
            tan = np.stack([u, np.cross(n, u)], axis=1)
        self.centers = StaticArray(c)
        self.normals = StaticArray(n)
        self.tangents = StaticArray(tan)
        self.scales = StaticArray(s)
        self.opacity = StaticArray(o)
        self.cutoff = float(cutoff)
        bounds = self._bounds_np(c, tan, s, float(cutoff))
        _init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, bounds.mean(axis=0), motion)

    @staticmethod
    def _half_extents(tan, s, cutoff):
        # Bounding half-extent of each elliptical footprint along every world axis.
        return cutoff * np.sqrt(np.sum((s[:, :, None] * tan) ** 2, axis=1))

    @classmethod
    def _bounds_np(cls, c, tan, s, cutoff):
        ext = cls._half_extents(tan, s, cutoff)
        return np.stack([(c - ext).min(axis=0), (c + ext).max(axis=0)])

    @property
    def num_disks(self) -> int:
        return len(self.centers)

    def bounds(self) -> np.ndarray:
        return self._bounds_np(
            np.asarray(self.centers), np.asarray(self.tangents), np.asarray(self.scales), self.cutoff
        )

    def _local_signed_distance(self, X):
        """Approximate signed distance to the union of footprints (brute force, O(M K)):
        ``sqrt(h^2 + e^2)`` with ``h`` the offset along the normal and ``e`` the in-plane
        distance beyond the footprint's ellipse (exact for round disks), signed by ``h``; the
        normal is the nearest disk's."""
        dtype = X.dtype
        c = jnp.asarray(np.asarray(self.centers), dtype)
        n = jnp.asarray(np.asarray(self.normals), dtype)
        tan = jnp.asarray(np.asarray(self.tangents), dtype)
        s = jnp.asarray(np.asarray(self.scales), dtype)
        d = X[:, None, :] - c[None]  # (M, K, D)
        h = jnp.sum(d * n[None], -1)
        a = jnp.einsum("mkd,kjd->mkj", d, tan)  # in-plane coordinates
        rho2 = jnp.sum((a / s[None]) ** 2, -1)
        a2 = jnp.sum(a * a, -1)
        pos = rho2 > 0
        rho = jnp.sqrt(jnp.where(pos, rho2, 1.0))
        alen = jnp.sqrt(jnp.where(pos, a2, 1.0))
        e = jnp.where(pos & (rho > self.cutoff), alen * (1.0 - self.cutoff / rho), 0.0)
        d2 = h * h + e * e
        j = jnp.argmin(d2, axis=1)
        d2j = jnp.take_along_axis(d2, j[:, None], 1)[:, 0]
        hj = jnp.take_along_axis(h, j[:, None], 1)[:, 0]
        ok = d2j > 0
        dist = jnp.where(ok, jnp.sqrt(jnp.where(ok, d2j, 1.0)), 0.0)
        return jnp.where(hj >= 0, dist, -dist), n[j]


def disks_from_spec(spec: dict, name: str, dim: int, base_dir) -> GaussianDisks:
    """``type = "disks"``: ``path`` (.npz or 2DGS .ply, see :func:`load_disks`); optional
    ``scale`` (uniform), ``rotate``, ``translate`` (applied in that order), ``cutoff`` (3.0),
    ``min_opacity`` (0.05), ``orient`` ("knn"), ``flip`` (false)."""
    path = _resolve_path(spec["path"], base_dir, name)
    data = load_disks(path, name)
    c = np.asarray(data["centers"], float)
    if c.ndim != 2 or c.shape[1] != dim:
        raise SceneError(f"collider {name!r}: disk centres must be (K, {dim}) in a {dim}D scene, got {c.shape}")
    scale, translate, rot = _placement(spec, name, dim)
    if np.ptp(scale) > 0:
        raise SceneError(f"collider {name!r}: disks accept only a uniform 'scale'")
    k = float(scale[0])
    normals = data.get("normals")
    tangents = data.get("tangents")
    rotations = data.get("rotations")
    if rotations is not None:
        r = _quaternion_to_matrix(np.asarray(rotations, float).reshape(-1, 4))
        r = np.einsum("ij,kjl->kil", rot, r)
        normals, tangents, rotations = r[:, :, 2], r[:, :, 0], None
    if normals is not None:
        normals = np.asarray(normals, float) @ rot.T
    if tangents is not None:
        tangents = np.asarray(tangents, float) @ rot.T
    return GaussianDisks(
        (c * k) @ rot.T + translate,
        normals=normals,
        scales=np.asarray(data["scales"], float) * k,
        tangents=tangents,
        opacity=data.get("opacity"),
        cutoff=float(spec.get("cutoff", 3.0)),
        min_opacity=float(spec.get("min_opacity", 0.05)),
        orient=str(spec.get("orient", "knn")),
        flip=bool(spec.get("flip", False)),
        contact=spec.get("contact", "sticky"),
        name=name,
        **_motion_args(spec, name, dim),
    )


_MOTION_KEYS = ("velocity", "angular_velocity", "pivot")
COLLIDER_TYPES.update(
    {
        "plane": (plane_from_spec, ("point", "normal"), _MOTION_KEYS),
        "box": (box_from_spec, ("lo", "hi"), ("rotate",) + _MOTION_KEYS),
        "mesh": (
            mesh_from_spec,
            (),
            ("path", "points", "segments", "closed", "scale", "translate", "rotate") + _MOTION_KEYS,
        ),
        "disks": (
            disks_from_spec,
            ("path",),
            ("scale", "translate", "rotate", "cutoff", "min_opacity", "orient", "flip") + _MOTION_KEYS,
        ),
    }
)
