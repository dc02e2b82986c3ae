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


def depth_inside(collider, times, x, margin: float = 0.1, chunk: int = 4096) -> np.ndarray:
    """Per frame and particle, how deep it is inside the collider (``-signed distance``; < 0 outside).

    Uses the collider's exact (brute-force) signed distance at each frame's time, for the
    particles within ``margin`` of a static collider's bounding box (``-margin`` elsewhere).
    A static collider is asked once for all frames' particles. The points go in blocks of
    ``chunk`` (the last one padded; fewer points: padded to a power of two), so that a
    collider's distance compiles once or twice, not once per frame.
    """
    out = np.full(x.shape[:2], -margin)
    flat_t = np.broadcast_to(np.asarray(times)[:, None], x.shape[:2]).reshape(-1)
    flat_x = x.reshape(-1, x.shape[-1])
    pick = np.arange(len(flat_x))
    static = not getattr(collider, "moving", True)
    if static:
        lo, hi = collider.bounds()
        pick = pick[np.all((flat_x > lo - margin) & (flat_x < hi + margin), axis=1)]
    depth = np.empty(len(pick))
    signed_distance = jax.jit(lambda points, t: collider.signed_distance(points, t)[0])
    groups = [np.arange(len(pick))] if static else [np.flatnonzero(flat_t[pick] == t) for t in np.unique(flat_t[pick])]
    for sel in groups:
        t = jnp.asarray(flat_t[pick[sel[0]]] if len(sel) else 0.0, x.dtype)
        for s in range(0, len(sel), chunk):
            part = sel[s : s + chunk]
            size = chunk if len(sel) > chunk else 1 << max(len(part) - 1, 0).bit_length()
            points = flat_x[pick[np.pad(part, (0, size - len(part)), mode="edge")]]
            depth[part] = -np.asarray(signed_distance(jnp.asarray(points), t))[: len(part)]
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


#: Spacing of the stations along x (one collider and one body each), metres; a collider
#: spans +-0.3 m about its station's centre (and [0.2, 0.8] along z in 3D).
STATION = 0.8


def station_centre(i: int) -> float:
    return 0.5 + STATION * i


def _write_square_mesh(folder, x0: float, top: float) -> str:
    """An open, two-triangle square ``[x0 - 0.3, x0 + 0.3] x [0.2, 0.8]`` at height ``top``, ``+`` up (.obj)."""
    path = f"{folder}/square_{x0:.3f}_{top:.5f}.obj"
    with open(path, "w") as f:
        for x, z in ((x0 - 0.3, 0.2), (x0 + 0.3, 0.2), (x0 + 0.3, 0.8), (x0 - 0.3, 0.8)):
            f.write(f"v {x} {top} {z}\n")
        f.write("f 1 3 2\nf 1 4 3\n")  # counter-clockwise seen from +y
    return path


def _write_disks(folder, x0: float, top: float, dim: int, dx: float) -> str:
    """Gaussian disks (sigma = dx, 2 dx apart) sampling the same top surface, normals up."""
    axes = [np.arange(x0 - 0.3 + dx, x0 + 0.3, 2 * dx)] + [np.arange(0.2 + dx, 0.8, 2 * dx)] * (dim - 2)
    tangential = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim - 1)
    centers = np.insert(tangential, 1, top, axis=1)
    normals = np.zeros_like(centers)
    normals[:, 1] = 1.0
    path = f"{folder}/disks_{dim}d_{x0:.3f}_{top:.5f}.npz"
    np.savez(path, centers=centers, normals=normals, scales=np.full((len(centers), dim - 1), dx))
    return path


