"""Fast batched rotation-variant SVD of 2x2 and 3x3 matrices with a safe derivative.

Every plasticity / Hencky-strain model needs ``F = U diag(sigma) V^T`` for each
particle. ``jnp.linalg.svd`` is slow on CPU for many tiny matrices and its derivative
is NaN at repeated singular values, which occur at ``F = I`` at the start of every
simulation. :func:`svd` fixes both:

* The forward pass is written in structure-of-arrays form: every matrix entry is a
  batch-shaped array and only elementwise ``jnp`` operations are used, so XLA fuses
  the whole decomposition into a few loops over the batch (no ``jnp.linalg`` calls,
  no per-matrix Python loops).

  - 2D: closed form (polar angles of the conformal / anti-conformal parts).
  - 3D: a fixed number of cyclic one-sided Jacobi sweeps (Hestenes; exact Givens
    angles computed from the 2x2 blocks of ``B^T B``, ``B = F V``) accumulating ``V``;
    a sorting network on the column norms; and a Givens QR of ``B = F V`` that gives
    ``U`` as a product of rotations (so it stays orthonormal with ``det U = +1`` even
    when ``sigma_3 ~ 0`` or the matrix is rank-deficient) and ``sigma = diag(R)``.
    This is the scheme of McAdams et al. 2011, "Computing the SVD of 3x3 matrices
    with minimal branching", with exact rather than approximate rotations.

* The derivative is a :func:`jax.custom_jvp` (so ``jax.jvp``/``jax.jacfwd`` work, and
  ``jax.grad``/``jax.vjp`` by transposition of the linear rule) using the standard
  SVD differentials, written in the split form that keeps the symmetric and the
  antisymmetric parts of ``dP = U^T dF V`` apart (its matrix products are
  :func:`jaxmpm.constitutive.base.matmul`: elementwise in forward mode, dot ops in
  reverse mode's transpose)::

      d sigma_i = dP_ii
      U^T dU = Omega_U,  V^T dV = Omega_V   (antisymmetric), for i != j:
      Omega_U[i, j] = ( S_ij / (sigma_j - sigma_i) + A_ij / (sigma_i + sigma_j) ) / 2
      Omega_V[i, j] = ( S_ij / (sigma_j - sigma_i) - A_ij / (sigma_i + sigma_j) ) / 2
      S = dP + dP^T,  A = dP - dP^T

  (equivalently ``Omega_U[i, j] = (sigma_j dP_ij + sigma_i dP_ji) / (sigma_j^2 -
  sigma_i^2)``, the ``(sigma_j - sigma_i)/(sigma_j^2 - sigma_i^2) = 1/(sigma_i +
  sigma_j)`` split).

Repeated singular values: tie-breaking, then clamping
-----------------------------------------------------
At exactly repeated singular values the SVD is not differentiable, and no finite
tangent ``(dU, d sigma, dV)`` can reproduce ``dF``: the part ``S_ij`` of the
perturbation that mixes two equal singular directions only enters through
``Omega * (f(sigma_j) - f(sigma_i))``, which is exactly ``0 * finite``. So merely
clamping the denominators keeps the gradient finite but makes isotropic functions
such as the Hencky Kirchhoff stress ``tau = U diag(2 mu log sigma + lam sum log
sigma) U^T`` lose their whole shear response at ``F = I`` (the gradient is wrong, not
just noisy). Two rules fix this:

1. **Tie-break (forward).** The returned singular values are separated by at least
   ``gap = g * |sigma|_max`` in magnitude: ``|sigma_1| - |sigma_2| >= gap`` and
   ``|sigma_2| - |sigma_3| >= gap``, with ``g = 2e-6`` for float32 (and narrower
   types) and ``g = 5e-11`` for float64. The perturbation is the minimal centred one
   (least-squares isotonic fit; e.g. ``(1, 1, 1) -> (1 + gap, 1, 1 - gap)``, so
   ``det`` and ``sum(log sigma)`` change only at second order), and it is exactly zero
   when the singular values are already separated by ``gap``. So :func:`svd` returns
   the exact SVD of a matrix within relative distance ``~1.5 g`` of ``F`` (a backward
   error below the accuracy targets, 1e-5 / 1e-10). With every
   ``|sigma_j - sigma_i|`` and ``|sigma_i + sigma_j|`` at least ``gap``, the ratios
   ``(f(sigma_j) - f(sigma_i)) / (sigma_j - sigma_i)`` that isotropic functions
   build from the tangents are divided differences of ``f`` over a step ``gap``, i.e.
   ``f'(sigma) + O(gap)``, so their gradients are correct at ``F = I`` and near it.
   The derivative rule treats the tie-break as a constant perturbation (``d sigma`` is
   that of the unperturbed SVD). Round-off in such divided differences is
   ``~ eps |f| / gap``: below 3e-6 relative in float64 in the tests (exact at
   ``F = I`` itself, where ``U = V = I``), but up to a few per cent in float32, where
   derivatives at (near-)repeated singular values other than ``F = I`` are only
   guaranteed finite.
2. **Clamp (derivative).** As a safety net (it can only act when ``F ~ 0``, where the
   tie-break gap vanishes), every denominator ``d`` is replaced by a sign-preserving
   clamp ``sign(d) * max(|d|, gap / 2)`` with ``sign(0) = +1`` and the gap floored at
   ``g * sqrt(tiny)``; divisions use the double-``where`` idiom, never ``nan_to_num``.

Conventions
-----------
``F = U @ diag(sigma) @ V^T`` with ``U`` and ``V`` proper rotations (``det = +1``) and
``|sigma_1| > |sigma_2| (> |sigma_3|)`` (strictly, by the tie-break, unless ``F = 0``), all
``sigma_i >= 0`` except the last one,
which carries the sign of ``det F`` (the "rotation-variant SVD" of MPM codes).
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..fusion import always_true, compute_once
from .base import matmul

__all__ = ["svd"]

# Relative tie-break gap between consecutive singular values (see module docstring).
_GAP_F32 = 2e-6
_GAP_F64 = 5e-11
# Number of cyclic one-sided Jacobi sweeps in 3D (each sweep = 3 Givens rotations).
_SWEEPS_F32 = 4
_SWEEPS_F64 = 5


def _gap_and_sweeps(dtype) -> tuple[float, int]:
    if jnp.dtype(dtype).itemsize >= 8:
        return _GAP_F64, _SWEEPS_F64
    return _GAP_F32, _SWEEPS_F32


def _safe_div(num, den):
    """``num / den`` where ``den != 0``, else 0 (double ``where``: no NaN in gradients)."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _givens(x, y):
    """Rotation ``(c, s)`` with ``c x + s y = hypot(x, y)`` and ``-s x + c y = 0``;
    ``(1, 0)`` when ``x = y = 0``."""
    r = jnp.sqrt(x * x + y * y)
    ok = r > 0
    r_safe = jnp.where(ok, r, 1.0)
    c = jnp.where(ok, x / r_safe, 1.0)
    s = jnp.where(ok, y / r_safe, 0.0)
    return c, s


