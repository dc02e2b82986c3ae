"""Every material against an independent reference written here from the documented formulas
(reference/algorithms.md §7, reference/anchors.md §1.4), at random states, in float64.

The references never call the library's SVD: the Hencky strain is the matrix logarithm of the
left stretch, ``L = ½ log(F Fᵀ)`` (numpy's symmetric eigensolver), the rotation is
``R = exp(-L) F``, and a return map acts on the eigenvalues of ``L`` (which are the library's
principal strains ``log σ``). The norm is the documented safe norm ``sqrt(x·x + 1e-8)``.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.constitutive import MATERIALS

pytestmark = pytest.mark.x64

N = 200
DT = 1e-3
SAFE_EPS = 1e-8


def _states(dim: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(F, C)`` of shapes ``(N, D, D)``: random stretches, shears and compressions with
    ``det F > 0`` and singular values in [0.3, 3] (away from the 0.05 clamp)."""
    rng = np.random.default_rng(seed)
    F = np.eye(dim) + 0.3 * rng.standard_normal((4 * N, dim, dim))
    sigma = np.linalg.svd(F, compute_uv=False)
    keep = (np.linalg.det(F) > 0) & (sigma.min(-1) > 0.3) & (sigma.max(-1) < 3.0)
    F = F[keep][:N]
    assert len(F) == N
    return F, 5.0 * rng.standard_normal((N, dim, dim))


def _sym_fn(A: np.ndarray, fn) -> np.ndarray:
    """``fn`` applied to the eigenvalues of the symmetric matrices ``A`` ``(N, D, D)``."""
    w, Q = np.linalg.eigh(A)
    return np.einsum("nij,nj,nkj->nik", Q, fn(w), Q)


def _log_stretch(F: np.ndarray) -> np.ndarray:
    """Hencky strain tensor ``L = ½ log(F Fᵀ)`` ``(N, D, D)``."""
    return _sym_fn(F @ np.swapaxes(F, -1, -2), lambda w: 0.5 * np.log(w))


def _rotation(F: np.ndarray) -> np.ndarray:
    """Polar rotation ``R = (F Fᵀ)^{-1/2} F``."""
    return _sym_fn(F @ np.swapaxes(F, -1, -2), lambda w: w**-0.5) @ F


def _trace(A: np.ndarray) -> np.ndarray:
    return np.trace(A, axis1=-2, axis2=-1)[:, None, None]


def _dev(L: np.ndarray) -> np.ndarray:
    return L - _trace(L) / L.shape[-1] * np.eye(L.shape[-1])


def _norm(A: np.ndarray) -> np.ndarray:
    return np.sqrt(np.sum(A * A, axis=(-2, -1)) + SAFE_EPS)[:, None, None]


