"""Parameter identification: one call, three optimisers, staged like PAC-NeRF/GIC.

``fit(model, params, observation, names, method="lm" | "adam" | "bfgs")`` minimises the
weighted loss of :mod:`jaxmpm.losses` (tracks, silhouettes, masked RGB, probes):

* ``"lm"`` (default): Levenberg–Marquardt (``optimistix``) on the residual vector with
  forward-mode Jacobians (one JVP per parameter; no reverse-mode tape).
* ``"adam"``: the reference, PAC-NeRF's optimiser: Adam (``optax``) with PAC-NeRF's
  per-parameter learning rates in its parameter spaces (:data:`ADAM_LEARNING_RATES`), a
  fresh random pixel batch per iteration for image terms, and the lowest-loss iterate
  returned (GIC). The gradient is forward mode by default (``grad="fwd"``).
* ``"bfgs"``: ``optimistix.BFGS`` on the scalar loss (forward-mode gradients).

**Stages** (``stages="auto"``, PAC-NeRF's schedule): (1) the initial velocity alone from
the pre-contact frames, when a ``velocity`` is among the names (without per-particle tracks,
whose contact is found in a rollout of the guess, first from the first observed interval,
then again from the frames before the contact of that velocity); (2) the other parameters on
the frames up to ``warmup_frames`` after contact; (3) the same on all frames. A stage whose
rollout is unhealthy (NaN, CFL number above ``cfl_limit``) at its starting point, or whose
solver stalls against unhealthy trial points, halves dt (doubles the substeps) and restarts
from the best point so far, up to ``max_dt_halvings`` times in all.

**Uncertainty**: standard deviations from the Gauss–Newton covariance
``s² (JᵀJ)⁻¹`` at the optimum (``s² = RSS / (m − p)``), mapped to physical units; each
parameter's from the last stage that fitted it.

Parameters are named (``"mu"``, ``"kappa"``, ``"E"``, ``"nu"``, ``"yield_stress"``,
``"eta"``, ``"friction_angle"``, ``"density"``, ``"velocity"``, ``"gravity"``,
``"<collider>.friction"``, ``"<body>.<param>"``) and optimised in PAC-NeRF's spaces:
log10 for E, mu, kappa, yield_stress, eta and density; a tanh-bounded Poisson ratio;
degrees for the friction angle; linear otherwise.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .errors import JaxmpmError, ObservationError
from .losses import Objective, build_objective, chamfer_residuals, frame_interpolation, frames_needed
from .model import Model, Params
from .observe import Observation

__all__ = [
    "LOG10_PARAMS",
    "NU_BOUNDS",
    "METHODS",
    "ADAM_LEARNING_RATES",
    "FitError",
    "FitResult",
    "Stage",
    "fit",
    "fit_scene",
    "plan_stages",
    "contact_time",
    "check_scene_compatible",
    "default_names",
    "parse_weights",
    "resolve_name",
    "get_param",
    "set_param",
    "to_unconstrained",
    "from_unconstrained",
    "apply_unconstrained",
    "track_residual_fn",
    # re-exported from jaxmpm.losses for compatibility
    "frame_interpolation",
    "frames_needed",
    "chamfer_residuals",
]

LOG10_PARAMS = frozenset({"E", "mu", "kappa", "yield_stress", "eta", "density"})
#: Poisson ratio bounds of the tanh map nu = mid + half * tanh((y - mid) / half).
NU_BOUNDS = (-0.45, 0.495)

#: ``"lm"`` is ``optimistix.LevenbergMarquardt`` on forward-mode Jacobians (the default: it
#: recovers every material of tests/test_fit.py from PAC-NeRF's guesses). ``"lm-direct"`` is
#: a hand-written NumPy LM on one compiled (r, J) function per stage (faster per iteration,
#: but it stopped at a wrong local minimum on the viscoplastic test case; kept for
#: comparison). ``"lm-optimistix"`` is an alias of ``"lm"``.
METHODS = ("lm", "adam", "bfgs", "lm-optimistix", "lm-direct")

#: PAC-NeRF's dynamic-stage Adam learning rates (configs' ``physical_params``; anchors §1.5),
#: in the optimisation space (log10 units for log parameters, degrees for the friction
#: angle). ``velocity`` (GIC's velocity stage: 1e-2…5e-2 m/s), collider ``friction``,
#: ``restitution`` and ``gravity`` are jaxmpm's choices.
ADAM_LEARNING_RATES = {
    "E": 0.1,
    "nu": 0.01,
    "mu": 0.1,
    "kappa": 0.1,
    "yield_stress": 0.1,
    "eta": 0.05,
    "friction_angle": 1.0,
    "density": 0.1,
    "velocity": 0.05,
    "friction": 0.02,
    "restitution": 0.02,
    "gravity": 0.1,
}

#: Default iterations per stage and method (PAC-NeRF: 50 Adam iterations on the early
#: window, 100 on all frames).
DEFAULT_MAX_STEPS = {"lm": 40, "lm-optimistix": 40, "lm-direct": 40, "bfgs": 60, "adam": 100}
ADAM_WINDOW_STEPS = 50

#: Consecutive rejected Levenberg–Marquardt steps (each shrinking the trust region) after
#: which the fit stops at a stationary point.
MAX_REJECTED_STEPS = 6


class FitError(JaxmpmError, RuntimeError):
    """A fit could not start (e.g. the simulation is unstable even at small dt)."""


# --------------------------------------------------------------------------- parameter paths


def resolve_name(model: Model, params: Params, name: str) -> tuple:
    """The path of a named parameter inside ``params``.

    ``"mu"`` names the only body that has ``mu``; ``"body1.mu"`` a given body;
    ``"floor.friction"`` a collider's parameter; ``"gravity"`` the gravity vector.
    """
    if not isinstance(name, str) or not name:
        raise JaxmpmError(f"parameter names must be non-empty strings, got {name!r}")
    if name == "gravity":
        return ("gravity",)
    if "." in name:
        owner, leaf = name.split(".", 1)
        for k, body in enumerate(model.bodies):
            if body.name == owner:
                if leaf not in params["bodies"][k]:
                    raise JaxmpmError(
                        f"parameter {name!r}: body {owner!r} ({_material_name(body)}) has no parameter {leaf!r}; "
                        f"it has: {', '.join(sorted(params['bodies'][k]))}"
                    )
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
        materials = ", ".join(sorted({_material_name(b) for b in model.bodies}))
        raise JaxmpmError(
            f"unknown parameter {name!r} for this scene's material ({materials}); this scene has: {', '.join(available)}"
        )
    if len(owners) > 1:
        choices = ", ".join(f"{model.bodies[k].name}.{name}" for k in owners)
        raise JaxmpmError(f"parameter {name!r} is ambiguous in a scene with several bodies; use one of {choices}")
    return ("bodies", owners[0], name)


def _material_name(body) -> str:
    return getattr(type(body.material), "name", type(body.material).__name__)


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


def default_names(model: Model) -> list[str]:
    """The material parameters that PAC-NeRF fits for a one-body scene's material."""
    from .constitutive import MATERIALS

    if len(model.bodies) != 1:
        raise JaxmpmError("this scene has several bodies: name the parameters to fit")
    return list(MATERIALS[_material_name(model.bodies[0])].required)