# ---------------------------------------------------------------------------------
# Tie-break: minimal centred separation of the singular-value magnitudes.
# ---------------------------------------------------------------------------------


def _separate2(a1, a2, gap):
    """Magnitudes ``a1 >= a2 >= 0`` -> ``a1' - a2' >= gap`` (least-squares, centred)."""
    h = 0.5 * gap
    b1, b2 = a1 - h, a2 + h
    avg = 0.5 * (b1 + b2)
    c1 = jnp.maximum(b1, avg)
    c2 = jnp.minimum(b2, avg)
    # c_i - b_i is exactly 0 when no separation is needed, so a_i is returned bit-exact.
    n1 = a1 + (c1 - b1)
    n2 = jnp.maximum(a2 + (c2 - b2), 0.0)
    n1 = jnp.maximum(n1, n2 + gap)
    return n1, n2


def _separate3(a1, a2, a3, gap):
    """Magnitudes ``a1 >= a2 >= a3 >= 0`` -> consecutive gaps ``>= gap``.

    Least-squares fit of ``a`` under the constraints: with ``a' = c + (gap, 0, -gap)``
    the constraints say ``c`` is non-increasing, so ``c`` is the isotonic regression
    of ``b = a - (gap, 0, -gap)``, which for three values has the min-max closed form
    ``c_i = min_{j<=i} max_{k>=i} mean(b_j..b_k)``. A final pass keeps ``a3' >= 0``.
    """
    b1, b2, b3 = a1 - gap, a2, a3 + gap
    m12 = 0.5 * (b1 + b2)
    m23 = 0.5 * (b2 + b3)
    m123 = (b1 + b2 + b3) / 3.0
    c1 = jnp.maximum(jnp.maximum(b1, m12), m123)
    c2 = jnp.minimum(jnp.maximum(m12, m123), jnp.maximum(b2, m23))
    c3 = jnp.minimum(jnp.minimum(m123, m23), b3)
    n1 = a1 + (c1 - b1)
    n2 = a2 + (c2 - b2)
    n3 = jnp.maximum(a3 + (c3 - b3), 0.0)
    n2 = jnp.maximum(n2, n3 + gap)
    n1 = jnp.maximum(n1, n2 + gap)
    return n1, n2, n3