def drop_collider(kind: str, dim: int, dx: float, top: float, x0: float, folder=None, thickness: float = THICK,
                  name: str = "c") -> dict:
    """The collider spec whose top surface is at ``top`` over ``[x0 - 0.3, x0 + 0.3]`` (x
    ``[0.2, 0.8]`` along z in 3D).

    ``kind``: ``plane`` (analytic, unbounded), ``box`` (``thickness`` cells thick, below
    ``top``), ``mesh`` (zero thickness: a polyline in 2D, a triangulated square in 3D),
    ``disks`` (:func:`_write_disks`). Files go to ``folder``.
    """
    lo, hi = [x0 - 0.3, 0.0, 0.2][:dim], [x0 + 0.3, top, 0.8][:dim]
    if kind == "plane":
        return {"type": "plane", "name": name, "point": [0.0, top, 0.0][:dim], "normal": [0.0, 1.0, 0.0][:dim]}
    if kind == "box":
        lo[1] = top - thickness * dx
        return {"type": "box", "name": name, "lo": lo, "hi": hi}
    if kind == "mesh" and dim == 2:
        return {"type": "mesh", "name": name, "points": [[x0 + 0.3, top], [x0 - 0.3, top]]}
    if kind == "mesh":
        return {"type": "mesh", "name": name, "path": _write_square_mesh(folder, x0, top)}
    if kind == "disks":
        return {"type": "disks", "name": name, "path": _write_disks(folder, x0, top, dim, dx), "orient": "none"}
    raise ValueError(kind)


def drop_substeps(dim: int) -> tuple[float, int, int]:
    """``dx``, substeps per frame and frames of the drop (stress-wave CFL <= 0.5, 0.4 s)."""
    return (0.02, 80, 20) if dim == 2 else (0.05, 40, 20)


def drop_spec(dim: int, material: str, stations, folder=None, collision: str = "cpic", contact: str = "sticky",
              friction: float = 0.0, frames: int | None = None, dx: float | None = None) -> tuple[dict, list[float]]:
    """Blocks (0.16 x 0.1 m in 2D, 0.2 x 0.1 x 0.2 m in 3D) dropped at 1 m/s from 4 cm above the
    top surface of each station's collider.

    ``stations``: ``(kind, thickness in cells or None, on_row)`` per station (a ``plane``
    must be alone). ``dx``: another grid than :func:`drop_substeps`'s, with the substeps
    scaled by the same ratio. That keeps a solid's stress-wave CFL number; a viscous fluid's
    grows as dx falls (``benchmarks/bench_colliders.py --convergence`` raises its substeps).
    Returns the spec and each station's top-surface height.
    """
    default_dx, substeps, default_frames = drop_substeps(dim)
    dx = dx or default_dx
    substeps = int(round(substeps * default_dx / dx))
    half = 0.08 if dim == 2 else 0.1
    bodies, colliders, tops = [], [], []
    for i, (kind, thickness, on_row) in enumerate(stations):
        x0, top = station_centre(i), drop_top(dx, on_row)
        col = drop_collider(kind, dim, dx, top, x0, folder, thickness or THICK, name=f"c{i}")
        colliders.append({**col, "contact": contact, "friction": friction})
        bodies.append({"shape": "box", "name": f"b{i}", "velocity": [0.0, -DROP_SPEED, 0.0][:dim],
                       "lo": [x0 - half, top + DROP_GAP, 0.5 - half][:dim],
                       "hi": [x0 + half, top + DROP_GAP + 0.1, 0.5 + half][:dim],
                       "material": dict(DROP_MATERIALS[material])})
        tops.append(top)
    hi = [station_centre(len(stations) - 1) + 0.5, 1.0, 1.0][:dim]
    spec = {
        "dim": dim, "dx": dx, "domain": {"lo": [0.0] * dim, "hi": hi}, "gravity": [0.0, -9.8, 0.0][:dim],
        "frames": frames or default_frames, "frame_dt": 0.02, "substeps": substeps, "collision": collision,
        "bodies": bodies, "colliders": colliders,
    }
    return spec, tops


def body_volumes(model, state):
    """Per body, ``sum J V0 / sum V0`` (jnp, traceable): J is the stored volume ratio of a
    Newtonian fluid (``aux``), det F otherwise."""
    from jaxmpm.constitutive import Newtonian

    out = []
    for body, sl in zip(model.bodies, model.body_slices()):
        J = state.aux[sl] if isinstance(body.material, Newtonian) else jnp.linalg.det(state.F[sl])
        out.append(jnp.sum(J * state.vol0[sl]) / jnp.sum(state.vol0[sl]))
    return jnp.stack(out)