def _lame(E: float, nu: float) -> tuple[float, float]:
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def _hencky_stress(L: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """StVK in Hencky strain: ``τ = 2μ L + λ tr(L) I``."""
    return 2 * mu * L + lam * _trace(L) * np.eye(L.shape[-1])


def _bingham(L: np.ndarray, F: np.ndarray, mu: float, tau_y: float, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """Viscoplastic (η > 0) / von Mises (η = 0) return map; the new strain and a yielded mask."""
    dim = L.shape[-1]
    s = 2 * mu * _dev(L)
    s_norm = 2 * mu * _norm(_dev(L))
    excess = s_norm - math.sqrt(2 / 3) * tau_y
    mu_hat = mu * _trace(F @ np.swapaxes(F, -1, -2)) / dim
    new_norm = s_norm - excess / (1 + eta / (2 * mu_hat * DT))
    yielded = excess > 0
    L_new = np.where(yielded, new_norm / s_norm * s / (2 * mu) + _trace(L) / dim * np.eye(dim), L)
    return L_new, yielded[:, 0, 0]


def _drucker_prager(L: np.ndarray, mu: float, lam: float, phi: float, cohesion: float) -> tuple[np.ndarray, np.ndarray]:
    """Klar et al.'s return map (apex moved to a tensile strength ``cohesion``); the new strain
    and the case of each state (0 inside the cone, 1 to the apex, 2 to the cone)."""
    dim = L.shape[-1]
    eye = np.eye(dim)
    shift = cohesion / (2 * mu + dim * lam)
    L = L - shift * eye
    sin_phi = math.sin(math.radians(phi))
    alpha = math.tan(math.radians(phi)) / math.sqrt(2) if dim == 2 else math.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi)
    tr = _trace(L)
    d_gamma = _norm(_dev(L))[:, 0, 0] + (dim * lam + 2 * mu) / (2 * mu) * tr[:, 0, 0] * alpha
    cone = L - np.maximum(d_gamma, 0)[:, None, None] * _dev(L) / _norm(_dev(L))
    L_new = np.where(tr >= 0, 0 * L, cone) + shift * eye
    case = np.where(tr[:, 0, 0] >= 0, 1, np.where(d_gamma > 0, 2, 0))
    return L_new, case


def _reference(name: str, p: dict, F: np.ndarray, C: np.ndarray, J: np.ndarray):
    """``(F_new, aux_new, τ, case)`` from the documented formulas; ``case`` marks which branch
    of a return map each state took (``None`` for materials without one)."""
    dim = F.shape[-1]
    eye = np.eye(dim)
    if name in ("elastic", "corotated"):
        mu, lam = _lame(p["E"], p["nu"])
        Jf = np.linalg.det(F)[:, None, None]
        if name == "elastic":  # neo-Hookean: τ = μ(F Fᵀ − I) + λ log J I
            tau = mu * (F @ np.swapaxes(F, -1, -2) - eye) + lam * np.log(Jf) * eye
        else:  # fixed corotated: τ = 2μ(F − R)Fᵀ + λ(J − 1)J I
            tau = 2 * mu * (F - _rotation(F)) @ np.swapaxes(F, -1, -2) + lam * (Jf - 1) * Jf * eye
        return F, J, tau, None
    if name == "newtonian":  # J ← max((1 + dt tr C) J, 0.05); τ = κ(J − J⁻⁶)I + μ J sym(C)
        J_new = np.maximum((1 + DT * np.trace(C, axis1=-2, axis2=-1)) * J, 0.05)[:, None, None]
        tau = p["kappa"] * (J_new - J_new**-6) * eye + p["mu"] * J_new * 0.5 * (C + np.swapaxes(C, -1, -2))
        return np.broadcast_to(eye, F.shape), J_new[:, 0, 0], tau, None
    L = _log_stretch(F)
    if name == "viscoplastic":
        mu, lam = p["mu"], p["kappa"] - 2 * p["mu"] / dim
        L_new, case = _bingham(L, F, mu, p["yield_stress"], p["eta"])
    elif name == "plasticine":
        mu, lam = _lame(p["E"], p["nu"])
        L_new, case = _bingham(L, F, mu, p["yield_stress"], 0.0)
    else:
        mu, lam = _lame(p["E"], p["nu"])
        L_new, case = _drucker_prager(L, mu, lam, p["friction_angle"], p.get("cohesion", 0.0))
    F_new = _sym_fn(L_new, np.exp) @ _rotation(F)
    return F_new, J, _hencky_stress(L_new, mu, lam), case


CASES = {
    "elastic": {"E": 1e5, "nu": 0.3},
    "corotated": {"E": 1e5, "nu": 0.3},
    "newtonian": {"mu": 3.0, "kappa": 1e4},
    "viscoplastic": {"mu": 2e3, "kappa": 1e5, "yield_stress": 2e3, "eta": 5.0},
    "plasticine": {"E": 2e5, "nu": 0.3, "yield_stress": 7.5e4},
    "sand": {"friction_angle": 35.0, "E": 3e5, "nu": 0.3},
    "sand+cohesion": {"friction_angle": 35.0, "E": 3e5, "nu": 0.3, "cohesion": 2e4},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_material_matches_the_documented_formulas(case, dim):
    """``Material.update`` (what a step calls) gives the reference's ``F``, internal state and
    Kirchhoff stress at random states, and every branch of the return map is exercised."""
    name = case.split("+")[0]
    material = MATERIALS[name]()
    p = CASES[case]
    F, C = _states(dim, seed=dim)
    J = np.random.default_rng(7).uniform(0.8, 1.2, N) if name == "newtonian" else np.zeros(N)
    params = {k: jnp.asarray(v, jnp.float64) for k, v in p.items()}
    F_lib, aux_lib, tau_lib = material.update(jnp.asarray(F), jnp.asarray(C), jnp.asarray(J), params, DT)
    F_ref, aux_ref, tau_ref, branch = _reference(name, p, F, C, J)
    tau_scale = np.abs(tau_ref).max()
    assert tau_scale > 0
    np.testing.assert_allclose(np.asarray(F_lib), F_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(aux_lib), aux_ref, rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.asarray(tau_lib), tau_ref, rtol=0, atol=1e-9 * tau_scale)
    if branch is not None:  # the states reach every branch, so each one is checked
        assert set(np.unique(branch).tolist()) == ({0, 1, 2} if name == "sand" else {False, True})


def test_yielded_states_lie_on_the_documented_yield_surfaces():
    """After the return map the deviatoric Kirchhoff stress of a yielded state has norm
    √(2/3)·τ_Y (plasticine), and sand's stress lies on ``||dev τ|| = −α tr τ`` with
    ``α = √(2/3)·2 sin φ/(3 − sin φ)`` (3D)."""
    F, C = _states(3, seed=11)
    aux = jnp.zeros(N)
    p = {k: jnp.asarray(v, jnp.float64) for k, v in CASES["plasticine"].items()}
    _, _, tau = MATERIALS["plasticine"]().update(jnp.asarray(F), jnp.asarray(C), aux, p, DT)
    s = np.linalg.norm(_dev(np.asarray(tau)), axis=(-2, -1))
    yield_norm = math.sqrt(2 / 3) * CASES["plasticine"]["yield_stress"]
    assert s.max() == pytest.approx(yield_norm, rel=1e-6)
    assert (s > yield_norm * (1 - 1e-6)).sum() > N // 4  # many states are on the surface

    p = {k: jnp.asarray(v, jnp.float64) for k, v in CASES["sand"].items()}
    _, _, tau = MATERIALS["sand"]().update(jnp.asarray(F), jnp.asarray(C), aux, p, DT)
    tau = np.asarray(tau)
    sin_phi = math.sin(math.radians(CASES["sand"]["friction_angle"]))
    alpha = math.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi)
    s, tr = np.linalg.norm(_dev(tau), axis=(-2, -1)), np.trace(tau, axis1=-2, axis2=-1)
    assert np.all(s <= -alpha * tr + 1e-6 * np.abs(tau).max())  # inside or on the cone
    on_cone = np.abs(s + alpha * tr) < 1e-6 * np.abs(tau).max()
    assert (on_cone & (tr < 0)).sum() > N // 4 and (tr <= 0).all()
