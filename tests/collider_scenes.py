"""Small collider scenes shared by the collider tests (CI-sized: 2D or coarse 3D)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxmpm.colliders import MeshCollider
from jaxmpm.constitutive import MATERIALS
from jaxmpm.model import Body, Model
from jaxmpm.state import Grid
from jaxmpm.step import simulate

#: Materials dropped on colliders (CFL-safe at the substeps used below).
FLUID = {"model": "newtonian", "mu": 1.0, "kappa": 1e4}
SAND = {"model": "sand", "friction_angle": 35.0, "E": 2e5}
ELASTIC = {"model": "elastic", "E": 1e5, "nu": 0.3}


def rollout(model, params, checkpoint=None):
    """Jitted rollout; fails on NaN. Returns the trajectory with NumPy ``x``/``v``/``times``."""
    traj = jax.jit(lambda p: simulate(model, p, checkpoint=checkpoint))(params)
    assert not np.asarray(traj.nan).any(), "the rollout produced NaN"
    return np.asarray(traj.times), np.asarray(traj.x), np.asarray(traj.v)


def depth_inside(collider, times, x, margin: float = 0.1, chunk: int = 8192) -> np.ndarray:
    """Per frame and particle, how deep it is inside the collider (``-signed distance``; < 0 outside).

    Uses the collider's exact (brute-force) signed distance at each frame's time, for the
    particles within ``margin`` of a static collider's bounding box (``-margin`` elsewhere).
    """
    out = np.full(x.shape[:2], -margin)
    flat_t = np.broadcast_to(np.asarray(times)[:, None], x.shape[:2]).reshape(-1)
    flat_x = x.reshape(-1, x.shape[-1])
    pick = np.arange(len(flat_x))
    if not getattr(collider, "moving", True):
        lo, hi = collider.bounds()
        pick = pick[np.all((flat_x > lo - margin) & (flat_x < hi + margin), axis=1)]
    depth = np.empty(len(pick))
    for t in np.unique(flat_t[pick]):
        sel = np.flatnonzero(flat_t[pick] == t)
        for s in range(0, len(sel), chunk):
            part = sel[s : s + chunk]
            sd, _ = collider.signed_distance(jnp.asarray(flat_x[pick[part]]), jnp.asarray(t, x.dtype))
            depth[part] = -np.asarray(sd)
    out.reshape(-1)[pick] = depth
    return out


class Incline:
    """A 2D elastic block on a rotated segment (an inclined mesh plane) under real gravity."""

    def __init__(
        self,
        theta: float,
        mu: float,
        *,
        dx: float = 0.02,
        frames: int = 8,
        substeps: int = 60,
        v0: float = 0.0,
        E: float = 2e5,
        contact: str = "friction",
        collision: str = "cpic",
        dtype=jnp.float32,
    ):
        th = math.radians(theta)
        self.down = np.array([math.cos(th), -math.sin(th)])  # down the slope
        self.normal = np.array([math.sin(th), math.cos(th)])  # the segment's "+" side (up)
        self.origin = np.array([0.1, 0.7])
        # a -> b runs up the slope so that the right-hand normal points up
        a, b = self.origin + 1.0 * self.down, self.origin - 0.05 * self.down
        ramp = MeshCollider(np.stack([a, b]), [[0, 1]], contact=contact, name="ramp")
        h = dx / 2
        s, n = np.arange(0.1, 0.26, h) + h / 2, np.arange(0.0, 0.08, h) + h / 2
        S, N = np.meshgrid(s, n, indexing="ij")
        x0 = self.origin + S.reshape(-1, 1) * self.down + N.reshape(-1, 1) * self.normal
        body = Body(name="block", material=MATERIALS["elastic"](), x0=jnp.asarray(x0, dtype),
                    vol0=jnp.full((len(x0),), h * h, dtype))
        self.model = Model(grid=Grid((0.0, 0.0), (1.0, 1.0), dx), bodies=(body,), colliders=(ramp,),
                           frame_dt=1 / 24, substeps=substeps, frames=frames, collision=collision)
        self.params = {
            "gravity": jnp.asarray([0.0, -9.8], dtype),
            "bodies": ({"E": jnp.asarray(E, dtype), "nu": jnp.asarray(0.3, dtype),
                        "density": jnp.asarray(1000.0, dtype), "velocity": jnp.asarray(v0 * self.down, dtype)},),
            "colliders": ({"friction": jnp.asarray(mu, dtype), "restitution": jnp.asarray(0.0, dtype)},),
        }
        self.expected = 9.8 * (math.sin(th) - mu * math.cos(th))
        self.dx = dx

    def height(self, x: np.ndarray) -> np.ndarray:
        """Height of points above the ramp's line."""
        return (x - self.origin) @ self.normal
