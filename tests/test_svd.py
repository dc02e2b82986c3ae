"""Tests of jaxmpm.constitutive.svd: forward accuracy, conventions, derivatives."""

import functools
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.constitutive import Viscoplastic
from jaxmpm.constitutive.models import _hencky

svd_mod = importlib.import_module("jaxmpm.constitutive.svd")
svd = svd_mod.svd
polar_rotation = svd_mod.polar_rotation
spectral_maps = svd_mod.spectral_maps

MU, LAM = 1.3, 0.7
# Reconstruction tolerance (relative, Frobenius): accuracy target plus the tie-break.
REC_TOL = {np.float32: 1e-5, np.float64: 2e-10}
ORTH_TOL = {np.float32: 3e-6, np.float64: 1e-13}


@pytest.fixture(params=[np.float32, pytest.param(np.float64, marks=pytest.mark.x64)], ids=["f32", "f64"])
def dtype(request):
    return request.param


def _rot(rng, n, d):
    """n random rotations (det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(n, d, d)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]
    q[:, :, 0] *= np.sign(np.linalg.det(q))[:, None]
    return q


def _compose(U, s, V):
    return np.einsum("...ij,...j,...kj->...ik", U, s, V)


def _special(d, rng):
    """A batch of awkward matrices: near-singular, det < 0, rotations, diagonal, I,
    repeated singular values, rank-deficient, zero."""
    n = 6
    eye = np.eye(d)
    mats = [
        eye,
        np.zeros((d, d)),
        -eye,
        2.0 * eye,
        np.diag([3.0, -1.0, 2.0][:d]),  # unsorted diagonal with a negative entry
        np.diag([-2.0, -0.5, 1.0][:d]),  # det > 0 with two negative entries (d = 3)
        np.diag([1e-7, 1.0, 1e-9][:d]),
    ]
    mats += list(_rot(rng, n, d))  # rotations: all singular values equal
    mats += list(_rot(rng, n, d) @ np.diag([1.0] * (d - 1) + [-1.0]))  # reflections
    rep = [2.0, 2.0, 1.0][:d] if d == 3 else [2.0, 2.0]
    rep_low = [2.0, 1.0, 1.0][:d] if d == 3 else [0.5, 0.5]
    for sv in (rep, rep_low, [1.0, 1e-6, 1e-6][:d], [1.0, 0.5, 0.0][:d], [1.0, 0.0, 0.0][:d],
               [1.5, 1.0, -1e-8][:d], [1.0, 1.0, -1.0][:d], [1.0, 1.0 + 1e-9, 1.0 - 1e-9][:d]):
        mats += list(_rot(rng, 3, d) @ np.diag(sv) @ np.swapaxes(_rot(rng, 3, d), 1, 2))
    mats += list(eye + 1e-7 * rng.normal(size=(n, d, d)))
    mats += list(rng.integers(-2, 3, size=(n, d, d)).astype(float))
    return np.stack(mats)


def _check(F, U, s, V, dtype):
    F = np.asarray(F, np.float64)
    U, s, V = (np.asarray(x, np.float64) for x in (U, s, V))
    d = F.shape[-1]
    assert U.shape == F.shape and V.shape == F.shape and s.shape == F.shape[:-1]
    assert np.isfinite(U).all() and np.isfinite(s).all() and np.isfinite(V).all()
    nrm = np.linalg.norm(F, axis=(-2, -1))
    err = np.linalg.norm(_compose(U, s, V) - F, axis=(-2, -1))
    assert np.all(err <= REC_TOL[dtype] * np.maximum(nrm, 1e-30)), err.max()
    for Q in (U, V):
        gram = np.swapaxes(Q, -1, -2) @ Q
        assert np.abs(gram - np.eye(d)).max() < ORTH_TOL[dtype]
        assert np.all(np.linalg.det(Q) > 0.5)  # proper rotations
    # Ordering: |sigma| strictly decreasing; only the last one may be negative, and it
    # carries the sign of det F.
    mag = np.abs(s)
    nonzero = mag[..., :1] > 0  # the zero matrix gets sigma = 0 exactly
    assert np.all((mag[..., :-1] > mag[..., 1:]) | ~nonzero)
    assert np.all(s[..., :-1] >= 0)
    det = np.linalg.det(F)
    clear = np.abs(det) > 1e-3 * nrm**d
    assert np.all(np.sign(s[..., -1][clear]) == np.sign(det[clear]))


N_RANDOM = 2000


@functools.lru_cache(maxsize=None)
def _run_forward(dim, dtype):
    """One jitted call (one compile) per (dim, dtype): svd of [random; special] matrices
    with two batch dims (1, N, D, D), and vmap(vmap(svd)) of the first 12 random ones
    viewed as (3, 4, D, D)."""
    rng = np.random.default_rng(0)
    F = np.concatenate([rng.normal(size=(N_RANDOM, dim, dim)), _special(dim, rng)]).astype(dtype)

    @jax.jit
    def run(F):
        return svd(F[None]), jax.vmap(jax.vmap(svd))(F[:12].reshape(3, 4, dim, dim))

    (U, s, V), vm = run(F)
    return F, (U[0], s[0], V[0]), (U.shape, s.shape, V.shape), vm


def _forward(dim, dtype):
    F, (U, s, V), _, _ = _run_forward(dim, dtype)
    return F, U, s, V


def test_random_reconstruction(dim, dtype):
    F, U, s, V = (x[:N_RANDOM] for x in _forward(dim, dtype))
    assert U.dtype == dtype and s.dtype == dtype and V.dtype == dtype
    _check(F, U, s, V, dtype)


def test_sigma_matches_numpy(dim, dtype):
    F, _, s, _ = (x[:N_RANDOM] for x in _forward(dim, dtype))
    ref = np.linalg.svd(F.astype(np.float64), compute_uv=False)
    relerr = np.abs(np.abs(np.asarray(s, np.float64)) - ref) / ref[:, :1]
    assert relerr.max() < (2e-6 if dtype == np.float32 else 1e-13)


def test_special_matrices(dim, dtype):
    F, U, s, V = (x[N_RANDOM:] for x in _forward(dim, dtype))
    _check(F, U, s, V, dtype)
    # Exact zero stays zero; the identity gets sigma = 1 up to the tie-break.
    assert np.all(np.asarray(s[1]) == 0)
    np.testing.assert_allclose(np.asarray(s[0]), 1.0, atol=5 * REC_TOL[dtype])
    # Well-separated diagonal input: exact result, bit for bit (no tie-break applied).
    expect = [3.0, 2.0, -1.0] if dim == 3 else [3.0, -1.0]
    assert np.asarray(s[4]).tolist() == expect


def test_batch_dims_vmap_jit(dim, dtype):
    F, (U, s, V), shapes, (Uv, sv, Vv) = _run_forward(dim, dtype)
    n = len(F)
    assert shapes == ((1, n, dim, dim), (1, n, dim), (1, n, dim, dim))
    assert Uv.shape == (3, 4, dim, dim) and sv.shape == (3, 4, dim) and Vv.shape == (3, 4, dim, dim)
    tol = 1e-6 if dtype == np.float32 else 1e-14
    for a, b in ((U, Uv), (s, sv), (V, Vv)):
        a12 = np.asarray(a[:12])
        np.testing.assert_allclose(a12, np.asarray(b).reshape(a12.shape), atol=tol)


def test_rejects_bad_input():
    with pytest.raises(ValueError):
        svd(jnp.zeros((3, 2)))
    with pytest.raises(ValueError):
        svd(jnp.zeros((4, 4)))
    with pytest.raises(TypeError):
        svd(jnp.zeros((3, 3), dtype=jnp.int32))
    with pytest.raises(ValueError, match="polar_rotation expects an array of shape"):
        polar_rotation(jnp.zeros((4, 4)))
    with pytest.raises(TypeError, match="polar_rotation expects a real floating-point array"):
        polar_rotation(jnp.zeros((3, 3), dtype=jnp.int32))
    with pytest.raises(ValueError, match="spectral_maps expects an array of shape"):
        spectral_maps(_principal, jnp.zeros((3, 2)), {})


# ---------------------------------------------------------------------------------
# Derivatives.
# ---------------------------------------------------------------------------------


def _random_separated(rng, n, d):
    """Random F = R1 diag(s) R2^T with well-separated |s| (and some det < 0)."""
    s = np.sort(rng.uniform(0.3, 2.0, size=(n, d)), axis=1)[:, ::-1].copy()
    s += np.arange(d)[::-1] * 0.3  # gaps >= 0.3
    s[::2, -1] *= -1
    return _rot(rng, n, d) @ (s[:, :, None] * np.swapaxes(_rot(rng, n, d), 1, 2))


@pytest.mark.x64
def test_jvp_matches_finite_differences(dim):
    rng = np.random.default_rng(3)
    F = _random_separated(rng, 16, dim)
    dF = rng.normal(size=F.shape)
    h = 1e-6

    @jax.jit
    def run(F, dF):
        return jax.jvp(svd, (F,), (dF,)), svd(jnp.stack([F + h * dF, F - h * dF]))

    ((U, s, V), (dU, ds, dV)), ((Up, Um), (sp, sm), (Vp, Vm)) = run(F, dF)
    for t, p, m in ((ds, sp, sm), (dU, Up, Um), (dV, Vp, Vm)):
        fd = (np.asarray(p) - np.asarray(m)) / (2 * h)
        np.testing.assert_allclose(np.asarray(t), fd, rtol=0, atol=1e-7 * (1 + np.abs(fd).max()))
    # Tangents are consistent with F = U diag(s) V^T, and U^T dU, V^T dV are antisymmetric.
    dF_rec = _compose(dU, s, V) + _compose(U, ds, V) + _compose(U, s, dV)
    np.testing.assert_allclose(dF_rec, dF, atol=1e-10)
    for Q, dQ in ((U, dU), (V, dV)):
        om = np.swapaxes(np.asarray(Q), -1, -2) @ np.asarray(dQ)
        np.testing.assert_allclose(om, -np.swapaxes(om, -1, -2), atol=1e-12)


def test_rotation_tangents_stay_rotations_at_ties(dim, dtype):
    """``U^T dU`` and ``V^T dV`` are antisymmetric (U and V stay rotations to first order) and
    finite on the awkward matrices too: repeated and zero singular values, down to F = 0,
    where the tie-break gap vanishes and only the rule's clamp acts (it must keep the
    coefficients' antisymmetry)."""
    rng = np.random.default_rng(8)
    F = _special(dim, rng).astype(dtype)
    dF = rng.normal(size=F.shape).astype(dtype)
    (U, _, V), (dU, _, dV) = jax.jit(lambda F, dF: jax.jvp(svd, (F,), (dF,)))(F, dF)
    for Q, dQ in ((U, dU), (V, dV)):
        om = np.swapaxes(np.asarray(Q, np.float64), -1, -2) @ np.asarray(dQ, np.float64)
        assert np.isfinite(om).all()
        asymmetry = np.abs(om + np.swapaxes(om, -1, -2)).max(axis=(-2, -1))
        assert (asymmetry <= 10 * ORTH_TOL[dtype] * np.abs(om).max(axis=(-2, -1))).all(), asymmetry


