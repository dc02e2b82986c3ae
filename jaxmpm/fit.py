"""Parameter identification: one call, staged like PAC-NeRF/GIC (the identification core's front).

``fit(model, params, observation, names, config=FitConfig(method="lm" | "adam" | "bfgs"))``
minimises the weighted loss of :mod:`jaxmpm.identify.residuals` (tracks, silhouettes, masked
RGB, probes) with a solver of :mod:`jaxmpm.identify.solvers`:

* ``"lm"`` (default): Levenberg–Marquardt (``optimistix``) on the residual vector with
  forward-mode Jacobians (one JVP per parameter; no reverse-mode tape).
* ``"adam"``: the reference, PAC-NeRF's optimiser: Adam (``optax``) with each parameter's
  declared learning rate in its fitting space (:class:`jaxmpm.parameters.Parameter`), a
  fresh random pixel batch per iteration for image terms, and the lowest-loss iterate
  returned (GIC). The gradient is forward mode by default (``grad="fwd"``).
* ``"bfgs"``: ``optimistix.BFGS`` on the scalar loss (forward-mode gradients).

**Stages** (``stages="auto"``, PAC-NeRF's schedule): (1) the initial velocity alone (with
the body's ``offset`` when it is fitted too: :data:`KINEMATIC`) from
the pre-contact frames, when a ``velocity`` is among the names (without per-particle tracks,
whose contact is found in a rollout of the guess, first from the first observed interval,
then again from the frames before the contact of that velocity; from silhouettes or untracked
points the first velocity stage starts from the better of the guess and the observed free
fall, :func:`free_fall_velocity`); (2) the other parameters on
the frames up to ``warmup_frames`` after contact; (3) the same on all frames. A stage whose
rollout is unhealthy (:func:`jaxmpm.step.unhealthy`: NaN, a CFL number above ``cfl_limit``,
energy growth, a stress-wave CFL number above 1) at its starting point, or whose
solver stalls against unhealthy trial points, halves dt (doubles the substeps) and restarts
from the best point so far, up to ``max_dt_halvings`` times in all. A halved dt is for health
only: when the last stage ends at one and its result is healthy at the scene's dt, that stage
is fitted once more there (the data's discretisation; a note says so).

**Uncertainty**: standard deviations from the Gauss–Newton covariance
``s² (JᵀJ)⁻¹`` at the optimum (``s² = RSS / (m − p)``,
:func:`jaxmpm.identify.uncertainty.gauss_newton_covariance`), with ``resolution=True`` raised
where the loss is rough to the smallest move it resolves
(:func:`jaxmpm.identify.uncertainty.resolved_std`: the loss is probed at ± the std along each
parameter's profile direction and further out until it changes as its curvature predicts;
the stage's record then holds a ``resolution`` entry and a note says so), mapped to physical
units; each parameter's from the last stage that fitted it.

**Numerical error** (``numerics=True``, ``jaxmpm fit --numerics``): after each parameter's
last stage, the stage is refitted from its result with dt halved and with the other transfer
(APIC / the FLIP blend, :mod:`jaxmpm.numerics`), a few iterations each: how far they move the
parameters is their numerical error (:func:`numerics_check`), which a statistical std does
not include; a note says where a move exceeds :data:`NUMERICS_NOTE_STDS` standard deviations.

Parameters are named (``"mu"``, ``"kappa"``, ``"E"``, ``"nu"``, ``"yield_stress"``,
``"eta"``, ``"friction_angle"``, ``"density"``, ``"velocity"``, ``"gravity"``,
``"<collider>.friction"``, ``"<body>.<param>"``: :func:`jaxmpm.identify.resolve_name`) and
optimised in the space their declaration gives (PAC-NeRF's: log10 for moduli, viscosities and
densities; a tanh-bounded Poisson ratio; degrees for the friction angle; linear otherwise).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from .errors import JaxmpmError, ObservationError
from .identify.parameters import (
    apply_unconstrained,
    check_names,
    check_varied,
    declaration,
    default_names,
    from_unconstrained,
    get_param,
    leaf_name,
    resolve_name,
    to_unconstrained,
    transform_of,
)
from .identify.residuals import Objective, Residuals, build_objective, frames_needed, observation_cameras
from .identify.solvers import SolverOutcome, adam, bfgs, levenberg_marquardt, loss_function, residuals_and_jacobian
from .identify.uncertainty import gauss_newton_covariance, physical_std, resolved_std
from .model import CPIC_RESTITUTION_NOTE, Model, Params, weak_restitution
from .numerics import (NUMERICS_REFIT_STEPS, Numerics, Refit, format_std, move_table, numerics_notes,
                       parameter_moves)
from .observe import Observation, check_observation_matches, check_scene_compatible
from .parameters import Log10

__all__ = [
    "METHODS",
    "FitConfig",
    "FitError",
    "FitResult",
    "Stage",
    "fit",
    "fit_scene",
    "plan_stages",
    "KINEMATIC",
    "contact_time",
]

#: The optimisers: Levenberg–Marquardt (optimistix), Adam (optax), BFGS (optimistix).
METHODS = ("lm", "adam", "bfgs")

#: Default iterations per stage and method (PAC-NeRF: 50 Adam iterations on the early
#: window, 100 on all frames).
DEFAULT_MAX_STEPS = {"lm": 40, "bfgs": 60, "adam": 100}
ADAM_WINDOW_STEPS = 50

#: Velocity refits after the first velocity stage when contact is re-detected with each fitted
#: velocity (images or untracked points; see :func:`_first_interval_stage`).
MAX_VELOCITY_REFITS = 3


#: The body's initial motion and placement: fitted in the pre-contact stage, before the
#: material, and refitted with it or held as ``refine_velocity`` says. A reconstructed body's
#: placement error would otherwise pass into a velocity fitted to the first frames alone
#: (docs/identify.md, session 36).
KINEMATIC = ("velocity", "offset")

#: The command lines' ``--refine-velocity`` choices: :attr:`FitConfig.refine_velocity`'s values.
REFINE_VELOCITY = {"auto": None, "yes": True, "no": False}

#: Decade offsets from the starting guess that a fit without per-particle tracks scans before
#: it fits each log10 material parameter (:attr:`FitConfig.scan`'s automatic choice). The
#: silhouette loss has plateaus where Levenberg–Marquardt stalls decades from the answer: on
#: the tiny block of docs/identify.md §4 (μ = 200 Pa·s from PAC-NeRF's guess of 10) it is
#: nearly flat from 10 to 50 Pa·s and LM stopped at 25; the sysid benchmark's box cases
#: stalled 0.19 (Newtonian μ) and 1–8 decades (viscoplastic) off without it
#: (docs/benchmark_sysid.md, session 34).
SCAN_DECADES = (-1.0, 1.0, 2.0, 3.0)

#: Moves of each velocity component tried where a stage that fits the velocity last stalls
#: without per-particle tracks (:attr:`FitConfig.polish`), in units of ``dx / T``: the velocity
#: error that shifts the body by one grid cell over the stage's observed time ``T``. On the sysid
#: benchmark's viscoplastic bunny (``dx / T`` = 64 mm/s: moves of 1, 3 and 10 mm/s) the
#: silhouette fit stalled with its x velocity 2.9 mm/s off, where a move of that one component
#: lowered the loss that Levenberg–Marquardt's steps could not, and LM from there met every
#: target (docs/benchmark_sysid.md, session 47).
VELOCITY_POLISH = (0.015, 0.05, 0.15)


def _finite_numbers(values, positive: bool = False) -> bool:
    """Whether ``values`` is a sequence (not a string) of finite real numbers (not bools), all
    positive when ``positive``."""
    if isinstance(values, (str, bytes)):
        return False
    return all(isinstance(d, (int, float)) and not isinstance(d, bool) and np.isfinite(d) and (d > 0 or not positive)
               for d in values)


class FitError(JaxmpmError, RuntimeError):
    """A fit could not start (e.g. the simulation is unstable even at small dt)."""


@dataclass(frozen=True)
class FitConfig:
    """How :func:`fit` runs (every field has PAC-NeRF's or a measured default).

    Attributes:
        method: ``"lm"`` (Levenberg–Marquardt), ``"adam"`` or ``"bfgs"``.
        stages: ``"auto"`` (PAC-NeRF's velocity → window → all frames, see
            :func:`plan_stages`), None (one stage: all names, all frames) or a list of
            :class:`Stage`.
        weights: loss weights per term (:func:`jaxmpm.identify.build_objective`).
        max_steps: iterations per stage (default 40 LM, 60 BFGS, 100 Adam — 50 on the
            window stage, as PAC-NeRF).
        rtol, atol: LM/BFGS tolerances on the step and the loss.
        checkpoint: checkpoint policy of the rollouts.
        max_dt_halvings: how often dt may be halved (in all) after unhealthy rollouts.
        cfl_limit: a rollout whose CFL number ``max|v| dt/dx`` exceeds this is unhealthy (the
            one health check, :func:`jaxmpm.step.unhealthy`).
        learning_rates: Adam learning rates by name or leaf (default: each parameter's
            declared rate).
        lr_decay: Adam: the learning rates decay exponentially to ``lr·lr_decay`` over a
            stage (GIC); default constant (PAC-NeRF).
        xtol, patience: Adam stops (converged) when no parameter moved more than ``xtol``
            (optimisation space) over the last ``patience`` iterations.
        grad: Adam's gradient: ``"fwd"`` (forward mode, one JVP per parameter) or ``"rev"``.
        seed: PRNG seed of Adam's random pixel batches.
        velocity_until: last observed time of the velocity stage (default: detected, see
            :func:`contact_time`).
        warmup_frames: frames after contact in the window stage (PAC-NeRF: 3).
        refine_velocity: also refit the velocity in the stages after its pre-contact stage.
            None (default): when that stage saw a single observed interval and no
            per-particle tracks (masks, images or untracked points): one frame of
            silhouettes pins a velocity only to a fraction of a pixel, and later stages that
            hold it turn its error into material error (the sysid benchmark's sand on the
            bunny: 0.017 m/s off, φ 0.59° off held, 0.04° refitted; docs/benchmark_sysid.md,
            session 33). False: held, PAC-NeRF's protocol. True: always refitted.
        renderer, num_pixels, probes, colors: image and probe options of the objective.
        uncertainty: compute the Gauss–Newton standard deviations.
        numerics: after each parameter's last stage, how far a refit at dt/2 and one with the
            other transfer move it (:func:`numerics_check`: at most
            :data:`NUMERICS_REFIT_STEPS` iterations each, from the fitted point);
            ``FitResult.numerics`` holds the moves, the stage's record the details, and a
            note names each parameter moved by more than :data:`NUMERICS_NOTE_STDS`
            standard deviations. Costs two short refits of the stage (one at dt/2) and
            their compilation.
        resolution: raise each standard deviation to the scale the loss resolves where it is
            rough (:func:`jaxmpm.identify.uncertainty.resolved_std`): for noise-free or
            CPIC fits, whose Gauss–Newton std only measures round-off and jumps. Two loss
            evaluations per parameter and try (on the sysid track cases, +3 to +30 s a fit).
        scan: decade offsets (e.g. ``(-1, 1, 2)``) tried before the first stage that fits a
            scalar log10 parameter (viscosity, moduli, yield stress): one parameter at a
            time, each at its starting value × 10^offset, the others at the best so far;
            the stage starts from the point with the lowest stage loss (:func:`scan_start`).
            Silhouette losses have plateaus where Levenberg–Marquardt stalls a decade or more
            from the answer; a coarse look across them costs one evaluation of the stage's
            residuals and Jacobian per point. None (default): :data:`SCAN_DECADES` when the
            observation has no per-particle tracks (masks, images or untracked points), no
            scan from tracks of every particle (whose loss has no such plateaus); ``()``: no
            scan. A fit whose scan moved its start and that does not converge is run again
            from the guess without the scan, and the lower loss of the last stage decides
            (a note says so; ``FitResult.timing["other_start"]`` has the other).
        polish: velocity moves (units of ``dx / T``, see :data:`VELOCITY_POLISH`) tried, each
            component in turn and both signs, where the last stage that fits a velocity stops
            without converging: a rough silhouette loss can hold Levenberg–Marquardt in a
            valley of the velocity that a move of a few mm/s leaves. When a move lowers the
            stage loss, the stage is solved again from there (a note says so; the stage's record
            has ``polish``). Costs a forward-only loss program and ``6 × D`` evaluations.
            None (default): :data:`VELOCITY_POLISH` without per-particle tracks, none from
            tracks of every particle; ``()``: none.
        free_fall_start: from silhouettes or untracked points, start the first velocity stage
            from the velocity the observed free fall gives (:func:`free_fall_velocity`) when
            its stage loss is lower than the guess's: the silhouette loss is far from
            quadratic at a guess of rest, where Levenberg–Marquardt creeps towards the answer
            over 15–20 trust-region steps, and a Chamfer loss between particle lattices has
            minima one particle spacing apart; two evaluations decide.
    """

    method: str = "lm"
    stages: Any = "auto"
    weights: dict[str, float] | None = None
    max_steps: int | None = None
    rtol: float = 1e-5
    atol: float = 1e-8
    checkpoint: str | None = "nested"
    max_dt_halvings: int = 3
    cfl_limit: float = 1.0
    learning_rates: dict[str, float] | None = None
    lr_decay: float | None = None
    xtol: float = 1e-3
    patience: int = 10
    grad: str = "fwd"
    seed: int = 0
    velocity_until: float | None = None
    warmup_frames: int = 3
    refine_velocity: bool | None = None
    renderer: Any = "volume"
    num_pixels: int = 256
    probes: dict | None = None
    colors: Any = "auto"
    uncertainty: bool = True
    numerics: bool = False
    resolution: bool = False
    scan: Sequence[float] | None = None
    polish: Sequence[float] | None = None
    free_fall_start: bool = True

    def check(self) -> None:
        """Raise JaxmpmError naming the first invalid field (called before any work)."""
        if self.method not in METHODS:
            raise JaxmpmError(f"unknown fit method {self.method!r}; expected one of {METHODS}")
        if self.grad not in ("fwd", "rev"):
            raise JaxmpmError(f"grad must be 'fwd' or 'rev', got {self.grad!r}")
        if self.max_steps is not None and (isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int)
                                           or self.max_steps < 1):
            raise JaxmpmError(f"max_steps must be a positive integer, got {self.max_steps!r}")
        if self.max_dt_halvings < 0:
            raise JaxmpmError(f"max_dt_halvings must be >= 0, got {self.max_dt_halvings}")
        if isinstance(self.stages, str) and self.stages not in ("auto", "single"):
            raise JaxmpmError(f"stages must be 'auto', None or a list of Stage, got {self.stages!r}")
        if self.scan is not None and not _finite_numbers(self.scan):
            raise JaxmpmError(f"scan must be a sequence of finite decade offsets, got {self.scan!r}")
        if self.polish is not None and not _finite_numbers(self.polish, positive=True):
            raise JaxmpmError(f"polish must be a sequence of positive finite moves (units of dx / T), got "
                              f"{self.polish!r}")

    def objective_options(self) -> dict:
        """The keyword arguments of :func:`jaxmpm.identify.build_objective` this configuration
        fits with (all but the frame window)."""
        return dict(weights=self.weights, probes=self.probes, renderer=self.renderer, num_pixels=self.num_pixels,
                    colors=self.colors, checkpoint=self.checkpoint, cfl_limit=self.cfl_limit)


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


#: Contact in a rollout (:func:`contact_time`, no per-particle tracks): a frame interval whose
#: displacements depart from one translation by more than this fraction of a grid cell. Free
#: flight departs by rounding (1e-6 to 3e-5 of a cell in float32); a body that begins to touch a
#: collider within the interval, by 3-12 % of a cell in the sysid benchmark's scenes.
CONTACT_ROLLOUT_TOL = 2e-3


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
    more than ``tol`` (95th percentile over the points). Uses the observed tracks when they
    are per-particle (``point_ids == "particles"``; default ``tol``: 5 % of a grid cell per
    frame, above the tracks' noise), else a rollout at ``params`` (the initial guess;
    :func:`fit` re-detects contact with the fitted velocity and refits it on a shorter window
    if needed), whose free flight departs from a translation by rounding only (default
    ``tol``: ``CONTACT_ROLLOUT_TOL`` of a cell, so an interval in which the body only begins
    to touch counts as contact). Returns None when nothing touches within the data, and 0.0
    when the body is in contact from the start.
    """
    from .step import simulate

    times = np.asarray(observation.times, float)
    if observation.tracks_particles and len(times) >= 2:
        tol = 0.05 * model.grid.dx if tol is None else tol
        x = np.asarray(observation.positions, float)
        disp = _velocity_dispersion(x)
        scale = np.diff(times) / model.frame_dt  # displacement tolerance per observed interval
        bad = np.flatnonzero(~(disp <= tol * np.maximum(scale, 1e-9)))
        return None if len(bad) == 0 else float(times[bad[0]])

    tol = CONTACT_ROLLOUT_TOL * model.grid.dx if tol is None else tol
    x = np.asarray(simulate(model, params, checkpoint=None, frames=frames_needed(model, times)).x, float)
    disp = _velocity_dispersion(x)
    bad = np.flatnonzero(~(disp <= tol))
    if len(bad) == 0:
        return None
    t = bad[0] * model.frame_dt
    before = times[times <= t + 1e-3 * model.frame_dt]
    return float(before[-1]) if len(before) else 0.0


def _last_stage_of(plan: Sequence[Stage]) -> dict[str, int]:
    """Each fitted name's last stage in ``plan`` (the one whose result and std it keeps)."""
    return {n: i for i, stage in enumerate(plan) for n in stage.names}


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
    refine_velocity: bool | None = None,
) -> tuple[list[Stage], list[str]]:
    """PAC-NeRF's schedule for ``names`` (see the module docstring) and notes about it;
    ``refine_velocity``: :attr:`FitConfig.refine_velocity`."""
    names = list(names)
    kinematic = [n for n in names if leaf_name(n) in KINEMATIC]
    rest = [n for n in names if leaf_name(n) not in KINEMATIC]
    times = np.asarray(observation.times, float)
    t_end = float(times.max())
    notes = []
    eps = 1e-3 * model.frame_dt  # observed times may be float32
    t_c = velocity_until if velocity_until is not None else contact_time(model, params, observation)
    stages: list[Stage] = []
    pre = times[(times > 0) & (times <= (t_c if t_c is not None else t_end) + eps)]
    if kinematic:
        if not rest:
            return [Stage(kinematic, None, "velocity (all frames)")], notes
        if t_c is None:
            notes.append("no contact within the observed frames: the velocity is fitted with the other parameters")
        elif len(pre) < 1 or t_c <= 0:
            notes.append("the body is in contact from the start: the velocity is fitted with the other parameters")
        else:
            stages.append(Stage(kinematic, float(t_c), f"velocity (pre-contact frames, t <= {t_c:.4g} s)"))
    if kinematic and stages and refine_velocity is None:
        refine_velocity = not observation.tracks_particles and len(pre) == 1
        if refine_velocity:
            notes.append(f"the velocity rests on one observed interval before contact (t <= {t_c:.4g} s) and no "
                         "per-particle tracks: it is refitted with the material after its stage "
                         "(refine_velocity=False holds it)")
    joint = rest + (kinematic if (refine_velocity or not stages) else [])
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
        std: standard deviations by name (physical units): the Gauss–Newton covariance's, or the
            scale the loss resolves where it is rough (``FitConfig.resolution``; the module's
            "Uncertainty").
        loss: loss after each accepted iteration, all stages in order (first = initial).
        iterations: solver iterations taken (all stages; both starts where the fit was run
            again from the guess, :attr:`FitConfig.scan`).
        seconds: wall time.
        converged: whether every parameter's last stage met its tolerance.
        message: a human-readable status (says so when the fit did not converge).
        substeps: substeps per frame used (may exceed the model's after dt halving).
        initial: the initial values by name.
        method: the optimiser.
        stages: per stage: names, window, iterations, loss, converged, message, seconds and
            its ``timing`` (``start_s``: the first residuals and Jacobian, compilation
            included; ``first_step_s``, ``step_s`` (median), ``steps_s`` (all), ``compile_s``
            (the first step's excess over the median); ``checks_s``: the Gauss–Newton stop
            checks; ``rejected_steps``, ``escapes``; ``uncertainty_s``). Where the fit was run
            again from the guess, the kept start's stages.
        notes: remarks (dt halvings, skipped stages).
        numerics: with :attr:`FitConfig.numerics`, by name: ``{"dt": move, "transfer":
            move}``, how far a refit at dt/2 and one with the other transfer move the
            value (physical units, the value's shape; None where that rollout is unhealthy;
            :func:`numerics_check`); empty otherwise.
        timing: where the time went (seconds): ``total_s``, ``planning_s`` (contact detection
            for the stages), ``solver_s``, ``compile_s`` (estimated), ``uncertainty_s``; where
            the fit was run again from the guess, ``other_start`` (the start not kept:
            ``start``, ``total_s``, ``iterations``, ``loss`` of its last stage, ``values``,
            ``converged``) and ``total_s`` over both.
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
    timing: dict = field(default_factory=dict)
    numerics: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """The ``fit.json`` contract (DESIGN §5.3) plus status fields."""
        plain = _plain
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
            "timing": json.loads(json.dumps(self.timing, default=float)),
            "numerics": {k: {c: None if v is None else plain(v) for c, v in d.items()} for k, d in self.numerics.items()},
        }


def _plain(v):
    """A number or nested list (JSON) from an array."""
    v = np.asarray(v)
    return v.item() if v.ndim == 0 else v.tolist()


# --------------------------------------------------------------------------- the fit


def fit(
    model: Model,
    params: Params,
    observation: Observation,
    names: Sequence[str] | None = None,
    config: FitConfig = FitConfig(),
    *,
    progress: Callable[[int, float], None] | None = None,
    log: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit named parameters of ``model`` to ``observation``.

    Arguments:
        model: static model (its frames are extended to cover the observed times).
        params: initial parameter pytree (the initial guess for the fitted names).
        observation: an :class:`~jaxmpm.observe.Observation` (tracks, masks/images, probes).
        names: parameter names (see :func:`jaxmpm.identify.resolve_name`); default: the material's.
        config: how to fit (:class:`FitConfig`: the optimiser, stages, loss weights, tolerances).
        progress: callback ``progress(iteration, loss)`` (iterations count across stages).
        log: callback ``log(message)`` for stage starts, dt halvings and notes.

    Returns:
        A :class:`FitResult`; ``converged`` is False (and ``message`` says so) when a stage
        did not meet its tolerance: the parameters are then the best found.

    Raises:
        JaxmpmError: unknown parameters or methods; ObservationError: unusable data;
        FitError: the rollout stays unhealthy after ``max_dt_halvings`` halvings.
    """
    start = time.perf_counter()
    say = log or (lambda msg: None)
    scene_model = model
    if not isinstance(config, FitConfig):
        raise JaxmpmError(f"config must be a FitConfig, got {type(config).__name__}")
    config.check()
    c = config
    if not isinstance(observation, Observation):
        raise ObservationError(f"expected an Observation, got {type(observation).__name__}")
    check_observation_matches(model, observation)
    names = default_names(model) if names is None else check_names(names)
    if not names:
        raise JaxmpmError("no parameters to fit")
    paths = {n: resolve_name(model, params, n) for n in names}
    check_varied(model, paths, "fitted")
    initial = {n: np.asarray(get_param(params, p)) for n, p in paths.items()}
    for n, v in initial.items():
        if transform_of(n).needs_positive() and np.any(v <= 0):
            raise JaxmpmError(f"initial value of {n!r} must be > 0 (fitted in log10), got {v}")
        if not np.all(np.isfinite(v)):
            raise JaxmpmError(f"initial value of {n!r} is not finite: {v}")
    objective_options = c.objective_options()
    # fail early on unusable data (before any rollout)
    build_objective(model, observation, **objective_options)

    notes: list[str] = [f"{n}: {CPIC_RESTITUTION_NOTE}" for n, p in paths.items()
                        if p[0] == "colliders" and p[2] == "restitution" and weak_restitution(model, p[1])]
    notes += [f"{n}: {APIC_VISCOSITY_NOTE}" for n in apic_viscosities(model, paths, observation)]
    planning_s = 0.0
    if c.stages == "auto":
        t_plan = time.perf_counter()
        plan, plan_notes = plan_stages(model, params, observation, names, velocity_until=c.velocity_until,
                                       warmup_frames=c.warmup_frames, refine_velocity=c.refine_velocity)
        planning_s += time.perf_counter() - t_plan
        notes += plan_notes
    elif c.stages is None or c.stages == "single":
        plan = [Stage(list(names), None, "all frames")]
    else:
        plan = list(c.stages)
        for s in plan:
            unknown = [n for n in s.names if n not in paths]
            if unknown:
                raise JaxmpmError(f"stage {s.label or s.names}: {unknown} are not among the fitted names {names}")
    for note in notes:
        say(note)
    kinematic_names = [n for n in names if leaf_name(n) in KINEMATIC]
    velocity_names = [n for n in kinematic_names if leaf_name(n) == "velocity"]
    eps = 1e-3 * model.frame_dt  # observed times may be float32
    # contact found in a rollout of the initial guess (no per-particle tracks): the velocity
    # starts on the first observed interval and contact is re-detected after each velocity stage
    t_guess = None
    if (c.stages == "auto" and c.velocity_until is None and kinematic_names and plan[0].names == kinematic_names
            and not observation.tracks_particles):
        t_guess = plan[0].until
        plan[0] = _first_interval_stage(plan[0], observation.times, model.frame_dt)
    replans_left = MAX_VELOCITY_REFITS if t_guess is not None else 0
    fall_velocity = None
    if t_guess is not None and c.free_fall_start and len(velocity_names) == 1:
        fall_velocity = free_fall_velocity(model, params, observation)

    y_all = {n: to_unconstrained(n, jnp.asarray(v, jnp.result_type(float))) for n, v in initial.items()}
    halvings_left = c.max_dt_halvings
    scene_substeps, returned = model.substeps, False  # dt is halved for health only: see the loop's end
    losses: list[float] = []
    records: list[dict] = []
    std: dict[str, np.ndarray] = {}
    numerics: dict[str, dict] = {}
    last_stage_of = _last_stage_of(plan)
    scan = (() if observation.tracks_particles else SCAN_DECADES) if c.scan is None else tuple(c.scan)
    polish = (() if observation.tracks_particles else VELOCITY_POLISH) if c.polish is None else tuple(c.polish)
    scan_left = set() if not scan else {
        n for n in names if isinstance(transform_of(n), Log10) and np.ndim(initial[n]) == 0}
    total_iterations = 0
    solved: set[str] = set()  # the names an earlier stage has fitted (their later stages start warm)
    for si, stage in enumerate(plan):
        stage_method = stage.method or c.method
        if stage_method not in METHODS:
            raise JaxmpmError(f"unknown fit method {stage_method!r}; expected one of {METHODS}")
        steps = stage.max_steps or c.max_steps or (
            ADAM_WINDOW_STEPS if (stage_method == "adam" and stage.until is not None and si < len(plan) - 1)
            else DEFAULT_MAX_STEPS[stage_method])
        t_stage = time.perf_counter()
        stage_scan = stage_fall = None
        say(f"stage {si + 1}/{len(plan)}: {', '.join(stage.names)} — {stage.label or 'all frames'} "
            f"[{stage_method}, {model.substeps} substeps/frame]")
        while True:
            objective = build_objective(model, observation, until=stage.until, **objective_options)
            fixed = {n: v for n, v in y_all.items() if n not in stage.names}
            snames = list(stage.names)
            stage_residuals = StageResiduals(objective.program, apply_unconstrained(model, params, list(fixed), fixed),
                                             tuple(snames))
            params_of = stage_residuals.params
            y0 = {n: y_all[n] for n in snames}
            to_scan = [n for n in snames if n in scan_left]
            if to_scan:
                y0, scanned = stage_scan = scan_start(stage_residuals, y0, to_scan, scan)
                scan_left.difference_update(to_scan)
                y_all.update(y0)
                moved = ", ".join(f"{n} x10^{d:+g}" for n, d in scanned["moved"].items()) or "none moved"
                notes.append(f"stage {si + 1}: scanned {scanned['points']} starting points ({moved}); "
                             f"loss {scanned['start_loss']:.4g} -> {scanned['best_loss']:.4g}")
                say(notes[-1])
            if fall_velocity is not None and snames == kinematic_names:
                v_name = velocity_names[0]
                guess = {v_name: to_unconstrained(v_name, jnp.asarray(fall_velocity, y0[v_name].dtype))}
                y0, picked = better_start(stage_residuals, y0, guess)
                fall_velocity = None  # the first velocity stage only: later ones start from its result
                y_all.update(y0)
                notes.append(f"stage {si + 1}: the observed free fall gives velocity "
                             f"{np.round(np.asarray(picked['candidate'], float), 3).tolist()} m/s; loss at the guess "
                             f"{picked['start_loss']:.4g}, there {picked['candidate_loss']:.4g}: started from "
                             + ("it" if picked["taken"] else "the guess"))
                say(notes[-1])
                stage_fall = {**picked, "candidate": np.asarray(picked["candidate"], float).tolist()}
            outcome = _solve(stage_method, objective, stage_residuals, y0, c, steps=steps, seed=c.seed + si,
                             progress=progress, offset=total_iterations,
                             warm=set(snames) <= solved and not to_scan and stage_fall is None)
            if outcome.unhealthy_start:
                why = objective.health(params_of(y0)) or "the loss is not finite (NaN residuals)"
                if halvings_left <= 0:
                    raise FitError(
                        f"stage {si + 1} ({stage.label}), at the starting point, with {model.substeps} substeps per "
                        f"frame: {why}; or try a different initial guess"
                    )
                model = model.with_substeps(2 * model.substeps)
                halvings_left -= 1
                notes.append(f"stage {si + 1}: {why} — halved dt ({model.substeps} substeps/frame)")
                say(notes[-1])
                continue
            total_iterations += outcome.iterations
            solved.update(snames)
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
        stage_losses, stage_timing = list(outcome.losses), dict(outcome.timing)
        stage_polish = None
        to_polish = [n for n in velocity_names if n in snames and last_stage_of[n] == si]
        if polish and to_polish and not outcome.converged:
            t_polish = time.perf_counter()
            window = stage.until if stage.until is not None else float(np.asarray(observation.times)[-1])
            unit = model.grid.dx / max(window, model.frame_dt)  # m/s that shift the body a cell over the window
            y_polished, stage_polish = polish_velocity(stage_residuals, {n: y_all[n] for n in snames}, to_polish,
                                                       [d * unit for d in polish])
            stage_polish["seconds"] = time.perf_counter() - t_polish
            if stage_polish["moved"]:
                moved = ", ".join(f"{k} {d * 1e3:+.3g} mm/s" for k, d in stage_polish["moved"].items())
                notes.append(f"stage {si + 1}: it stopped without converging; moving {moved} lowered its loss "
                             f"{stage_polish['start_loss']:.4g} -> {stage_polish['best_loss']:.4g}: solved again "
                             "from there")
                say(notes[-1])
                stopped = outcome
                outcome = _solve(stage_method, objective, stage_residuals, y_polished, c, steps=steps,
                                 seed=c.seed + si, progress=progress, offset=total_iterations)
                total_iterations += outcome.iterations
                outcome.iterations += stopped.iterations
                losses += outcome.losses
                stage_losses += outcome.losses
                stage_timing = {k: stage_timing.get(k, 0.0) + outcome.timing.get(k, 0.0) if k != "step_s"
                                else stage_timing.get(k, outcome.timing.get(k, 0.0))  # a median: the first solve's
                                for k in {*stage_timing, *outcome.timing}}
                for n in snames:
                    y_all[n] = outcome.y[n]
            else:
                notes.append(f"stage {si + 1}: it stopped without converging; no velocity move of "
                             f"{', '.join(f'{d * unit * 1e3:.3g}' for d in polish)} mm/s lowered its loss")
                say(notes[-1])
            stage_timing["polish_s"] = stage_polish["seconds"]
        record = {
            "label": stage.label,
            "names": snames,
            "until": stage.until,
            "frames": objective.frames,
            "method": stage_method,
            "iterations": outcome.iterations,
            "loss": [stage_losses[0], min(stage_losses)] if stage_losses else [],
            "converged": bool(outcome.converged),
            "message": outcome.message,
            "seconds": time.perf_counter() - t_stage,
            "substeps": model.substeps,
            "terms": objective.terms,
            "timing": stage_timing,
        }
        if stage_scan is not None:
            record["scan"] = stage_scan[1]
        if stage_polish is not None:
            record["polish"] = stage_polish
        if stage_fall is not None:
            record["free_fall_start"] = stage_fall
        records.append(record)
        say(f"stage {si + 1}: {outcome.message}")
        final_names = [n for n in snames if last_stage_of[n] == si]
        if c.uncertainty and final_names:
            t_std = time.perf_counter()
            stage_std, statistical, unresolved = _stage_std(objective, stage_residuals,
                                                             {n: y_all[n] for n in snames}, outcome.jacobian,
                                                             c.resolution)
            std.update({n: stage_std[n] for n in final_names})
            rough = [n for n in final_names
                     if np.any(np.asarray(stage_std[n]) > 3.0 * np.asarray(statistical[n])) or n in unresolved]
            if rough:
                record["resolution"] = {n: {"std": _plain(stage_std[n]), "statistical_std": _plain(statistical[n]),
                                            "resolved": n not in unresolved} for n in rough}
                notes.append(
                    f"stage {si + 1}: the loss is rough below the scale of the Gauss-Newton std for "
                    + ", ".join(f"{n} (std {format_std(stage_std[n])} instead of {format_std(statistical[n])}"
                                f"{'; not resolved up to a move of 1 + |y|' if n in unresolved else ''})" for n in rough)
                    + ": moves below that change the loss by jumps, not as its derivative predicts")
                say(notes[-1])
            record["timing"]["uncertainty_s"] = time.perf_counter() - t_std
        if c.numerics and final_names:
            t_num = time.perf_counter()
            say(f"stage {si + 1}: numerics check (the stage refitted at dt/2 and with the other transfer)")
            check = record["numerics"] = numerics_check(
                stage_residuals, lambda other, until=stage.until: build_objective(other, observation, until=until,
                                                                                 **objective_options),
                {n: y_all[n] for n in snames}, rtol=c.rtol, atol=c.atol, say=say)
            numerics.update(move_table(check, final_names))
            moved = numerics_notes(check, final_names, std, made_by_model=observation.made_by(model))
            for note in moved:
                notes.append(f"stage {si + 1}: {note}")
                say(notes[-1])
            record["timing"]["numerics_s"] = time.perf_counter() - t_num
        if replans_left and stage.until is not None and set(snames) == set(kinematic_names):
            replans_left -= 1
            now = apply_unconstrained(model, params, list(y_all), y_all)
            t_plan = time.perf_counter()
            t_new = contact_time(model, now, observation)
            planning_s += time.perf_counter() - t_plan
            t_c = t_new if t_new is not None else t_guess
            rest, rest_notes = plan_stages(model, now, observation, names, velocity_until=t_c,
                                           warmup_frames=c.warmup_frames, refine_velocity=c.refine_velocity)
            same_window = abs(t_c - stage.until) <= eps
            if same_window and rest and rest[0].names == kinematic_names:
                rest = rest[1:]  # the velocity was just fitted on exactly this window
            plan[si + 1:] = rest
            last_stage_of = _last_stage_of(plan)
            if t_c <= eps:
                notes.append("with the fitted velocity the body is in contact from the first frames: the velocity "
                             "is refitted with the other parameters")
                say(notes[-1])
            elif not same_window:
                notes.append(f"with the fitted velocity the body touches by t = {t_c:.4g} s: the velocity is "
                             "refitted on the frames before that")
                say(notes[-1])
            for note in rest_notes if t_c > eps else []:  # (in contact from the start: said above)
                if note not in notes:
                    notes.append(note)
                    say(note)
        if si == len(plan) - 1 and model.substeps != scene_substeps and not returned:
            # A halved dt changes the discretised model the data are fitted with: where the
            # result is healthy at the scene's dt, its last stage is fitted again there.
            returned = True
            at_scene = model.with_substeps(scene_substeps)
            why = build_objective(at_scene, observation, until=stage.until, **objective_options).health(
                apply_unconstrained(at_scene, params, list(y_all), y_all))
            if why is None:
                notes.append(f"stage {si + 1} ended at {model.substeps} substeps/frame (dt halved for health); its "
                             f"result is healthy at the scene's {scene_substeps}: stage {si + 2} fits its "
                             "parameters again there")
                model = at_scene
                plan.append(replace(stage, label=f"{stage.label or 'all frames'}, again at the scene's dt"))
                last_stage_of = _last_stage_of(plan)
            else:
                notes.append(f"the result stays at {model.substeps} substeps/frame: at the scene's {scene_substeps} "
                             f"it is unhealthy ({why})")
            say(notes[-1])

    final_params = apply_unconstrained(model, params, names, y_all)
    values = {n: np.asarray(get_param(final_params, p)) for n, p in paths.items()}
    deciding = [records[i] for i in sorted(set(last_stage_of.values()))]
    outside = outside_their_range(values)
    notes += outside
    for note in outside:
        say(note)
    converged = all(r["converged"] for r in deciding) and not outside
    if converged:
        message = f"converged ({total_iterations} iterations in {len(records)} stage{'s' if len(records) > 1 else ''})"
        if len(records) == 1:
            message = records[0]["message"]
    else:
        failed = [f"stage {records.index(r) + 1} ({r['label']}): {r['message']}" for r in deciding if not r["converged"]]
        failed += [note.split(":")[0] for note in outside]
        message = f"did not converge — {'; '.join(failed)}; returning the best parameters so far"
    stage_timing = [r["timing"] for r in records]
    timing = {
        "total_s": time.perf_counter() - start,
        "planning_s": planning_s,
        "solver_s": sum(t.get("start_s", 0.0) + t.get("steps_s", 0.0) + t.get("checks_s", 0.0) for t in stage_timing),
        "compile_s": sum(t.get("compile_s", 0.0) for t in stage_timing),
        "uncertainty_s": sum(t.get("uncertainty_s", 0.0) for t in stage_timing),
        "numerics_s": sum(t.get("numerics_s", 0.0) for t in stage_timing),
        "polish_s": sum(t.get("polish_s", 0.0) for t in stage_timing),
    }
    result = FitResult(
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
        method=c.method,
        stages=records,
        notes=notes,
        timing=timing,
        numerics=numerics,
    )
    if not converged and any(r.get("scan", {}).get("moved") for r in records):
        result = _also_from_the_guess(result, scene_model, params, observation, names, c, progress=progress, log=log)
    return result


#: The note of a viscosity fitted with APIC's transfers to data they did not make (docs/materials.md,
#: "In fits"; ``benchmarks/flip_fit.py``).
APIC_VISCOSITY_NOTE = (
    "a viscosity fitted with APIC transfers (flip = 0): if these data were not made by APIC on this grid (a real "
    "fluid, another grid or simulator), the transfers' numerical dissipation is fitted as viscosity and it comes out "
    "low (a 2D collapsing column at 10 cells across: 0.19 decades low at 5 Pa s, 0 found at 0.5 Pa s); the scene key "
    "flip = 0.99 cut that bias about 5x (docs/materials.md, 'In fits')"
)


def apic_viscosities(model: Model, paths: dict, observation: Observation) -> list[str]:
    """The fitted names (``paths``: name -> parameter path) that are a body's viscosity (a
    material parameter in Pa s) fitted with APIC transfers (``model.flip == 0``) to data that
    this model on this grid need not have made (:meth:`jaxmpm.observe.Observation.made_by`;
    :data:`APIC_VISCOSITY_NOTE`)."""
    if model.flip != 0.0 or observation.made_by(model):
        return []
    return [n for n, p in paths.items()
            if p[0] == "bodies" and getattr(model.bodies[p[1]].material.parameter(p[2]), "unit", None) == "Pa s"]


def outside_their_range(values: dict) -> list[str]:
    """One note per fitted value outside its parameter's valid range (or not finite), or fitted
    in a log space and not positive: a log10 parameter whose optimisation variable ran off
    until ``10^y`` underflowed to 0. The data did not hold it; a scene with it would not load,
    or (a viscosity or yield stress, whose valid range includes 0) its 0 is the underflow's,
    not the data's."""
    advice = ("the data did not hold it (its optimisation variable ran off): do not use this value, fix the "
              "parameter or fit it from data that constrain it")
    notes = []
    for name, value in values.items():
        d = declaration(name)
        v = np.ravel(np.asarray(value, float))
        shown = f"{float(v[0]):g}" if v.size == 1 else np.array2string(v, precision=4)
        unit = f" {d.unit}" if d and d.unit else ""
        if not np.all(np.isfinite(v)) or (d is not None and not all(float(x) in d.range for x in v)):
            valid = "finite" if d is None else d.range.text
            notes.append(f"{name} ended outside its valid range ({valid}): {shown}{unit}; {advice}")
        elif d is not None and d.transform.needs_positive() and not np.all(v > 0):
            notes.append(f"{name} ended at {shown}{unit}: fitted in log10, it reaches 0 only where 10^y underflows; "
                         f"{advice}")
    return notes


def _also_from_the_guess(scanned: FitResult, model: Model, params: Params, observation: Observation,
                         names: Sequence[str], config: FitConfig, *, progress, log) -> FitResult:
    """A fit whose scan moved its start and that then did not converge, fitted again from
    the guess without the scan; the result with the lower loss of the last stage is kept
    (both end on the same frames at the same dt, or the scanned one is kept). A scan looks
    at one parameter at a time and can start a stage in another basin than the guess's; a
    fit that does not converge there may have stopped in a worse one."""
    say = log or (lambda msg: None)
    say("the fit from the scanned start did not converge: fitting again from the guess without the scan")
    offset = scanned.iterations
    try:
        other = fit(model, params, observation, names, replace(config, scan=()), log=log,
                    progress=None if progress is None else (lambda i, value: progress(i + offset, value)))
    except FitError as err:  # the scanned start's result is not lost
        note = f"fitting again from the guess without the scan failed ({err}); the scanned start's result is kept"
        say(note)
        return replace(scanned, notes=scanned.notes + [note])
    a, b = scanned.stages[-1], other.stages[-1]
    comparable = a["frames"] == b["frames"] and a["substeps"] == b["substeps"] and a["loss"] and b["loss"]
    take_other = bool(comparable and b["loss"][1] < a["loss"][1])
    kept, dropped = (other, scanned) if take_other else (scanned, other)
    which = ("the guess without the scan" if take_other else "the scanned start")
    note = (f"fitted from the scanned start and from the guess without it: last-stage loss {a['loss'][1]:.4g} "
            f"and {b['loss'][1]:.4g}; kept {which}" if comparable else
            "fitted from the scanned start and from the guess without it; their last stages differ in frames or dt, "
            "so the scanned start's result is kept")
    say(note)
    return replace(
        kept,
        iterations=scanned.iterations + other.iterations,
        seconds=scanned.seconds + other.seconds,
        notes=kept.notes + [note],
        timing={**kept.timing, "total_s": scanned.timing["total_s"] + other.timing["total_s"],
                "other_start": {"start": "scan" if take_other else "guess", "total_s": dropped.timing["total_s"],
                                "iterations": dropped.iterations, "loss": dropped.stages[-1]["loss"],
                                "values": {n: _plain(v) for n, v in dropped.values.items()},
                                "converged": dropped.converged}},
    )


class StageResiduals(eqx.Module):
    """The residuals of one stage as a function of its variables ``y`` (a dict of
    optimisation-space values by name): the objective's
    :class:`~jaxmpm.identify.residuals.Residuals` at ``base`` with ``names`` set from ``y``.
    A pytree: stages that fit the same names over windows of one observation share one
    compiled residual-and-Jacobian program (:func:`jaxmpm.identify.solvers.residuals_and_jacobian`)."""

    program: Residuals
    base: Params
    names: tuple[str, ...] = eqx.field(static=True)

    def params(self, y: dict) -> Params:
        """``base`` with the stage's names set from ``y``."""
        return apply_unconstrained(self.program.model, self.base, list(self.names), y)

    def __call__(self, y: dict):
        return self.program(self.params(y)).astype(jnp.result_type(float))


def _solve(method: str, objective: Objective, residuals: StageResiduals, y0: dict, c: FitConfig, *, steps: int,
           seed: int, progress, offset: int, warm: bool = False) -> SolverOutcome:
    """One stage's solver run on ``objective`` over the variables ``y0`` (optimisation space);
    ``warm``: every variable starts from an earlier stage's result."""
    dtype = jnp.result_type(float)
    if method == "lm":
        return levenberg_marquardt(residuals, y0, max_steps=steps, rtol=c.rtol, atol=c.atol, progress=progress,
                                   offset=offset, warm=warm)
    if method == "bfgs":
        def loss(y):
            return objective.loss(residuals.params(y)).astype(dtype)

        return bfgs(loss, y0, max_steps=steps, rtol=c.rtol, atol=c.atol, progress=progress, offset=offset)

    def loss(y, key):
        return objective.loss(residuals.params(y), key).astype(dtype)

    return adam(loss, y0, max_steps=steps, learning_rates=c.learning_rates, lr_decay=c.lr_decay, xtol=c.xtol,
                patience=c.patience, grad=c.grad, seed=seed, progress=progress, offset=offset, names=list(y0))


def coordinate_search(loss: Callable[[dict], float], y0: dict, coordinates: Sequence[tuple[str, int | None]],
                      offsets: Sequence[float]):
    """A greedy look along coordinates: each coordinate ``(name, index)`` of ``y0`` (``index``
    None for a scalar variable, else a component of a vector one) in turn is moved to its
    value in ``y0`` plus every offset, the others held at the best point so far, and kept where
    ``loss`` is lowest (a NaN or infinite loss never wins).

    Returns:
        ``(y, record)``: the best point and ``{"points", "start_loss", "best_loss", "moved":
        {label: offset}}`` (labels ``name`` or ``name[index]``).
    """
    def value(y):
        v = float(loss(y))
        return v if np.isfinite(v) else np.inf

    best = dict(y0)
    start = best_loss = value(best)
    moved, points = {}, 1
    for name, index in coordinates:
        for d in offsets:
            if d == 0:
                continue
            moved_to = y0[name] + d if index is None else best[name].at[index].set(y0[name][index] + d)
            trial = {**best, name: moved_to}
            v = value(trial)
            points += 1
            if v < best_loss:
                best, best_loss = trial, v
                moved[name if index is None else f"{name}[{index}]"] = float(d)
    return best, {"points": points, "start_loss": start, "best_loss": best_loss, "moved": moved}


def scan_start(residuals: Callable[[dict], Any], y0: dict, names: Sequence[str], offsets: Sequence[float]):
    """A coarse, coordinate-wise look at the loss ``sum(residuals(y)**2)`` before a stage:
    each of ``names`` (scalar log10 variables of ``y0``) in turn is moved to
    ``y0[name] + offset`` for every offset, the others held at the best point so far, and
    kept where the loss is lowest (:func:`coordinate_search`).

    Unhealthy points (NaN loss) are skipped. Costs ``len(names) × len(offsets)`` evaluations
    of the stage's residual-and-Jacobian program (the one its solver uses: nothing new is
    compiled, :func:`jaxmpm.identify.solvers.loss_function`).

    Returns:
        ``(y, scanned)``: the best point (optimisation space) and a record ``{"points",
        "start_loss", "best_loss", "moved": {name: offset}}`` for fit.json and the notes.
    """
    loss_of = loss_function(residuals, y0)
    flat = lambda y: jax.flatten_util.ravel_pytree(y)[0]  # noqa: E731
    return coordinate_search(lambda y: loss_of(flat(y)), y0, [(n, None) for n in names], offsets)


@eqx.filter_jit
def _stage_loss(residuals: StageResiduals, y: dict):
    """``sum(residuals(y)**2)``, forward only: one compilation per stage structure."""
    return jnp.sum(residuals(y) ** 2)


def polish_velocity(residuals: StageResiduals, y: dict, names: Sequence[str], moves: Sequence[float]):
    """:func:`coordinate_search` over every component of the velocity variables ``names`` of
    ``y`` (m/s) by ``± moves`` (m/s), on the stage loss ``sum(residuals(y)**2)`` (a forward-only
    program of its own: an evaluation of the residual-and-Jacobian program would cost the
    stage's JVPs too). Returns ``(y, record)`` as :func:`coordinate_search`."""
    offsets = [sign * m for m in moves for sign in (-1.0, 1.0)]
    coordinates = [(n, i) for n in names for i in range(int(np.size(y[n])))]
    return coordinate_search(lambda p: _stage_loss(residuals, p), y, coordinates, offsets)


def free_fall_velocity(model, params: Params, observation: Observation) -> np.ndarray | None:
    """The initial velocity ``(D,)`` (m/s, at t = 0) of a single body that the observed free
    fall gives, or None (not one body, neither untracked points nor 3D masks, fewer than two
    free-fall frames).

    From points without per-particle ids (``observation.positions``): the mean of the points
    seen in the first two observed frames, over the first observed interval (the one the
    first velocity stage fits), with the simulator's free flight undone exactly (symplectic
    Euler at the model's substep ``h``: over a time ``T`` the centre moves ``v T + g T (T +
    h) / 2``). From 3D silhouettes: :func:`jaxmpm.reconstruct.free_fall.free_fall` (the
    body's triangulated centre over its leading rigid frames, ``v0`` from a parabola or, from
    two frames, corrected by the scene's gravity).
    """
    if len(model.bodies) != 1:
        return None
    times = np.asarray(observation.times, float)
    gravity = np.asarray(params["gravity"], float)
    if observation.positions is not None and not observation.tracks_particles and len(times) >= 2:
        x = np.asarray(observation.positions[:2], float)
        seen = np.all(np.isfinite(x), axis=(0, 2))
        if not seen.any():
            return None
        span, h = times[1] - times[0], model.frame_dt / model.substeps
        v = (x[1, seen].mean(axis=0) - x[0, seen].mean(axis=0)) / span - gravity * (span + h) / 2
        return v - gravity * times[0]
    if observation.masks is None or model.dim != 3:
        return None
    from .reconstruct.free_fall import free_fall

    cameras = observation_cameras(observation)
    fall = free_fall(observation.masks, cameras, times, model.grid.dx, gravity=gravity)
    if fall.velocity is None or not np.all(np.isfinite(fall.velocity)):
        return None
    return np.asarray(fall.velocity, float) - gravity * times[0]  # the velocity of the first frame, back to t = 0


def better_start(residuals: Callable[[dict], Any], y0: dict, candidate: dict) -> tuple[dict, dict]:
    """``y0`` with ``candidate``'s entries when that lowers the loss ``sum(residuals(y)**2)``
    (two evaluations of the stage's residual-and-Jacobian program; nothing is compiled for
    it). Returns the point and a record ``{"start_loss", "candidate_loss", "taken",
    "candidate"}`` for fit.json and the notes."""
    loss_of = loss_function(residuals, y0)
    flatten = lambda y: jax.flatten_util.ravel_pytree(y)[0]  # noqa: E731
    trial = {**y0, **candidate}
    start, there = (float(loss_of(flatten(y))) for y in (y0, trial))
    taken = bool(np.isfinite(there) and not there >= start)
    record = {"start_loss": start, "candidate_loss": there, "taken": taken,
              "candidate": np.asarray(next(iter(candidate.values())))}
    return (trial if taken else dict(y0)), record


def _stage_std(objective: Objective, residuals: StageResiduals, y: dict, jacobian=None,
               resolution: bool = False) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[str]]:
    """Standard deviations (physical units) of the variables ``y`` of one stage: the
    Gauss–Newton ones, with ``resolution`` raised to the scale the loss resolves where it is
    rough (:func:`jaxmpm.identify.uncertainty.resolved_std`). ``jacobian``: the solver's ``(rj,
    (r, J) at y or None)`` when it has them (no recompilation).

    Returns the standard deviations, the statistical ones (both by name) and the names the loss
    did not resolve up to a move of ``1 + |y|`` (whose std is that cap)."""
    rj, at_y = jacobian if jacobian is not None else (None, None)
    flat, unravel = jax.flatten_util.ravel_pytree(y)
    if rj is None:
        rj = residuals_and_jacobian(residuals, y)[0]
    r, J = at_y if at_y is not None else (np.asarray(a, np.float64) for a in rj(flat))
    cov = gauss_newton_covariance(J, r, count=objective.count)
    statistical = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    as_dict = lambda v: unravel(jnp.asarray(v, flat.dtype))  # noqa: E731
    gauss_newton = physical_std(list(y), y, as_dict(statistical))
    if not resolution:
        return gauss_newton, gauss_newton, []

    def loss_of(point):
        return float(np.sum(np.asarray(rj(jnp.asarray(point, flat.dtype))[0], np.float64) ** 2))

    std, resolved = resolved_std(loss_of, np.asarray(flat, np.float64), r, J, statistical, dtype=flat.dtype)
    unresolved = [n for n, ok in as_dict(resolved.astype(float)).items() if not np.all(np.asarray(ok) > 0.5)]
    return physical_std(list(y), y, as_dict(std)), gauss_newton, unresolved