# --------------------------------------------------------------------------- track residuals


def track_residual_fn(model: Model, observation: Observation, checkpoint: str | None = "nested"):
    """``residuals(params) -> (R,)`` comparing simulated and observed tracks.

    With ``point_ids == "particles"`` the residual is the position error of every observed
    point (NaN points contribute 0); otherwise it is the symmetric Chamfer distance per
    frame. Residuals are scaled so that ``sum(r**2)`` is the mean squared error in m^2.
    (A thin wrapper of :func:`jaxmpm.losses.build_objective` with tracks only.)
    """
    if observation.positions is None:
        raise ObservationError("the observation has no 'positions' (tracks) to fit")
    weights = {"tracks": 1.0, "silhouette": 0.0, "rgb": 0.0, "probes": 0.0}
    objective = build_objective(model, observation, weights=weights, checkpoint=checkpoint, cfl_limit=math.inf)
    return lambda params: objective._residuals_of(objective.simulate(params))


# --------------------------------------------------------------------------- stages


@dataclass
class Stage:
    """One stage of a staged fit.

    Attributes:
        names: the parameters fitted in this stage.
        until: last observed time used (seconds); None for all.
        label: a short description (printed and written to fit.json).
        method: optimiser of this stage (default: the fit's).
        max_steps: iteration cap of this stage (default: the fit's).
    """

    names: list[str]
    until: float | None = None
    label: str = ""
    method: str | None = None
    max_steps: int | None = None


def _velocity_dispersion(x: np.ndarray) -> np.ndarray:
    """Per interval, how far the displacements depart from a common translation (95th
    percentile of ``|d_p − median d|``): 0 in free flight, large after contact."""
    d = np.diff(x, axis=0)
    dev = np.linalg.norm(d - np.nanmedian(d, axis=1, keepdims=True), axis=-1)
    dev = np.where(np.isfinite(dev), dev, np.nan)
    return np.nanpercentile(dev, 95, axis=1)


def contact_time(model: Model, params: Params, observation: Observation, *, tol: float | None = None) -> float | None:
    """The last observed time before the body first touches anything (a collider, a wall).

    In free flight every particle moves with one velocity (no stress), so contact shows
    as the first frame interval whose displacements depart from a common translation by
    more than ``tol`` (default 5 % of a grid cell per frame, 95th percentile over the
    points). Uses the observed tracks when they are per-particle (``point_ids ==
    "particles"``), else a rollout at ``params`` (the initial guess; :func:`fit` re-detects
    contact with the fitted velocity and refits it on a shorter window if needed). Returns None when nothing touches within the data, and
    0.0 when the body is in contact from the start.
    """
    times = np.asarray(observation.times, float)
    tol = 0.05 * model.grid.dx if tol is None else tol
    if observation.positions is not None and observation.point_ids == "particles" and len(times) >= 2:
        x = np.asarray(observation.positions, float)
        disp = _velocity_dispersion(x)
        scale = np.diff(times) / model.frame_dt  # displacement tolerance per observed interval
        bad = np.flatnonzero(~(disp <= tol * np.maximum(scale, 1e-9)))
        return None if len(bad) == 0 else float(times[bad[0]])
    from .step import simulate

    frames = frames_needed(model, times)
    traj = jax.jit(lambda p: simulate(model, p, frames=frames))(params)
    x = np.asarray(traj.x, float)
    disp = _velocity_dispersion(x)
    bad = np.flatnonzero(~(disp <= tol))
    if len(bad) == 0:
        return None
    t = bad[0] * model.frame_dt
    before = times[times <= t + 1e-3 * model.frame_dt]
    return float(before[-1]) if len(before) else 0.0


def _first_interval_stage(stage: Stage, times, frame_dt: float) -> Stage:
    """``stage`` (a velocity stage) shortened to the first observed interval.

    Without per-particle tracks, contact is found in a rollout of the initial guess, which
    (typically dropped from rest) lands later than the truth; fitted on that window the
    velocity also sees frames after the true contact, which it cannot explain, and takes
    many iterations. The first interval is almost always before contact and enough to pin
    the velocity; :func:`fit` then re-detects contact with it and refits on the frames before.
    """
    t = np.sort(np.asarray(times, float))
    first = t[t > 0]
    if not len(first) or first[0] >= stage.until - 1e-3 * frame_dt:
        return stage
    return replace(stage, until=float(first[0]), label=f"velocity (first observed interval, t <= {first[0]:.4g} s)")


def plan_stages(
    model: Model,
    params: Params,
    observation: Observation,
    names: Sequence[str],
    *,
    velocity_until: float | None = None,
    warmup_frames: int = 3,
    refine_velocity: bool = False,
) -> tuple[list[Stage], list[str]]:
    """PAC-NeRF's schedule for ``names`` (see the module docstring) and notes about it."""
    names = list(names)
    vel = [n for n in names if _leaf(n) == "velocity"]
    rest = [n for n in names if _leaf(n) != "velocity"]
    times = np.asarray(observation.times, float)
    t_end = float(times.max())
    notes = []
    eps = 1e-3 * model.frame_dt  # observed times may be float32
    t_c = velocity_until if velocity_until is not None else contact_time(model, params, observation)
    stages: list[Stage] = []
    pre = times[(times > 0) & (times <= (t_c if t_c is not None else t_end) + eps)]
    if vel:
        if not rest:
            return [Stage(vel, None, "velocity (all frames)")], notes
        if t_c is None:
            notes.append("no contact within the observed frames: the velocity is fitted with the other parameters")
        elif len(pre) < 1 or t_c <= 0:
            notes.append("the body is in contact from the start: the velocity is fitted with the other parameters")
        else:
            stages.append(Stage(vel, float(t_c), f"velocity (pre-contact frames, t <= {t_c:.4g} s)"))
    joint = rest + (vel if (refine_velocity or not stages) else [])
    if t_c is not None and warmup_frames > 0:
        window = float(t_c) + warmup_frames * model.frame_dt
        later = times[times > window + eps]
        inside = times[(times > 0) & (times <= window + eps)]
        if len(later) and len(inside) >= 2:
            stages.append(Stage(list(joint), window, f"window (t <= {window:.4g} s, {warmup_frames} frames after contact)"))
    stages.append(Stage(list(joint), None, f"all frames (t <= {t_end:.4g} s)"))
    return stages, notes


