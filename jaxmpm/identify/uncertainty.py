"""Parameter uncertainty from the Gauss–Newton approximation at an optimum: one covariance."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .parameters import from_unconstrained

__all__ = ["gauss_newton_covariance", "physical_std"]


def gauss_newton_covariance(J: np.ndarray, r: np.ndarray, *, groups: np.ndarray | None = None,
                            count: int | None = None) -> np.ndarray:
    """Covariance of the parameters (optimisation space) of a least-squares fit at its optimum.

    Arguments:
        J: ``(M, p)`` Jacobian of the residuals ``r`` ``(M,)`` (weights already applied).
        groups: ``(M,)`` the group of each residual entry (e.g. its observed frame), or None.
            Entries of one group share one error (same dynamics), so they are not independent:
            with more groups than ``p + 1`` the frame-clustered sandwich
            ``A⁻¹ (Σ_g s_g s_gᵀ) A⁻¹ · G / (G − p)`` with ``s_g = J_gᵀ r_g`` is returned.
        count: the number of informative residual entries when there are no groups (default M).

    Returns:
        ``(p, p)``: the sandwich above, or ``s² A⁻¹`` with ``A = JᵀJ`` and ``s² = RSS / (n − p)``,
        ``n`` the number of groups (or of entries). The latter treats residuals as independent
        with equal variance, so it is a lower bound when they are correlated (neighbouring
        pixels, points of one frame).
    """
    J = np.asarray(J, np.float64)
    r = np.asarray(r, np.float64)
    m, p = J.shape
    A_inv = np.linalg.pinv(J.T @ J)
    if groups is not None:
        labels, index = np.unique(np.asarray(groups), return_inverse=True)
        G = len(labels)
        if G > p + 1:
            S = np.zeros((G, p))
            np.add.at(S, index, J * r[:, None])
            return A_inv @ (S.T @ S * G / (G - p)) @ A_inv
        n = G
    else:
        n = m if count is None else min(m, int(count))
    return float(r @ r) / max(n - p, 1) * A_inv


def physical_std(names, y: dict, std_y: dict, physical=from_unconstrained) -> dict[str, np.ndarray]:
    """Standard deviations in physical units from those of the optimisation variables ``y``
    (first-order: ``|d value / d y| · std_y``, elementwise for vector parameters);
    ``physical(name, y)`` maps a variable to its physical value."""
    out = {}
    for n in names:
        yn = jnp.ravel(jnp.asarray(y[n]))
        slope = jax.vmap(jax.grad(lambda t, n=n: jnp.sum(physical(n, t))))(yn)
        out[n] = np.abs(np.asarray(slope)).reshape(np.shape(y[n])) * np.asarray(std_y[n]).reshape(np.shape(y[n]))
    return out
