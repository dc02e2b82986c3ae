"""Parameter identification from tracked points (Levenberg–Marquardt, forward-mode Jacobians).

Parameters are named (``"mu"``, ``"kappa"``, ``"E"``, ``"nu"``, ``"yield_stress"``,
``"eta"``, ``"friction_angle"``, ``"density"``, ``"velocity"``, ``"gravity"``,
``"<collider>.friction"``, ``"<body>.<param>"``) and optimised in PAC-NeRF's spaces:
log10 for E, mu, kappa, yield_stress, eta and density; a tanh-bounded Poisson ratio;
degrees for the friction angle; linear otherwise.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .errors import JaxmpmError, ObservationError
from .model import Model, Params
from .observe import Observation
from .step import simulate

LOG10_PARAMS = frozenset({"E", "mu", "kappa", "yield_stress", "eta", "density"})
#: Poisson ratio bounds of the tanh map nu = mid + half * tanh((y - mid) / half).
NU_BOUNDS = (-0.45, 0.495)


#: Consecutive rejected Levenberg–Marquardt steps (each shrinking the trust region) after
#: which the fit stops at a stationary point.
MAX_REJECTED_STEPS = 8


class FitError(JaxmpmError, RuntimeError):
    """A fit could not start (e.g. the simulation is unstable even at small dt)."""


# --------------------------------------------------------------------------- parameter paths


def resolve_name(model: Model, params: Params, name: str) -> tuple:
    """The path of a named parameter inside ``params``.

    ``"mu"`` names the only body that has ``mu``; ``"body1.mu"`` a given body;
    ``"floor.friction"`` a collider's parameter; ``"gravity"`` the gravity vector.
    """
    if name == "gravity":
        return ("gravity",)
    if "." in name:
        owner, leaf = name.split(".", 1)
        for k, body in enumerate(model.bodies):
            if body.name == owner:
                if leaf not in params["bodies"][k]:
                    raise JaxmpmError(f"parameter {name!r}: body {owner!r} has no parameter {leaf!r}")
                return ("bodies", k, leaf)
        for k, collider in enumerate(model.colliders):
            if collider.name == owner:
                if leaf not in params["colliders"][k]:
                    raise JaxmpmError(f"parameter {name!r}: collider {owner!r} has no parameter {leaf!r}")
                return ("colliders", k, leaf)
        raise JaxmpmError(f"parameter {name!r}: no body or collider named {owner!r}")
    owners = [k for k, bp in enumerate(params["bodies"]) if name in bp]
    if not owners:
        available = sorted({key for bp in params["bodies"] for key in bp} | {"gravity"})
        raise JaxmpmError(f"unknown parameter {name!r}; this scene has: {', '.join(available)}")
    if len(owners) > 1:
        choices = ", ".join(f"{model.bodies[k].name}.{name}" for k in owners)
        raise JaxmpmError(f"parameter {name!r} is ambiguous in a scene with several bodies; use one of {choices}")
    return ("bodies", owners[0], name)


def get_param(params: Params, path: tuple):
    node = params
    for key in path:
        node = node[key]
    return node


def set_param(params: Params, path: tuple, value) -> Params:
    """A copy of ``params`` with the leaf at ``path`` replaced (pure; works under tracing)."""
    if not path:
        return value
    key, rest = path[0], path[1:]
    if isinstance(params, dict):
        out = dict(params)
        out[key] = set_param(params[key], rest, value)
        return out
    out = list(params)
    out[key] = set_param(params[key], rest, value)
    return type(params)(out)


def _leaf(name: str) -> str:
    return name.rsplit(".", 1)[-1]


def to_unconstrained(name: str, value):
    """Physical value -> optimisation variable (PAC-NeRF's spaces)."""
    leaf = _leaf(name)
    if leaf in LOG10_PARAMS:
        return jnp.log10(value)
    if leaf == "nu":
        lo, hi = NU_BOUNDS
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        return mid + half * jnp.arctanh((value - mid) / half)
    return value


def from_unconstrained(name: str, y):
    """Optimisation variable -> physical value."""
    leaf = _leaf(name)
    if leaf in LOG10_PARAMS:
        return 10.0**y
    if leaf == "nu":
        lo, hi = NU_BOUNDS
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        return mid + half * jnp.tanh((y - mid) / half)
    return y


def apply_unconstrained(model: Model, params: Params, names, y: dict) -> Params:
    """``params`` with the named leaves set from optimisation variables (cast to the leaves' dtype)."""
    for name in names:
        path = resolve_name(model, params, name)
        dtype = jnp.asarray(get_param(params, path)).dtype
        params = set_param(params, path, from_unconstrained(name, y[name]).astype(dtype))
    return params


# --------------------------------------------------------------------------- track residuals


def frame_interpolation(frame_dt: float, times: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame indices ``i0, i1`` and weights ``a`` so that ``x(t) = (1-a) x[i0] + a x[i1]``."""
    s = np.asarray(times, float) / frame_dt
    i0 = np.clip(np.floor(s + 1e-6).astype(int), 0, num_frames - 1)
    i1 = np.minimum(i0 + 1, num_frames - 1)
    a = np.where(i1 > i0, np.clip(s - i0, 0.0, 1.0), 0.0)
    a = np.where(a < 1e-6, 0.0, a)
    return i0, i1, a


def frames_needed(model: Model, times: np.ndarray) -> int:
    return max(2, int(math.ceil(float(np.max(times)) / model.frame_dt - 1e-6)) + 1)


def chamfer_residuals(sim, obs, valid):
    """Per-point nearest-neighbour distances in both directions (set-to-set, ``(M + N,)``)."""
    d2 = jnp.sum((obs[:, None, :] - sim[None, :, :]) ** 2, axis=-1)
    d2 = jnp.where(valid[:, None], d2, jnp.inf)
    obs_to_sim = jnp.where(valid, jnp.min(d2, axis=1), 0.0)
    sim_to_obs = jnp.min(d2, axis=0)
    return jnp.sqrt(jnp.concatenate([obs_to_sim, sim_to_obs]) + 1e-12)


def track_residual_fn(model: Model, observation: Observation, checkpoint: str | None = "nested"):
    """``residuals(params) -> (R,)`` comparing simulated and observed tracks.

    With ``point_ids == "particles"`` the residual is the position error of every observed
    point (NaN points contribute 0); otherwise it is the symmetric Chamfer distance per
    frame. Residuals are scaled so that ``sum(r**2)`` is the mean squared error in m^2.
    """
    if observation.positions is None:
        raise ObservationError("the observation has no 'positions' (tracks) to fit")
    obs = np.asarray(observation.positions, float)
    T, N, D = obs.shape
    if D != model.dim:
        raise ObservationError(f"observed positions are {D}-D but the scene is {model.dim}-D")
    by_id = observation.point_ids == "particles"
    if by_id and N != model.num_particles:
        raise ObservationError(
            f"observation has point_ids='particles' with {N} points but the scene has {model.num_particles} particles"
        )
    times = np.asarray(observation.times, float)
    frames = frames_needed(model, times)
    i0, i1, a = frame_interpolation(model.frame_dt, times, frames)
    valid = ~np.any(np.isnan(obs), axis=-1)
    dtype = model.bodies[0].x0.dtype
    obs_j = jnp.asarray(np.where(valid[..., None], obs, 0.0), dtype)
    valid_j = jnp.asarray(valid)
    a_j = jnp.asarray(a, dtype)[:, None, None]
    scale = 1.0 / math.sqrt(max(int(valid.sum()), 1))

    def residuals(params):
        traj = simulate(model, params, checkpoint=checkpoint, frames=frames)
        x = (1.0 - a_j) * traj.x[i0] + a_j * traj.x[i1]
        if by_id:
            r = jnp.where(valid_j[..., None], x - obs_j, 0.0)
            return scale * r.reshape(-1)
        r = jax.vmap(chamfer_residuals)(x, obs_j, valid_j)
        return (1.0 / math.sqrt(r.size)) * r.reshape(-1)

    return residuals


# --------------------------------------------------------------------------- the fit


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        params: the full parameter pytree at the estimate.
        values: fitted values by name (physical units).
        std: standard deviations by name from the Gauss–Newton covariance (physical units).
        loss: loss (mean squared error, m^2) after each accepted iteration, first = initial.
        iterations: solver iterations taken.
        seconds: wall time.
        converged: whether the solver's tolerance was met within ``max_steps``.
        message: a human-readable status.
        substeps: substeps per frame used (may exceed the model's after dt halving).
    """

    params: Params
    values: dict[str, Any]
    std: dict[str, Any]
    loss: list[float]
    iterations: int
    seconds: float
    converged: bool
    message: str
    substeps: int
    initial: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict:
        """The ``fit.json`` contract (DESIGN §5.3) plus status fields."""

        def plain(v):
            v = np.asarray(v)
            return v.item() if v.ndim == 0 else v.tolist()

        return {
            "params": {k: plain(v) for k, v in self.values.items()},
            "std": {k: plain(v) for k, v in self.std.items()},
            "loss": [float(v) for v in self.loss],
            "seconds": float(self.seconds),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "message": self.message,
            "substeps": int(self.substeps),
            "initial": {k: plain(v) for k, v in self.initial.items()},
        }


def fit(
    model: Model,
    params: Params,
    observation: Observation,
    names: list[str] | tuple[str, ...],
    *,
    max_steps: int = 40,
    rtol: float = 1e-5,
    atol: float = 1e-8,
    checkpoint: str | None = "nested",
    max_dt_halvings: int = 3,
    progress: Callable[[int, float], None] | None = None,
) -> FitResult:
    """Fit named parameters to the tracked positions of ``observation``.

    Levenberg–Marquardt (``optimistix``) with forward-mode Jacobians (one JVP per
    parameter; no reverse-mode tape). If the simulation is unstable at the initial guess
    (CFL > 1 or NaN), the number of substeps is doubled and the fit restarted, up to
    ``max_dt_halvings`` times; unstable trial steps during the fit are rejected by the
    trust region.

    Arguments:
        model: static model (its ``frames`` are extended to cover the observed times).
        params: initial parameter pytree (the initial guess for the fitted names).
        observation: an :class:`~jaxmpm.observe.Observation` with ``positions``.
        names: parameter names (see :func:`resolve_name`).
        max_steps: maximum solver iterations.
        rtol, atol: solver tolerances on the step and the loss.
        checkpoint: checkpoint policy of the rollouts.
        max_dt_halvings: how often dt may be halved when the initial guess is unstable.
        progress: optional callback ``progress(iteration, loss)``.

    Returns:
        A :class:`FitResult`.
    """
    names = list(dict.fromkeys(names))
    if not names:
        raise JaxmpmError("no parameters to fit")
    paths = {n: resolve_name(model, params, n) for n in names}
    initial = {n: np.asarray(get_param(params, p)) for n, p in paths.items()}
    for n, v in initial.items():
        if _leaf(n) in LOG10_PARAMS and np.any(v <= 0):
            raise JaxmpmError(f"initial value of {n!r} must be > 0 (fitted in log10), got {v}")
    start = time.perf_counter()
    for attempt in range(max_dt_halvings + 1):
        residual_fn = track_residual_fn(model, observation, checkpoint)
        # optimisation variables in JAX's default float (float64 when x64 is on: optimistix's
        # damping terms take that dtype), cast to the model's dtype inside the residuals
        y0 = {n: to_unconstrained(n, jnp.asarray(v, jnp.result_type(float))) for n, v in initial.items()}

        def residuals(y):
            r = residual_fn(apply_unconstrained(model, params, names, y))
            return r.astype(jnp.result_type(float))

        r0 = jax.jit(residuals)(y0)
        if bool(jnp.all(jnp.isfinite(r0))):
            break
        if attempt == max_dt_halvings:
            raise FitError(
                f"the simulation is unstable (NaN) at the initial guess even with {model.substeps} substeps per frame; "
                "try a smaller dt (more substeps) or a different initial guess"
            )
        model = model.with_substeps(2 * model.substeps)

    def fn(y, args):  # optimistix's solver interface: (residuals, aux)
        return residuals(y), None

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    options = {"jac": "fwd"}
    tags = frozenset()
    f_struct = jax.eval_shape(lambda: r0)
    state = solver.init(fn, y0, None, options, f_struct, None, tags)

    @eqx.filter_jit
    def advance(y, state):
        y, state, _ = solver.step(fn, y, None, options, state, tags)
        done, result = solver.terminate(fn, y, None, options, state, tags)
        loss = jnp.sum(state.f_info.residual**2)
        return y, state, done, result, loss

    y = y0
    losses = [float(jnp.sum(r0**2))]
    if progress is not None:
        progress(0, losses[0])
    converged, stalled, iterations = False, False, 0
    for iterations in range(1, max_steps + 1):
        y, state, done, result, loss = advance(y, state)
        # step 1 only evaluates the initial guess; later accepted steps move to a lower loss
        accepted = iterations > 1 and int(state.num_steps_since_acceptance) == 0
        if accepted:
            losses.append(float(loss))
        if progress is not None:
            progress(iterations, losses[-1])
        if bool(done):
            converged = result == optx.RESULTS.successful
            break
        # At the loss's numerical floor no trial step can decrease it, so the trust region
        # shrinks without the tolerance test ever passing: that is a stationary point too.
        if int(state.num_steps_since_acceptance) >= MAX_REJECTED_STEPS:
            converged = stalled = True
            break
    # optimistix returns the last *accepted* point as y (trial points live in the state).
    y_best = y
    final_params = apply_unconstrained(model, params, names, y_best)
    values = {n: np.asarray(get_param(final_params, p)) for n, p in paths.items()}
    std = _gauss_newton_std(residuals, y_best, names)
    if stalled:
        message = (f"converged in {iterations} iterations (the last {MAX_REJECTED_STEPS} trial steps could not "
                   "lower the loss further: a stationary point at this precision)")
    elif converged:
        message = f"converged in {iterations} iterations"
    else:
        message = f"did not converge within {max_steps} iterations; returning the best parameters so far"
    return FitResult(
        params=final_params,
        values=values,
        std=std,
        loss=losses,
        iterations=iterations,
        seconds=time.perf_counter() - start,
        converged=converged,
        message=message,
        substeps=model.substeps,
        initial=initial,
    )


def _gauss_newton_std(residuals, y: dict, names) -> dict[str, np.ndarray]:
    """Standard deviations from ``s^2 (J^T J)^-1`` with ``s^2 = RSS / (m - p)``, mapped to physical units.

    This treats residuals as independent, so it is a lower bound when they are correlated.
    """
    flat, unravel = jax.flatten_util.ravel_pytree(y)
    J = jax.jit(jax.jacfwd(lambda f: residuals(unravel(f))))(flat)
    r = jax.jit(residuals)(y)
    J, r = np.asarray(J, float), np.asarray(r, float)
    m, p = J.shape
    s2 = float(r @ r) / max(m - p, 1)
    cov = s2 * np.linalg.pinv(J.T @ J)
    std_y = unravel(jnp.asarray(np.sqrt(np.clip(np.diag(cov), 0.0, None)), flat.dtype))
    out = {}
    for n in names:
        slope = jax.vmap(jax.grad(lambda t, n=n: jnp.sum(from_unconstrained(n, t))))(jnp.ravel(y[n]))
        out[n] = np.abs(np.asarray(slope).reshape(np.shape(y[n]))) * np.asarray(std_y[n])
    return out
