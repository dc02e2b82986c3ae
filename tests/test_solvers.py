"""The identification core's Levenberg–Marquardt: bounds (a minimum outside the box stops on
its bound, exactly), host residuals with Jacobians asked for only at accepted points, and the
unbounded path unchanged by the bounds' code."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.identify.solvers import levenberg_marquardt

TOL = dict(max_steps=50, rtol=1e-5, atol=1e-8)


def test_a_minimum_outside_the_bound_stops_exactly_on_it():
    """r(y) = y + 1 with y >= 0: the unconstrained minimum -1 is out of bounds; y = 0 exactly."""
    out = levenberg_marquardt(lambda y: jnp.stack([y["y"] + 1.0]), {"y": jnp.asarray(2.0)}, lower=np.array([0.0]),
                              **TOL)
    assert float(out.y["y"]) == 0.0, out.message
    assert out.converged, out.message
    # unbounded, the same problem goes to its minimum
    free = levenberg_marquardt(lambda y: jnp.stack([y["y"] + 1.0]), {"y": jnp.asarray(2.0)}, **TOL)
    assert abs(float(free.y["y"]) + 1.0) < 1e-5 and free.converged


def _coupled(y):
    """Minimum (a, b) = (-1, 2.5) without bounds; with a >= 0, (0, 2): the free b follows."""
    a, b = y[0], y[1]
    return [a + 1.0, (b - 2.0) + 0.5 * a]


def test_one_parameter_on_its_bound_and_the_other_at_its_constrained_minimiser():
    out = levenberg_marquardt(lambda y: jnp.stack(_coupled(y["ab"])), {"ab": jnp.asarray([3.0, -4.0])},
                              lower=np.array([0.0, -np.inf]), **TOL)
    a, b = np.asarray(out.y["ab"], float)
    assert a == 0.0 and abs(b - 2.0) < 1e-5, (a, b, out.message)
    assert out.converged, out.message


def test_host_residuals_with_scaling_and_bounds_evaluate_the_jacobian_only_at_accepted_points():
    """Discovery's call: host NumPy residuals and Jacobian, Marquardt scaling, a loss-decrease
    stop, an upper bound as well (b <= 1 is active too: then a = 0, b = 1)."""
    jacobians = []

    def residuals(y):
        return np.asarray(_coupled(y))

    def jacobian(y):
        jacobians.append(y.copy())
        return np.array([[1.0, 0.0], [0.5, 1.0]])

    out = levenberg_marquardt(residuals, np.array([3.0, -4.0]), jacobian=jacobian, lower=np.array([0.0, -np.inf]),
                              upper=np.array([np.inf, 1.0]), scaled=True, ftol=1e-9, **TOL)
    assert isinstance(out.y, np.ndarray) and out.converged, out.message
    np.testing.assert_array_equal(out.y, [0.0, 1.0])
    assert len(jacobians) == len(out.losses)  # the start and each accepted step, no rejected trial


def test_an_uninformative_parameter_is_held_when_scaled():
    """A parameter the residuals do not depend on stays where it is (its Jacobian column is 0)."""
    out = levenberg_marquardt(lambda y: np.array([y[0] - 1.0, 2.0 * (y[0] - 1.0)]), np.array([0.0, 5.0]),
                              jacobian=lambda y: np.array([[1.0, 0.0], [2.0, 1e-9]]), scaled=True, **TOL)
    assert abs(out.y[0] - 1.0) < 1e-5 and out.y[1] == 5.0, out.y


@pytest.mark.x64
def test_the_unbounded_path_takes_the_steps_it_took_before_bounds():
    """Pinned from the implementation before bounds were added (same residual, start and
    tolerances): 14 trial points, 14 losses and this minimum."""
    t = jnp.linspace(0.0, 1.0, 20, dtype=jnp.float64)
    data = 2.0 * jnp.exp(-1.3 * t) + 0.3 * jnp.sin(5 * t)

    def residuals(y):
        return y["a"] * jnp.exp(-y["k"] * t) + y["b"] * jnp.sin(y["w"] * t) - data

    y0 = {n: jnp.asarray(v, jnp.float64) for n, v in zip("akbw", (1.0, 0.1, 0.0, 3.0))}
    out = levenberg_marquardt(residuals, y0, max_steps=40, rtol=1e-5, atol=1e-8)
    assert out.iterations == 14 and len(out.losses) == 14, (out.iterations, out.message)
    assert out.converged
    for n, v in {"a": 2.0, "b": 0.3, "k": 1.3, "w": 5.0}.items():
        assert abs(float(out.y[n]) - v) < 1e-10
    # infinite bounds take the bounded code path to the same minimum
    boxed = levenberg_marquardt(residuals, y0, max_steps=40, rtol=1e-5, atol=1e-8, lower=np.full(4, -np.inf),
                                upper=np.full(4, np.inf))
    for n in "akbw":
        assert abs(float(boxed.y[n]) - float(out.y[n])) < 1e-8


def test_the_loss_decrease_stop_shortens_a_slow_descent(monkeypatch):
    """A large-residual fit (an exponential through scattered data) converges linearly: the
    relative decreases fall by decades over the last iterations. With ``ftol`` the fit follows
    the same path until the Gauss–Newton step promises less than ``ftol`` (or a step lowers the
    loss by less, then checked like a Cauchy pass): fewer iterations, the same loss to the
    ``ftol`` (discover sets ``ftol`` from its statistics' sample size)."""
    t = np.array([0.5, 1.0, 1.5, 2.0, 2.5])
    data = np.array([3.0, 0.2, 4.0, 0.5, 6.0])

    def residuals(y):
        return y[1] * np.exp(y[0] * t) - data

    def jacobian(y):
        return np.stack([t * y[1] * np.exp(y[0] * t), np.exp(y[0] * t)], axis=1)

    from jaxmpm.identify import solvers

    monkeypatch.setattr(solvers, "CREEP", 0.0)  # the loss-decrease stop alone (the creep stop: below)
    fit = lambda ftol: levenberg_marquardt(residuals, np.array([1.0, 0.1]), jacobian=jacobian, scaled=True,  # noqa: E731
                                           ftol=ftol, max_steps=200, rtol=1e-10, atol=1e-14)
    full, early = fit(1e-12), fit(1e-3)
    n = len(early.losses)
    np.testing.assert_array_equal(early.losses, full.losses[:n])  # the same path, cut short
    assert early.iterations < full.iterations and n < len(full.losses)
    assert early.converged and early.losses[-1] <= full.losses[-1] * (1.0 + 1e-3)
    # where it stopped, the decreases still to come add up to less than ftol ...
    assert full.losses[n - 1] - full.losses[-1] < 1e-3 * full.losses[n - 1]
    # ... and one step before, more was left: it did not stop early
    assert full.losses[n - 2] - full.losses[-1] > 1e-3 * full.losses[n - 2] or n == 1
    assert "less than ftol" in early.message, early.message


def test_a_creeping_descent_ends_at_a_gauss_newton_stationary_point(monkeypatch):
    """A large-residual fit (an exponential through scattered data) converges linearly, its
    relative decreases falling by decades: once an accepted step lowers the loss by less than
    ``CREEP`` where the undamped Gauss–Newton step is within ``1e-3 (1 + |y|)``, the stage ends
    (converged, and says why) instead of creeping on. Without the creep stop the same descent
    goes on (here for twice the iterations), lowering the loss by less than 1 % more."""
    from jaxmpm.identify import solvers

    t = np.array([0.5, 1.0, 1.5, 2.0, 2.5])
    data = np.array([0.08, 2.92, 0.63, 5.22, 2.19])  # scattered enough that its steps are not "good"

    def residuals(y):
        return y[1] * np.exp(y[0] * t) - data

    def jacobian(y):
        return np.stack([t * y[1] * np.exp(y[0] * t), np.exp(y[0] * t)], axis=1)

    def fit():
        return levenberg_marquardt(residuals, np.array([1.0, 0.1]), jacobian=jacobian, scaled=True, max_steps=300,
                                   rtol=1e-10, atol=1e-14)

    early = fit()
    assert early.converged and "less than 0.1 %" in early.message, early.message
    assert early.losses[-1] > (1.0 - solvers.CREEP) * early.losses[-2]  # the last step crept ...
    y = np.asarray(early.y)
    delta = np.linalg.lstsq(jacobian(y), -residuals(y), rcond=None)[0]
    assert np.all(np.abs(delta) <= 1e-3 * (1.0 + np.abs(y)))  # ... at a Gauss-Newton stationary point
    assert np.any(np.abs(delta) > 1e-6 * (1.0 + np.abs(y)))  # (not yet at the minimum: a real cut)
    creep = solvers.CREEP
    monkeypatch.setattr(solvers, "CREEP", 0.0)
    full = fit()
    assert full.iterations > early.iterations
    np.testing.assert_array_equal(early.losses, full.losses[: len(early.losses)])  # the same path until then
    assert full.losses[-1] < early.losses[-1] <= full.losses[-1] * (1.0 + 10 * creep)
