"""The solvers of the identification core.

* :func:`levenberg_marquardt`: optimistix's Levenberg–Marquardt algorithm run on the host over
  residuals and their Jacobian (one compiled forward-mode function for a JAX residual, or the
  caller's host functions), residuals scaled to a unit starting loss, with a Gauss–Newton test
  of what a stall means (stationary point, the loss's round-off floor, or a rough loss to escape
  by line search). It is the one least-squares solver of ``fit`` and ``discover``. Discovery
  adds options: bounds (an active set that pins a parameter on the bound its step crosses, so
  it can stop exactly there: extension parameters have their null values on bounds, a drag, a
  friction or a restitution cannot be negative, and the likelihood-ratio test is one-sided
  there; optimistix's solver has no bounds), Marquardt's scaling of the damping and a stop on
  a small relative decrease of the loss. Without them, none of their code runs: ``fit``'s
  iterates are the unbounded algorithm's, step for step.
* :func:`bfgs` (optimistix) and :func:`adam` (optax, PAC-NeRF's optimiser) on the scalar loss.

Each returns a :class:`SolverOutcome`.
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

from .parameters import ADAM_LEARNING_RATES, leaf_name

__all__ = [
    "SolverOutcome",
    "MAX_REJECTED_STEPS",
    "residuals_and_jacobian",
    "loss_function",
    "gauss_newton_step",
    "at_round_off_floor",
    "gauss_newton_escape",
    "levenberg_marquardt",
    "bfgs",
    "adam",
]

#: Consecutive rejected Levenberg–Marquardt steps (each shrinking the trust region) after
#: which the solver asks whether it stands at a stationary point.
MAX_REJECTED_STEPS = 6
#: Round-off floor tests (each one extra evaluation) a stage may spend at the first rejected
#: trial from each accepted point, before ``MAX_REJECTED_STEPS``: a rejection at the floor ends
#: the stage at once. (Further rejections from the same point would repeat the same probe.)
MAX_FLOOR_CHECKS = 4
#: ... and only when the Gauss–Newton step promises less than this fraction of the loss: near
#: a minimum the step promises the loss above its irreducible part, so a promise of less than
#: half means most of the loss is irreducible (noise or misfit); a larger promise is not at
#: the floor, and its probe would be wasted.
FLOOR_GATE = 0.5
#: An accepted step that lowers the loss by less than this fraction, and by less than
#: ``TRUST_HIGH`` of what the linear model predicted, "creeps": the stage then ends if the
#: undamped Gauss–Newton step there is within tolerance (the test the iteration cap applies),
#: instead of creeping on to the cap. Measured: silhouette velocity stages crept for 15–20
#: steps (accepted ones lowering the loss in its fifth digit, between rejections) to a cap that
#: then found the Gauss–Newton step within tolerance. A descent whose steps do what the linear
#: model predicts (a linear or zero-residual fit, however large its irreducible loss) never
#: creeps, so its tighter Cauchy test keeps deciding.
CREEP = 1e-3
#: A rejected trial whose loss rise is at least this fraction of the previous rejected trial's
#: from the same point, although the trust region shrank by ``TRUST_SHRINK`` in between, met a
#: jump of the loss (a contact or return-map switch: on a smooth loss the rise shrinks with the
#: step); the Gauss–Newton line search (:func:`gauss_newton_escape`) then tries to step over it.
JUMP = 0.5


@dataclass
class SolverOutcome:
    """What a solver returns: the parameters (optimisation space), the loss after each accepted
    iteration (first = initial), iterations, whether it converged and why (``message``), and
    whether unstable rollouts stopped it (``unhealthy_trial``) or it could not start
    (``unhealthy_start``)."""

    y: dict
    losses: list
    iterations: int
    converged: bool
    message: str
    unhealthy_trial: bool = False
    unhealthy_start: bool = False
    jacobian: Any = None  # (rj, (r, J) at y or None) when the solver has them (LM), for the covariance
    timing: dict = field(default_factory=dict)  # seconds: where the solver's time went (see the solvers)


def _rj(residuals, flat, like):
    unravel = jax.flatten_util.ravel_pytree(like)[1]
    basis = jnp.eye(flat.size, dtype=flat.dtype)
    g = lambda v: residuals(unravel(v))  # noqa: E731
    r, J = jax.vmap(lambda t: jax.jvp(g, (flat,), (t,)), out_axes=(None, 0))(basis)
    return r, J.T


# One compilation per structure: residual functions that are equinox Modules (fit's stage
# residuals) and equal up to their arrays share this program (fit's windows, its velocity
# refits, its scans and escapes). A plain function gets a program of its own.
_SHARED_RJ = eqx.filter_jit(_rj)


def residuals_and_jacobian(residuals: Callable, y0: dict):
    """``rj(flat) -> (r, J)`` (compiled) and the ravel/unravel pair of ``y0``: the residuals and
    their Jacobian by forward mode, one JVP per parameter sharing one primal rollout.

    When ``residuals`` is an equinox Module the compilation is shared with every equal one
    (same static fields, same array shapes: :class:`jaxmpm.identify.residuals.Residuals`)."""
    flat0, unravel = jax.flatten_util.ravel_pytree(y0)
    program = _SHARED_RJ if isinstance(residuals, eqx.Module) else eqx.filter_jit(_rj)
    like = jax.tree_util.tree_map(jnp.asarray, y0)
    return (lambda flat: program(residuals, flat, like)), flat0, unravel


def loss_function(residuals: Callable, y0: dict, rj=None):
    """``loss(flat) -> sum(r**2)`` by the residual-and-Jacobian program ``rj`` (default
    :func:`residuals_and_jacobian`'s): no compilation of its own, at the cost of the JVPs in
    every call. For the few losses a stage needs (a scan before it, line searches): on
    ``jaxmpm demo --video --quick`` the window stage with its seven-point scan took 42.8 s
    with a loss program of its own and 33.6 s this way (an evaluation of ``rj`` costs 0.39 s
    there, the loss's own 0.13 s; compiling that loss cost ~14 s)."""
    rj = rj or residuals_and_jacobian(residuals, y0)[0]
    return lambda flat: jnp.sum(rj(flat)[0] ** 2)


#: Step lengths tried along the Gauss–Newton direction when the trust region has collapsed.
ESCAPE_STEPS = (1.0, 0.5, 0.25, 0.125, 0.0625)
#: At most this many such escapes per stage.
MAX_ESCAPES = 4
#: The verdicts of :func:`gauss_newton_escape` that count as converged.
STATIONARY = ("stationary", "floor")


def gauss_newton_step(rj, flat, rtol) -> tuple[np.ndarray | None, bool]:
    """The undamped Gauss–Newton step at ``flat`` (``None`` if the residuals or Jacobian are
    not finite) and whether every component of it is within ``max(rtol, 1e-3) (1 + |y|)`` in
    optimisation units (decades, degrees, m/s): a stationary point at this precision."""
    r, J = (np.asarray(a, np.float64) for a in rj(flat))
    return _gauss_newton_from(r, J, np.asarray(flat, np.float64), rtol)


def _projected(solve: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], J: np.ndarray, r: np.ndarray,
               y: np.ndarray, bounds: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The point ``y + step`` of a linearised step kept within ``bounds = (lower (P,), upper (P,))``.

    ``solve(J_free (M, F), r_free (M,), free (P,) bool) -> (F,)`` is the step of the free
    parameters for the residuals ``r_free`` (``r`` plus what the pinned parameters' steps
    change). An active set: a free parameter whose step would leave the box is pinned on the
    bound it crosses (it stays put if already on it) and the others are solved again given
    that, until none leaves; so a parameter stops exactly on its bound and the others move as
    the linear model wants them to with it there. A non-finite step comes back non-finite
    (a rejected trial)."""
    lower, upper = bounds
    free = np.ones(y.shape, bool)
    fixed = y.copy()  # where the pinned parameters go: onto their bounds
    while True:
        step = np.where(free, 0.0, fixed - y)
        if free.any():
            step[free] = solve(J[:, free], r + J[:, ~free] @ step[~free], free)
        point = np.where(free, y + step, fixed)
        clipped = np.clip(point, lower, upper)
        out = free & (clipped != point)
        if not out.any():
            return point
        fixed = np.where(out, clipped, fixed)
        free &= ~out


def _gauss_newton_from(r, J, y, rtol,
                       bounds: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray | None, bool]:
    """:func:`gauss_newton_step` from residuals ``r`` and Jacobian ``J`` already evaluated at
    ``y``; within ``bounds`` (:func:`_projected`) when given."""
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return None, False
    solve = lambda A, b, free=None: np.linalg.lstsq(A, -b, rcond=None)[0]  # noqa: E731
    delta = solve(J, r) if bounds is None else _projected(solve, J, r, y, bounds) - y
    return delta, within_tolerance(delta, y, rtol)


def within_tolerance(step: np.ndarray, y: np.ndarray, rtol: float) -> bool:
    """Whether every component of ``step (P,)`` at ``y (P,)`` is within ``max(rtol, 1e-3) (1 + |y|)``
    (optimisation units: decades, degrees, m/s): the precision every LM stop test asks for."""
    return bool(np.all(np.abs(step) <= max(rtol, 1e-3) * (1.0 + np.abs(y))))


#: Largest component of the probe step that measures a loss's round-off noise, relative to
#: ``1 + |y|`` (optimisation units): far above float32's resolution, far below any fitted feature.
NOISE_PROBE = 1e-4
#: A probe's remainder above this multiple of the loss is not round-off noise but a jump (a
#: contact switch within the probe): at a pure round-off floor the remainder of two independent
#: noises is about twice the loss; across a jump it was 50 times (the viscoplastic bunny).
JUMP_NOISE = 4.0


def at_round_off_floor(rj, flat, delta, r=None, J=None) -> bool:
    """Whether the Gauss–Newton step ``delta`` at ``flat`` promises less than the loss's own
    round-off noise.

    The step's predicted decrease is ``|J delta|^2`` (``delta`` solves the linear least
    squares). The noise is measured, not assumed: a probe step ``t delta`` so short that its
    second-order term is negligible changes the residuals by ``t J delta`` plus whatever the
    rollout's round-off (amplified by contact and return-map switching) adds; that remainder
    ``|r(y + t delta) - r(y) - t J delta|^2`` is the loss change noise alone causes. When the
    promise is below it, no step can be told apart from noise: a stationary point at this
    precision (the loss's floor), though the step itself may not be small in a poorly
    determined direction. ``r, J`` at ``flat`` are evaluated unless given.

    When the whole step is short enough to be the probe and moves no residual at all (in the
    residuals' own precision), it lies below the loss's resolution: the floor too. (The
    remainder would then be the linear model's change for the step *as rounded* to the
    parameters' precision, which a component too small to round, such as a velocity
    near 0 beside one near 1 m/s, makes smaller than the promise: at 8,000 particles each
    stage used to wait for six rejected trials there.)
    """
    if r is None or J is None:
        r, J = (np.asarray(a, np.float64) for a in rj(flat))
    y = np.asarray(flat, np.float64)
    # the step's largest component, relative to 1 + |y|, becomes NOISE_PROBE
    t = min(NOISE_PROBE / max(float(np.max(np.abs(delta) / (1.0 + np.abs(y)))), 1e-300), 1.0)
    r_t = np.asarray(rj(jnp.asarray(y + t * delta, flat.dtype))[0])
    precision, r_t = r_t.dtype, r_t.astype(np.float64)  # the residuals' own precision
    y_t = np.asarray(jnp.asarray(y + t * delta, flat.dtype), np.float64)  # the probe as rounded
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J)) and np.all(np.isfinite(r_t))):
        return False
    # (compared in that precision: r may carry a float64 rescaling's last bit)
    if t == 1.0 and np.array_equal(r_t.astype(precision), np.asarray(r, np.float64).astype(precision)):
        return True
    noise = float(np.sum((r_t - r - J @ (y_t - y)) ** 2))
    promised = float(np.sum((J @ delta) ** 2))
    # a remainder many times the loss itself is a jump of the loss within the probe, not noise
    # about this point (a repeat of the rollout here could not have found the loss it did)
    return promised <= noise <= JUMP_NOISE * float(np.sum(np.asarray(r, np.float64) ** 2))


def gauss_newton_escape(loss_of, rj, flat, f, rtol, r=None, J=None,
                        bounds: tuple[np.ndarray, np.ndarray] | None = None):
    """After ``MAX_REJECTED_STEPS`` rejected trust-region steps, a rejected one within the step
    tolerance or one that met a jump of the loss (:data:`JUMP`): is this a stationary point?

    A float32 MPM loss is rough on small scales (return-map branches, contact switching), so
    the trust region can collapse far from a minimum: the local slope it sees disagrees with
    the trend. Here the undamped Gauss–Newton step ``delta`` is computed from ``(r, J)`` at
    ``flat`` and tried at the lengths ``ESCAPE_STEPS``.

    Returns ``((new_flat, new_loss), "rough")`` for the first length that lowers the loss,
    else ``(None, verdict)``: ``"stationary"`` (the test of :func:`gauss_newton_step`),
    ``"floor"`` (no length helped and the step promises less than the loss's round-off noise,
    :func:`at_round_off_floor`) or ``"rough"`` (stuck away from a stationary point).
    ``r, J`` at ``flat`` are evaluated unless given. With ``bounds`` the step and the trial
    points stay within them (:func:`_projected`).
    """
    if r is None or J is None:
        r, J = (np.asarray(a, np.float64) for a in rj(flat))
    delta, stationary = _gauss_newton_from(r, J, np.asarray(flat, np.float64), rtol, bounds)
    if delta is None:
        return None, "rough"
    if stationary:
        return None, "stationary"
    y = np.asarray(flat, np.float64)
    for alpha in ESCAPE_STEPS:
        point = y + alpha * delta if bounds is None else np.clip(y + alpha * delta, *bounds)
        trial = jnp.asarray(point, flat.dtype)
        f_t = float(loss_of(trial))
        if np.isfinite(f_t) and f_t < f:
            return (trial, f_t), "rough"
    return None, "floor" if at_round_off_floor(rj, flat, delta, r, J) else "rough"


def _lm_message(how: str, iterations: int, max_steps: int) -> str:
    """The stage message of :func:`levenberg_marquardt` for how it stopped: ``"converged"`` (tolerance
    test), ``"stationary"`` (rejected steps at a Gauss-Newton stationary point), ``"floor"``
    (rejected steps at the loss's round-off floor), ``"creep"`` (a step lowered the loss by less
    than :data:`CREEP` at a Gauss-Newton stationary point), ``"rough"``
    (stuck away from one), ``"unstable"`` (trial steps made the simulation unstable), ``"cap"``
    (iteration limit), ``"cap-stationary"`` (iteration limit at a Gauss-Newton stationary
    point: converged), ``"resolution"`` (a line search gained less than ``ftol``: converged) or
    ``"promise"`` (the Gauss-Newton step promises less than ``ftol``: converged)."""
    n = f"{iterations} iteration{'s' * (iterations != 1)}"
    return {
        "converged": f"converged in {n}",
        "stationary": (f"converged in {n} (the last trial steps could not "
                       "lower the loss further and the Gauss-Newton step is within tolerance: a stationary point "
                       "at this precision)"),
        "resolution": (f"converged in {n} (trial steps were rejected and the line search along the Gauss-Newton "
                       "step lowered the loss by less than ftol, the resolution asked for)"),
        "promise": (f"converged in {n} (the Gauss-Newton step promises to lower the loss by less than ftol, "
                    "the resolution asked for)"),
        "floor": (f"converged in {n} (at the loss's round-off floor: the Gauss-Newton step promises less than "
                  "the loss's measured round-off noise, so no step can be told from noise; parameters in poorly "
                  "determined directions are known only to their std)"),
        "rough": (f"stalled after {n} away from a stationary point: the Gauss-Newton step is "
                  "still large but neither the trust region nor a line search along it lowers the loss (a rough "
                  "loss at this precision; try another starting point or method='adam', or float64 where the "
                  "roughness is round-off rather than the model's own jumps such as CPIC's contact decisions)"),
        "unstable": f"stalled after {n}: the trial steps made the simulation unstable",
        "creep": (f"converged in {n} (the last step lowered the loss by less than "
                  f"{100 * CREEP:g} % and the Gauss-Newton step there is within tolerance: a stationary point at this "
                  "precision)"),
        "cap": f"did not converge within {max_steps} iterations",
        "cap-stationary": (f"converged in {n} (the iteration limit was reached, but the "
                           "Gauss-Newton step there is within tolerance: a stationary point at this precision)"),
    }[how]


#: With ``scaled``, a parameter whose Jacobian column's norm is at most this fraction of the
#: largest at the start is held where it is: the data carry no information about it (e.g. a
#: slip plane's motion along itself), and a damping scaled by that norm would let it run off.
INERT = 1e-5
#: ... and the first damping is this fraction of each parameter's curvature ``|J_j|^2``
#: (Marquardt's customary start: nearly a Gauss–Newton step).
MARQUARDT_START = 1e-3

#: optimistix's ClassicalTrustRegion: a step is accepted when the loss falls by at least
#: ``TRUST_LOW`` of the decrease the linear model predicts, and the step size (the inverse of
#: the damping) grows by ``TRUST_GROW`` when it falls by ``TRUST_HIGH`` of it, or shrinks by
#: ``TRUST_SHRINK`` on a rejection; the step size starts at 1.
TRUST_LOW, TRUST_HIGH, TRUST_GROW, TRUST_SHRINK = 0.01, 0.99, 3.5, 0.25


def _damped_step(r: np.ndarray, J: np.ndarray, step_size: float, eps: float, D: np.ndarray | None = None) -> np.ndarray:
    """The damped Gauss–Newton step ``argmin |J d + r|^2 + |D d|^2 / step_size`` (a least-squares
    solve of ``[J; D/sqrt(step_size)] d = [-r; 0]``; ``D (P,)`` a diagonal scaling, the identity
    when ``None``), NaN where ``r`` or ``J`` is not finite."""
    p = J.shape[1]
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return np.full(p, np.nan)
    damping = 1.0 / step_size if step_size > eps else np.finfo(np.float64).max ** 0.5
    A = np.vstack([J, math.sqrt(damping) * (np.eye(p) if D is None else np.diag(D))])
    return np.linalg.lstsq(A, np.concatenate([-r, np.zeros(p)]), rcond=None)[0]


def _cauchy_converged(rtol: float, atol: float, y, dy, r, dr) -> bool:
    """optimistix's Cauchy test: the last accepted step is small in the parameters *and* the
    residuals (max norm of the change relative to ``atol + rtol |value|``)."""
    return bool(np.max(np.abs(dy) / (atol + rtol * np.abs(y))) < 1 and np.max(np.abs(dr) / (atol + rtol * np.abs(r))) < 1)


def levenberg_marquardt(
    residuals: Callable,
    y0: Any,
    *,
    max_steps: int,
    rtol: float,
    atol: float,
    progress: Callable[[int, float], None] | None = None,
    offset: int = 0,
    jacobian: Callable[[np.ndarray], np.ndarray] | None = None,
    lower: np.ndarray | None = None,
    upper: np.ndarray | None = None,
    ftol: float | None = None,
    scaled: bool = False,
    warm: bool = False,
) -> SolverOutcome:
    """Levenberg–Marquardt on ``residuals(y) -> (M,)``, optionally within bounds.

    Arguments:
        residuals, y0: without ``jacobian``, a JAX function of the parameter pytree ``y0``
            (fit's path; the Jacobian by forward mode, :func:`residuals_and_jacobian`); with
            it, a host function ``(P,) -> (M,)`` of the float64 vector ``y0 (P,)``.
        jacobian: ``(P,) -> (M, P)`` of host residuals, evaluated only at accepted points.
        lower, upper: ``(P,)`` bounds of the flattened parameters (optimisation units; ±inf or
            ``None`` where there is none); ``y0`` is clipped into them.
        max_steps: trial points (rejected ones included); ``rtol``, ``atol``: the tolerances.
        progress: ``progress(offset + iteration, loss)`` every iteration.
        ftol: an accepted step that lowers the loss by less than this fraction also passes
            the tolerance test (then checked like the Cauchy test's pass); a line search
            (below) that lowers it by less ends the solve, converged to this resolution; and
            so does an accepted point (the start included) where the Gauss–Newton step (within
            the bounds) promises less: no trial is spent on a decrease the caller does not
            resolve (e.g. parameters the data barely see).
        scaled: damp each parameter by its own curvature (Marquardt: ``D = |J_j|`` at the
            start, first damping :data:`MARQUARDT_START` of it) instead of optimistix's
            identity, and hold the parameters the data do not see (:data:`INERT`): invariant
            to the parameters' units, for parameters of unrelated kinds.
        warm: ``y0`` is an earlier solve's result (a later stage of a fit): the round-off
            floor test below also runs before the first trial, so that a stage that starts at
            its floor costs one evaluation and a probe instead of a rejected trial as well.

    The algorithm is optimistix's ``LevenbergMarquardt`` (a damped Gauss–Newton descent in a
    classical trust region, :data:`TRUST_LOW` ...; Cauchy termination), run on the host over
    one compiled function that returns the residuals and their Jacobian together
    (:func:`residuals_and_jacobian`: one primal rollout shared by the JVPs of all parameters).
    Every trial point costs one such call; the small damped least-squares solve is NumPy's.
    (optimistix's own loop linearises the rollout and materialises the Jacobian operator
    separately, and compiles a second program: measured 1.6–3× slower per iteration and
    ~20 s more compilation per stage on the demo; see docs/fitting.md.) Residuals are scaled
    to a unit starting loss so that the first damping (1) is comparable with ``JᵀJ``.

    Converged when the Cauchy test passes (a small step and a small change of the residuals,
    ``rtol``/``atol``) *and* the undamped Gauss–Newton step there is within
    ``max(rtol, 1e-3) (1 + |y|)`` in optimisation units (decades, degrees, m/s); or, after
    ``MAX_REJECTED_STEPS`` rejected steps (or a rejected step itself within that tolerance: a
    smaller trust region could not change the verdict), at such a stationary point or at the loss's
    round-off floor (:func:`at_round_off_floor`; this is tested at the first rejection from
    each accepted point too, at most ``MAX_FLOOR_CHECKS`` times a stage, so that a stage at the
    floor ends at once instead of spending five more trials); or after an accepted step that
    lowered the loss by less than :data:`CREEP` (relative) and than the linear model
    predicted, at such a stationary point. A collapsed trust region away from both is
    escaped by a line search along the Gauss–Newton step (:func:`gauss_newton_escape`, at
    most ``MAX_ESCAPES`` times), and so is a jump of the loss (:data:`JUMP`: the rise of a
    rejected trial did not shrink with the trust region), at once. At the iteration cap it has
    converged only if the Gauss–Newton step is within tolerance.

    With bounds, every step (damped, Gauss–Newton, escape) is taken with the active set of
    :func:`_projected` (parameters pinned on the bounds they would cross), so the stop tests
    measure the constrained Gauss–Newton step: a minimum on a bound is a stationary point, and
    a trial is accepted only where the linear model promises a decrease. Without bounds none
    of this runs (the iterates are the unbounded algorithm's, step for step).
    ``y`` of the outcome is a pytree like ``y0`` (JAX path) or the float64 vector ``(P,)``.
    """
    clock = time.perf_counter()
    if jacobian is None:
        rj, flat0, unravel = residuals_and_jacobian(residuals, y0)
        dtype = flat0.dtype
        loss_of = loss_function(residuals, y0, rj)
        result = lambda v: unravel(jnp.asarray(v, dtype))  # noqa: E731
    else:
        flat0, dtype = np.asarray(y0, np.float64), jnp.result_type(float)

        def rj(flat):  # the residuals, and the Jacobian when asked for
            v = np.asarray(flat, np.float64)
            return residuals(v), lambda: jacobian(v)

        def loss_of(v):
            return float(np.sum(np.asarray(residuals(np.asarray(v, np.float64)), np.float64) ** 2))

        result = lambda v: np.asarray(v, np.float64)  # noqa: E731
    eps = float(jnp.finfo(dtype).eps)
    bounds = None
    if lower is not None or upper is not None:
        shape = np.shape(flat0)
        bounds = (np.broadcast_to(np.asarray(-np.inf if lower is None else lower, np.float64), shape),
                  np.broadcast_to(np.asarray(np.inf if upper is None else upper, np.float64), shape))
        flat0 = np.clip(np.asarray(flat0, np.float64), *bounds)

    def evaluate(y):  # r (M,) and J (M, P), or a function returning it (host residuals)
        r, J = rj(jnp.asarray(y, dtype))
        return np.asarray(r, np.float64), J

    def matrix(J) -> np.ndarray:
        return np.asarray(J() if callable(J) else J, np.float64)

    r_start, J_start = evaluate(flat0)
    timing = {"start_s": time.perf_counter() - clock}
    if not np.all(np.isfinite(r_start)):
        return SolverOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True, timing=timing)
    f0 = float(r_start @ r_start)
    scale = 1.0 / math.sqrt(f0) if 0.0 < f0 < math.inf else 1.0

    y = np.asarray(flat0, np.float64)  # the last accepted point ...
    r = J = None  # ... its scaled residuals and Jacobian (None before the first evaluation)
    y_eval, evaluated = y, (r_start * scale, J_start)  # the trial point (and its evaluation, when known)
    step_size, first, since_accept, last_rise, jump_tried = 1.0, True, 0, None, False
    D = None  # the damping's diagonal scaling (None: the identity)
    losses = [f0]
    converged, stalled, succeeded, verdict, iterations = False, False, False, "rough", 0
    escapes, rejected, floor_checks, at_floor, crept_stationary = 0, 0, 0, False, False
    at_y = None  # (r, J) unscaled at the final y when the stop checks evaluated them
    steps_s, checks_s = [], 0.0
    for iterations in range(1, max_steps + 1):
        t_step = time.perf_counter()
        if evaluated is None:
            r_e, J_e = evaluate(y_eval)
            r_e = r_e * scale
        else:
            r_e, J_e = evaluated
        evaluated = None
        f_e = float(r_e @ r_e)
        if first:
            accept, good = True, False
        else:
            predicted = 0.5 * (float(np.sum((J @ (y_eval - y) + r) ** 2)) - float(r @ r))
            change = 0.5 * (f_e - float(r @ r))
            accept = bool(change <= TRUST_LOW * predicted)  # False for a NaN loss
            if bounds is not None:  # a projected step may promise no decrease: never accept a rise for it
                accept = accept and predicted < 0
            good = bool(change < TRUST_HIGH * predicted and predicted < 0)
        step_size *= (TRUST_GROW if good else 1.0) if accept else TRUST_SHRINK
        crept = collapsed = jump = False
        if accept:
            r_prev = np.zeros_like(r_e) if r is None else r
            # (a step the linear model predicted, "good", is the fast phase: it never creeps)
            crept = not (first or good) and f_e > (1.0 - CREEP) * float(r_prev @ r_prev)
            succeeded = _cauchy_converged(rtol, atol, y_eval, y_eval - y, r_e, r_e - r_prev)
            if ftol is not None and not first:  # or the loss fell by less than ftol (relative)
                succeeded = succeeded or float(r @ r) - f_e < ftol * float(r @ r)
            if not first:
                losses.append(f_e / scale**2)
            y, r, J, since_accept, last_rise, jump_tried = y_eval, r_e, matrix(J_e) * scale, 0, None, False
        else:
            succeeded, since_accept, rejected = False, since_accept + 1, rejected + 1
            collapsed = within_tolerance(y_eval - y, y, rtol)  # a smaller region cannot change the verdict
            rise = f_e - float(r @ r)
            # the trust region shrank, the rise did not: a jump lies closer than the smaller step
            jump = not jump_tried and last_rise is not None and rise > 0 and rise >= JUMP * last_rise
            last_rise = rise if np.isfinite(rise) else None
        first = False
        if scaled and D is None:  # the Jacobian's column norms at the start (the scaled residuals')
            norms = np.linalg.norm(J, axis=0)
            D = math.sqrt(MARQUARDT_START) * norms
            inert = norms <= INERT * float(np.max(norms, initial=0.0))
            if inert.any():  # held where they are: their bounds close on them
                lo, hi = bounds if bounds is not None else (np.full(y.shape, -np.inf), np.full(y.shape, np.inf))
                bounds = (np.where(inert, y, lo), np.where(inert, y, hi))
        if accept and ftol is not None:  # at a new point: does the linear model promise ftol at all?
            t_check = time.perf_counter()
            delta, _ = _gauss_newton_from(r, J, y, rtol, bounds)
            promised = float(r @ r) - float(np.sum((r + J @ delta) ** 2)) if delta is not None else math.inf
            checks_s += time.perf_counter() - t_check
            if promised < ftol * float(r @ r):
                steps_s.append(time.perf_counter() - t_step)
                if progress is not None:
                    progress(offset + iterations, losses[-1])
                at_y, converged, verdict = (r / scale, J / scale), True, "promise"
                break
        if bounds is None:
            y_eval = y + _damped_step(r, J, step_size, eps, D)
        else:
            y_eval = _projected(lambda A, b, free: _damped_step(b, A, step_size, eps, None if D is None else D[free]),
                                J, r, y, bounds)
        steps_s.append(time.perf_counter() - t_step)
        if progress is not None:
            progress(offset + iterations, losses[-1])
        if crept:  # a creeping descent at a Gauss-Newton stationary point: the cap's test, now
            t_check = time.perf_counter()
            at_y = (r / scale, J / scale)
            crept_stationary = _gauss_newton_from(*at_y, y, rtol, bounds)[1]
            checks_s += time.perf_counter() - t_check
            if crept_stationary:
                converged = True
                break
        # The Cauchy test also passes when the trust region has collapsed on a rough loss far
        # from a minimum; and at the loss's numerical floor the region shrinks without the test
        # ever passing. Both end here: a stationary point only if the undamped Gauss-Newton step
        # is within tolerance or promises less than the loss's round-off noise.
        if (since_accept == 1 or (warm and iterations == 1)) and floor_checks < MAX_FLOOR_CHECKS:
            # a rejected trial at the loss's round-off floor: no step can be told from noise,
            # so waiting for more rejections would only spend rollouts (tested once per
            # accepted point: the probe from the same point along the same step repeats itself)
            t_check = time.perf_counter()
            at_y = (r / scale, J / scale)
            delta, _ = _gauss_newton_from(*at_y, y, rtol, bounds)
            promised = float(np.sum((J @ delta) ** 2)) if delta is not None else math.inf  # scaled loss units
            probe = promised <= FLOOR_GATE * float(r @ r)
            floor_checks += probe
            if probe and at_round_off_floor(rj, jnp.asarray(y, dtype), delta, *at_y):
                checks_s += time.perf_counter() - t_check
                at_floor = converged = True
                break
            checks_s += time.perf_counter() - t_check
        stop_test = succeeded or since_accept >= MAX_REJECTED_STEPS or collapsed
        if stop_test or (jump and escapes < MAX_ESCAPES):
            t_check = time.perf_counter()
            flat = jnp.asarray(y, dtype)
            at_y = (r / scale, J / scale)
            found, verdict = gauss_newton_escape(loss_of, rj, flat, losses[-1], rtol, *at_y, bounds=bounds)
            checks_s += time.perf_counter() - t_check
            if stop_test and found is not None and ftol is not None and losses[-1] - found[1] < ftol * losses[-1]:
                found, verdict = None, "resolution"  # a gain the caller does not resolve: stop here
            if found is not None and escapes < MAX_ESCAPES:
                escapes += 1
                y_eval, r, J, at_y = np.asarray(found[0], np.float64), None, None, None
                losses.append(found[1])
                step_size, first = 1.0, True  # a fresh trust region at the better point (accepted: resets the rest)
                continue
            if not stop_test and verdict not in STATIONARY:  # not to be stepped over: the region shrinks on
                jump_tried = True  # (the same line search is not tried again from this point)
                continue
            stalled = not succeeded
            converged = verdict in STATIONARY or verdict == "resolution"
            break
    if r is None:  # the iteration limit came right after an escape: its point is the result
        r_e, J_e = evaluate(y_eval)
        y, r, J = y_eval, r_e * scale, matrix(J_e) * scale
    unhealthy = False
    if at_floor:
        how = "floor"
    elif crept_stationary:
        how = "creep"
    elif verdict in ("resolution", "promise"):
        how = verdict
    elif stalled:  # the next trial point: is the simulation unstable there?
        unhealthy = not np.all(np.isfinite(evaluate(y_eval)[0]))
        if unhealthy:
            converged = False
        how = "unstable" if unhealthy else verdict
    elif succeeded:  # the Cauchy test passed: checked against the Gauss-Newton step above
        how = {"stationary": "converged", "floor": "floor"}.get(verdict, "rough")
    else:  # the limit; converged all the same if the Gauss-Newton step is within tolerance
        t_check = time.perf_counter()
        at_y = (r / scale, J / scale)
        converged = _gauss_newton_from(*at_y, y, rtol, bounds)[1]
        checks_s += time.perf_counter() - t_check
        how = "cap-stationary" if converged else "cap"
    timing.update(_step_timing(steps_s), checks_s=checks_s, rejected_steps=rejected, escapes=escapes,
                  floor_checks=floor_checks)
    return SolverOutcome(result(y), losses, iterations, converged, _lm_message(how, iterations, max_steps), unhealthy,
                         jacobian=(rj, at_y), timing=timing)


def _step_timing(steps_s: list[float]) -> dict:
    """Seconds of a solver's iterations: the first (compilation included), the median of the
    others, their sum, and the compilation estimated as the first's excess over the median."""
    if not steps_s:
        return {"first_step_s": 0.0, "step_s": 0.0, "steps_s": 0.0, "compile_s": 0.0}
    if len(steps_s) == 1:  # nothing to compare the first with
        return {"first_step_s": steps_s[0], "step_s": 0.0, "steps_s": steps_s[0], "compile_s": 0.0}
    median = float(np.median(steps_s[1:]))
    return {"first_step_s": steps_s[0], "step_s": median, "steps_s": float(np.sum(steps_s)),
            "compile_s": max(steps_s[0] - median, 0.0)}


def bfgs(loss_fn, y0, *, max_steps, rtol, atol, progress, offset) -> SolverOutcome:
    f0 = jax.jit(loss_fn)(y0)
    if not bool(jnp.isfinite(f0)):
        return SolverOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
    # BFGS starts from an identity Hessian, so its first steps scale with the gradient:
    # minimise the loss relative to its initial value to make them O(1)
    scale = float(f0) if float(f0) > 0 else 1.0

    def fn(y, args):
        return loss_fn(y) / scale, None

    solver = optx.BFGS(rtol=rtol, atol=atol)
    options = {"autodiff_mode": "fwd"}
    tags = frozenset()
    f0 = f0 / scale
    f_struct = jax.eval_shape(lambda: f0)
    state = solver.init(fn, y0, None, options, f_struct, None, tags)

    @eqx.filter_jit
    def advance(y, state):
        y, state, _ = solver.step(fn, y, None, options, state, tags)
        done, result = solver.terminate(fn, y, None, options, state, tags)
        return y, state, done, result

    y = y0
    losses = [float(f0) * scale]
    converged, iterations = False, 0
    best = (losses[0], y0)
    steps_s = []
    for iterations in range(1, max_steps + 1):
        t_step = time.perf_counter()
        y, state, done, result = advance(y, state)
        f = float(state.f_info.f) * scale  # waits for the step
        steps_s.append(time.perf_counter() - t_step)
        if iterations > 1 and np.isfinite(f) and f < losses[-1]:
            losses.append(f)
            best = (f, y)
        if progress is not None:
            progress(offset + iterations, losses[-1])
        if bool(done):
            converged = result == optx.RESULTS.successful
            break
    y = best[1]
    unhealthy = False
    if bool(done) and not converged:  # the solver gave up (e.g. its line search failed)
        unhealthy = not bool(jnp.isfinite(jax.jit(loss_fn)(state.y_eval)))
    message = f"converged in {iterations} iterations" if converged else f"did not converge within {max_steps} iterations"
    return SolverOutcome(y, losses, iterations, converged, message, unhealthy, timing=_step_timing(steps_s))


def _learning_rates(names, y0, learning_rates) -> dict:
    out = {}
    for n in names:
        leaf = leaf_name(n)
        lr = (learning_rates or {}).get(n, (learning_rates or {}).get(leaf, ADAM_LEARNING_RATES.get(leaf, 0.01)))
        out[n] = jnp.broadcast_to(jnp.asarray(lr, jnp.result_type(float)), jnp.shape(y0[n]))
    return out


def adam(
    loss_fn, y0, *, max_steps, learning_rates, lr_decay, xtol, patience, grad, seed, progress, offset, names
) -> SolverOutcome:
    import optax

    lrs = _learning_rates(names, y0, learning_rates)
    decay = 1.0 if lr_decay is None else float(lr_decay)
    opt = optax.scale_by_adam()
    _, unravel = jax.flatten_util.ravel_pytree(y0)

    def value_and_grad(y, key):
        if grad == "rev":
            return jax.value_and_grad(loss_fn)(y, key)
        flat, _ = jax.flatten_util.ravel_pytree(y)
        f = lambda v: loss_fn(unravel(v), key)  # noqa: E731
        basis = jnp.eye(flat.size, dtype=flat.dtype)
        # one JVP per parameter; the primal does not depend on the tangent, so it runs once
        value, g = jax.vmap(lambda t: jax.jvp(f, (flat,), (t,)), out_axes=(None, 0))(basis)
        return value, unravel(g)

    @jax.jit
    def advance(y, opt_state, key, factor):
        value, g = value_and_grad(y, key)
        with jax.numpy_dtype_promotion("standard"):  # optax mixes its int32 step count with floats
            updates, opt_state = opt.update(g, opt_state, y)
        new = jax.tree_util.tree_map(lambda a, u, lr: a - (factor * lr).astype(a.dtype) * u, y, updates, lrs)
        ok = jnp.isfinite(value) & jnp.all(jnp.isfinite(jax.flatten_util.ravel_pytree(g)[0]))
        return new, opt_state, value, ok

    base = jax.random.PRNGKey(seed)
    y, opt_state = y0, opt.init(y0)
    losses, history = [], []
    best = (math.inf, y0)
    converged, unhealthy, iterations = False, False, 0
    steps_s = []
    for iterations in range(1, max_steps + 1):
        factor = jnp.asarray(decay ** ((iterations - 1) / max(max_steps - 1, 1)), jnp.result_type(float))
        t_step = time.perf_counter()
        new, new_state, value, ok = advance(y, opt_state, jax.random.fold_in(base, iterations), factor)
        value = float(value)  # waits for the step
        steps_s.append(time.perf_counter() - t_step)
        if not bool(ok):
            unhealthy = True
            iterations -= 1
            if iterations == 0:
                return SolverOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
            break
        losses.append(value)
        if value < best[0]:
            best = (value, y)
        if progress is not None:
            progress(offset + iterations, value)
        history.append(np.asarray(jax.flatten_util.ravel_pytree(y)[0]))
        y, opt_state = new, new_state
        if len(history) > patience and np.max(np.abs(history[-1] - history[-1 - patience])) < xtol:
            converged = True
            break
    y_out = best[1] if np.isfinite(best[0]) else y
    if converged:
        message = f"converged in {iterations} iterations (parameters moved < {xtol:g} over the last {patience})"
    elif unhealthy:
        message = f"stopped after {iterations} iterations: the loss or its gradient became non-finite"
    else:
        message = f"did not converge within {max_steps} iterations (Adam; the lowest-loss iterate is returned)"
    return SolverOutcome(y_out, losses, iterations, converged, message, unhealthy, timing=_step_timing(steps_s))