# ---------------------------------------------------------------------------------
# Forward passes (structure of arrays).
# ---------------------------------------------------------------------------------


def _entries(F, d):
    return [[F[..., i, j] for j in range(d)] for i in range(d)]


def _stack(m):
    return jnp.stack([jnp.stack(row, axis=-1) for row in m], axis=-2)


def _scale(f):
    """Max-abs entry (1 where all are zero) so squares can neither overflow nor underflow."""
    m = jnp.abs(f[0][0])
    for row in f:
        for x in row:
            m = jnp.maximum(m, jnp.abs(x))
    return jnp.where(m > 0, m, 1.0)


def _svd2_impl(F):
    gap_rel, _ = _gap_and_sweeps(F.dtype)
    f = _entries(F, 2)
    m = _scale(f)
    a, b, c, d = f[0][0] / m, f[0][1] / m, f[1][0] / m, f[1][1] / m
    # M = Rot(phi) diag(sx, sy) Rot(theta): split into conformal (E, H) and
    # anti-conformal (P, G) parts.
    e = 0.5 * (a + d)
    p = 0.5 * (a - d)
    g = 0.5 * (c + b)
    h = 0.5 * (c - b)
    q = jnp.sqrt(e * e + h * h)
    r = jnp.sqrt(p * p + g * g)
    sx = q + r  # >= |sy|
    sy = _safe_div(a * d - b * c, sx)  # = q - r, without cancellation
    a1 = jnp.arctan2(g, p)
    a2 = jnp.arctan2(h, e)
    theta = 0.5 * (a2 - a1)
    phi = 0.5 * (a2 + a1)
    cp, sp = jnp.cos(phi), jnp.sin(phi)
    ct, st = jnp.cos(theta), jnp.sin(theta)
    u = [[cp, -sp], [sp, cp]]
    v = [[ct, st], [-st, ct]]  # V = Rot(-theta), V^T = Rot(theta)
    n1, n2 = _separate2(sx, jnp.abs(sy), gap_rel * sx)
    sig2 = jnp.where(sy < 0, -n2, n2)
    return u, [n1 * m, sig2 * m], v