def pile(x: np.ndarray, top: float, x0: float) -> dict:
    """What a user sees of a pile resting on a surface at ``top`` about ``x0``, from the
    positions of its last frames ``(T, n, D)`` (m): its height above the surface and its
    thickness (highest particle minus lowest; the mean over the frames), footprint (extent
    along x), centre of mass relative to ``(x0, top)``, and the lowest particle over all frames.
    ``bulk_thickness`` and ``bulk_footprint`` are the same extents between the 1st and 99th
    percentiles, which grains splashed away from the pile do not move."""
    y = x[..., 1]

    def bulk(a):
        lo, hi = np.percentile(a, [1.0, 99.0], axis=1)
        return float(np.mean(hi - lo))

    return {
        "height": float(np.mean(y.max(axis=1)) - top),
        "thickness": float(np.mean(y.max(axis=1) - y.min(axis=1))),
        "footprint": float(np.mean(np.ptp(x[..., 0], axis=1))),
        "bulk_thickness": bulk(y),
        "bulk_footprint": bulk(x[..., 0]),
        "com": x[-1].mean(axis=0) - np.asarray([x0, top, 0.5][: x.shape[-1]]),
        "lowest": float(y.min() - top),
    }


def drop_run(spec: dict, tops, last: int = 5) -> tuple[list[dict], object]:
    """Simulate a drop spec; per station its :func:`pile` over the ``last`` frames (plus
    ``volume``: :func:`body_volumes` averaged over them, and ``lowest``: over the whole run),
    and the trajectory."""
    from jaxmpm.scene import load_scene

    scene = load_scene(spec)
    model = scene.model
    traj = jax.jit(lambda p: simulate(model, p, checkpoint=None, observe=lambda s: body_volumes(model, s)))(scene.params)
    assert not np.asarray(traj.nan).any(), "the rollout produced NaN"
    x = np.asarray(traj.x)
    volumes = np.mean(np.asarray(traj.extra[-last:], np.float64), axis=0)
    out = []
    for i, (sl, top) in enumerate(zip(model.body_slices(), tops)):
        p = pile(x[-last:, sl], top, station_centre(i))
        p["lowest"] = float(x[:, sl, 1].min() - top)
        p["volume"] = float(volumes[i])
        out.append(p)
    return out, traj


#: The face placements of the resting-block scene: metres above the node row at 0.2 m.
PLACEMENT_ROW = 0.2


def placement_spec(offsets, kind: str = "box", contact: str = "slip", dx: float = 0.05) -> tuple[dict, list[float]]:
    """2D elastic blocks (0.2 x 0.1 m, E = 50 kPa, 2 x 2 particles a cell) dropped at 1 m/s, one
    per face offset (metres above the node row at :data:`PLACEMENT_ROW`), 2 s: on boxes 0.6 m
    apart (``kind="box"``) or on a plane (``kind="plane"``, one offset). Returns the spec and
    each block's face height (docs/colliders.md, "Where a face lies between node rows")."""
    tops = [PLACEMENT_ROW + o for o in offsets]
    material = {"model": "elastic", "E": 5e4, "nu": 0.3, "density": 1000.0}
    bodies = [{"shape": "box", "lo": [0.2 + 0.6 * k, 0.3], "hi": [0.4 + 0.6 * k, 0.4], "ppc": 4,
               "velocity": [0, -1.0], "material": material, "name": f"block{k}"} for k in range(len(tops))]
    if kind == "box":
        colliders = [{"type": "box", "name": f"box{k}", "lo": [0.1 + 0.6 * k, 0.0], "hi": [0.5 + 0.6 * k, top],
                      "contact": contact} for k, top in enumerate(tops)]
    else:
        if len(tops) != 1:
            raise ValueError("a plane scene takes one offset")
        colliders = [{"type": "plane", "name": "plane", "point": [0.0, tops[0]], "normal": [0.0, 1.0],
                      "contact": contact}]
    spec = {"dim": 2, "dx": dx, "domain": {"lo": [0, 0], "hi": [0.6 * len(tops), 0.6]}, "frames": 48,
            "frame_dt": 1 / 24, "substeps": 40, "gravity": [0, -9.8], "bodies": bodies, "colliders": colliders}
    return spec, tops
