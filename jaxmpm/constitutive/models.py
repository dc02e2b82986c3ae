"""The PAC-NeRF materials (with PAC-NeRF's exact conventions) and fixed-corotated elasticity.

Notation (D = 2 or 3): ``F = U diag(sigma) V^T`` with U, V rotations, ``sigma`` clamped
to ``>= 0.05``; Hencky strain ``eps = log sigma``; deviatoric part
``eps_hat = eps - (tr eps / D) 1``; ``||.||`` is the safe norm ``sqrt(x·x + 1e-8)``.
"""

from __future__ import annotations

import abc
import math
from dataclasses import replace
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..fusion import sum_last
from ..parameters import ANGLE, NON_NEGATIVE, POISSON, POSITIVE, Linear, Log10, Parameter, TanhBounded
from .base import (
    SIGMA_MIN,
    Material,
    Params,
    det,
    lame_from_young,
    matmul,
    safe_norm,
)
from .svd import polar_rotation, spectral_maps, svd

_SQRT_2_3 = math.sqrt(2.0 / 3.0)

# --------------------------------------------------------------------------- parameters
# Learning rates: PAC-NeRF's dynamic-stage Adam rates (anchors §1.5). Guesses: PAC-NeRF's
# initial guesses for its 45-sequence batch (anchors §1.8).

#: Poisson ratio bounds of the tanh map ``nu = mid + half tanh((y - mid) / half)``.
NU_BOUNDS = (-0.45, 0.495)

YOUNG = Parameter("E", "Pa", POSITIVE, Log10(), 0.1, 10**5.5, "Young's modulus")
POISSON_RATIO = Parameter("nu", "", POISSON, TanhBounded(*NU_BOUNDS), 0.01, 0.25, "Poisson ratio")
VISCOSITY = Parameter("mu", "Pa s", NON_NEGATIVE, Log10(), 0.1, 10.0, "dynamic viscosity")
BULK = Parameter("kappa", "Pa", POSITIVE, Log10(), 0.1, 1e4, "bulk modulus")
SHEAR = Parameter("mu", "Pa", POSITIVE, Log10(), 0.1, 100.0, "shear modulus")
YIELD = Parameter("yield_stress", "Pa", NON_NEGATIVE, Log10(), 0.1, 10.0, "yield stress")
PLASTIC_VISCOSITY = Parameter("eta", "Pa s", NON_NEGATIVE, Log10(), 0.05, 1.0, "plastic viscosity")
FRICTION_ANGLE = Parameter("friction_angle", "deg", ANGLE, Linear(), 1.0, 10.0, "Drucker-Prager friction angle")


def _hencky_strain(sigma):
    """Principal Hencky strains ``log sigma``, the singular values clamped to ``SIGMA_MIN``."""
    return jnp.log(jnp.maximum(sigma, SIGMA_MIN))


def _hencky(F):
    U, sigma, V = svd(F)
    return U, _hencky_strain(sigma), V


def _from_hencky(U, eps, V):
    return matmul(U * jnp.exp(eps)[:, None, :], V.mT)


def _principal_stress(eps, mu, lam):
    """StVK in Hencky strain: the principal Kirchhoff stresses ``2 mu eps + lam tr eps``."""
    return 2.0 * mu * eps + lam * sum_last(eps, keepdims=True)


def _principal_kirchhoff(U, eps, mu, lam):
    """``tau = U diag(2 mu eps + lam tr eps) U^T`` from the left singular vectors and the
    principal Hencky strains."""
    return matmul(U * _principal_stress(eps, mu, lam)[:, None, :], U.mT)


def _deviatoric(eps):
    return eps - sum_last(eps, keepdims=True) / eps.shape[-1]


def _bulk_lame(mu, kappa, dim):
    """``lam = kappa - 2 mu / D`` (PAC-NeRF stores lam = kappa - 2 mu / 3 in 3D)."""
    return kappa - 2.0 * mu / dim