def numerics_check(residuals: StageResiduals, objective_for: Callable[[Model], Objective], y: dict, *,
                   rtol: float, atol: float, say: Callable[[str], None] = lambda line: None) -> dict:
    """How the fitted variables ``y`` of one stage depend on the numerics
    (:func:`jaxmpm.numerics.parameter_moves`): the stage refitted from ``y`` with dt halved and
    with the other transfer, each by at most :data:`~jaxmpm.numerics.NUMERICS_REFIT_STEPS`
    Levenberg–Marquardt iterations of the fit's solver (tolerances ``rtol`` and ``atol``).

    Arguments:
        residuals: the stage's residuals (its model is the one fitted).
        objective_for: ``objective_for(model)``, the stage's objective for a model with other
            numerics (same observation, frames and options).
        y: the fitted variables (optimisation space) by name.
        say: gets one line per refit (its iterations and losses).

    Returns:
        :func:`~jaxmpm.numerics.parameter_moves`' ``{"dt": check, "transfer": check}``.
    """
    model = residuals.program.model

    def refit(numerics: Numerics) -> Refit | None:
        other = StageResiduals(objective_for(numerics.apply(model)).program, residuals.base, residuals.names)
        run = levenberg_marquardt(other, y, max_steps=NUMERICS_REFIT_STEPS, rtol=rtol, atol=atol, warm=True)
        if run.unhealthy_start:
            say(f"  refit {numerics.describe(model.flip)}: unhealthy at the fitted point")
            return None
        say(f"  refit {numerics.describe(model.flip)}: {run.iterations} iterations, loss {float(run.losses[0]):.4e} -> "
            f"{float(min(run.losses)):.4e}{'' if run.converged else ' (not converged)'}")
        return Refit(y=run.y, losses=(float(run.losses[0]), float(min(run.losses))), iterations=run.iterations,
                     converged=bool(run.converged))

    return parameter_moves(refit, y, from_unconstrained, substeps=model.substeps, flip=model.flip)


def fit_scene(scene, observation: Observation, names: Sequence[str] | None = None, config: FitConfig = FitConfig(),
              **callbacks) -> FitResult:
    """:func:`fit` for a loaded :class:`~jaxmpm.scene.Scene` (its params are the initial guess).

    Checks first that the observation's embedded scene (if any) matches this one
    (:func:`jaxmpm.observe.check_scene_compatible`); ``names`` default to the material's
    parameters; ``callbacks`` are :func:`fit`'s ``progress`` and ``log``.
    """
    check_scene_compatible(scene.spec, observation.scene_spec)
    return fit(scene.model, scene.params, observation, names, config, **callbacks)