def _rotation_via_svd(F):
    U, _, V = svd(F)
    return svd_mod.matmul(U, V.mT)


def test_polar_rotation_is_svds_rotation_with_its_derivatives(dim, dtype):
    """:func:`polar_rotation`'s own rule (``dR = U (Omega_U - Omega_V) V^T``) agrees with
    differentiating ``U V^T`` through :func:`svd`: same value (bit for bit outside a
    derivative; the rule's primal multiplies the factors it stores, which may round apart by
    an ulp), same tangents (forward mode) and cotangents (reverse mode, the rule transposed),
    on separated and on awkward matrices; its tangents are rotation tangents (``R^T dR``
    antisymmetric) and finite down to F = 0."""
    rng = np.random.default_rng(9)
    F = np.concatenate([_random_separated(rng, 16, dim), _special(dim, rng)]).astype(dtype)
    dF = rng.normal(size=F.shape).astype(dtype)
    W = rng.normal(size=F.shape).astype(dtype)

    @jax.jit
    def run(F, dF):
        out = []
        for rot in (polar_rotation, _rotation_via_svd):
            R, dR = jax.jvp(rot, (F,), (dF,))
            out.append((R, dR, jax.grad(lambda F: jnp.sum(W * rot(F)))(F)))
        return out

    (R, dR, g), (R_ref, dR_ref, g_ref) = (tuple(np.asarray(x, np.float64) for x in t) for t in run(F, dF))
    np.testing.assert_array_equal(jax.jit(polar_rotation)(F), jax.jit(_rotation_via_svd)(F))
    np.testing.assert_allclose(R, R_ref, rtol=0, atol=np.finfo(dtype).eps)  # |R_ij| <= 1
    separated = slice(0, 16)  # at ties both rules are finite but huge, and round apart
    tol = 10 * ORTH_TOL[dtype]
    for mine, ref in ((dR, dR_ref), (g, g_ref)):
        np.testing.assert_allclose(mine[separated], ref[separated], rtol=0,
                                   atol=tol * np.abs(ref[separated]).max())
    om = np.swapaxes(R, -1, -2) @ dR
    assert np.isfinite(om).all() and np.isfinite(g).all()
    asymmetry = np.abs(om + np.swapaxes(om, -1, -2)).max(axis=(-2, -1))
    assert (asymmetry <= tol * np.abs(om).max(axis=(-2, -1))).all(), asymmetry


