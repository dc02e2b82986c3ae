"""The resolved standard deviation: the statistical one where the loss follows its
Gauss–Newton model, the scale at which it starts to where the loss jumps below it."""

import numpy as np
import pytest

from jaxmpm.identify.uncertainty import gauss_newton_covariance, resolved_std


def _problem(seed=0, correlated=False):
    """A linear least-squares problem r(y) = J (y - y_hat) + e at its optimum y_hat."""
    rng = np.random.default_rng(seed)
    m, p = 200, 2
    J = rng.normal(size=(m, p))
    if correlated:  # the second column nearly the first: a long, thin valley
        J[:, 1] = J[:, 0] + 0.05 * J[:, 1]
    e = 0.01 * rng.normal(size=m)
    e -= J @ np.linalg.lstsq(J, e, rcond=None)[0]  # residual orthogonal to J: y_hat is the optimum
    y_hat = np.array([2.0, 4.5])
    return J, e, y_hat


def _std(J, r):
    return np.sqrt(np.diag(gauss_newton_covariance(J, r)))


def _smooth_loss(J, r, y_hat):
    return lambda point: float(np.sum((r + J @ (np.asarray(point, np.float64) - y_hat)) ** 2))


@pytest.mark.parametrize("correlated", [False, True])
def test_a_smooth_loss_keeps_its_statistical_std(correlated):
    J, r, y_hat = _problem(correlated=correlated)
    std = _std(J, r)
    out, resolved = resolved_std(_smooth_loss(J, r, y_hat), y_hat, r, J, std, dtype=np.float64)
    np.testing.assert_array_equal(out, std)
    assert resolved.all()


def test_rounding_of_the_probe_points_does_not_raise_a_smooth_std():
    """float32 points round a move of a tiny std to zero or to a few ulps; the model is compared
    for the move as rounded, so an exact quadratic still keeps its std (1e-9 here)."""
    J, r, y_hat = _problem()
    y32 = np.asarray(y_hat, np.float32).astype(np.float64)
    out, resolved = resolved_std(_smooth_loss(J, r, y32), y32, r, J, np.array([1e-9, 1e-9]), dtype=np.float32)
    np.testing.assert_array_equal(out, [1e-9, 1e-9])
    assert resolved.all()


def test_a_loss_with_jumps_is_resolved_only_where_its_curvature_beats_them():
    """The smooth loss plus jumps of size B on a lattice of spacing w in both variables (each
    cell a pseudo-random level): a move h along variable i changes the model by h^2 / a_ii
    (a = (JᵀJ)⁻¹), so the loss follows the model only from h ~ sqrt(B a_ii) on."""
    J, r, y_hat = _problem()
    std = _std(J, r)
    B, w = 1e-2, 1e-5

    def rough(point):
        cell = np.floor((np.asarray(point, np.float64) - y_hat) / w).astype(np.int64)
        level = ((cell[0] * 73856093) ^ (cell[1] * 19349663)) % 1000 / 1000.0
        return _smooth_loss(J, r, y_hat)(point) + B * level

    out, resolved = resolved_std(rough, y_hat, r, J, std, dtype=np.float64)
    a = np.diag(np.linalg.inv(J.T @ J))
    crossover = np.sqrt(B * a)
    assert resolved.all()
    assert np.all(out > 3 * std), (out, std)  # the statistical std claims far more than the loss resolves
    assert np.all(out > 0.3 * crossover) and np.all(out < 10 * crossover), (out, crossover)


def test_a_loss_that_never_follows_its_model_is_unresolved_up_to_the_cap():
    J, r, y_hat = _problem()
    std = _std(J, r)
    noise = np.random.default_rng(3)
    out, resolved = resolved_std(lambda point: _smooth_loss(J, r, y_hat)(point) + 1e6 * noise.uniform(),
                                 y_hat, r, J, std, cap=0.5, dtype=np.float64)
    assert not resolved.any()
    np.testing.assert_allclose(out, 0.5 * (1 + np.abs(y_hat)))


def test_a_rollout_that_fails_further_out_leaves_the_scale_reached():
    """A NaN loss (an unstable rollout) at a large move counts as not following the model."""
    J, r, y_hat = _problem()
    std = _std(J, r)

    def blows_up(point):
        move = np.abs(np.asarray(point) - y_hat).max()
        return np.nan if move > 1e-3 else _smooth_loss(J, r, y_hat)(point) + 1.0 * (move > 0)

    out, resolved = resolved_std(blows_up, y_hat, r, J, std, cap=0.5, dtype=np.float64)
    assert not resolved.any() and np.all(np.isfinite(out)) and np.all(out > std)