# --------------------------------------------------------------------------- results


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        params: the full parameter pytree at the estimate.
        values: fitted values by name (physical units).
        std: standard deviations by name from the Gauss–Newton covariance (physical units).
        loss: loss after each accepted iteration, all stages in order (first = initial).
        iterations: solver iterations taken (all stages).
        seconds: wall time.
        converged: whether every parameter's last stage met its tolerance.
        message: a human-readable status (says so when the fit did not converge).
        substeps: substeps per frame used (may exceed the model's after dt halving).
        initial: the initial values by name.
        method: the optimiser.
        stages: per stage: names, window, iterations, loss, converged, message, seconds.
        notes: remarks (dt halvings, skipped stages).
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
    method: str = "lm"
    stages: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

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
            "method": self.method,
            "stages": json.loads(json.dumps(self.stages, default=float)),
            "notes": list(self.notes),
        }


@dataclass
class _StageOutcome:
    y: dict
    losses: list
    iterations: int
    converged: bool
    message: str
    unhealthy_trial: bool = False
    unhealthy_start: bool = False
    jacobian: Any = None  # (r, J) at y when the solver has them (LM), for the covariance


# --------------------------------------------------------------------------- solvers


def _float_dtype():
    return jnp.result_type(float)



def residuals_and_jacobian(residuals: Callable, y0: dict):
    """``rj(flat) -> (r, J)`` (jitted) and the ravel/unravel pair of ``y0``: the residuals and
    their Jacobian by forward mode, one JVP per parameter sharing one primal rollout."""
    flat0, unravel = jax.flatten_util.ravel_pytree(y0)

    @jax.jit
    def rj(flat):
        basis = jnp.eye(flat.size, dtype=flat.dtype)
        g = lambda v: residuals(unravel(v))  # noqa: E731
        r, J = jax.vmap(lambda t: jax.jvp(g, (flat,), (t,)), out_axes=(None, 0))(basis)
        return r, J.T

    return rj, flat0, unravel


#: Velocity refits after the first velocity stage when contact is re-detected with each fitted
#: velocity (images or untracked points; see :func:`_first_interval_stage`).
MAX_VELOCITY_REFITS = 3

#: Step lengths tried along the Gauss–Newton direction when the trust region has collapsed.
ESCAPE_STEPS = (1.0, 0.5, 0.25, 0.125, 0.0625)
#: At most this many such escapes per stage.
MAX_ESCAPES = 4
#: The verdicts of :func:`_gauss_newton_escape` that count as converged.
STATIONARY = ("stationary", "floor")


def _gauss_newton_step(rj, flat, rtol) -> tuple[np.ndarray | None, bool]:
    """The undamped Gauss–Newton step at ``flat`` (``None`` if the residuals or Jacobian are
    not finite) and whether every component of it is within ``max(rtol, 1e-3) (1 + |y|)`` in
    optimisation units (decades, degrees, m/s): a stationary point at this precision."""
    r, J = (np.asarray(a, np.float64) for a in rj(flat))
    return _gauss_newton_from(r, J, np.asarray(flat, np.float64), rtol)


def _gauss_newton_from(r, J, y, rtol) -> tuple[np.ndarray | None, bool]:
    """:func:`_gauss_newton_step` from residuals ``r`` and Jacobian ``J`` already evaluated at ``y``."""
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        return None, False
    delta = np.linalg.lstsq(J, -r, rcond=None)[0]
    return delta, bool(np.all(np.abs(delta) <= max(rtol, 1e-3) * (1.0 + np.abs(y))))


#: Largest component of the probe step that measures a loss's round-off noise, relative to
#: ``1 + |y|`` (optimisation units): far above float32's resolution, far below any fitted feature.
NOISE_PROBE = 1e-4