@pytest.mark.x64
def test_polar_rotation_jvp_matches_finite_differences(dim):
    rng = np.random.default_rng(10)
    F = _random_separated(rng, 16, dim)
    _assert_jvp_matches_central_differences(polar_rotation, (F,), (rng.normal(size=F.shape),))


def _assert_jvp_matches_central_differences(fn, primals, tangents, h=1e-6):
    """``jax.jvp(fn)`` against ``(fn(x + h t) - fn(x - h t)) / 2h``, every output leaf."""
    def shifted(sign):
        return fn(*jax.tree_util.tree_map(lambda x, t: x + sign * h * t, primals, tangents))

    out = jax.jvp(fn, primals, tangents)[1]
    for t, a, b in zip(*(jax.tree_util.tree_leaves(o) for o in (out, shifted(1), shifted(-1)))):
        fd = (np.asarray(a) - np.asarray(b)) / (2 * h)
        np.testing.assert_allclose(np.asarray(t), fd, rtol=0, atol=1e-7 * (1 + np.abs(fd).max()))


def _principal(sigma, p):
    """Principal values of the spectral-map tests: coupled across sigma, and through ``p``."""
    eps = jnp.log(jnp.maximum(jnp.abs(sigma), 0.05))
    return jnp.exp(p["s"] * eps), p["m"] * eps + p["l"] * jnp.sum(eps, axis=-1, keepdims=True)