def viscoplastic_projection(eps, mu, yield_stress, eta, dt):
    """Bingham return map of Yue et al. 2015 as implemented by PAC-NeRF, on the principal
    Hencky strains ``eps`` ``(N, D)``.

    ``s_tr = 2 mu eps_hat``, ``y = ||s_tr|| - sqrt(2/3) tau_Y``; where ``y > 0``:
    ``||s_new|| = ||s_tr|| - y / (1 + eta / (2 mu_hat dt))`` with
    ``mu_hat = mu sum(sigma^2) / D``; ``eps_new = s_new / (2 mu) + tr eps / D``.
    ``eta = 0`` is the exact von Mises projection (plasticine).
    """
    dim = eps.shape[-1]
    eps_hat = _deviatoric(eps)
    s_norm = 2.0 * mu * safe_norm(eps_hat, keepdims=True)
    excess = s_norm - _SQRT_2_3 * yield_stress
    mu_hat = mu * sum_last(jnp.exp(2.0 * eps), keepdims=True) / dim
    new_norm = s_norm - excess / (1.0 + eta / (2.0 * mu_hat * dt))
    scale = jnp.where(excess > 0, new_norm / s_norm, 1.0)
    return scale * eps_hat + sum_last(eps, keepdims=True) / dim


def drucker_prager_projection(eps, mu, lam, friction_angle, cohesion=0.0):
    """Drucker–Prager return map of Klar et al. 2016 (PAC-NeRF's sand) on the principal
    Hencky strains ``eps`` ``(N, D)``.

    ``alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi))``; if ``tr eps >= 0`` the particle is
    projected to the cone tip (``eps = 0``); otherwise
    ``dgamma = ||eps_hat|| + (D lam + 2 mu) / (2 mu) tr(eps) alpha`` and
    ``eps <- eps - max(dgamma, 0) eps_hat / ||eps_hat||``. A ``cohesion`` (Pa, the tensile
    strength) moves the cone's apex to mean stress ``+cohesion``: the strain is shifted by
    ``cohesion / (2 mu + D lam)`` before the projection and back after it.
    """
    dim = eps.shape[-1]
    shift = cohesion / (2.0 * mu + dim * lam)
    eps = eps - shift
    alpha = drucker_prager_alpha(friction_angle, dim)
    trace = sum_last(eps, keepdims=True)
    eps_hat = _deviatoric(eps)
    eps_hat_norm = safe_norm(eps_hat, keepdims=True)
    dgamma = eps_hat_norm + (dim * lam + 2.0 * mu) / (2.0 * mu) * trace * alpha
    cone = eps - jnp.maximum(dgamma, 0.0) / eps_hat_norm * eps_hat
    return jnp.where(trace >= 0, jnp.zeros_like(eps), cone) + shift


class HenckyPlastic(Material):
    """StVK-in-Hencky-strain elasticity with a return map that acts on the principal Hencky
    strains (viscoplastic, plasticine, sand).

    Subclasses give :meth:`lame` and :meth:`project`; this class builds the return map
    ``F = U exp(project(log sigma)) V^T`` and the stress
    ``tau = U diag(2 mu eps + lam tr eps) U^T``. :meth:`update` does both from **one** SVD
    of ``F_trial`` (the projected ``F``'s SVD is ``U, exp(eps_new), V``), instead of a second
    SVD of the projected ``F`` for the stress, with :func:`~jaxmpm.constitutive.svd.spectral_maps`,
    whose derivative rule never forms the singular vectors' own tangents.
    """

    @abc.abstractmethod
    def lame(self, params: Params, dim: int) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """Lamé parameters ``(mu, lam)`` (Pa) of the elastic part in ``dim`` dimensions."""

    @abc.abstractmethod
    def project(self, eps: Float[Array, "N D"], params: Params, dt: float) -> Float[Array, "N D"]:
        """The return map on the principal Hencky strains ``eps = log sigma``."""

    def return_map(self, F_trial, C, aux, params, dt):
        U, eps, V = _hencky(F_trial)
        return _from_hencky(U, self.project(eps, params, dt), V), aux

    def kirchhoff(self, F, C, aux, params):
        U, eps, _ = _hencky(F)
        return _principal_kirchhoff(U, eps, *self.lame(params, F.shape[-1]))

    def update(self, F_trial, C, aux, params, dt):
        def principal(sigma, params):
            eps = self.project(_hencky_strain(sigma), params, dt)
            # the stress sees the strains clamped as an SVD of the projected F would clamp them
            eps_stress = jnp.maximum(eps, math.log(SIGMA_MIN))
            return jnp.exp(eps), _principal_stress(eps_stress, *self.lame(params, sigma.shape[-1]))

        F, tau = spectral_maps(principal, F_trial, params)
        return F, aux, tau