def _svd3_impl(F):
    gap_rel, sweeps = _gap_and_sweeps(F.dtype)
    f = _entries(F, 3)
    m = _scale(f)
    # Columns of B = F V (b[j][k] = B[k, j]) and of V (v[j][k] = V[k, j]).
    b = [[f[k][j] / m for k in range(3)] for j in range(3)]
    one = jnp.ones_like(m)
    zero = jnp.zeros_like(m)
    v = [[one if k == j else zero for k in range(3)] for j in range(3)]

    def dot(x, y):
        return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]

    # One-sided (Hestenes) Jacobi: rotate column pairs of B until they are orthogonal;
    # this is two-sided Jacobi on B^T B with its entries recomputed from B each time.
    # The sweeps run in a fori_loop: unrolled, XLA duplicates the deep elementwise graph
    # across fusions, which blows up both compile time and run time.
    def sweep(_, state):
        b = [list(state[0:3]), list(state[3:6]), list(state[6:9])]
        v = [list(state[9:12]), list(state[12:15]), list(state[15:18])]
        for p, q in ((0, 1), (0, 2), (1, 2)):
            app = dot(b[p], b[p])
            aqq = dot(b[q], b[q])
            apq = dot(b[p], b[q])
            dd = aqq - app
            # t = tan(angle) that zeroes the (p, q) entry of B^T B (smaller root).
            num = 2.0 * jnp.where(dd >= 0, apq, -apq)
            den = jnp.abs(dd) + jnp.sqrt(dd * dd + 4.0 * apq * apq)
            t = _safe_div(num, den)
            cs = jax.lax.rsqrt(1.0 + t * t)
            sn = t * cs
            for cols in (b, v):
                xp, xq = cols[p], cols[q]
                cols[p] = [cs * xp[k] - sn * xq[k] for k in range(3)]
                cols[q] = [sn * xp[k] + cs * xq[k] for k in range(3)]
        return tuple(x for col in b + v for x in col)

    state = jax.lax.fori_loop(0, sweeps, sweep, tuple(x for col in b + v for x in col))
    b = [list(state[0:3]), list(state[3:6]), list(state[6:9])]
    v = [list(state[9:12]), list(state[12:15]), list(state[15:18])]

    # Sort columns by decreasing norm; a swap negates one column to keep det V = +1.
    nrm = [dot(b[j], b[j]) for j in range(3)]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        swap = nrm[i] < nrm[j]
        nrm[i], nrm[j] = jnp.where(swap, nrm[j], nrm[i]), jnp.where(swap, nrm[i], nrm[j])
        for cols in (b, v):
            xi, xj = cols[i], cols[j]
            cols[i] = [jnp.where(swap, xj[k], xi[k]) for k in range(3)]
            cols[j] = [jnp.where(swap, -xi[k], xj[k]) for k in range(3)]

    # Givens QR of B: R = G3 G2 G1 B, U = (G3 G2 G1)^T. Rows r[i][j] = R[i, j].
    r = [[b[j][i] for j in range(3)] for i in range(3)]
    u = [[one if i == j else zero for j in range(3)] for i in range(3)]  # u[i][j] = U[i, j]

    def rotate(i, k, c, s):
        # rows i, k of R <- [[c, s], [-s, c]] @ rows; columns i, k of U <- U @ G^T.
        ri, rk = r[i], r[k]
        r[i] = [c * ri[j] + s * rk[j] for j in range(3)]
        r[k] = [-s * ri[j] + c * rk[j] for j in range(3)]
        for row in u:
            ui, uk = row[i], row[k]
            row[i] = c * ui + s * uk
            row[k] = -s * ui + c * uk

    c, s = _givens(r[0][0], r[1][0])
    rotate(0, 1, c, s)
    c, s = _givens(r[0][0], r[2][0])
    rotate(0, 2, c, s)
    c, s = _givens(r[1][1], r[2][1])
    rotate(1, 2, c, s)
    s1, s2, s3 = r[0][0], r[1][1], r[2][2]  # s1, s2 >= 0; s3 carries sign(det F)

    n1, n2, n3 = _separate3(s1, s2, jnp.abs(s3), gap_rel * s1)
    n3 = jnp.where(s3 < 0, -n3, n3)
    return u, [n1 * m, n2 * m, n3 * m], [[v[j][i] for j in range(3)] for i in range(3)]