def _spectral_via_svd(F, p):
    U, sigma, V = svd(F)
    a, b = _principal(sigma, p)
    return svd_mod.matmul(U * a[..., None, :], V.mT), svd_mod.matmul(U * b[..., None, :], U.mT)


def test_spectral_maps_match_the_svd_path_with_derivatives(dim, dtype):
    """:func:`spectral_maps`' own rule (tangents in the singular bases, no ``dU``/``dV``) agrees
    with composing ``U diag(a) V^T`` and ``U diag(b) U^T`` from :func:`svd`: same values, same
    tangents and cotangents with respect to F and to the parameters of the principal-value
    function, on separated matrices; finite on the awkward ones down to F = 0."""
    rng = np.random.default_rng(11)
    F = np.concatenate([_random_separated(rng, 16, dim), _special(dim, rng)]).astype(dtype)
    dF = rng.normal(size=F.shape).astype(dtype)
    p = {k: jnp.asarray(v, dtype) for k, v in (("s", 0.8), ("m", 2.0), ("l", 0.5))}
    dp = {k: jnp.asarray(v, dtype) for k, v in (("s", 0.3), ("m", -1.0), ("l", 0.7))}
    W = [rng.normal(size=F.shape).astype(dtype) for _ in range(2)]

    @jax.jit
    def run(F, dF, p, dp):
        out = []
        for fn in (lambda F, p: spectral_maps(_principal, F, p), _spectral_via_svd):
            values, tangents = jax.jvp(fn, (F, p), (dF, dp))
            grads = jax.grad(lambda F, p: sum(jnp.sum(w * x) for w, x in zip(W, fn(F, p))), argnums=(0, 1))(F, p)
            out.append((values, tangents, grads))
        return out

    (values, tangents, grads), (values_ref, tangents_ref, grads_ref) = run(F, dF, p, dp)
    for mine, ref in zip(values, values_ref):
        np.testing.assert_array_equal(mine, ref)
    separated = slice(0, 16)
    tol = 20 * ORTH_TOL[dtype]
    for mine, ref in zip(tangents, tangents_ref):
        mine, ref = np.asarray(mine, np.float64)[separated], np.asarray(ref, np.float64)[separated]
        np.testing.assert_allclose(mine, ref, rtol=0, atol=tol * np.abs(ref).max())
    gF, gp = grads
    gF_ref, gp_ref = grads_ref
    gF, gF_ref = np.asarray(gF, np.float64), np.asarray(gF_ref, np.float64)
    np.testing.assert_allclose(gF[separated], gF_ref[separated], rtol=0, atol=tol * np.abs(gF_ref[separated]).max())
    assert all(np.isfinite(np.asarray(t)).all() for t in tangents) and np.isfinite(gF).all()
    # the parameters' cotangents sum over all matrices, awkward ones included: compare the
    # separated ones alone
    gp_sep, gp_sep_ref = jax.jit(lambda F, p: [
        jax.grad(lambda p: sum(jnp.sum(w[separated] * x) for w, x in zip(W, fn(F[separated], p))))(p)
        for fn in (lambda F, p: spectral_maps(_principal, F, p), _spectral_via_svd)])(F, p)
    for k in p:
        np.testing.assert_allclose(float(gp_sep[k]), float(gp_sep_ref[k]), rtol=tol * 10)