def _at_round_off_floor(rj, flat, delta, r=None, J=None) -> bool:
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
    """
    if r is None or J is None:
        r, J = (np.asarray(a, np.float64) for a in rj(flat))
    y = np.asarray(flat, np.float64)
    # the step's largest component, relative to 1 + |y|, becomes NOISE_PROBE
    t = min(NOISE_PROBE / max(float(np.max(np.abs(delta) / (1.0 + np.abs(y)))), 1e-300), 1.0)
    r_t = np.asarray(rj(jnp.asarray(y + t * delta, flat.dtype))[0], np.float64)
    y_t = np.asarray(jnp.asarray(y + t * delta, flat.dtype), np.float64)  # the probe as rounded
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J)) and np.all(np.isfinite(r_t))):
        return False
    noise = float(np.sum((r_t - r - J @ (y_t - y)) ** 2))
    promised = float(np.sum((J @ delta) ** 2))
    return promised <= noise


def _gauss_newton_escape(loss_of, rj, flat, f, rtol):
    """After ``MAX_REJECTED_STEPS`` rejected trust-region steps: is this a stationary point?

    A float32 MPM loss is rough on small scales (return-map branches, contact switching), so
    the trust region can collapse far from a minimum: the local slope it sees disagrees with
    the trend. Here the undamped Gauss–Newton step ``delta`` is computed from ``(r, J)`` at
    ``flat`` and tried at the lengths ``ESCAPE_STEPS``.

    Returns ``((new_flat, new_loss), "rough")`` for the first length that lowers the loss,
    else ``(None, verdict)``: ``"stationary"`` (the test of :func:`_gauss_newton_step`),
    ``"floor"`` (no length helped and the step promises less than the loss's round-off noise,
    :func:`_at_round_off_floor`) or ``"rough"`` (stuck away from a stationary point).
    """
    r, J = (np.asarray(a, np.float64) for a in rj(flat))
    delta, stationary = _gauss_newton_from(r, J, np.asarray(flat, np.float64), rtol)
    if delta is None:
        return None, "rough"
    if stationary:
        return None, "stationary"
    y = np.asarray(flat, np.float64)
    for alpha in ESCAPE_STEPS:
        trial = jnp.asarray(y + alpha * delta, flat.dtype)
        f_t = float(loss_of(trial))
        if np.isfinite(f_t) and f_t < f:
            return (trial, f_t), "rough"
    return None, "floor" if _at_round_off_floor(rj, flat, delta, r, J) else "rough"


def _lm_message(how: str, iterations: int, max_steps: int) -> str:
    """The stage message of both LM paths for how it stopped: ``"converged"`` (tolerance
    test), ``"stationary"`` (rejected steps at a Gauss-Newton stationary point), ``"floor"``
    (rejected steps at the loss's round-off floor), ``"rough"``
    (stuck away from one), ``"unstable"`` (trial steps made the simulation unstable), ``"cap"``
    (iteration limit) or ``"cap-stationary"`` (iteration limit at a Gauss-Newton stationary
    point: converged)."""
    return {
        "converged": f"converged in {iterations} iterations",
        "stationary": (f"converged in {iterations} iterations (the last {MAX_REJECTED_STEPS} trial steps could not "
                       "lower the loss further and the Gauss-Newton step is within tolerance: a stationary point "
                       "at this precision)"),
        "floor": (f"converged in {iterations} iterations (at the loss's round-off floor: no trial step lowered it "
                  "and the Gauss-Newton step promises less than the loss's measured round-off noise; parameters "
                  "in poorly determined directions are known only to their std)"),
        "rough": (f"stalled after {iterations} iterations away from a stationary point: the Gauss-Newton step is "
                  "still large but neither the trust region nor a line search along it lowers the loss (a rough "
                  "loss at this precision; try float64, another starting point or method='adam')"),
        "unstable": f"stalled after {iterations} iterations: the trial steps made the simulation unstable",
        "cap": f"did not converge within {max_steps} iterations",
        "cap-stationary": (f"converged in {iterations} iterations (the iteration limit was reached, but the "
                           "Gauss-Newton step there is within tolerance: a stationary point at this precision)"),
    }[how]


def _run_lm(residuals, y0, *, max_steps, rtol, atol, progress, offset) -> _StageOutcome:
    """Levenberg–Marquardt with Marquardt's diagonal scaling and Nielsen's damping update.

    Every evaluation computes the residuals and the full Jacobian in one forward-mode pass
    (one compiled function per stage); the Jacobian at the accepted point is kept for the
    covariance. Converged when an accepted step changes no parameter by more than
    ``rtol (1 + |y|)`` (optimisation units: decades, degrees, m/s) and the loss by no more
    than ``atol + rtol f``, or the loss has fallen by ten orders of magnitude; or, at the
    loss's numerical floor, after ``MAX_REJECTED_STEPS`` consecutive rejected steps when the
    undamped Gauss–Newton step is within ``max(rtol, 1e-3) (1 + |y|)``. When it is not, the
    trust region collapsed on a rough loss: :func:`_gauss_newton_escape` tries that step (line
    search) and the solver restarts from the better point (at most ``MAX_ESCAPES`` times); failing that the
    stage has converged only if that step promises less than the loss's measured round-off
    noise (:func:`_at_round_off_floor`), else it reports that it stalled.
    """
    rj, flat, unravel = residuals_and_jacobian(residuals, y0)
    r, J = (np.asarray(a, np.float64) for a in rj(flat))
    if not np.all(np.isfinite(r)) or not np.all(np.isfinite(J)):
        return _StageOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
    y = np.asarray(flat, np.float64)
    f = float(r @ r)
    losses = [f]
    lam, nu = None, 2.0
    converged = stalled = unhealthy = False
    rejected = escapes = 0
    verdict = "rough"
    loss_of = jax.jit(lambda v: jnp.sum(residuals(unravel(v)) ** 2))  # compiled only if a stall needs it
    iterations = 0
    for iterations in range(1, max_steps + 1):
        g = J.T @ r
        A = J.T @ J
        d = np.diag(A).copy()
        d = np.maximum(d, 1e-12 * max(float(d.max()), 1e-300))
        if lam is None:
            lam = 1e-3
        try:
            step = np.linalg.solve(A + lam * np.diag(d), -g)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(A + lam * np.diag(d), -g, rcond=None)[0]
        predicted = -(2.0 * step @ g + step @ A @ step)  # f - |r + J step|^2
        trial = y + step
        r_t, J_t = (np.asarray(a, np.float64) for a in rj(jnp.asarray(trial, flat.dtype)))
        finite = bool(np.all(np.isfinite(r_t)) and np.all(np.isfinite(J_t)))
        f_t = float(r_t @ r_t) if finite else math.inf
        rho = (f - f_t) / predicted if predicted > 0 else -1.0
        if finite and f_t < f and rho > 1e-4:
            small_step = bool(np.all(np.abs(step) <= rtol * (1.0 + np.abs(y))))
            small_change = (f - f_t) <= atol + rtol * f
            y, r, J, f = trial, r_t, J_t, f_t
            losses.append(f)
            lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu, rejected, unhealthy = 2.0, 0, False
            if progress is not None:
                progress(offset + iterations, f)
            # Cauchy criterion (as optimistix): the step AND the loss change are both small
            if (small_step and small_change) or f <= 1e-10 * losses[0]:
                converged = True
                break
        else:
            lam *= nu
            nu *= 2.0
            rejected += 1
            unhealthy = not finite
            if progress is not None:
                progress(offset + iterations, f)
            # At the loss's numerical floor no trial step can decrease it, so the damping
            # grows without the tolerance test ever passing: a stationary point too.
            if rejected >= MAX_REJECTED_STEPS:
                found, verdict = _gauss_newton_escape(loss_of, rj, jnp.asarray(y, flat.dtype), f, rtol)
                if found is not None and escapes < MAX_ESCAPES:
                    escapes += 1
                    y = np.asarray(found[0], np.float64)
                    r, J = (np.asarray(a, np.float64) for a in rj(found[0]))
                    f = float(r @ r)
                    losses.append(f)
                    lam, nu, rejected, unhealthy = None, 2.0, 0, False
                    continue
                stalled = True
                converged = verdict in STATIONARY and not unhealthy
                break
    if stalled:
        how = "unstable" if unhealthy else verdict
    elif converged:
        how = "converged"
    else:  # the iteration limit; converged all the same if the Gauss-Newton step is within tolerance
        converged = _gauss_newton_step(rj, jnp.asarray(y, flat.dtype), rtol)[1]
        how = "cap-stationary" if converged else "cap"
    message = _lm_message(how, iterations, max_steps)
    y_out = unravel(jnp.asarray(y, flat.dtype))
    # only a stall against unstable trial points calls for a smaller dt: single rejected
    # unstable trials are the trust region doing its job
    return _StageOutcome(y_out, losses, iterations, converged, message, stalled and unhealthy, jacobian=(r, J))

def _run_lm_optimistix(residuals, y0, *, max_steps, rtol, atol, progress, offset) -> _StageOutcome:
    r0 = jax.jit(residuals)(y0)
    if not bool(jnp.all(jnp.isfinite(r0))):
        return _StageOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
    f0 = float(jnp.sum(r0**2))
    # optimistix's trust region starts at damping 1 on the loss: residuals scaled to a unit
    # starting loss make that comparable to J^T J, instead of first steps ~f0 times too short
    # that take several iterations to grow (losses are reported unscaled)
    scale = 1.0 / math.sqrt(f0) if 0.0 < f0 < math.inf else 1.0

    def fn(y, args):  # optimistix's solver interface: (residuals, aux)
        return residuals(y) * scale, None

    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    options = {"jac": "fwd"}
    tags = frozenset()
    f_struct = jax.eval_shape(lambda: r0)
    state = solver.init(fn, y0, None, options, f_struct, None, tags)

    @eqx.filter_jit
    def advance(y, state):
        y, state, _ = solver.step(fn, y, None, options, state, tags)
        done, result = solver.terminate(fn, y, None, options, state, tags)
        loss = jnp.sum(state.f_info.residual**2) / scale**2
        return y, state, done, result, loss

    y = y0
    losses = [f0]
    converged, stalled, verdict, iterations = False, False, "rough", 0
    escape_tools, escapes, fresh = None, 0, True
    succeeded = False
    for iterations in range(1, max_steps + 1):
        y, state, done, result, loss = advance(y, state)
        # a fresh state's first step only evaluates its starting point; later accepted steps
        # move to a lower loss
        accepted = not fresh and int(state.num_steps_since_acceptance) == 0
        fresh = False
        if accepted:
            losses.append(float(loss))
        if progress is not None:
            progress(offset + iterations, losses[-1])
        succeeded = bool(done) and result == optx.RESULTS.successful
        if bool(done) and not succeeded:
            converged = False
            break
        # optimistix's Cauchy test (small step AND small loss change) also passes when its
        # trust region has collapsed on a rough loss far from a minimum; and at the loss's
        # numerical floor the region shrinks without the test ever passing. Both end here:
        # a stationary point only if the undamped Gauss-Newton step is within tolerance or
        # promises less than the loss's round-off noise (_gauss_newton_escape's verdicts).
        if succeeded or int(state.num_steps_since_acceptance) >= MAX_REJECTED_STEPS:
            if escape_tools is None:
                rj, _, unravel = residuals_and_jacobian(residuals, y)
                loss_of = jax.jit(lambda v: jnp.sum(residuals(unravel(v)) ** 2))
                escape_tools = (rj, unravel, loss_of)
            rj, unravel, loss_of = escape_tools
            flat = jax.flatten_util.ravel_pytree(y)[0]
            found, verdict = _gauss_newton_escape(loss_of, rj, flat, losses[-1], rtol)
            if found is not None and escapes < MAX_ESCAPES:
                escapes += 1
                y = unravel(found[0])
                losses.append(found[1])
                state = solver.init(fn, y, None, options, f_struct, None, tags)
                fresh = True
                continue
            stalled = not succeeded
            converged = verdict in STATIONARY
            break
    # optimistix returns the last *accepted* point as y (trial points live in the state).
    unhealthy = False
    if stalled:
        trial = jax.jit(residuals)(state.y_eval)
        unhealthy = not bool(jnp.all(jnp.isfinite(trial)))
        if unhealthy:
            converged = False
    if stalled:
        how = "unstable" if unhealthy else verdict
    elif succeeded:  # optimistix's tolerance test passed: checked against the Gauss-Newton step above
        how = {"stationary": "converged", "floor": "floor"}.get(verdict, "rough")
    elif iterations >= max_steps:  # the limit; converged all the same if the Gauss-Newton step is within tolerance
        rj = residuals_and_jacobian(residuals, y)[0] if escape_tools is None else escape_tools[0]
        converged = _gauss_newton_step(rj, jax.flatten_util.ravel_pytree(y)[0], rtol)[1]
        how = "cap-stationary" if converged else "cap"
    else:  # optimistix stopped with a failure result before the limit
        how = "cap"
    return _StageOutcome(y, losses, iterations, converged, _lm_message(how, iterations, max_steps), unhealthy)


def _run_bfgs(loss_fn, y0, *, max_steps, rtol, atol, progress, offset) -> _StageOutcome:
    f0 = jax.jit(loss_fn)(y0)
    if not bool(jnp.isfinite(f0)):
        return _StageOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
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
    for iterations in range(1, max_steps + 1):
        y, state, done, result = advance(y, state)
        f = float(state.f_info.f) * scale
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
    return _StageOutcome(y, losses, iterations, converged, message, unhealthy)


def _learning_rates(names, y0, learning_rates) -> dict:
    out = {}
    for n in names:
        leaf = _leaf(n)
        lr = (learning_rates or {}).get(n, (learning_rates or {}).get(leaf, ADAM_LEARNING_RATES.get(leaf, 0.01)))
        out[n] = jnp.broadcast_to(jnp.asarray(lr, _float_dtype()), jnp.shape(y0[n]))
    return out


def _run_adam(
    loss_fn, y0, *, max_steps, learning_rates, lr_decay, xtol, patience, grad, seed, progress, offset, names
) -> _StageOutcome:
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
    for iterations in range(1, max_steps + 1):
        factor = jnp.asarray(decay ** ((iterations - 1) / max(max_steps - 1, 1)), _float_dtype())
        new, new_state, value, ok = advance(y, opt_state, jax.random.fold_in(base, iterations), factor)
        value = float(value)
        if not bool(ok):
            unhealthy = True
            iterations -= 1
            if iterations == 0:
                return _StageOutcome(y0, [], 0, False, "unhealthy at the starting point", unhealthy_start=True)
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
    return _StageOutcome(y_out, losses, iterations, converged, message, unhealthy)


def _gauss_newton_std(residuals, y: dict, names, count: int | None = None, rj=None) -> dict[str, np.ndarray]:
    """Standard deviations from ``s^2 (J^T J)^-1`` with ``s^2 = RSS / (m - p)``, mapped to physical units.

    ``m`` is ``count`` (the informative residual entries) or the residual vector's length;
    ``rj`` the residuals and Jacobian at ``y`` when known (else computed, forward mode).
    This treats residuals as independent with equal variance, so it is a lower bound when
    they are correlated (e.g. neighbouring pixels).
    """
    flat, unravel = jax.flatten_util.ravel_pytree(y)
    if rj is None:
        rj = residuals_and_jacobian(residuals, y)[0](flat)
    r, J = (np.asarray(a, float) for a in rj)
    m, p = J.shape
    m = m if count is None else min(m, int(count))
    s2 = float(r @ r) / max(m - p, 1)
    cov = s2 * np.linalg.pinv(J.T @ J)
    std_y = unravel(jnp.asarray(np.sqrt(np.clip(np.diag(cov), 0.0, None)), flat.dtype))
    out = {}
    for n in names:
        slope = jax.vmap(jax.grad(lambda t, n=n: jnp.sum(from_unconstrained(n, t))))(jnp.ravel(y[n]))
        out[n] = np.abs(np.asarray(slope).reshape(np.shape(y[n]))) * np.asarray(std_y[n])
    return out


# --------------------------------------------------------------------------- the fit


def fit(
    model: Model,
    params: Params,
    observation: Observation,
    names: Sequence[str] | None = None,
    *,
    method: str = "lm",
    stages: str | Sequence[Stage] | None = "auto",
    weights: dict[str, float] | None = None,
    max_steps: int | None = None,
    rtol: float = 1e-5,
    atol: float = 1e-8,
    checkpoint: str | None = "nested",
    max_dt_halvings: int = 3,
    cfl_limit: float = 1.0,
    progress: Callable[[int, float], None] | None = None,
    log: Callable[[str], None] | None = None,
    learning_rates: dict[str, float] | None = None,
    lr_decay: float | None = None,
    xtol: float = 1e-3,
    patience: int = 10,
    grad: str = "fwd",
    seed: int = 0,
    velocity_until: float | None = None,
    warmup_frames: int = 3,
    refine_velocity: bool = False,
    renderer: Any = "volume",
    num_pixels: int = 256,
    probes: dict | None = None,
    colors: Any = "auto",
    uncertainty: bool = True,
) -> FitResult:
    """Fit named parameters of ``model`` to ``observation``.

    Arguments:
        model: static model (its frames are extended to cover the observed times).
        params: initial parameter pytree (the initial guess for the fitted names).
        observation: an :class:`~jaxmpm.observe.Observation` (tracks, masks/images, probes).
        names: parameter names (see :func:`resolve_name`); default: the material's.
        method: ``"lm"`` (Levenberg–Marquardt), ``"adam"`` or ``"bfgs"``.
        stages: ``"auto"`` (PAC-NeRF's velocity → window → all frames, see
            :func:`plan_stages`), None (one stage: all names, all frames) or a list of
            :class:`Stage`.
        weights: loss weights per term (:func:`jaxmpm.losses.build_objective`).
        max_steps: iterations per stage (default 40 LM, 60 BFGS, 100 Adam — 50 on the
            window stage, as PAC-NeRF).
        rtol, atol: LM/BFGS tolerances on the step and the loss.
        checkpoint: checkpoint policy of the rollouts.
        max_dt_halvings: how often dt may be halved (in all) after unhealthy rollouts.
        cfl_limit: a rollout whose CFL number ``max|v| dt/dx`` exceeds this is unhealthy.
        progress: callback ``progress(iteration, loss)`` (iterations count across stages).
        log: callback ``log(message)`` for stage starts, dt halvings and notes.
        learning_rates: Adam learning rates by name or leaf (default
            :data:`ADAM_LEARNING_RATES`).
        lr_decay: Adam: the learning rates decay exponentially to ``lr·lr_decay`` over a
            stage (GIC); default constant (PAC-NeRF).
        xtol, patience: Adam stops (converged) when no parameter moved more than ``xtol``
            (optimisation space) over the last ``patience`` iterations.
        grad: Adam's gradient: ``"fwd"`` (forward mode, one JVP per parameter) or ``"rev"``.
        seed: PRNG seed of Adam's random pixel batches.
        velocity_until: last observed time of the velocity stage (default: detected, see
            :func:`contact_time`).
        warmup_frames: frames after contact in the window stage (PAC-NeRF: 3).
        refine_velocity: also refit the velocity in the later stages.
        renderer, num_pixels, probes, colors: image and probe options of the objective.
        uncertainty: compute the Gauss–Newton standard deviations.

    Returns:
        A :class:`FitResult`; ``converged`` is False (and ``message`` says so) when a stage
        did not meet its tolerance: the parameters are then the best found.

    Raises:
        JaxmpmError: unknown parameters or methods; ObservationError: unusable data;
        FitError: the rollout stays unhealthy after ``max_dt_halvings`` halvings.
    """
    start = time.perf_counter()
    say = log or (lambda msg: None)
    if method not in METHODS:
        raise JaxmpmError(f"unknown fit method {method!r}; expected one of {METHODS}")
    if grad not in ("fwd", "rev"):
        raise JaxmpmError(f"grad must be 'fwd' or 'rev', got {grad!r}")
    if not isinstance(observation, Observation):
        raise ObservationError(f"expected an Observation, got {type(observation).__name__}")
    _check_observation(model, observation)
    names = default_names(model) if names is None else list(dict.fromkeys(names))
    if not names:
        raise JaxmpmError("no parameters to fit")
    paths = {n: resolve_name(model, params, n) for n in names}
    initial = {n: np.asarray(get_param(params, p)) for n, p in paths.items()}
    for n, v in initial.items():
        if _leaf(n) in LOG10_PARAMS and np.any(v <= 0):
            raise JaxmpmError(f"initial value of {n!r} must be > 0 (fitted in log10), got {v}")
        if not np.all(np.isfinite(v)):
            raise JaxmpmError(f"initial value of {n!r} is not finite: {v}")
    objective_options = dict(weights=weights, probes=probes, renderer=renderer, num_pixels=num_pixels,
                             colors=colors, checkpoint=checkpoint, cfl_limit=cfl_limit)
    # fail early on unusable data (before any rollout)
    build_objective(model, observation, **objective_options)

    notes: list[str] = []
    if stages == "auto":
        plan, plan_notes = plan_stages(model, params, observation, names, velocity_until=velocity_until,
                                       warmup_frames=warmup_frames, refine_velocity=refine_velocity)
        notes += plan_notes
    elif stages is None or stages == "single":
        plan = [Stage(list(names), None, "all frames")]
    elif isinstance(stages, str):
        raise JaxmpmError(f"stages must be 'auto', None or a list of Stage, got {stages!r}")
    else:
        plan = list(stages)
        for s in plan:
            unknown = [n for n in s.names if n not in paths]
            if unknown:
                raise JaxmpmError(f"stage {s.label or s.names}: {unknown} are not among the fitted names {names}")
    for note in notes:
        say(note)
    vel_names = [n for n in names if _leaf(n) == "velocity"]
    eps = 1e-3 * model.frame_dt  # observed times may be float32
    # contact found in a rollout of the initial guess (no per-particle tracks): the velocity
    # starts on the first observed interval and contact is re-detected after each velocity stage
    t_guess = None
    if (stages == "auto" and velocity_until is None and vel_names and plan[0].names == vel_names
            and not (observation.positions is not None and observation.point_ids == "particles")):
        t_guess = plan[0].until
        plan[0] = _first_interval_stage(plan[0], observation.times, model.frame_dt)
    replans_left = MAX_VELOCITY_REFITS if t_guess is not None else 0

    y_all = {n: to_unconstrained(n, jnp.asarray(v, _float_dtype())) for n, v in initial.items()}
    halvings_left = max_dt_halvings
    losses: list[float] = []
    records: list[dict] = []
    std: dict[str, np.ndarray] = {}
    last_stage_of = {n: i for i, s in enumerate(plan) for n in s.names}
    total_iterations = 0
    for si, stage in enumerate(plan):
        stage_method = stage.method or method
        if stage_method not in METHODS:
            raise JaxmpmError(f"unknown fit method {stage_method!r}; expected one of {METHODS}")
        steps = stage.max_steps or max_steps or (
            ADAM_WINDOW_STEPS if (stage_method == "adam" and stage.until is not None and si < len(plan) - 1)
            else DEFAULT_MAX_STEPS[stage_method])
        t_stage = time.perf_counter()
        say(f"stage {si + 1}/{len(plan)}: {', '.join(stage.names)} — {stage.label or 'all frames'} "
            f"[{stage_method}, {model.substeps} substeps/frame]")
        while True:
            objective = build_objective(model, observation, until=stage.until, **objective_options)
            fixed = {n: v for n, v in y_all.items() if n not in stage.names}
            base = apply_unconstrained(model, params, list(fixed), fixed)
            snames = list(stage.names)

            def params_of(y, base=base, snames=snames):
                return apply_unconstrained(model, base, snames, y)

            y0 = {n: y_all[n] for n in snames}
            outcome = _solve(stage_method, objective, params_of, y0, steps=steps, rtol=rtol, atol=atol,
                             progress=progress, offset=total_iterations, learning_rates=learning_rates,
                             lr_decay=lr_decay, xtol=xtol, patience=patience, grad=grad, seed=seed + si,
                             names=snames)
            if outcome.unhealthy_start:
                ok, why = objective.health(params_of(y0))
                why = why or "not finite (NaN loss)"
                if halvings_left <= 0:
                    raise FitError(
                        f"stage {si + 1} ({stage.label}): the simulation is {why} even with {model.substeps} "
                        "substeps per frame; try a smaller dt (more substeps) or a different initial guess"
                    )
                model = model.with_substeps(2 * model.substeps)
                halvings_left -= 1
                notes.append(f"stage {si + 1}: {why}; halved dt ({model.substeps} substeps/frame)")
                say(notes[-1])
                continue
            total_iterations += outcome.iterations
            for n in snames:
                y_all[n] = outcome.y[n]
            if outcome.unhealthy_trial and not outcome.converged and halvings_left > 0:
                model = model.with_substeps(2 * model.substeps)
                halvings_left -= 1
                notes.append(f"stage {si + 1}: unstable trial points stopped the solver; halved dt "
                             f"({model.substeps} substeps/frame) and continued from the best point")
                say(notes[-1])
                losses += outcome.losses
                continue
            break
        losses += outcome.losses
        record = {
            "label": stage.label,
            "names": snames,
            "until": stage.until,
            "frames": objective.frames,
            "method": stage_method,
            "iterations": outcome.iterations,
            "loss": [outcome.losses[0], min(outcome.losses)] if outcome.losses else [],
            "converged": bool(outcome.converged),
            "message": outcome.message,
            "seconds": time.perf_counter() - t_stage,
            "substeps": model.substeps,
            "terms": objective.terms,
        }
        records.append(record)
        say(f"stage {si + 1}: {outcome.message}")
        final_names = [n for n in snames if last_stage_of[n] == si]
        if uncertainty and final_names:
            def res(y, params_of=params_of, objective=objective):
                return objective.residuals(params_of(y)).astype(_float_dtype())

            stage_std = _gauss_newton_std(res, {n: y_all[n] for n in snames}, snames, objective.count,
                                          rj=outcome.jacobian)
            std.update({n: stage_std[n] for n in final_names})
        if replans_left and stage.until is not None and set(snames) == set(vel_names):
            replans_left -= 1
            now = apply_unconstrained(model, params, list(y_all), y_all)
            t_new = contact_time(model, now, observation)
            t_c = t_new if t_new is not None else t_guess
            rest, _ = plan_stages(model, now, observation, names, velocity_until=t_c,
                                  warmup_frames=warmup_frames, refine_velocity=refine_velocity)
            same_window = abs(t_c - stage.until) <= eps
            if same_window and rest and rest[0].names == vel_names:
                rest = rest[1:]  # the velocity was just fitted on exactly this window
            plan[si + 1:] = rest
            last_stage_of = {n: i for i, s in enumerate(plan) for n in s.names}
            if t_c <= eps:
                notes.append("with the fitted velocity the body is in contact from the first frames: the velocity "
                             "is refitted with the other parameters")
                say(notes[-1])
            elif not same_window:
                notes.append(f"with the fitted velocity the body touches by t = {t_c:.4g} s: the velocity is "
                             "refitted on the frames before that")
                say(notes[-1])

    final_params = apply_unconstrained(model, params, names, y_all)
    values = {n: np.asarray(get_param(final_params, p)) for n, p in paths.items()}
    deciding = [records[i] for i in sorted(set(last_stage_of.values()))]
    converged = all(r["converged"] for r in deciding)
    if converged:
        message = f"converged ({total_iterations} iterations in {len(records)} stage{'s' if len(records) > 1 else ''})"
        if len(records) == 1:
            message = records[0]["message"]
    else:
        failed = "; ".join(f"stage {records.index(r) + 1} ({r['label']}): {r['message']}" for r in deciding if not r["converged"])
        message = f"did not converge — {failed}; returning the best parameters so far"
    return FitResult(
        params=final_params,
        values=values,
        std=std,
        loss=losses,
        iterations=total_iterations,
        seconds=time.perf_counter() - start,
        converged=converged,
        message=message,
        substeps=model.substeps,
        initial=initial,
        method=method,
        stages=records,
        notes=notes,
    )


def _solve(method, objective: Objective, params_of, y0, *, steps, rtol, atol, progress, offset, learning_rates,
           lr_decay, xtol, patience, grad, seed, names) -> _StageOutcome:
    dtype = _float_dtype()
    if method in ("lm", "lm-optimistix", "lm-direct"):
        def residuals(y):
            return objective.residuals(params_of(y)).astype(dtype)

        run = _run_lm if method == "lm-direct" else _run_lm_optimistix
        return run(residuals, y0, max_steps=steps, rtol=rtol, atol=atol, progress=progress, offset=offset)
    if method == "bfgs":
        def loss(y):
            return objective.loss(params_of(y)).astype(dtype)

        return _run_bfgs(loss, y0, max_steps=steps, rtol=rtol, atol=atol, progress=progress, offset=offset)

    def loss(y, key):
        return objective.loss(params_of(y), key).astype(dtype)

    return _run_adam(loss, y0, max_steps=steps, learning_rates=learning_rates, lr_decay=lr_decay, xtol=xtol,
                     patience=patience, grad=grad, seed=seed, progress=progress, offset=offset, names=names)


# --------------------------------------------------------------------------- checks, scenes


def _check_observation(model: Model, observation: Observation) -> None:
    spec = observation.scene_spec
    if spec is not None and spec.get("dim") not in (None, model.dim):
        raise ObservationError(f"the observation's scene is {spec.get('dim')}-D but the model is {model.dim}-D")
    if spec is not None and isinstance(spec.get("bodies"), list) and len(spec["bodies"]) != len(model.bodies):
        raise ObservationError(
            f"the observation's scene has {len(spec['bodies'])} bodies but the model has {len(model.bodies)}"
        )


_GEOMETRY_KEYS = ("shape", "lo", "hi", "center", "radius", "path", "scale", "translate", "rotate")
_COLLIDER_KEYS = ("type", "point", "normal", "lo", "hi", "path", "scale", "translate", "rotate", "points",
                  "segments", "closed", "contact", "velocity", "angular_velocity")


def _same(a, b) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, str) and isinstance(b, str) and a != b:
        from pathlib import Path

        return Path(a).name == Path(b).name  # a path made absolute by Scene.to_json
    return a == b


def check_scene_compatible(spec: dict, observed: dict | None) -> None:
    """Raise ObservationError when an observation's scene disagrees with the fitted scene.

    Material *values*, initial velocities, substeps, frame counts and grid spacing may
    differ (they are what a fit varies, or numerical choices); the dimension, domain,
    bodies' shapes and material models, and the colliders' geometry and contact may not.
    """
    if observed is None:
        return
    diffs = []
    for key in ("dim",):
        if not _same(spec.get(key), observed.get(key)):
            diffs.append(f"{key}: {spec.get(key)!r} vs {observed.get(key)!r}")
    for key in ("lo", "hi"):
        a, b = spec.get("domain", {}).get(key), observed.get("domain", {}).get(key)
        if not _same(a, b):
            diffs.append(f"domain.{key}: {a} vs {b}")
    bodies, obodies = spec.get("bodies", []), observed.get("bodies", [])
    if len(bodies) != len(obodies):
        diffs.append(f"{len(bodies)} bodies vs {len(obodies)}")
    for k, (b, o) in enumerate(zip(bodies, obodies)):
        for key in _GEOMETRY_KEYS:
            if not _same(b.get(key), o.get(key)):
                diffs.append(f"bodies[{k}].{key}: {b.get(key)!r} vs {o.get(key)!r}")
        m1, m2 = (b.get("material") or {}).get("model"), (o.get("material") or {}).get("model")
        if m1 != m2:
            diffs.append(f"bodies[{k}].material.model: {m1!r} vs {m2!r}")
    cols, ocols = spec.get("colliders", []), observed.get("colliders", [])
    if len(cols) != len(ocols):
        diffs.append(f"{len(cols)} colliders vs {len(ocols)}")
    for k, (c, o) in enumerate(zip(cols, ocols)):
        for key in _COLLIDER_KEYS:
            if not _same(c.get(key), o.get(key)):
                diffs.append(f"colliders[{k}].{key}: {c.get(key)!r} vs {o.get(key)!r}")
    if diffs:
        shown = "; ".join(diffs[:6]) + (f"; and {len(diffs) - 6} more" if len(diffs) > 6 else "")
        raise ObservationError(f"the observation was made for a different scene (this scene vs the observation's): {shown}")


def fit_scene(scene, observation: Observation, names: Sequence[str] | None = None, **kwargs) -> FitResult:
    """:func:`fit` for a loaded :class:`~jaxmpm.scene.Scene` (its params are the initial guess).

    Checks first that the observation's embedded scene (if any) matches this one
    (:func:`check_scene_compatible`); ``names`` default to the material's parameters.
    """
    check_scene_compatible(scene.spec, observation.scene_spec)
    return fit(scene.model, scene.params, observation, names, **kwargs)


def parse_weights(text: str | None) -> dict | None:
    """``"tracks=1,silhouette=0.5"`` -> ``{"tracks": 1.0, "silhouette": 0.5}``."""
    if not text:
        return None
    out = {}
    for item in text.split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition("=")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            raise JaxmpmError(f"--weights: expected name=number pairs (e.g. tracks=1,silhouette=0.5), got {item!r}") from None
        if not sep:
            raise JaxmpmError(f"--weights: expected name=number pairs, got {item!r}")
    return out