def _svd_soa(F):
    """``(u, s, v)``: nested lists of batch-shaped arrays, ``u[i][j] = U[..., i, j]``."""
    return _svd2_impl(F) if F.shape[-1] == 2 else _svd3_impl(F)


def _pack(u, s, v):
    return _stack(u), jnp.stack(s, axis=-1), _stack(v)


# ---------------------------------------------------------------------------------
# Derivative.
# ---------------------------------------------------------------------------------


def _clamp_signed(d, lo):
    """``sign(d) * max(|d|, lo)`` with ``sign(0) = +1`` (never 0 when ``lo > 0``)."""
    return jnp.where(jnp.abs(d) >= lo, d, jnp.where(d < 0, -lo, lo))


@jax.custom_jvp
def _svd(F):
    return _pack(*_svd_soa(F))


def _rule_coefficients(sigma: Array) -> tuple[Array, Array]:
    """The derivative rules' primal-only coefficients ``(k_sym, k_skew)``, ``(..., D, D)``:
    ``k_sym[i, j] = 0.5 / (sigma_j - sigma_i)`` (antisymmetric) and ``k_skew[i, j] =
    0.5 / (sigma_i + sigma_j)`` (symmetric), zero on the diagonal (so is Omega); one division
    per pair ``i < j``, the denominators clamped (see the module docstring)."""
    n = sigma.shape[-1]
    gap_rel, _ = _gap_and_sweeps(sigma.dtype)
    floor = float(np.sqrt(np.finfo(jnp.dtype(sigma.dtype)).tiny))
    # Clamp level: half the tie-break gap, so it can only act when F ~ 0.
    lo = (0.5 * gap_rel) * jnp.maximum(jnp.abs(sigma[..., 0]), floor)
    zero = jnp.zeros_like(sigma[..., 0])
    k_sym, k_skew = [[zero] * n for _ in range(n)], [[zero] * n for _ in range(n)]
    for i, j in itertools.combinations(range(n), 2):
        a = 0.5 / _clamp_signed(sigma[..., j] - sigma[..., i], lo)
        k_sym[i][j], k_sym[j][i] = a, -a
        k_skew[i][j] = k_skew[j][i] = 0.5 / _clamp_signed(sigma[..., i] + sigma[..., j], lo)
    return _stack(k_sym), _stack(k_skew)


def _rotated_tangent(U: Array, V: Array, dF: Array) -> Array:
    """``dP = U^T dF V``."""
    return matmul(matmul(U.mT, dF), V)


def _singular_tangents(U: Array, sigma: Array, V: Array, dF: Array) -> tuple[Array, Array, Array]:
    """The SVD's tangent in its own bases: ``d sigma`` and ``Omega_U = U^T dU``,
    ``Omega_V = V^T dV`` (the module docstring's split form)."""
    k_sym, k_skew = _rule_coefficients(sigma)
    dP = _rotated_tangent(U, V, dF)
    dPt = jnp.swapaxes(dP, -1, -2)
    sym = (dP + dPt) * k_sym
    skew = (dP - dPt) * k_skew
    # (the diagonal's entries stacked: ``jnp.diagonal`` is a gather, 3.7 CPU ms per step at
    # k = 6 tangents)
    dsigma = jnp.stack([dP[..., i, i] for i in range(dP.shape[-1])], axis=-1)
    return dsigma, sym + skew, sym - skew


def _factors_once(F: Array) -> tuple[Array, Array, Array]:
    """``(U, sigma, V)`` of :func:`svd`, computed once and stored (a conditional).

    The rules need the three factors of one decomposition. Where singular values repeat, the
    decomposition is not unique (any rotation of the repeated pair's plane is one), so two
    evaluations that round differently can return ``U`` of one decomposition and ``V`` of
    another. XLA re-computes elementwise work inside each consumer's fusion, and its CPU
    backend's classic emitters rounded those copies differently: at two equal singular values
    the Hencky stress's gradient came out 10^2-10^4 times its size off
    (``tests/test_svd.py::test_grad_isotropic_matches_fd``, which the suite runs on those
    emitters). Stored once, the factors are consistent whatever the compiler does.
    """
    return compute_once(lambda F: _pack(*_svd_soa(F)), F, token=always_true(F))


