"""Small scene specs shared by the tests (CI-sized: 2D or coarse 3D)."""

from __future__ import annotations

import copy

import pytest

# ``dim`` for a test of dimension-generic code whose 3D case runs the 2D case's code path at
# several times its compile time: 2D in the default run, 3D with ``-m slow``.
DIMS_3D_SLOW = pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)], ids=["2d", "3d"])


def slow(*values):
    """One case of a parameter matrix that runs only with ``-m slow``: a case whose code path
    another case of the same matrix, or another test, takes in the default run (the same code
    in 3D, a material with no code of its own on the path tested), at a cost the default
    run's budget does not have room for."""
    return pytest.param(*values, marks=pytest.mark.slow)


def block_spec(
    dim: int = 2,
    material: dict | None = None,
    *,
    dx: float = 0.05,
    lo=None,
    hi=None,
    frames: int = 8,
    substeps: int = 40,
    velocity=None,
    gravity=None,
    floor: dict | None = None,
    domain_hi: float = 1.0,
    ppc: int | None = None,
) -> dict:
    """A block of material in a unit domain, optionally above a floor plane."""
    material = material or {"model": "newtonian", "mu": 10.0, "kappa": 1e4}
    lo = lo or [0.4, 0.3, 0.4][:dim]
    hi = hi or [0.6, 0.5, 0.6][:dim]
    spec = {
        "dim": dim,
        "dx": dx,
        "domain": {"lo": [0.0] * dim, "hi": [domain_hi] * dim},
        "frames": frames,
        "frame_dt": 1.0 / 24.0,
        "substeps": substeps,
        "gravity": gravity if gravity is not None else [0.0, -9.8, 0.0][:dim],
        "bodies": [
            {
                "shape": "box",
                "lo": lo,
                "hi": hi,
                "velocity": velocity if velocity is not None else [0.0] * dim,
                "material": copy.deepcopy(material),
                **({"ppc": ppc} if ppc else {}),
            }
        ],
    }
    if floor is not None:
        spec["colliders"] = [{"type": "plane", "name": "floor", **floor}]
    return spec


#: One CI-sized parameter set per material (truth) and PAC-NeRF's initial guess for it.
MATERIAL_CASES = {
    "newtonian": ({"model": "newtonian", "mu": 200.0, "kappa": 1e5}, {"mu": 1.0, "kappa": 1e3}),
    "viscoplastic": (
        {"model": "viscoplastic", "mu": 1e4, "kappa": 1e6, "yield_stress": 3e3, "eta": 10.0},
        {"mu": 100.0, "kappa": 1e5, "yield_stress": 10.0, "eta": 1.0},
    ),
    "elastic": ({"model": "elastic", "E": 1e5, "nu": 0.3}, {"E": 10**5.5, "nu": 0.25}),
    "plasticine": (
        {"model": "plasticine", "E": 1e5, "nu": 0.3, "yield_stress": 2e3},
        {"E": 1e4, "nu": 0.25, "yield_stress": 1e3},
    ),
    "sand": ({"model": "sand", "friction_angle": 40.0}, {"friction_angle": 10.0}),
}


def final_position_loss(scene, names):
    """A smooth loss of the last frame's positions as a function of the parameters ``names``
    (scene-file names, ``jnp`` array of values in that order): what the gradient tests
    compare with central differences."""
    import jax.numpy as jnp

    from jaxmpm.identify import resolve_name, set_param
    from jaxmpm.step import simulate

    paths = [resolve_name(scene.model, scene.params, n) for n in names]

    def loss(values):
        params = scene.params
        for path, value in zip(paths, values):
            params = set_param(params, path, value)
        x = simulate(scene.model, params).x[-1]
        return jnp.mean(x[:, 0] ** 3 + 2.0 * x[:, 1] ** 2 + x[:, 0] * x[:, 1])

    return loss