class Elastic(Material):
    """Compressible neo-Hookean: ``tau = mu (F F^T - I) + lam log(J) I``; no plasticity.

    Parameters: ``E`` (Pa), ``nu``.
    """

    name: ClassVar[str] = "elastic"
    parameters: ClassVar = (YOUNG, POISSON_RATIO)

    def return_map(self, F_trial, C, aux, params, dt):
        return F_trial, aux

    def kirchhoff(self, F, C, aux, params):
        mu, lam = lame_from_young(params["E"], params["nu"])
        dim = F.shape[-1]
        eye = jnp.eye(dim, dtype=F.dtype)
        log_J = jnp.log(det(F))  # NaN when inverted: reported by the health checks
        FFt = matmul(F, F.mT)
        return mu * (FFt - eye) + lam * log_J[:, None, None] * eye


class Corotated(Material):
    """Fixed-corotated elasticity (Stomakhin et al. 2012), the usual MPM benchmark material:
    ``tau = 2 mu (F - R) F^T + lam (J - 1) J I`` with ``R = U V^T``; no plasticity.

    Not a PAC-NeRF material; it is here for comparisons with Taichi/Warp MPM codes.
    Parameters: ``E`` (Pa), ``nu``.
    """

    name: ClassVar[str] = "corotated"
    parameters: ClassVar = (YOUNG, POISSON_RATIO)

    def return_map(self, F_trial, C, aux, params, dt):
        return F_trial, aux

    def kirchhoff(self, F, C, aux, params):
        mu, lam = lame_from_young(params["E"], params["nu"])
        R = polar_rotation(F)
        J = det(F)[:, None, None]
        eye = jnp.eye(F.shape[-1], dtype=F.dtype)
        return 2.0 * mu * matmul(F - R, F.mT) + lam * (J - 1.0) * J * eye


class Newtonian(Material):
    """PAC-NeRF's J-only fluid: ``tau = kappa (J - J^-6) I + mu J sym(C)``.

    Only the volume ratio J is evolved (``J <- (1 + dt tr C) J``, clamped ``>= 0.05``),
    stored in ``aux``; ``F`` stays the identity. Note there is **no factor 2** on the
    viscous term: PAC-NeRF's ``mu`` is twice the textbook dynamic viscosity.

    Parameters: ``mu`` (Pa·s), ``kappa`` (Pa).
    """

    name: ClassVar[str] = "newtonian"
    parameters: ClassVar = (VISCOSITY, BULK)

    def init_aux(self, n, dtype):
        return jnp.ones((n,), dtype)

    def return_map(self, F_trial, C, aux, params, dt):
        trace = jnp.trace(C, axis1=-2, axis2=-1)
        J = jnp.maximum((1.0 + dt * trace) * aux, SIGMA_MIN)
        eye = jnp.broadcast_to(jnp.eye(F_trial.shape[-1], dtype=F_trial.dtype), F_trial.shape)
        return eye, J

    def kirchhoff(self, F, C, aux, params):
        J = aux[:, None, None]
        eye = jnp.eye(F.shape[-1], dtype=F.dtype)
        pressure_part = params["kappa"] * (J - J**-6) * eye
        return pressure_part + params["mu"] * J * 0.5 * (C + jnp.swapaxes(C, -1, -2))


