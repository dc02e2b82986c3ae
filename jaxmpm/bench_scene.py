"""The step benchmark's scene: a cube of elastic material in the unit box (plain NumPy).

Shared by ``jaxmpm bench`` (which works from an installed package) and the Taichi and Warp
peers in ``benchmarks/peers/`` (a source checkout), so that every code starts from
bit-identical particles and parameters.

The scene: a cube of elastic material (fixed-corotated, E = 1e5 Pa, nu = 0.3,
rho = 1000 kg/m^3) sampled at about 8 particles per cell (2 per axis, jittered with
a fixed seed), centred in the unit box [0, 1]^3, which is covered by a
``grid_n``^3 node grid of spacing ``dx = 1 / grid_n``. Slip walls act on the nodes
that lie strictly within ``bound = 3`` cells of a face of the box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Seed of the particle jitter / subset selection. Fixed so that every run, and
#: every peer, starts from exactly the same particles.
SEED = 0

#: Default problem size of the side-by-side benchmark.
DEFAULT_N_PARTICLES = 25_000
DEFAULT_GRID_N = 64


@dataclass(frozen=True)
class MPMParams:
    """Physical and numerical parameters of the reference MLS-MPM step (SI units)."""

    grid_n: int = DEFAULT_GRID_N
    dt: float = 1e-4
    E: float = 1e5
    nu: float = 0.3
    rho: float = 1000.0
    gravity: tuple[float, float, float] = field(default=(0.0, -9.8, 0.0))
    bound: int = 3

    @property
    def dx(self) -> float:
        return 1.0 / self.grid_n

    @property
    def inv_dx(self) -> float:
        return float(self.grid_n)

    @property
    def p_vol(self) -> float:
        """Particle volume, (dx/2)^3 (8 particles per cell)."""
        return (0.5 * self.dx) ** 3

    @property
    def p_mass(self) -> float:
        return self.rho * self.p_vol

    @property
    def mu(self) -> float:
        """First Lame parameter (shear modulus)."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        """Second Lame parameter."""
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))


def cube_cells(n_particles: int) -> int:
    """Edge length, in cells, of the smallest cube holding ``n_particles`` at 8 per cell."""
    if n_particles <= 0:
        raise ValueError(f"n_particles must be positive, got {n_particles}")
    s = max(1, int(math.ceil((n_particles / 8.0) ** (1.0 / 3.0) - 1e-9)))
    while 8 * s**3 < n_particles:
        s += 1
    return s


def sample_cube(
    n_particles: int,
    grid_n: int = DEFAULT_GRID_N,
    seed: int = SEED,
    center: tuple[float, float, float] | None = None,
    bound: int = 3,
) -> np.ndarray:
    """Particle positions of the benchmark cube, ``(n_particles, 3)`` float32.

    The cube has an edge of ``s = cube_cells(n_particles)`` cells. It is filled with
    a regular lattice of 2 points per cell per axis, ``(2 s)^3`` points, each
    jittered uniformly by up to a quarter of the lattice spacing; ``n_particles`` of
    them are then drawn without replacement (kept in lattice order), so that the
    cloud is always a cube at (very nearly) 8 particles per cell. The same seed
    gives the same particles everywhere.

    Arguments:
        n_particles: number of particles.
        grid_n: nodes per axis of the grid over [0, 1]^3 (dx = 1 / grid_n).
        seed: seed of the NumPy generator.
        center: centre of the cube in metres; default the middle of the box.
        bound: wall thickness in cells; the cube must fit inside the walls.
    """
    dx = 1.0 / grid_n
    s = cube_cells(n_particles)
    if center is None:
        center = (0.5, 0.5, 0.5)
    center_arr = np.asarray(center, dtype=np.float64)
    lo = center_arr - 0.5 * s * dx
    hi = center_arr + 0.5 * s * dx
    # Keep one full stencil (2 cells) of clearance from the wall nodes.
    wall_lo, wall_hi = (bound + 1) * dx, 1.0 - (bound + 1) * dx
    if np.any(lo < wall_lo) or np.any(hi > wall_hi):
        raise ValueError(
            f"a cube of {n_particles} particles ({s} cells per edge, centre {tuple(center)}) "
            f"does not fit inside the walls of a {grid_n}^3 grid; use a larger grid_n"
        )
    rng = np.random.default_rng(seed)
    h = 0.5 * dx  # lattice spacing: 2 particles per cell per axis
    m = 2 * s
    idx = np.stack(
        np.meshgrid(np.arange(m), np.arange(m), np.arange(m), indexing="ij"), axis=-1
    ).reshape(-1, 3)
    pts = lo + (idx + 0.5) * h
    pts = pts + rng.uniform(-0.25 * h, 0.25 * h, size=pts.shape)
    if len(pts) > n_particles:
        keep = np.sort(rng.choice(len(pts), size=n_particles, replace=False))
        pts = pts[keep]
    return np.ascontiguousarray(pts, dtype=np.float32)


#: Velocity gradient (1/s) of the gradient benchmark's initial velocity field
#: ``v = v0 + GRAD_SCENE_VELOCITY_GRADIENT (x - centre)``: a stretch plus a shear, so that the
#: cube deforms from the first step (at rest it is in exact free fall, no stress, and the loss
#: would not depend on the material). 200 steps move a corner by about 1 cm, far from the walls.
GRAD_SCENE_VELOCITY_GRADIENT = ((4.0, 2.0, 0.0), (0.0, -3.0, 1.5), (-1.0, 0.0, 2.0))


#: The parameters of the gradient benchmark, in order: Young's modulus, Poisson's ratio, density
#: and the three components of the initial (uniform part of the) velocity.
GRAD_PARAMETERS = ("E", "nu", "density", "vx", "vy", "vz")


def grad_scene_velocity(x: np.ndarray) -> np.ndarray:
    """The gradient benchmark's initial velocity field without ``v0``: ``L (x - c)`` with
    ``L = GRAD_SCENE_VELOCITY_GRADIENT`` and ``c`` the cloud's centroid, ``(N, 3)`` float32."""
    x = np.asarray(x, np.float64)
    rel = x - x.mean(axis=0)
    return np.ascontiguousarray(rel @ np.asarray(GRAD_SCENE_VELOCITY_GRADIENT).T, dtype=np.float32)


def initial_state(
    n_particles: int,
    grid_n: int = DEFAULT_GRID_N,
    v0: tuple[float, float, float] = (0.0, 0.0, 0.0),
    center: tuple[float, float, float] | None = None,
    seed: int = SEED,
) -> dict[str, np.ndarray]:
    """Initial particle arrays: ``x``, ``v`` ``(N, 3)``, ``C``, ``F`` ``(N, 3, 3)``, float32."""
    x = sample_cube(n_particles, grid_n, seed=seed, center=center)
    n = len(x)
    v = np.broadcast_to(np.asarray(v0, dtype=np.float32), (n, 3)).copy()
    C = np.zeros((n, 3, 3), np.float32)
    F = np.broadcast_to(np.eye(3, dtype=np.float32), (n, 3, 3)).copy()
    return {"x": x, "v": v, "C": C, "F": F}