@pytest.mark.x64
def test_spectral_maps_jvp_matches_finite_differences(dim):
    rng = np.random.default_rng(12)
    F = _random_separated(rng, 16, dim)
    dF = rng.normal(size=F.shape)
    p = {"s": jnp.asarray(0.8), "m": jnp.asarray(2.0), "l": jnp.asarray(0.5)}
    dp = {"s": jnp.asarray(0.3), "m": jnp.asarray(-1.0), "l": jnp.asarray(0.7)}
    _assert_jvp_matches_central_differences(lambda F, p: spectral_maps(_principal, F, p), (F, p), (dF, dp))


def _jac_test_fn(F):
    U, s, V = svd(F)
    return jnp.concatenate([U.ravel(), s**2, V.ravel(), (U @ jnp.diag(s) @ V.T).ravel()])


@functools.lru_cache(maxsize=None)
def _jacobians(dim):
    """jacfwd and jacrev of _jac_test_fn at a random F and at F = I (one compile)."""
    F = _random_separated(np.random.default_rng(4), 1, dim)[0]
    run = jax.jit(lambda F: (jax.jacfwd(_jac_test_fn)(F), jax.jacrev(_jac_test_fn)(F)))
    return run(F), run(np.eye(dim))


@pytest.mark.x64
def test_jacfwd_matches_jacrev(dim):
    (jf, jr), (jf_eye, jr_eye) = _jacobians(dim)
    np.testing.assert_allclose(np.asarray(jf), np.asarray(jr), atol=1e-12)
    # d(U diag(s) V^T)/dF is the identity map.
    d2 = dim * dim
    np.testing.assert_allclose(np.asarray(jf[-d2:]).reshape(d2, d2), np.eye(d2), atol=1e-12)
    assert np.isfinite(np.asarray(jf_eye)).all() and np.isfinite(np.asarray(jr_eye)).all()


