"""The closed solid box collider, optionally rotated."""

from __future__ import annotations

from typing import Callable, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import SceneError
from .base import RigidCollider, init_motion, rotation_matrix, static_vector

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
        lo_t = static_vector(lo_a, dim, name, "lo")
        hi_t = static_vector(hi, dim, name, "hi")
        if not all(h > l for l, h in zip(lo_t, hi_t)):
            raise SceneError(f"collider {name!r}: need lo < hi on every axis, got lo={list(lo_t)}, hi={list(hi_t)}")
        nrot = 3 if dim == 3 else 1
        rot = np.zeros(nrot) if rotate is None else static_vector(rotate, nrot, name, "rotate")
        self.lo, self.hi = lo_t, hi_t
        self.rotation = tuple(tuple(float(c) for c in row) for row in rotation_matrix(rot, dim))
        centre = 0.5 * (np.asarray(lo_t) + np.asarray(hi_t))
        init_motion(self, name, contact, dim, velocity, angular_velocity, pivot, centre, motion)

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