@_svd.defjvp
def _svd_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, sigma, V = _factors_once(F)
    dsigma, omega_u, omega_v = _singular_tangents(U, sigma, V, dF)
    return (U, sigma, V), (matmul(U, omega_u), dsigma, matmul(V, omega_v))


@jax.custom_jvp
def _polar_rotation(F):
    U, _, V = _pack(*_svd_soa(F))
    return matmul(U, V.mT)


@_polar_rotation.defjvp
def _polar_rotation_jvp(primals, tangents):
    # dR = dU V^T + U dV^T = U (Omega_U - Omega_V) V^T, and Omega_U - Omega_V = 2 skew: the
    # symmetric part and dU, dV themselves are never formed (4 small products, not 6).
    # The factors and the coefficients are computed once (a conditional): XLA's fusion
    # otherwise re-derived the SVD's sorting and QR and the divisions for every entry of dR
    # and tangent (1.65 of the corotated material's 5.2 CPU ms per step of a one-tangent
    # Jacobian at 25k particles; docs/benchmarks.md, session 31).
    (F,), (dF,) = primals, tangents

    def factors(F):
        U, sigma, V = _pack(*_svd_soa(F))
        return U, V, 2.0 * _rule_coefficients(sigma)[1]

    U, V, coef = compute_once(factors, F, token=always_true(F))
    dP = _rotated_tangent(U, V, dF)
    omega = (dP - jnp.swapaxes(dP, -1, -2)) * coef
    return matmul(U, V.mT), matmul(matmul(U, omega), V.mT)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _spectral_maps(fn, F, args):
    U, sigma, V = _pack(*_svd_soa(F))
    return _compose_spectral(U, V, *fn(sigma, args))


def _compose_spectral(U, V, a, b):
    """``(U diag(a) V^T, U diag(b) U^T)``."""
    return matmul(U * a[..., None, :], V.mT), matmul(U * b[..., None, :], U.mT)


@_spectral_maps.defjvp
def _spectral_maps_jvp(fn, primals, tangents):
    # With Omega_U = U^T dU, Omega_V = V^T dV (antisymmetric) and A = U diag(a) V^T:
    # dA = U (Omega_U diag(a) - diag(a) Omega_V + diag(da)) V^T, and for B = U diag(b) U^T:
    # dB = U (Omega_U diag(b) - diag(b) Omega_U + diag(db)) U^T. dU and dV themselves are never
    # formed (6 small products per tangent, not 8).
    (F, args), (dF, dargs) = primals, tangents
    U, sigma, V = _factors_once(F)
    dsigma, omega_u, omega_v = _singular_tangents(U, sigma, V, dF)
    (a, b), (da, db) = jax.jvp(fn, (sigma, args), (dsigma, dargs))
    eye = jnp.eye(sigma.shape[-1], dtype=sigma.dtype)
    x = omega_u * a[..., None, :] - a[..., :, None] * omega_v + da[..., :, None] * eye
    y = omega_u * (b[..., None, :] - b[..., :, None]) + db[..., :, None] * eye
    return _compose_spectral(U, V, a, b), (matmul(matmul(U, x), V.mT), matmul(matmul(U, y), U.mT))