@pytest.mark.x64
def test_reconstruction_jacobian_at_identity(dim):
    # F -> U diag(sigma) V^T is the identity map. At F = I the SVD is not differentiable,
    # and a derivative that only clamps denominators loses the symmetric off-diagonal
    # part of dF entirely (error 0.5). With the tie-break it is recovered up to
    # round-off eps / gap.
    (_, _), (jf, jr) = _jacobians(dim)
    d2 = dim * dim
    for J in (jf, jr):
        np.testing.assert_allclose(np.asarray(J[-d2:]).reshape(d2, d2), np.eye(d2), atol=1e-4)


# Isotropic test functions: the library's Hencky strain and Kirchhoff stress (through svd);
# the references use only numpy's symmetric eigensolver (log of the left stretch
# V = sqrt(F F^T)), which is smooth at repeated singular values, so central differences of
# them are the truth. The library clamps sigma >= 0.05 (an inverted F is not a material
# state), so the points here have det F > 0.


def _hencky_energy(F):
    _, e, _ = _hencky(F)
    return MU * jnp.sum(e**2, axis=-1) + 0.5 * LAM * jnp.sum(e, axis=-1) ** 2


def _kirchhoff(F):
    """The viscoplastic material's stress, whose Lame pair is (MU, LAM) for kappa = LAM + 2 MU / D."""
    params = {"mu": MU, "kappa": LAM + 2 * MU / F.shape[-1]}
    batch = F.reshape((-1,) + F.shape[-2:])
    tau = Viscoplastic().kirchhoff(batch, jnp.zeros_like(batch), jnp.zeros(batch.shape[:1], F.dtype), params)
    return tau.reshape(F.shape)


def _proper(F):
    """F with the reflections among them turned into rotations (flip the last column)."""
    flip = np.where(np.linalg.det(F) < 0, -1.0, 1.0)
    F = F.copy()
    F[..., :, -1] *= flip[..., None]
    return F


def _log_stretch_ref(F):
    w, Q = np.linalg.eigh(F @ np.swapaxes(F, -1, -2))
    return np.einsum("...ij,...j,...kj->...ik", Q, 0.5 * np.log(w), Q)


def _hencky_energy_ref(F):
    L = _log_stretch_ref(F)
    tr = np.trace(L, axis1=-2, axis2=-1)
    return MU * np.sum(L * L, axis=(-2, -1)) + 0.5 * LAM * tr**2


def _kirchhoff_ref(F):
    L = _log_stretch_ref(F)
    tr = np.trace(L, axis1=-2, axis2=-1)
    return 2 * MU * L + LAM * tr[..., None, None] * np.eye(F.shape[-1])


def _central_fd(f, F, h=1e-5):
    """Batched gradient of a per-matrix scalar function by central differences."""
    G = np.zeros_like(F)
    d = F.shape[-1]
    for i in range(d):
        for j in range(d):
            E = np.zeros_like(F)
            E[..., i, j] = h
            G[..., i, j] = (f(F + E) - f(F - E)) / (2 * h)
    return G


def _grad_points(d, rng):
    """Named batches of evaluation points: random, identity, near identity, and
    exactly repeated singular values (two equal; all equal but != 1)."""
    R1, R2 = _rot(rng, 4, d), _rot(rng, 4, d)
    rep = [1.3, 1.3, 0.8][:d] if d == 3 else [1.3, 1.3]
    return {
        "random": _proper(_random_separated(rng, 4, d)),
        "identity": np.broadcast_to(np.eye(d), (4, d, d)).copy(),
        "near_identity": np.eye(d) + 1e-9 * rng.normal(size=(4, d, d)),
        "two_equal": R1 @ np.diag(rep) @ np.swapaxes(R2, 1, 2),
        "all_equal": 1.2 * R1,
    }


