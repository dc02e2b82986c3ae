"""Parameter uncertainty from the Gauss–Newton approximation at an optimum: one covariance, and
the scale below which a rough loss no longer follows it."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .parameters import from_unconstrained

__all__ = ["gauss_newton_covariance", "physical_std", "resolved_std"]


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


#: The loss "follows its Gauss–Newton model" at a move ``±δ`` when the mean of its two measured
#: changes is within this factor of the model's curvature term ``δᵀ JᵀJ δ`` (either way: the
#: model's linear terms cancel in the mean, and a loss that grows faster than its quadratic
#: further out still resolves the move).
RESOLUTION_FACTOR = 2.0


def resolved_std(loss_of: Callable[[np.ndarray], float], y: np.ndarray, r: np.ndarray, J: np.ndarray,
                 std: np.ndarray, *, cap: float = 1.0, factor: float = RESOLUTION_FACTOR,
                 dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Per variable, the smallest move the loss resolves: its statistical standard deviation
    where the loss follows the Gauss–Newton model at that scale, else the scale at which it
    first does.

    ``s² (JᵀJ)⁻¹`` assumes the loss is the model's quadratic around the optimum down to the
    standard deviations. A rough loss is not: CPIC's discrete decisions (a node switching side,
    the reference face switching) make it jump, in float64 as in float32, and below some scale
    the jumps, not the curvature, decide which parameters fit best. There a fit lands anywhere
    within that scale (a sysid case from four starting points, with CPIC's reference face still
    chosen hard: μ 0.0005 to 0.009 decades off, its statistical σ 2.6·10⁻⁴ decades). So each variable ``i`` is moved along its profile
    direction ``d_i = (JᵀJ)⁻¹ e_i / (JᵀJ)⁻¹_ii`` (the others follow it as their correlation
    asks) by ``±h``, from its standard deviation up, and the mean of the loss's two measured
    changes is compared with the model's curvature term; the first ``h`` at which they agree
    within ``factor`` is the resolved scale. On a smooth loss that is the first ``h`` tried, and
    the standard deviation stands. Each try costs two evaluations of ``loss_of``; the scale
    grows by the factor the disagreement asks for (between 2 and 100 times).

    Arguments:
        loss_of: the loss (sum of squared residuals) at a point ``(P,)`` of ``dtype``.
        y: ``(P,)`` the optimum (optimisation units); ``r (M,)`` and ``J (M, P)`` there.
        std: ``(P,)`` the statistical standard deviations (square roots of the covariance's diagonal).
        cap: the largest move tried, in units of ``1 + |y_i|``.
        factor: :data:`RESOLUTION_FACTOR`.
        dtype: the points' dtype (the moves are compared as rounded to it).

    Returns:
        ``(P,)`` standard deviations ``>= std`` and ``(P,)`` bool: whether the loss followed the
        model at some move up to the cap (where not, the cap is returned).
    """
    y, r, J = (np.asarray(a, np.float64) for a in (y, r, J))
    A = J.T @ J
    A_inv = np.linalg.pinv(A)
    f0 = float(r @ r)
    out = np.asarray(std, np.float64).copy()
    resolved = np.ones(y.shape, bool)
    for i in range(y.size):
        a = A_inv[i, i]
        if not (a > 0 and np.isfinite(out[i])):
            continue
        d = A_inv[:, i] / a
        top = cap * (1.0 + abs(y[i]))
        h = min(max(out[i], 1e-7 * (1.0 + abs(y[i]))), top)
        raised = False
        while True:
            changes, curvature = [], 0.0
            for sign in (1.0, -1.0):
                point = np.asarray(y + sign * h * d, dtype)
                move = point.astype(np.float64) - y  # as rounded
                curvature += 0.5 * float(move @ A @ move)
                changes.append(float(loss_of(point)) - f0)
            mean = 0.5 * sum(changes)
            ratio = mean / curvature if curvature > 0 and np.isfinite(mean) else np.nan
            if 1.0 / factor <= ratio <= factor:
                break
            if h >= top:
                resolved[i] = False
                break
            # jumps of a roughly constant size against a curvature term ~h^2: aim where it would
            # win (a loss that rose too little grows the move by the least step, 2)
            grow = np.sqrt(abs(ratio) / factor) if np.isfinite(ratio) and ratio != 0 else 10.0
            h = min(h * float(np.clip(grow, 2.0, 100.0)), top)
            raised = True
        if raised:
            out[i] = max(out[i], h)
    return out, resolved


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