class Viscoplastic(HenckyPlastic):
    """Non-Newtonian Bingham fluid (Hencky StVK + the viscoplastic return map,
    :func:`viscoplastic_projection`).

    Elasticity ``tau = U diag(2 mu eps + lam tr eps) U^T`` with ``lam = kappa - 2 mu / D``;
    yield at ``||s|| = sqrt(2/3) tau_Y`` with plastic viscosity ``eta``.

    Parameters: ``mu`` (Pa), ``kappa`` (Pa), ``yield_stress`` (Pa), ``eta`` (Pa·s).
    """

    name: ClassVar[str] = "viscoplastic"
    parameters: ClassVar = (SHEAR, replace(BULK, guess=1e5), YIELD, PLASTIC_VISCOSITY)

    def lame(self, params, dim):
        return params["mu"], _bulk_lame(params["mu"], params["kappa"], dim)

    def project(self, eps, params, dt):
        return viscoplastic_projection(eps, params["mu"], params["yield_stress"], params["eta"], dt)


class Plasticine(HenckyPlastic):
    """von Mises plasticity: the viscoplastic model with ``eta = 0`` and E, nu elasticity.

    Parameters: ``E`` (Pa), ``nu``, ``yield_stress`` (Pa).
    """

    name: ClassVar[str] = "plasticine"
    parameters: ClassVar = (replace(YOUNG, guess=1e4), POISSON_RATIO, replace(YIELD, guess=1e3))

    def lame(self, params, dim):
        return lame_from_young(params["E"], params["nu"])

    def project(self, eps, params, dt):
        mu, _ = self.lame(params, eps.shape[-1])
        return viscoplastic_projection(eps, mu, params["yield_stress"], 0.0, dt)


def drucker_prager_alpha(friction_angle, dim: int):
    """Cone slope alpha of the Drucker–Prager yield surface ``||s|| = -alpha tr(tau)``.

    3D: Klar et al. / PAC-NeRF, ``alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi))`` (the cone
    through Mohr–Coulomb's triaxial-compression corners).

    2D (PAC-NeRF has no 2D model, so this is jaxmpm's choice): ``alpha = tan(phi) / sqrt(2)``.
    In 2D ``||s|| = |tau_1 - tau_2| / sqrt(2)``, so in steady simple shear (equal normal
    stresses p) the yield stress is ``tau = tan(phi) p``: a flowing layer stops at slopes below
    phi, i.e. phi is the angle of repose. The 3D formula used in 2D would give a repose angle of
    ``atan(4 sin(phi) / (sqrt(3) (3 - sin(phi))))`` (about 32 degrees for phi = 40 degrees).
    """
    phi = jnp.deg2rad(friction_angle)
    if dim == 2:
        return jnp.tan(phi) / math.sqrt(2.0)
    sin_phi = jnp.sin(phi)
    return _SQRT_2_3 * 2.0 * sin_phi / (3.0 - sin_phi)


class Sand(HenckyPlastic):
    """Drucker–Prager sand (Klar et al. 2016), cohesionless, as PAC-NeRF implements it
    (:func:`drucker_prager_projection`).

    Parameters: ``friction_angle`` (degrees), ``E`` (Pa, default 1e6), ``nu`` (default 0.3).
    A body-parameter entry ``cohesion`` (Pa; set by the ``cohesion`` extension, not a scene
    parameter) moves the cone's apex to a tensile strength.
    """

    name: ClassVar[str] = "sand"
    parameters: ClassVar = (FRICTION_ANGLE, YOUNG, POISSON_RATIO)
    defaults: ClassVar[dict[str, float]] = {"E": 1e6, "nu": 0.3}

    def lame(self, params, dim):
        return lame_from_young(params["E"], params["nu"])

    def project(self, eps, params, dt):
        mu, lam = self.lame(params, eps.shape[-1])
        return drucker_prager_projection(eps, mu, lam, params["friction_angle"], params.get("cohesion", 0.0))


MATERIALS: dict[str, type[Material]] = {
    cls.name: cls for cls in (Elastic, Newtonian, Viscoplastic, Plasticine, Sand, Corotated)
}