def svd(
    F: Float[Array, "*batch d d"],
) -> tuple[Float[Array, "*batch d d"], Float[Array, "*batch d"], Float[Array, "*batch d d"]]:
    """Rotation-variant SVD ``F = U @ diag(sigma) @ V^T`` of 2x2 or 3x3 matrices.

    Args:
        F: array of shape ``(..., D, D)`` with ``D`` in {2, 3} and any leading batch
            dimensions; a real floating dtype (float32 or float64). Outputs keep it.

    Returns:
        ``(U, sigma, V)`` with shapes ``(..., D, D)``, ``(..., D)``, ``(..., D, D)``:
        ``U`` and ``V`` are rotations (orthonormal, ``det = +1``); ``sigma`` is sorted
        by decreasing magnitude, ``sigma[..., :-1] >= 0`` and ``sigma[..., -1]`` has the
        sign of ``det F``. Consecutive magnitudes are separated by at least
        ``g * |sigma_1|`` (``g`` = 2e-6 in float32, 5e-11 in float64; see the module
        docstring): a tie-break that keeps derivatives of isotropic functions correct
        at repeated singular values, e.g. at ``F = I``.

    Accuracy: ``|F - U diag(sigma) V^T| / |F|`` about 1e-6 (float32) / 1e-14 (float64)
    for well-separated singular values, at most ``~1.5 g`` larger otherwise.

    Differentiable in forward and reverse mode (``jax.custom_jvp``); derivatives are
    finite everywhere, including at repeated singular values.
    """
    F = jnp.asarray(F)
    _check_input(F, "svd")
    return _svd(F)


def _check_input(F: Array, name: str) -> None:
    if F.ndim < 2 or F.shape[-1] != F.shape[-2] or F.shape[-1] not in (2, 3):
        raise ValueError(
            f"{name} expects an array of shape (..., D, D) with D in {{2, 3}}, got {F.shape}"
        )
    if not jnp.issubdtype(F.dtype, jnp.floating):
        raise TypeError(f"{name} expects a real floating-point array, got dtype {F.dtype}")


def polar_rotation(F: Float[Array, "*batch d d"]) -> Float[Array, "*batch d d"]:
    """The rotation ``R = U V^T`` of :func:`svd` (the rotation of the polar decomposition
    ``F = R S``, ``det R = +1``; for ``det F < 0`` the sign goes to ``S``), for 2x2 or 3x3
    matrices with any leading batch dimensions.

    Same value as ``U @ V.mT`` from :func:`svd` (bit for bit; under a derivative the rule's
    primal multiplies its stored factors and may round an ulp apart), with a derivative rule of
    its own:
    ``dR = U (Omega_U - Omega_V) V^T`` (4 small products per tangent instead of the 6 of
    differentiating ``U`` and ``V`` apart), finite at repeated singular values as :func:`svd`'s.
    """
    F = jnp.asarray(F)
    _check_input(F, "polar_rotation")
    return _polar_rotation(F)


def spectral_maps(fn, F: Float[Array, "*batch d d"], args) -> tuple[Float[Array, "*batch d d"], Float[Array, "*batch d d"]]:
    """``(U diag(a) V^T, U diag(b) U^T)`` with ``(a, b) = fn(sigma, args)``, from one
    :func:`svd` ``F = U diag(sigma) V^T`` (2x2 or 3x3 matrices, any leading batch dimensions):
    what a Hencky-strain material computes, the projected deformation gradient and the
    Kirchhoff stress of principal values ``a`` and ``b`` (``(..., D)`` each).

    ``fn(sigma, args)`` is any JAX function of the singular values and of ``args`` (a pytree
    of arrays, differentiated too, e.g. the material's parameters; ``fn`` must not close over
    traced values). The derivative rule works in the singular bases:
    ``dA = U (Omega_U diag(a) - diag(a) Omega_V + diag(da)) V^T`` and
    ``dB = U (Omega_U diag(b) - diag(b) Omega_U + diag(db)) U^T``, with :func:`svd`'s
    ``Omega`` coefficients (finite at repeated singular values), so ``dU`` and ``dV`` are never
    formed: 6 small products per tangent instead of 8.
    """
    F = jnp.asarray(F)
    _check_input(F, "spectral_maps")
    return _spectral_maps(fn, F, args)