# Relative gradient error tolerance in float64. At exactly repeated singular values
# other than 1, round-off in the divided differences (f(s_j) - f(s_i)) / gap is
# eps * |f| / gap ~ 1e-6 (see the svd module docstring).
GRAD_TOL = {
    "random": 1e-7,
    "identity": 1e-7,
    "near_identity": 1e-7,
    "two_equal": 3e-6,
    "all_equal": 3e-6,
}


@functools.lru_cache(maxsize=None)
def _isotropic_grads(dim):
    """Values and gradients of both test functions at all _grad_points (one compile)."""
    rng = np.random.default_rng(5)
    W = rng.normal(size=(dim, dim))
    pts = _grad_points(dim, rng)
    allF = np.concatenate(list(pts.values()))

    def kirch_w(F):
        return jnp.sum(jnp.asarray(W) * _kirchhoff(F), axis=(-2, -1))

    @jax.jit
    def run(F):
        return (
            (_hencky_energy(F), jax.grad(lambda F: jnp.sum(_hencky_energy(F)))(F)),
            (kirch_w(F), jax.grad(lambda F: jnp.sum(kirch_w(F)))(F)),
        )

    (he, ghe), (kw, gkw) = run(allF)

    def kirch_w_ref(F):
        return np.sum(W * _kirchhoff_ref(F), axis=(-2, -1))

    return pts, {"hencky": (he, ghe, _hencky_energy_ref), "kirchhoff": (kw, gkw, kirch_w_ref)}


@pytest.mark.x64
@pytest.mark.parametrize("which", ["hencky", "kirchhoff"])
def test_grad_isotropic_matches_fd(dim, which):
    pts, results = _isotropic_grads(dim)
    vals, grads, f_ref = results[which]
    allF = np.concatenate(list(pts.values()))
    # Sanity: our function values match the reference.
    np.testing.assert_allclose(np.asarray(vals), f_ref(allF), atol=1e-9)
    grads = np.asarray(grads)
    assert np.isfinite(grads).all()
    k = 0
    for name, F in pts.items():
        g = grads[k : k + len(F)]
        k += len(F)
        fd = _central_fd(f_ref, F)
        scale = max(np.linalg.norm(fd), 1.0)  # the Hencky gradient vanishes at rotations
        err = np.linalg.norm(g - fd) / scale
        assert err < GRAD_TOL[name], (name, err)


def test_grads_finite_float32(dim):
    rng = np.random.default_rng(6)
    d = dim
    F = np.concatenate(
        [
            np.broadcast_to(np.eye(d), (2, d, d)),
            np.eye(d) + 1e-7 * rng.normal(size=(2, d, d)),
            _rot(rng, 2, d),
            _rot(rng, 2, d) @ np.diag([2.0, 2.0, 1.0][:d]),
            _proper(_random_separated(rng, 2, d)),
        ]
    ).astype(np.float32)
    W = rng.normal(size=(d, d)).astype(np.float32)

    def loss(F):
        return jnp.sum(_hencky_energy(F)) + jnp.sum(jnp.asarray(W) * _kirchhoff(F))

    def uv(F):
        # Depends on U and V themselves: at F = 0 (where even the tie-break gap
        # vanishes) only the clamp keeps the derivative finite.
        U, s, V = svd(F)
        return jnp.sum(U * W) + jnp.sum(V * W) + jnp.sum(s)

    g, g0 = jax.jit(lambda F: (jax.grad(loss)(F), jax.grad(uv)(jnp.zeros_like(F))))(F)
    for x in (g, g0):
        assert x.dtype == np.float32 and np.isfinite(np.asarray(x)).all()
    # The Kirchhoff-stress gradient at F = I is still right in float32.
    eye = np.broadcast_to(np.eye(d), (2, d, d)).copy()
    fd = _central_fd(lambda X: np.sum(W * _kirchhoff_ref(X), axis=(-2, -1)), eye)
    np.testing.assert_allclose(np.asarray(g[:2]), fd, rtol=0, atol=1e-3 * np.abs(fd).max())
