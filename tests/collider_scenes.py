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


# ------------------------------------------------------------------------------------------
# "A collider is a collider": the same drop onto every kind and thickness of collider
# ------------------------------------------------------------------------------------------

#: Materials of the thickness drop (stiff enough to rest, CFL-safe at ``drop_substeps``).
DROP_MATERIALS = {
    "sand": {"model": "sand", "friction_angle": 30.0, "density": 2000.0},
    "newtonian": {"model": "newtonian", "mu": 200.0, "kappa": 1e5},
    "elastic": ELASTIC,
}
#: Box thicknesses of the sweep, in cells.
THICKNESSES = (0.1, 0.3, 0.5, 1.0, 1.5)
#: Thickness of the "thick" box, in cells (more than the stencil: no opposed nodes).
THICK = 8.0
#: Height of the colliders' top surface on a node row (``on_row``), metres; between two rows
#: it is half a cell higher.
DROP_TOP = 0.3
#: Drop: the body starts this far above the top surface, at this speed (m, m/s).
DROP_GAP, DROP_SPEED = 0.04, 1.0


def drop_top(dx: float, on_row: bool) -> float:
    """Height of the top surface: on the node row at :data:`DROP_TOP` or half a cell above it."""
    return DROP_TOP + (0.0 if on_row else 0.5 * dx)


def _write_square_mesh(folder, top: float) -> str:
    """An open, two-triangle square ``[0.2, 0.8]^2`` at height ``top``, ``+`` side up (.obj)."""
    path = f"{folder}/square_{top:.5f}.obj"
    with open(path, "w") as f:
        for x, z in ((0.2, 0.2), (0.8, 0.2), (0.8, 0.8), (0.2, 0.8)):
            f.write(f"v {x} {top} {z}\n")
        f.write("f 1 3 2\nf 1 4 3\n")  # counter-clockwise seen from +y
    return path


def _write_disks(folder, top: float, dim: int, dx: float) -> str:
    """Gaussian disks (sigma = dx, 2 dx apart) sampling the top surface ``[0.2, 0.8]^(D-1)``, normals up."""
    axis = np.arange(0.2 + dx, 0.8, 2 * dx)
    tangential = np.stack(np.meshgrid(*[axis] * (dim - 1), indexing="ij"), -1).reshape(-1, dim - 1)
    centers = np.insert(tangential, 1, top, axis=1)
    normals = np.zeros_like(centers)
    normals[:, 1] = 1.0
    path = f"{folder}/disks_{dim}d_{top:.5f}.npz"
    np.savez(path, centers=centers, normals=normals, scales=np.full((len(centers), dim - 1), dx))
    return path


def drop_collider(kind: str, dim: int, dx: float, top: float, folder=None, thickness: float = THICK) -> dict:
    """The collider spec whose top surface is at ``top`` over ``[0.2, 0.8]^(D-1)``.

    ``kind``: ``plane`` (analytic, unbounded), ``box`` (``thickness`` cells thick, below
    ``top``), ``mesh`` (zero thickness: a polyline in 2D, a triangulated square in 3D),
    ``disks`` (:func:`_write_disks`). Files go to ``folder``.
    """
    lo, hi = [0.2] * dim, [0.8] * dim
    if kind == "plane":
        return {"type": "plane", "name": "c", "point": [0.0, top, 0.0][:dim], "normal": [0.0, 1.0, 0.0][:dim]}
    if kind == "box":
        lo[1], hi[1] = top - thickness * dx, top
        return {"type": "box", "name": "c", "lo": lo, "hi": hi}
    if kind == "mesh" and dim == 2:
        return {"type": "mesh", "name": "c", "points": [[0.8, top], [0.2, top]]}
    if kind == "mesh":
        return {"type": "mesh", "name": "c", "path": _write_square_mesh(folder, top)}
    if kind == "disks":
        return {"type": "disks", "name": "c", "path": _write_disks(folder, top, dim, dx)}
    raise ValueError(kind)


def drop_substeps(dim: int) -> tuple[float, int, int]:
    """``dx``, substeps per frame and frames of the drop (stress-wave CFL <= 0.5, 0.4 s)."""
    return (0.02, 80, 20) if dim == 2 else (0.05, 40, 20)


def drop_spec(dim: int, material: str, collider: dict, top: float, collision: str = "cpic") -> dict:
    """A block (0.16 x 0.1 m in 2D, 0.2 x 0.1 x 0.2 m in 3D) dropped at 1 m/s from 4 cm above ``top``."""
    dx, substeps, frames = drop_substeps(dim)
    half = 0.08 if dim == 2 else 0.1
    lo = [0.5 - half, top + DROP_GAP, 0.5 - half][:dim]
    hi = [0.5 + half, top + DROP_GAP + 0.1, 0.5 + half][:dim]
    return {
        "dim": dim, "dx": dx, "domain": {"lo": [0.0] * dim, "hi": [1.0] * dim}, "gravity": [0.0, -9.8, 0.0][:dim],
        "frames": frames, "frame_dt": 0.02, "substeps": substeps, "collision": collision,
        "bodies": [{"shape": "box", "lo": lo, "hi": hi, "velocity": [0.0, -DROP_SPEED, 0.0][:dim],
                    "material": dict(DROP_MATERIALS[material])}],
        "colliders": [collider],
    }


def body_volume(model, state) -> float:
    """``sum J V0`` (m^D): J is the stored volume ratio of a Newtonian fluid (``aux``), det F otherwise."""
    from jaxmpm.constitutive import Newtonian

    parts = []
    for body, sl in zip(model.bodies, model.body_slices()):
        if isinstance(body.material, Newtonian):
            J = np.asarray(state.aux[sl])
        else:
            J = np.linalg.det(np.asarray(state.F[sl], np.float64))
        parts.append(np.sum(J * np.asarray(state.vol0[sl])))
    return float(sum(parts))


def pile(x: np.ndarray, top: float) -> dict:
    """What a user sees of a pile resting on a surface at ``top``: its height (highest particle
    above ``top``), footprint (extent along x), centre of mass and the lowest particle (m)."""
    return {
        "height": float(x[:, 1].max() - top),
        "footprint": float(np.ptp(x[:, 0])),
        "com": x.mean(axis=0),
        "lowest": float(x[:, 1].min() - top),
    }


def drop_run(spec: dict):
    """Simulate a drop spec; returns the scene, the trajectory (NumPy ``x``) and the final state."""
    from jaxmpm.scene import load_scene

    scene = load_scene(spec)
    traj = jax.jit(lambda p: simulate(scene.model, p, checkpoint=None))(scene.params)
    return scene, traj, np.asarray(traj.x)
