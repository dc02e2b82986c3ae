"""Discrepancy discovery: show what the model gets wrong, name the cause, extend it, measure the gain.

The workflow (:func:`discover`; ``jaxmpm discover SCENE OBS.npz --out DIR``):

1. **Fit the base model** (its material parameters, or the names given) on the *training*
   part of the data; the rest is held out (default: the last 30 % of the observed times —
   a forecast; or whole sequences, or camera views).
2. **Show**: decompose the base model's residual by time phase (free flight, impact,
   post-contact, settling), region (each collider's contact band, free surface, interior),
   direction (normal / tangential to the collider, vertical / horizontal) and growth law in
   time (log-log slope of the centre-of-mass error), and rerun the fit at ``dt / 2`` and
   with the other transfer (APIC / the FLIP blend) to separate discretisation error from
   missing physics (:mod:`jaxmpm.discover_report`).
3. **Name**: screen every extension of :mod:`jaxmpm.extensions` at its null value with a
   score test from forward-mode Jacobians (the Gauss–Newton prediction of how much of the
   training error the extension would remove, base parameters re-adjusted, bounds
   respected), refit the best few, and keep an extension only when it passes **all** of:
   held-out gain ``>= min_gain``, a likelihood-ratio test on per-frame errors at level
   ``alpha`` (one-sided for parameters whose null is a bound), and a held-out improvement
   larger than the numerical error measured by the ``dt / 2`` check. The verdict cautions
   against a kept extension whose improvement is within the transfer check's change: it may
   stand in for the transfers' numerical dissipation.
4. **Extend and measure**: the chosen extension's parameters with standard deviations
   (frame-clustered sandwich covariance), base and extended held-out errors and the gain;
   greedily add further extensions while the gain stays significant.

**The statistic.** Residuals of particles (or pixels) observed at the same time share the
same dynamics error, so they are not independent samples. Every residual entry belongs to a
*group* — one observed frame (tracks, silhouettes) or one frame-length time bin (probes) —
and is scaled so that the sum of squares over a group is that group's mean squared error.
Errors are RMS over groups (``sqrt(mean_g MSE_g)``), likelihood-ratio tests use the number
of training groups ``n`` as the sample size: ``Λ = n ln(RSS_0 / RSS_1)`` against χ² with
the number of added parameters as degrees of freedom, or the boundary mixture
``½χ²_0 + ½χ²_1`` (Self & Liang 1987; 5 % critical value 2.71) for one parameter whose null
is a bound. Temporal correlation between frames is not modelled by the test; it is why the
held-out (forecast) gain is the primary criterion.
"""

from __future__ import annotations

import math
import time as _time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence as _Seq

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import extensions as X
from .errors import JaxmpmError, ObservationError
from .identify.parameters import from_unconstrained, get_param, resolve_name, set_param, to_unconstrained, transform_of
from .identify.residuals import Frames, image_terms, make_fit_renderer, probe_term, track_term
from .identify.solvers import levenberg_marquardt
from .identify.uncertainty import gauss_newton_covariance, physical_std
from .model import Model, Params
from .numerics import (CHECK_FLIP, NUMERICS_REFIT_STEPS, Numerics, Refit, format_std, move_table, numerics_notes,
                       other_flip, parameter_moves, transfer_name, transfer_runs)
from .observe import Observation
from .step import health_message, simulate, unhealthy

__all__ = [
    "Sequence",
    "Candidate",
    "Discovery",
    "discover",
    "default_parameters",
    "DEFAULT_EXTENSIONS",
    "Numerics",
    "transfer_caution",
    "within_transfer_change",
]

def _F():  # noqa: N802 - JAX's default float (float64 only when x64 is enabled)
    return jnp.result_type(float)


#: All extension ids, in the order they are screened.
DEFAULT_EXTENSIONS = tuple(X.EXTENSIONS)

#: 5 % critical values: chi2 with 1..6 dof, and the boundary mixture (1/2 chi2_0 + 1/2 chi2_1).
_BOUNDARY_CRIT = 2.705543


def _chi2_sf(x: float, dof: int) -> float:
    from scipy.stats import chi2

    return float(chi2.sf(max(x, 0.0), max(dof, 1)))


def p_value(statistic: float, dof: int, boundary: bool) -> float:
    """p-value of a likelihood-ratio / score statistic: χ²_dof, or the boundary mixture
    ``½χ²_0 + ½χ²_1`` when one parameter's null value is a bound of its domain."""
    if boundary and dof == 1:
        return 0.5 * _chi2_sf(statistic, 1) if statistic > 0 else 1.0
    return _chi2_sf(statistic, dof)


# =========================================================================== inputs


@dataclass
class Sequence:
    """One observed sequence: the base model, its parameters and the data.

    Attributes:
        model: the static model.
        params: the base parameter pytree (the initial guess of the fitted parameters).
        observation: the data (tracks, masks and/or probes).
        name: used in reports and for ``holdout_sequences``.
        probes: extra probe functions ``{name: fn(state, model)}`` for probe data.
        renderer: a renderer for mask data (default: a volume renderer over the domain;
            2D scenes are lifted to a thin slab at z = 0).
    """

    model: Model
    params: Params
    observation: Observation
    name: str = "sequence"
    probes: dict | None = None
    renderer: Any = None


def default_parameters(model: Model) -> list[str]:
    """The base parameters fitted by default: each body's required material parameters
    (PAC-NeRF's), except the bulk modulus ``kappa`` of fluids (a numerical compressibility)."""
    names = []
    several = len(model.bodies) > 1
    for body in model.bodies:
        for p in type(body.material).required():
            if p == "kappa":
                continue
            names.append(f"{body.name}.{p}" if several else p)
    return list(dict.fromkeys(names))


# =========================================================================== compiled pieces
# Module-level and keyed on the model's *structure* (equinox filter_jit), so every sequence,
# candidate and refit with the same scene layout shares one compilation.

#: The most tangents one forward-mode rollout carries (they share its primal); a Jacobian of
#: more columns is split into chunks of equal size.
JVP_BATCH = 8


@eqx.filter_jit
def _rollout(model, params, frames):
    traj = simulate(model, params, checkpoint=None, frames=frames)
    return Frames.of(traj), ~jnp.any(unhealthy(traj))


@eqx.filter_jit
def _rollout_jvp(model, params, tangent, frames):
    def f(p):
        return Frames.of(simulate(model, p, checkpoint=None, frames=frames))

    return jax.jvp(f, (params,), (tangent,))


@eqx.filter_jit
def _rollout_jvps(model, params, tangents, frames):
    """The rollout and its derivatives along ``tangents`` (params pytrees with a leading axis
    ``(k, ...)``): one primal shared by the ``k`` tangent rollouts."""
    return jax.vmap(lambda t: _rollout_jvp(model, params, t, frames), out_axes=(None, 0))(tangents)


@eqx.filter_jit
def _obs_eval(term, frames, t0):
    return term.residuals(frames, t0)


@eqx.filter_jit
def _obs_jvps(term, frames, t0, d_frames, dt0):
    """The residuals' derivatives along the ``k`` tangents ``d_frames, dt0`` (leading axis)."""
    return jax.vmap(lambda d, d0: jax.jvp(term.residuals, (frames, t0), (d, d0))[1])(d_frames, dt0)


@dataclass
class _Groups:
    """Per residual entry its group; per group its time, kind, view and sequence."""

    entry_group: np.ndarray
    time: np.ndarray
    kind: list
    label: list
    sequence: np.ndarray


def silhouette_renderer(model, **options):
    """The renderer of silhouette data: :func:`jaxmpm.identify.residuals.make_fit_renderer`'s
    volume renderer with level-set silhouettes softer than its default (``sharpness = 10``):
    compared with binary masks this leaves a small error floor at the true parameters but
    widens the basin in which the Gauss–Newton screen and the refits see a body that is
    displaced by several pixels."""
    options.setdefault("sharpness", 10.0)
    return make_fit_renderer("volume", model, **options)


# =========================================================================== the problem


@dataclass
class _Entry:
    """One block of the flat parameter vector."""

    name: str
    kind: str  # "base" | "ext"
    size: int
    shape: tuple
    lower: np.ndarray
    upper: np.ndarray
    spec: X.ParamSpec | None = None

    @property
    def extension(self) -> str | None:
        return None if self.spec is None else self.spec.extension


class _SeqData:
    def __init__(self, seq: Sequence, candidates, dtype, num_pixels, frames_margin):
        self.seq = seq
        self.model = seq.model
        base = X.strip(seq.params)
        self.candidates = [e for e in candidates if X.applicable(seq.model, e) is None]
        self.params = X.enable(seq.model, base, self.candidates)
        self.specs = [s for e in self.candidates for s in X.parameter_specs(seq.model, base, e)]
        obs = seq.observation
        model = seq.model
        every = np.ones(len(obs.times), bool)
        parts = []  # (term, layout)
        t_all = [np.asarray(obs.times, float)]
        if obs.positions is not None:
            parts.append(track_term(model, obs, every, dtype, normalise="group"))
        if obs.masks is not None:
            H, W = np.shape(obs.masks)[2:4]
            renderer = seq.renderer if seq.renderer is not None else silhouette_renderer(model)
            parts += image_terms(model, obs, every, dtype, weights={"silhouette": 1.0}, renderer=renderer,
                                 num_pixels=num_pixels, margin=max(2, int(0.08 * max(H, W))), normalise="group")
        if obs.probe_names is not None:
            parts.append(probe_term(model, obs, None, dtype, extra=seq.probes, normalise="group"))
            pt = np.asarray(obs.probe_times, float)
            t_all.append(pt[np.isfinite(pt)])
        if not parts:
            raise ObservationError(f"sequence {seq.name!r}: no tracks, masks or probes to compare with")
        self.observables = [term for term, _ in parts]
        tmax = max(float(np.max(t)) for t in t_all if len(t))
        self.frames = max(3, int(math.ceil(tmax / model.frame_dt - 1e-6)) + 1 + frames_margin)
        # groups, numbered locally then offset by the problem
        eg, gt, gk, gl = [], [], [], []
        for _, layout in parts:
            off = len(gt)
            eg.append(np.where(layout.groups >= 0, layout.groups + off, -1))
            gt += list(layout.group_times)
            gk += list(layout.group_kinds)
            gl += list(layout.group_labels)
        self.entry_group = np.concatenate(eg)
        self.group_time = np.asarray(gt, float)
        self.group_kind = gk
        self.group_label = gl


@dataclass
class _Costs:
    """What a :class:`_Problem` has spent so far: forward rollouts (``rollouts``, their wall
    seconds ``rollout_s``), forward-mode Jacobian rollouts (``jvp_rollouts``, each one primal
    shared by several tangents; ``tangents`` counts the tangents carried, padding included;
    ``jvp_s``), Levenberg–Marquardt runs, their iterations and rejected trial steps; and per
    compiled program (``calls``: key -> the seconds of each call, the phase of its first call)
    what the compilation estimate needs."""

    rollouts: int = 0
    rollout_s: float = 0.0
    jvp_rollouts: int = 0
    tangents: int = 0
    jvp_s: float = 0.0
    fits: int = 0
    iterations: int = 0
    rejected_steps: int = 0
    calls: dict = field(default_factory=dict)
    phase: int = 0  # the phase being recorded (set by the workflow)

    COUNTERS = ("rollouts", "rollout_s", "jvp_rollouts", "tangents", "jvp_s", "fits", "iterations", "rejected_steps")

    def call(self, key, seconds: float) -> None:
        self.calls.setdefault(key, (self.phase, []))[1].append(seconds)

    def counters(self) -> dict:
        return {k: getattr(self, k) for k in self.COUNTERS}

    def compile_s(self) -> dict[int, float]:
        """Estimated compilation per phase: for every program called more than once, its first
        call's excess over the median of the others, in the phase of that first call
        (a program called once, e.g. the dt/2 rollout, has no estimate: its whole first call
        counts as a rollout)."""
        out: dict[int, float] = {}
        for phase, seconds in self.calls.values():
            if len(seconds) > 1:
                out[phase] = out.get(phase, 0.0) + max(seconds[0] - float(np.median(seconds[1:])), 0.0)
        return out


class _Problem:
    """The flat parameter vector over all sequences, residuals and forward-mode Jacobians
    (what they cost is counted in ``costs``)."""

    def __init__(self, sequences, names, candidates, num_pixels, dtype):
        self.dtype = dtype
        margin = 2 if "time_offset" in candidates else 0
        self.seqs = [_SeqData(s, candidates, dtype, num_pixels, margin) for s in sequences]
        self.candidates = [e for e in candidates if any(e in sd.candidates for sd in self.seqs)]
        # groups
        eg, gt, gk, gl, gs = [], [], [], [], []
        for i, sd in enumerate(self.seqs):
            off = len(gt)
            eg.append(np.where(sd.entry_group >= 0, sd.entry_group + off, -1))
            gt += list(sd.group_time)
            gk += sd.group_kind
            gl += sd.group_label
            gs += [i] * len(sd.group_time)
        self.groups = _Groups(np.concatenate(eg), np.asarray(gt), gk, gl, np.asarray(gs))
        self.num_groups = len(gt)
        # parameter layout
        self.entries: list[_Entry] = []
        self.paths = []  # per base entry: per sequence its path (or None)
        for n in names:
            paths = []
            shape = None
            for sd in self.seqs:
                try:
                    path = resolve_name(sd.model, sd.params, n)
                except JaxmpmError:
                    path = None
                paths.append(path)
                if path is not None and shape is None:
                    shape = tuple(np.shape(get_param(sd.params, path)))
            if shape is None:
                raise JaxmpmError(f"parameter {n!r} names nothing in any sequence")
            size = int(np.prod(shape)) if shape else 1
            lo, hi = transform_of(n).bounds()  # e.g. the tanh-bounded nu: out of saturation
            self.entries.append(_Entry(n, "base", size, shape, np.full(size, lo), np.full(size, hi)))
            self.paths.append(paths)
        seen = {}
        for sd in self.seqs:
            for s in sd.specs:
                if s.name not in seen:
                    seen[s.name] = s
                else:  # the same name in several sequences: the tighter bounds
                    t = seen[s.name]
                    lo = max(x for x in (t.lower, s.lower) if x is not None) if (t.lower is not None or s.lower is not None) else None
                    hi = min(x for x in (t.upper, s.upper) if x is not None) if (t.upper is not None or s.upper is not None) else None
                    seen[s.name] = X.ParamSpec(t.extension, t.key, t.shape, lo, hi, t.unit, t.scale)
        for e in self.candidates:
            for s in seen.values():
                if s.extension != e:
                    continue
                lo = np.full(s.size, -np.inf if s.lower is None else s.lower)
                hi = np.full(s.size, np.inf if s.upper is None else s.upper)
                self.entries.append(_Entry(s.name, "ext", s.size, s.shape, lo, hi, s))
        self.slices = {}
        i = 0
        for en in self.entries:
            self.slices[en.name] = slice(i, i + en.size)
            i += en.size
        self.size = i
        self.column_extension = [en.extension for en in self.entries for _ in range(en.size)]  # None: base
        self.lower = np.concatenate([en.lower for en in self.entries])
        self.upper = np.concatenate([en.upper for en in self.entries])
        self.costs = _Costs()
        self._remembered: list = []  # (key, residuals), the latest first

    # ---- vectors

    def initial(self) -> np.ndarray:
        th = np.zeros(self.size)
        for en, paths in zip(self.entries, self.paths):
            sd, path = next((sd, p) for sd, p in zip(self.seqs, paths) if p is not None)
            v = np.asarray(to_unconstrained(en.name, jnp.asarray(get_param(sd.params, path), _F())))
            th[self.slices[en.name]] = np.ravel(v)
        return th

    def columns(self, names) -> np.ndarray:
        return np.concatenate([np.arange(self.slices[n].start, self.slices[n].stop) for n in names]) if names else np.zeros(0, int)

    def base_names(self) -> list[str]:
        return [en.name for en in self.entries if en.kind == "base"]

    def ext_names(self, extension: str) -> list[str]:
        return [en.name for en in self.entries if en.kind == "ext" and en.extension == extension]

    def entry(self, name) -> _Entry:
        return next(en for en in self.entries if en.name == name)

    def active(self, theta, keep=()) -> frozenset[str]:
        """The extensions a rollout at ``theta`` carries: those named in ``keep`` (whose
        columns are wanted) and those with an offset away from its null value. The others are
        left out: at null an extension is the base model (see :mod:`jaxmpm.extensions`), yet
        its hooks still cost the step (all ten candidates of the 3D drag case together made a
        rollout 2.4x slower)."""
        theta = np.asarray(theta)
        moved = {en.extension for en in self.entries if en.kind == "ext" and np.any(theta[self.slices[en.name]] != 0)}
        return frozenset(moved | set(keep))

    def unpack(self, theta, i: int, active) -> Params:
        """The parameter pytree of sequence ``i`` at ``theta`` (traceable) with the extensions
        in ``active`` (:meth:`active`, decided from a concrete ``theta``)."""
        sd = self.seqs[i]
        p = sd.params
        for en, paths in zip(self.entries, self.paths):
            path = paths[i]
            if path is None:
                continue
            leaf = get_param(p, path)
            val = from_unconstrained(en.name, theta[self.slices[en.name]])
            p = set_param(p, path, jnp.reshape(val, jnp.shape(leaf)).astype(jnp.asarray(leaf).dtype))
        ext = {k: dict(v) for k, v in p["extensions"].items() if k in active}
        dtype = jnp.asarray(p["gravity"]).dtype
        for s in sd.specs:
            if s.extension in active:
                ext[s.extension][s.key] = jnp.reshape(theta[self.slices[s.name]], s.shape).astype(dtype)
        p = dict(p)
        p["extensions"] = ext
        return p

    def physical(self, name, y):
        """Optimisation variable -> physical value (extension offsets are linear)."""
        return from_unconstrained(name, y) if self.entry(name).kind == "base" else y

    def values(self, theta) -> dict[str, np.ndarray]:
        """Physical values of every entry."""
        out = {}
        for en in self.entries:
            v = np.asarray(self.physical(en.name, jnp.asarray(theta[self.slices[en.name]], _F())))
            out[en.name] = v.reshape(en.shape) if en.shape else v.reshape(())
        return out

    # ---- evaluation

    def _t0(self, params):
        t0 = X.time_offset(params)
        return jnp.zeros((), self.dtype) if t0 is None else jnp.asarray(t0).astype(self.dtype)

    #: sequences that need no rollout in fits (all their groups held out); set by the workflow
    skip: frozenset = frozenset()

    def trajectories(self, theta, numerics: Numerics = Numerics(), skip=frozenset()):
        out = []
        for i, sd in enumerate(self.seqs):
            if i in skip:
                out.append(None)
                continue
            clock = _time.perf_counter()
            active = self.active(theta)
            p = self.unpack(jnp.asarray(theta), i, active)
            model = numerics.apply(sd.model)
            frames, ok = _rollout(model, p, sd.frames)
            out.append((frames, bool(ok), p))  # (bool waits for the rollout)
            seconds = _time.perf_counter() - clock
            self.costs.rollouts += 1
            self.costs.rollout_s += seconds
            self.costs.call(("rollout", i, numerics, active), seconds)
        return out

    def health(self, theta, numerics: Numerics = Numerics()) -> str | None:
        """Why the first unhealthy sequence's rollout at ``theta`` (with ``numerics``) is
        unhealthy (:func:`jaxmpm.step.health_message`: the frame, the reason and a dt), or None."""
        active = self.active(theta)
        for i, sd in enumerate(self.seqs):
            p = self.unpack(jnp.asarray(theta, _F()), i, active)
            model = numerics.apply(sd.model)
            why = health_message(model, simulate(model, p, checkpoint=None, frames=sd.frames))
            if why is not None:
                return f"sequence {sd.seq.name!r}: {why}" if len(self.seqs) > 1 else why
        return None

    #: how many recent residual evaluations are remembered (the workflow asks again for points
    #: its solver has just evaluated: a fit's estimate, a refit's start)
    REMEMBERED = 4

    def residuals(self, theta, numerics: Numerics = Numerics(), trajectories=None, training_only: bool = False) -> np.ndarray:
        """All residuals at ``theta``; with ``training_only``, sequences whose data are all held
        out are not simulated (their entries are 0). The last :data:`REMEMBERED` evaluations
        are returned again without a rollout."""
        skip = self.skip if training_only else frozenset()
        key = None
        if trajectories is None:
            key = (np.asarray(theta, np.float64).tobytes(), numerics, skip)
            known = next((r for k, r in self._remembered if k == key), None)
            if known is not None:
                return known.copy()
        trajs = trajectories or self.trajectories(theta, numerics, skip)
        rs = []
        for sd, tr in zip(self.seqs, trajs):
            if tr is None:
                rs.append(np.zeros(sum(sd.sizes)))
                continue
            frames, ok, p = tr
            t0 = self._t0(p)
            parts = [np.asarray(_obs_eval(o, frames, t0), float) for o in sd.observables]
            sd.sizes = [len(q) for q in parts]
            r = np.concatenate(parts)
            if not ok:
                r = np.full_like(r, np.nan)
            rs.append(r)
        r = np.where(self.groups.entry_group >= 0, np.concatenate(rs), 0.0)
        if key is not None:
            self._remembered = [(key, r.copy()), *self._remembered][:self.REMEMBERED]
        return r

    def jacobian(self, theta, cols, numerics: Numerics = Numerics()) -> np.ndarray:
        """Columns ``cols`` of the residual Jacobian ``(M, len(cols))`` (with the models'
        numerics changed by ``numerics``): per sequence, the
        columns its parameters depend on, in order of the parameter vector (so grouped by
        extension), up to :data:`JVP_BATCH` tangents to a rollout sharing one primal (chunks
        of one size, the last padded with zero tangents). Each chunk's rollout carries only
        the extensions :meth:`active` names for its columns."""
        theta_np = np.asarray(theta)
        theta = jnp.asarray(theta, _F())
        M = len(self.groups.entry_group)
        J = np.zeros((M, len(cols)))
        start = 0
        for i, sd in enumerate(self.seqs):
            rows = slice(start, start + sum(sd.sizes))
            start = rows.stop
            if i in self.skip:  # held out entirely: no training rows
                continue

            def keep(c):
                return {self.column_extension[c]} - {None}

            # each column's tangent once, with every requested column's extension on; a chunk
            # then keeps only its own extensions' entries (the others carry zeros)
            every = self.active(theta_np, set().union(*(keep(c) for c in cols)))
            tangents = {}
            for j in sorted(range(len(cols)), key=lambda j: cols[j]):
                e = jnp.zeros_like(theta).at[cols[j]].set(1.0)
                p, tp = jax.jvp(lambda th, i=i: self.unpack(th, i, every), (theta,), (e,))
                tp = jax.tree_util.tree_map(lambda a, b: jnp.asarray(b).astype(jnp.asarray(a).dtype), p, tp)
                if any(bool(jnp.any(leaf != 0)) for leaf in jax.tree_util.tree_leaves(tp)):
                    tangents[j] = tp
            live = list(tangents)
            if not live:
                continue
            chunks = -(-len(live) // JVP_BATCH)
            size = -(-len(live) // chunks)
            for k in range(0, len(live), size):
                chunk = live[k:k + size]
                active = self.active(theta_np, set().union(*(keep(cols[j]) for j in chunk)))
                p = self.unpack(theta, i, active)
                batch = [dict(tangents[j], extensions={x: v for x, v in tangents[j]["extensions"].items() if x in active})
                         for j in chunk]
                batch = batch + [jax.tree_util.tree_map(jnp.zeros_like, batch[0])] * (size - len(batch))  # padding
                stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *batch)
                clock = _time.perf_counter()
                frames, d_frames = _rollout_jvps(numerics.apply(sd.model), p, stacked, sd.frames)
                dt0 = jax.vmap(self._t0)(stacked)
                t0 = self._t0(p)
                dr = np.concatenate([np.asarray(_obs_jvps(o, frames, t0, d_frames, dt0), float)
                                     for o in sd.observables], axis=1)
                seconds = _time.perf_counter() - clock
                self.costs.jvp_rollouts += 1
                self.costs.tangents += size
                self.costs.jvp_s += seconds
                self.costs.call(("jvp", i, size, numerics, active), seconds)
                J[rows, chunk] = dr[:len(chunk)].T
        J[self.groups.entry_group < 0] = 0.0
        return J

    # ---- errors

    def group_mse(self, r) -> np.ndarray:
        g = self.groups.entry_group
        ok = g >= 0
        return np.bincount(g[ok], weights=r[ok] ** 2, minlength=self.num_groups)

    def error(self, r, mask) -> float:
        """RMS over the groups in ``mask`` of the per-group RMS error."""
        mse = self.group_mse(r)
        return float(np.sqrt(np.mean(mse[mask]))) if np.any(mask) else float("nan")


# =========================================================================== least squares


@dataclass
class _Fit:
    """A least-squares fit: the full parameter vector ``theta (P,)``, all residuals there
    ``r (M,)`` (held-out entries included), the training loss, trial points spent, the free
    parameters' names, the training loss after each accepted step, the covariance, and the
    solver's Jacobian at ``theta`` when it has it (``(M, len(free))``, training rows; the
    covariance reuses it instead of spending ``len(free)`` JVP rollouts again), and whether the
    solver converged (rather than stopping on its iteration budget)."""

    theta: np.ndarray
    r: np.ndarray
    loss: float
    iterations: int
    free: list
    history: list
    cov: np.ndarray | None = None
    jacobian: np.ndarray | None = None
    converged: bool = False


#: Tolerances of the Levenberg–Marquardt's Cauchy test (those of :class:`jaxmpm.FitConfig`), and
#: the smallest relative decrease of the training loss an accepted step must make not to stop it.
_RTOL, _ATOL, _FTOL = 1e-5, 1e-8, 1e-5
#: The change of a likelihood-ratio or score statistic (``n ln(RSS_0 / RSS_1)``, χ² critical
#: values 2.7–3.8) that a fit need not resolve: an accepted step lowering the training loss by
#: a fraction δ changes them by about ``n δ``, so a fit stops once ``n δ`` falls below this
#: (unless :data:`_FTOL` is the larger). Measured (docs/benchmarks.md, target 4): base fits of
#: the discover_time cases spent 19 of 22 iterations lowering the loss by < 1e-4 (relative)
#: each, and iterations 5–21 (150 of 165 s) lowering it by 2e-4 in all (``n δ`` 8e-3 with
#: 42 training frames).
STATISTIC_RESOLUTION = 0.01


class _Phases:
    """The workflow's phases, each with its wall time and what the problem spent in it (the
    ``timing`` block of :class:`Discovery`; see :meth:`timing`)."""

    def __init__(self, costs: _Costs):
        self.costs, self.rows = costs, []

    @contextmanager
    def __call__(self, name: str, since: float | None = None):
        """Record phase ``name`` (its clock started at ``since`` if given)."""
        self.costs.phase = len(self.rows)
        row = {"phase": name}
        self.rows.append(row)
        before, clock = self.costs.counters(), _time.perf_counter() if since is None else since
        try:
            yield
        finally:
            row["wall_s"] = _time.perf_counter() - clock
            row.update({k: v - before[k] for k, v in self.costs.counters().items()})

    def timing(self, total_s: float) -> dict:
        """``{"total_s", "phases": [...], "totals": {...}}``: per phase its ``wall_s``, the
        counters of :class:`_Costs` spent in it, ``compile_s`` (estimated: the first calls'
        excess over later calls of the same program) and ``host_s`` (wall time outside the
        rollouts: the solver's linear algebra, statistics, unpacking parameters)."""
        compile_s = self.costs.compile_s()
        phases = []
        for k, row in enumerate(self.rows):
            row = dict(row, compile_s=compile_s.get(k, 0.0))
            row["host_s"] = max(row["wall_s"] - row["rollout_s"] - row["jvp_s"], 0.0)
            phases.append(row)
        totals = {k: sum(r[k] for r in phases) for k in (*_Costs.COUNTERS, "compile_s", "host_s")}
        return {"total_s": total_s, "phases": phases, "totals": totals}


def _train_groups(problem: _Problem, train_entries) -> int:
    """How many groups (frames) have training entries: the statistics' sample size ``n``."""
    g = problem.groups.entry_group
    return max(int(np.unique(g[(g >= 0) & np.asarray(train_entries, bool)]).size), 1)


def _lm(problem: _Problem, theta0, free_names, train_entries, *, max_iter=25, progress=None,
        numerics: Numerics = Numerics()) -> _Fit:
    """The identification core's Levenberg–Marquardt, within the parameters' bounds, on the
    training residuals (held-out entries weigh 0; sequences held out entirely are not
    simulated) of the models with ``numerics``; all residuals are then evaluated once at the
    estimate. An accepted step that lowers the loss by less than ``max(_FTOL,
    STATISTIC_RESOLUTION / n)`` (relative; ``n`` training groups) ends it.

    Raises:
        JaxmpmError: the loss is not finite at ``theta0`` (an unstable simulation).
    """
    cols = problem.columns(free_names)
    w = np.asarray(train_entries, float)
    theta = np.array(theta0, float)
    theta[cols] = np.clip(theta[cols], problem.lower[cols], problem.upper[cols])

    def full(sub):
        th = theta.copy()
        th[cols] = sub
        return th

    iterations, history, jac, converged = 0, [], None, True
    if len(cols):
        out = levenberg_marquardt(
            lambda sub: w * problem.residuals(full(sub), numerics, training_only=True), theta[cols],
            jacobian=lambda sub: w[:, None] * problem.jacobian(full(sub), cols, numerics),
            lower=problem.lower[cols], upper=problem.upper[cols], scaled=True,
            ftol=max(_FTOL, STATISTIC_RESOLUTION / _train_groups(problem, train_entries)),
            max_steps=max_iter, rtol=_RTOL, atol=_ATOL, progress=progress)
        problem.costs.fits += 1
        problem.costs.iterations += out.iterations
        problem.costs.rejected_steps += int(out.timing.get("rejected_steps", 0))
        if not out.unhealthy_start:
            theta, iterations, history, converged = full(out.y), out.iterations, out.losses, bool(out.converged)
            at_y = out.jacobian[1] if out.jacobian is not None else None
            jac = None if at_y is None else (np.asarray(at_y[0], float), np.asarray(at_y[1], float))
    r = problem.residuals(theta, numerics)
    loss = float(np.sum(np.where(w > 0, w * r, 0.0) ** 2))  # held-out entries may be NaN (an unstable forecast)
    if not np.isfinite(loss):
        why = problem.health(theta, numerics) or "the residuals are NaN"
        raise JaxmpmError(f"the simulation is unstable at the starting parameters ({why}); "
                          "use more substeps or a better initial guess")
    if jac is not None:  # the solver's last Jacobian, if it was taken here (its residuals are these)
        r_solver, J_solver = jac
        here = np.where(w > 0, w * r, 0.0)
        jac = J_solver if np.allclose(r_solver, here, rtol=1e-5, atol=1e-6 * max(np.abs(here).max(), 1e-300)) else None
    return _Fit(theta=theta, r=r, loss=loss, iterations=iterations, free=list(free_names),
                history=history or [loss], jacobian=jac, converged=converged)


def _moved(v) -> str:
    return "none (unhealthy)" if v is None else format_std(v)


def _parameter_moves(problem: _Problem, fit: _Fit, train_entries, say: Callable[[str], None]) -> dict:
    """:func:`jaxmpm.numerics.parameter_moves` of ``fit``'s free parameters: the fit refitted
    from its estimate at dt/2 and with the other transfer, by at most
    :data:`~jaxmpm.numerics.NUMERICS_REFIT_STEPS` iterations each (each iteration's loss to
    ``say``)."""
    model = problem.seqs[0].model

    def by_name(theta) -> dict:
        return {n: np.asarray(theta[problem.slices[n]]).reshape(problem.entry(n).shape) for n in fit.free}

    def refit(numerics: Numerics) -> Refit | None:
        what = numerics.describe(model.flip)
        try:
            run = _lm(problem, fit.theta, fit.free, train_entries, max_iter=NUMERICS_REFIT_STEPS, numerics=numerics,
                      progress=lambda i, loss: say(f"  refit {what}, iteration {i}: training loss {loss:.4e}"))
        except JaxmpmError:  # unhealthy at the estimate with these numerics
            say(f"  refit {what}: unhealthy at the fitted point")
            return None
        return Refit(y=by_name(run.theta), losses=(float(run.history[0]), float(min(run.history))),
                     iterations=run.iterations, converged=run.converged)

    return parameter_moves(refit, by_name(fit.theta), lambda n, y: np.asarray(problem.physical(n, jnp.asarray(y, _F()))),
                           substeps=model.substeps, flip=model.flip)


def _covariance(problem: _Problem, fit: _Fit, train_entries) -> np.ndarray:
    """Frame-clustered sandwich covariance of the free parameters (optimisation space; see
    :func:`jaxmpm.identify.uncertainty.gauss_newton_covariance`) over the training groups.
    Parameters pinned at a bound are held fixed (their std is reported as 0)."""
    cols_all = problem.columns(fit.free)
    th = fit.theta[cols_all]
    pinned = np.isclose(th, problem.lower[cols_all], atol=1e-12) | np.isclose(th, problem.upper[cols_all], atol=1e-12)
    cols = cols_all[~pinned]
    full = np.zeros((len(cols_all), len(cols_all)))
    if len(cols) == 0:
        return full
    J = fit.jacobian[:, ~pinned] if fit.jacobian is not None else problem.jacobian(fit.theta, cols)
    g = problem.groups.entry_group
    rows = (g >= 0) & train_entries
    keep = np.flatnonzero(~pinned)
    full[np.ix_(keep, keep)] = gauss_newton_covariance(J[rows], fit.r[rows], groups=g[rows])
    return full


def _std_physical(problem: _Problem, theta, names, cov) -> dict[str, np.ndarray]:
    """Standard deviations in physical units of the entries ``names`` from ``cov`` (their order)."""
    sd_opt = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    y, std_y, k = {}, {}, 0
    for n in names:
        en = problem.entry(n)
        y[n] = jnp.asarray(theta[problem.slices[n]], _F()).reshape(en.shape)
        std_y[n] = sd_opt[k:k + en.size].reshape(en.shape)
        k += en.size
    out = physical_std(names, y, std_y, physical=problem.physical)
    return {n: (out[n] if problem.entry(n).shape else float(out[n])) for n in names}


# =========================================================================== results


@dataclass
class Candidate:
    """One screened extension.

    Attributes:
        id: extension id.
        score: linearised fraction of the training error (RSS) the extension would remove
            at its null value (Gauss–Newton, base parameters re-adjusted, bounds respected).
        score_p: p-value of the score statistic ``n ln(RSS_0 / RSS_lin)``.
        refit: whether it was refitted.
        gain: fraction of held-out RMS error removed by the refitted extension.
        train_error, heldout_error: RMS errors after the refit.
        lrt: likelihood-ratio statistic ``n ln(RSS_0 / RSS_1)`` on training groups.
        p_value: its p-value.
        parameters, std: fitted extension parameters and standard deviations.
        selected: kept in the extended model.
        reason: why it was or was not kept.
        step: the greedy step (1 = first extension added) at which it was evaluated.
        lin_step, boundary, fit, cov: working state of the workflow (the screen's linearised
            step, whether the null lies on a bound, the refit and its covariance); not reported.
    """

    id: str
    score: float
    score_p: float
    dof: int
    refit: bool = False
    gain: float | None = None
    train_error: float | None = None
    heldout_error: float | None = None
    lrt: float | None = None
    p_value: float | None = None
    parameters: dict = field(default_factory=dict)
    std: dict = field(default_factory=dict)
    selected: bool = False
    reason: str = ""
    step: int = 1
    lin_step: Any = field(default=None, repr=False)
    boundary: bool = field(default=False, repr=False)
    fit: Any = field(default=None, repr=False)
    cov: Any = field(default=None, repr=False)


def _plain(v):
    v = np.asarray(v, float)
    return float(v) if v.ndim == 0 else v.tolist()


@dataclass
class Discovery:
    """The outcome of :func:`discover` (see :meth:`to_json` for ``report.json``).

    With ``discover(numerics=True)``, ``numerics`` holds the base fit's parameters' moves by
    name (``{"dt": move, "transfer": move}``, physical units, as
    :attr:`jaxmpm.FitResult.numerics`), ``extended_numerics`` those of the extended fit (base
    and extension parameters; empty when nothing is selected), ``numerics_check`` the refits'
    records by fit (``{"base": ..., "extended": ...}``, :func:`jaxmpm.numerics.parameter_moves`;
    None where not run) and ``notes`` a note for each parameter whose error is numerical more
    than statistical.

    ``timing`` says where the time went, phase by phase (setup, base fit, base uncertainty,
    dt/2 check, transfer check, the numerics checks, each step's screen and each refit): wall
    seconds; forward rollouts and their seconds; forward-mode Jacobian rollouts, the tangents
    they carried and their seconds; Levenberg–Marquardt runs, iterations and rejected trial
    steps; compilation (estimated) and host seconds
    (:func:`jaxmpm.discover_report.format_timing` prints it as a table).
    """

    discrepancy: bool
    cause: str | None
    causes: list
    parameters: dict
    std: dict
    gain: float
    base_error: float
    extended_error: float
    base_train_error: float
    extended_train_error: float
    candidates: list
    base_values: dict
    base_std: dict
    extended_values: dict
    convergence: dict
    verdict: str
    settings: dict
    seconds: float
    not_applicable: dict
    timing: dict = field(default_factory=dict)
    numerics: dict = field(default_factory=dict)
    extended_numerics: dict = field(default_factory=dict)
    numerics_check: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    # internals for the report
    problem: Any = field(default=None, repr=False)
    base_theta: Any = field(default=None, repr=False)
    extended_theta: Any = field(default=None, repr=False)
    train_groups: Any = field(default=None, repr=False)
    heldout_groups: Any = field(default=None, repr=False)
    base_history: list = field(default_factory=list)

    def to_json(self) -> dict:
        """The ``report.json`` contract (DESIGN §5.3) plus extra fields (``details``)."""
        cands = []
        for c in self.candidates:
            cands.append({
                "id": c.id,
                "score": float(c.score),
                "gain": None if c.gain is None else float(c.gain),
                "parameters": {k: _plain(v) for k, v in c.parameters.items()},
            })
        return {
            "discrepancy": bool(self.discrepancy),
            "cause": self.cause,
            "parameters": {k: _plain(v) for k, v in self.parameters.items()},
            "gain": float(self.gain),
            "candidates": cands,
            "base_error": float(self.base_error),
            "extended_error": float(self.extended_error),
            "details": {
                "causes": list(self.causes),
                "std": {k: _plain(v) for k, v in self.std.items()},
                "verdict": self.verdict,
                "base_parameters": {k: _plain(v) for k, v in self.base_values.items()},
                "base_std": {k: _plain(v) for k, v in self.base_std.items()},
                "extended_parameters": {k: _plain(v) for k, v in self.extended_values.items()},
                "base_train_error": float(self.base_train_error),
                "extended_train_error": float(self.extended_train_error),
                "candidates": [
                    {
                        "id": c.id, "step": c.step, "score": float(c.score), "score_p": float(c.score_p), "dof": c.dof,
                        "refit": c.refit, "gain": None if c.gain is None else float(c.gain),
                        "train_error": None if c.train_error is None else float(c.train_error),
                        "heldout_error": None if c.heldout_error is None else float(c.heldout_error),
                        "lrt": None if c.lrt is None else float(c.lrt),
                        "p_value": None if c.p_value is None else float(c.p_value),
                        "std": {k: _plain(v) for k, v in c.std.items()},
                        "selected": c.selected, "reason": c.reason,
                    }
                    for c in self.candidates
                ],
                "convergence": self.convergence,
                **{key: {k: {c: None if v is None else _plain(v) for c, v in d.items()} for k, d in moves.items()}
                   for key, moves in (("numerics", self.numerics), ("extended_numerics", self.extended_numerics))},
                "numerics_check": self.numerics_check,
                "notes": list(self.notes),
                "not_applicable": self.not_applicable,
                "settings": self.settings,
                "seconds": float(self.seconds),
                "timing": self.timing,
            },
        }


# =========================================================================== the workflow


def _holdout_masks(problem: _Problem, holdout, holdout_sequences, holdout_views):
    g = problem.groups
    heldout = np.zeros(problem.num_groups, bool)
    names = [sd.seq.name for sd in problem.seqs]
    if holdout_sequences:
        unknown = set(holdout_sequences) - set(names)
        if unknown:
            raise JaxmpmError(f"holdout_sequences: no sequence named {sorted(unknown)} (have {names})")
        for i, n in enumerate(names):
            if n in holdout_sequences:
                heldout |= g.sequence == i
    if holdout and holdout > 0:
        if not 0 < holdout < 1:
            raise JaxmpmError(f"holdout must be a fraction in (0, 1), got {holdout}")
        for i in range(len(problem.seqs)):
            if names[i] in (holdout_sequences or ()):
                continue
            sel = g.sequence == i
            t = g.time[sel]
            # hold out the last `holdout` fraction of distinct times (at least one)
            ut = np.unique(t)
            k = max(1, int(round(holdout * len(ut))))
            cut = ut[-k]
            heldout[np.flatnonzero(sel)[t >= cut]] = True
    train = ~heldout
    entry_train = np.zeros(len(g.entry_group), bool)
    ok = g.entry_group >= 0
    entry_train[ok] = train[g.entry_group[ok]]
    if holdout_views:
        raise JaxmpmError("holdout_views is not supported yet; hold out later times or sequences")
    if not train.any():
        raise JaxmpmError("nothing left to train on after the hold-out")
    return train, heldout, entry_train


#: ridge (relative to unit-norm Jacobian columns) of the screen's least squares
_SCREEN_RIDGE = 1e-4


def _linear_screen(J, r, w, base_cols_local, ext_cols_local, lo, hi):
    """Gauss–Newton prediction of the training RSS with only the base columns free and with the
    extension's columns added (bounded least squares). Returns (RSS_base, RSS_ext, step)."""
    from scipy.optimize import lsq_linear

    Jw, rw = w[:, None] * J, w * r
    norms = np.linalg.norm(Jw, axis=0)
    dead = norms <= 1e-7 * max(np.max(norms), 1e-300)  # no information (e.g. a slip plane's tangential motion)
    Jw = np.where(dead[None, :], 0.0, Jw)
    norms = np.where(dead, 1.0, norms)
    b = -rw
    # A small ridge on the unit-norm columns: float32 Jacobians are accurate to ~1e-6, so a
    # direction that only the difference of two nearly collinear columns spans (an extension
    # that duplicates a base parameter) is noise and must not be credited with a gain.
    ridge = _SCREEN_RIDGE
    cb = Jw[:, base_cols_local] / norms[base_cols_local]
    if cb.shape[1]:
        aug = np.vstack([cb, ridge * np.eye(cb.shape[1])])
        sb = np.linalg.lstsq(aug, np.concatenate([b, np.zeros(cb.shape[1])]), rcond=None)[0]
        rss_b = float(np.sum((cb @ sb - b) ** 2))
    else:
        rss_b = float(b @ b)
    cols = np.concatenate([base_cols_local, ext_cols_local]).astype(int)
    A = Jw[:, cols] / norms[cols]
    lb = np.concatenate([np.full(len(base_cols_local), -np.inf), lo * norms[ext_cols_local]])
    ub = np.concatenate([np.full(len(base_cols_local), np.inf), hi * norms[ext_cols_local]])
    lb = np.minimum(lb, 0.0)
    ub = np.maximum(ub, 0.0)
    aug = np.vstack([A, ridge * np.eye(A.shape[1])])
    res = lsq_linear(aug, np.concatenate([b, np.zeros(A.shape[1])]), bounds=(lb, ub),
                     method="bvls" if A.shape[1] < 40 else "trf")
    rss_e = float(np.sum((A @ res.x - b) ** 2))
    step = res.x / norms[cols]
    return rss_b, min(rss_e, rss_b), step[len(base_cols_local):]


def pruned_reason(score: float, score_p: float, best_gain: float | None, alpha: float) -> str | None:
    """Why ``discover``'s prune skips the refit of a candidate, or None to refit it.

    ``score``: the share of the training error the screen predicts the candidate removes, with
    its p-value ``score_p``; ``best_gain``: the largest held-out gain of a refit that passed in
    this step (None before one passes). A candidate is skipped when its screen is not
    significant at ``alpha``, or when it is predicted to remove less of the training error than
    that held-out gain. Selection is by held-out gain, and a refit seldom gains more held out
    than it removes in training; comparing with the passing refit's *training* share instead
    skipped the selected cause of the 2D dam break (docs/discover.md)."""
    if not score_p < alpha:
        return f"not refitted: the screen is not significant (p {score_p:.3g} >= {alpha})"
    if best_gain is not None and score < best_gain:
        return (f"not refitted: it is predicted to remove {score:.1%} of the training error, "
                f"less than the {best_gain:.1%} held-out gain of a passing refit")
    return None


def _refit(problem, current: _Fit, theta_initial, free, cols, lin_step, entry_train, max_iter, progress=None,
           good_enough: Callable[[_Fit], bool] | None = None):
    """Fit base + extension from two starts and keep the better training loss: the current fit
    (a warm start) and, unless its result is ``good_enough``, the scene's own values of the base
    parameters (the current ones may have compensated for the missing physics and sit in a
    poor basin); the extension starts at its linearised (Gauss–Newton) estimate when that
    beats its null value."""
    starts = [current.theta.copy()]
    alt = current.theta.copy()
    base_cols = problem.columns([n for n in current.free if problem.entry(n).kind == "base"])
    alt[base_cols] = theta_initial[base_cols]
    if not np.allclose(alt, starts[0]):
        starts.append(alt)
    best, err = None, None
    for start in starts:
        guess = start.copy()
        guess[cols] = np.clip(start[cols] + lin_step, problem.lower[cols], problem.upper[cols])
        r_g = problem.residuals(guess, training_only=True)
        loss_g = float(np.sum((entry_train * r_g) ** 2))
        r_s = problem.residuals(start, training_only=True)
        loss_s = float(np.sum((entry_train * r_s) ** 2))
        if np.isfinite(loss_g) and (not np.isfinite(loss_s) or loss_g < loss_s):
            start = guess
        try:
            f = _lm(problem, start, free, entry_train, max_iter=max_iter, progress=progress)
        except JaxmpmError as e:
            err = str(e)
            continue
        if best is None or f.loss < best.loss:
            best = f
        if good_enough is not None and good_enough(best):
            break
    return best if best is not None else err


def discover(
    sequences: Sequence | _Seq[Sequence] | Model,
    params: Params | None = None,
    observation: Observation | None = None,
    *,
    names: list[str] | None = None,
    extensions: _Seq[str] | None = None,
    holdout: float = 0.3,
    holdout_sequences: _Seq[str] | None = None,
    holdout_views=None,
    top: int = 3,
    min_gain: float = 0.1,
    alpha: float = 0.05,
    max_extensions: int = 3,
    max_iter: int = 25,
    convergence: bool = True,
    numerics: bool = False,
    noise_floor: float | None = None,
    num_pixels: int = 256,
    prune: bool = True,
    progress: Callable[[str], None] | None = None,
) -> Discovery:
    """Run the discrepancy workflow (see the module docstring).

    Arguments:
        sequences: a :class:`Sequence` or a list of them (sharing parameter names); or a
            model, with ``params`` and ``observation`` given separately.
        names: base parameters to fit (default :func:`default_parameters` of the first model).
        extensions: extension ids to consider (default: all; inapplicable ones are listed in
            the result's ``not_applicable``).
        holdout: fraction of the latest observed times held out in every sequence (forecast).
        holdout_sequences: names of sequences held out entirely (fit on the others).
        top: how many of the best-scoring extensions are refitted at each greedy step.
        min_gain: smallest held-out gain (fraction of held-out RMS error removed) kept.
        alpha: level of the likelihood-ratio test.
        max_extensions: most extensions added greedily.
        max_iter: Levenberg–Marquardt iterations per fit.
        convergence: the numerical checks: rerun the fitted base model at ``dt / 2`` (its
            change is the numerical error an improvement must exceed) and with the other
            transfer (:class:`Numerics`; its change is reported, and the verdict cautions
            against an extension whose improvement is within it: :func:`transfer_caution`).
        numerics: the fits' numerical error in parameter space: how far a short refit at
            dt/2 and one with the other transfer move each parameter of the base fit and, when
            an extension is selected, of the extended fit (:func:`jaxmpm.numerics.parameter_moves`,
            at most :data:`~jaxmpm.numerics.NUMERICS_REFIT_STEPS` iterations each; the result's
            ``numerics``, ``extended_numerics`` and ``numerics_check``), with a note for each
            parameter moved by more than :data:`~jaxmpm.numerics.NUMERICS_NOTE_STDS` of its std
            (``notes``).
        noise_floor: observation noise (RMS, in the data's units) if known: a base model whose
            held-out error is within 1.5 times it has nothing to explain.
        num_pixels: pixels per view and frame for silhouettes.
        prune: refit only candidates whose score is significant at ``alpha``, none that the
            screen predicts to remove less of the training error than the held-out gain of a
            passing refit of the same step, and no second start once the warm start passes.
            ``False`` refits the ``top`` best from both starts whatever their scores (for
            strongly nonlinear residuals, e.g. silhouettes, where the score can understate
            an effect).
        progress: optional callback receiving one line per stage.

    Returns:
        A :class:`Discovery`; :func:`jaxmpm.discover_report.write_report` turns it into
        ``report.md``, ``report.json`` and plots.
    """
    start = _time.perf_counter()
    say = progress or (lambda s: None)
    if isinstance(sequences, Model):
        if params is None or observation is None:
            raise JaxmpmError("discover(model, params, observation): give params and observation")
        sequences = [Sequence(sequences, params, observation)]
    elif isinstance(sequences, Sequence):
        sequences = [sequences]
    sequences = list(sequences)
    if not sequences:
        raise JaxmpmError("no sequences to discover from")
    dtype = sequences[0].model.bodies[0].x0.dtype
    names = list(dict.fromkeys(names)) if names is not None else default_parameters(sequences[0].model)
    requested = list(extensions) if extensions is not None else list(DEFAULT_EXTENSIONS)
    for e in requested:
        if e not in X.EXTENSIONS:
            raise JaxmpmError(f"unknown extension {e!r}; known: {', '.join(X.EXTENSIONS)}")
    not_applicable = {}
    for e in requested:
        reasons = [X.applicable(s.model, e) for s in sequences]
        if all(r is not None for r in reasons):
            not_applicable[e] = reasons[0]
    problem = _Problem(sequences, names, [e for e in requested if e not in not_applicable], num_pixels, dtype)
    phase = _Phases(problem.costs)
    with phase("setup", since=start):
        train, heldout, entry_train = _holdout_masks(problem, holdout, holdout_sequences, holdout_views)
        problem.residuals(problem.initial())  # sizes of every sequence's residuals
    n_train = int(train.sum())
    problem.skip = frozenset(i for i in range(len(problem.seqs)) if not np.any(train[problem.groups.sequence == i]))

    # ---- 1. the base fit
    say(f"fitting the base model ({', '.join(names)}) on {n_train} training frames; "
        f"{int(heldout.sum())} held out")
    theta0 = problem.initial()
    with phase("base fit"):
        base = _lm(problem, theta0, problem.base_names(), entry_train, max_iter=max_iter,
                   progress=lambda i, l: say(f"  base fit iteration {i}: training loss {l:.4e}"))
    base_train_err = problem.error(base.r, train)
    base_err = problem.error(base.r, heldout) if heldout.any() else base_train_err
    with phase("base uncertainty"):
        base_cov = _covariance(problem, base, entry_train)
        base_std = _std_physical(problem, base.theta, problem.base_names(), base_cov)
    base_values = {n: problem.values(base.theta)[n] for n in problem.base_names()}
    say(f"base model: training error {base_train_err:.4g}, held-out error {base_err:.4g}")

    # ---- 2. convergence check (numerical error)
    made_by_model = all(sd.seq.observation.made_by(sd.model) for sd in problem.seqs)  # on its own grid
    conv = {}
    numerical = 0.0
    if convergence:
        rows = heldout if heldout.any() else train  # the groups both checks are measured on
        say("convergence check: the fitted base model at dt/2")
        with phase("dt/2 check"):
            r_half = problem.residuals(base.theta, Numerics(substeps_factor=2))
        numerical = problem.error(r_half - base.r, rows)
        conv = {
            "dt_factor": 0.5,
            "heldout_error_dt": base_err,
            "heldout_error_dt2": problem.error(r_half, rows),
            "numerical_error": numerical,
            "numerical_fraction": numerical / max(base_err, 1e-300),
        }
        say(f"  numerical error (dt vs dt/2): {numerical:.3g} ({100 * conv['numerical_fraction']:.1f} % of the base error)")
        flip = problem.seqs[0].model.flip
        say(f"transfer check: the fitted base model with {transfer_name(other_flip(flip))} in place of "
            f"{transfer_name(flip)}")
        with phase("transfer check"):
            factor, r_same, r_other = transfer_runs(lambda numerics: problem.residuals(base.theta, numerics), base.r,
                                                    r_half, lambda r: bool(np.all(np.isfinite(r))))
        for at, unhealthy in (("dt", factor == 2), ("dt/2", not np.all(np.isfinite(r_other)))):
            if unhealthy:
                say(f"  the rollout with the other transfer is unhealthy at {at}")
        conv.update(_transfer_check(problem, r_same, r_other, rows, base_err, flip, factor))
        conv["data_made_by_model"] = made_by_model
        if conv["transfer_error"] is not None:
            say(f"  transfer change{' at dt/2' if factor == 2 else ''}: {conv['transfer_error']:.3g} "
                f"({100 * conv['transfer_fraction']:.1f} % of the base error)")

    # ---- the fits' numerical error in parameter space (numerics=True): the base fit's here,
    # the extended fit's once the extensions are selected
    checks, notes = {"base": None, "extended": None}, []

    def numerics_check(model: str, fit: _Fit, stds: dict) -> dict:
        """``model``'s (base, extended) fit refitted with other numerics: its parameters' moves."""
        say(f"numerics check: the {model} fit refitted at dt/2 and with the other transfer")
        with phase(f"numerics check ({model})"):
            checks[model] = _parameter_moves(problem, fit, entry_train, say)
        moves = move_table(checks[model], fit.free)
        for n, m in moves.items():
            sd = ("unknown" if n not in stds else "0: held on its bound" if not np.any(np.asarray(stds[n]) > 0)
                  else format_std(stds[n]))
            say(f"  {n}: dt/2 move {_moved(m['dt'])}, transfer move {_moved(m['transfer'])} (std {sd})")
        for note in numerics_notes(checks[model], fit.free, stds, refit="rerun discover", made_by_model=made_by_model):
            notes.append(f"{model} model: {note}")
            say(f"  note: {notes[-1]}")
        return moves

    base_moves = numerics_check("base", base, base_std) if numerics and problem.base_names() else {}

    # ---- 3-4. screen, refit, select (greedy)
    current = base
    current_names = problem.base_names()
    current_train_err, current_err = base_train_err, base_err
    selected: list[str] = []
    improvements: dict[str, float] = {}  # each selected extension's held-out improvement
    all_cands: list[Candidate] = []
    remaining = list(problem.candidates)
    verdict_notes = []
    if noise_floor is not None and base_err <= 1.5 * noise_floor:
        verdict_notes.append(f"the base model's held-out error {base_err:.3g} is within 1.5x the noise floor {noise_floor:.3g}")
        remaining = []
    step_no = 0
    ext_cov = None
    while remaining and len(selected) < max_extensions:
        step_no += 1
        say(f"step {step_no}: screening {len(remaining)} extensions at their null values (score test)")
        with phase(f"step {step_no}: screen"):
            base_cols = problem.columns(current_names)
            ext_cols = {e: problem.columns(problem.ext_names(e)) for e in remaining}
            all_cols = np.concatenate([base_cols] + [ext_cols[e] for e in remaining])
            if current.jacobian is not None and current.free == current_names:
                # the current fit's last Jacobian is its columns at this point (training rows,
                # which are all the screen weighs): only the extensions' columns are new
                J = np.concatenate([current.jacobian, problem.jacobian(current.theta, all_cols[len(base_cols):])], axis=1)
            else:
                J = problem.jacobian(current.theta, all_cols)
            w = entry_train.astype(float)
            local = {c: i for i, c in enumerate(all_cols)}
            b_loc = np.array([local[c] for c in base_cols], int)
            cands = []
            for e in remaining:
                e_loc = np.array([local[c] for c in ext_cols[e]], int)
                lo = problem.lower[ext_cols[e]] - current.theta[ext_cols[e]]
                hi = problem.upper[ext_cols[e]] - current.theta[ext_cols[e]]
                rss_b, rss_e, lin_step = _linear_screen(J, current.r, w, b_loc, e_loc, lo, hi)
                score = (rss_b - rss_e) / max(rss_b, 1e-300)
                stat = n_train * math.log(max(rss_b, 1e-300) / max(rss_e, 1e-300))
                specs = [problem.entry(n).spec for n in problem.ext_names(e)]
                dof = int(sum(s.size for s in specs))
                boundary = dof == 1 and specs[0].bounded
                c = Candidate(id=e, score=float(score), score_p=p_value(stat, dof, boundary), dof=dof, step=step_no)
                c.lin_step = lin_step
                c.boundary = boundary
                cands.append(c)
        cands.sort(key=lambda c: -c.score)
        for c in cands:
            say(f"  {c.id:18s} score {c.score:7.4f}  p {c.score_p:.3g}")
        best_cand, best_fit = None, None
        # the rule needs a held-out improvement above the numerical error: when the current
        # held-out error is itself within it, no refit can pass, so none is run
        hopeless = convergence and current_err <= numerical
        best_gain = None  # the largest held-out gain of a passing refit of this step

        def judge(f, c):
            """The selection rule on candidate ``c`` refitted as ``f``: its numbers, and the
            conditions it fails (none: it passes)."""
            train_error = problem.error(f.r, train)
            heldout_error = problem.error(f.r, heldout) if heldout.any() else train_error
            gain = 1.0 - heldout_error / max(current_err, 1e-300)
            lrt = n_train * math.log(max(current.loss, 1e-300) / max(f.loss, 1e-300))
            p = p_value(lrt, c.dof, c.boundary)
            reasons = []
            if gain < min_gain:
                reasons.append(f"held-out gain {gain:.1%} < {min_gain:.0%}")
            if not p < alpha:
                reasons.append(f"likelihood-ratio p = {p:.3g} >= {alpha}")
            if convergence and current_err - heldout_error <= numerical:
                reasons.append(f"the improvement {current_err - heldout_error:.3g} is within the numerical error "
                               f"{numerical:.3g}")
            return dict(train_error=train_error, heldout_error=heldout_error, gain=gain, lrt=lrt, p_value=p), reasons

        for c in cands[:top]:
            if c.score <= 1e-9:
                c.reason = "no predicted improvement"
                continue
            if hopeless:
                c.reason = (f"not refitted: the held-out error {current_err:.3g} is within the numerical error "
                            f"{numerical:.3g}, so no improvement can exceed it")
                continue
            skip = pruned_reason(c.score, c.score_p, best_gain, alpha) if prune else None
            if skip:
                c.reason = skip
                continue
            say(f"  refitting base + {c.id}")
            free = current_names + problem.ext_names(c.id)
            with phase(f"step {step_no}: refit {c.id}"):
                f = _refit(problem, current, theta0, free, problem.columns(problem.ext_names(c.id)), c.lin_step,
                           entry_train, max_iter,
                           progress=lambda i, l, c=c: say(f"    {c.id} refit iteration {i}: training loss {l:.4e}"),
                           good_enough=(lambda f, c=c: not judge(f, c)[1]) if prune else None)
                if not isinstance(f, str):
                    try:
                        cov = _covariance(problem, f, entry_train)
                        stds = _std_physical(problem, f.theta, free, cov)
                        c.std = {n: stds[n] for n in problem.ext_names(c.id)}
                    except Exception:  # noqa: BLE001 - diagnostics only
                        cov, c.std = None, {}
            if isinstance(f, str):
                c.reason = f"refit failed: {f}"
                continue
            c.refit = True
            numbers, reasons = judge(f, c)
            for name, value in numbers.items():  # train_error, heldout_error, gain, lrt, p_value
                setattr(c, name, value)
            vals = problem.values(f.theta)
            c.parameters = {n: vals[n] for n in problem.ext_names(c.id)}
            c.fit, c.cov = f, cov
            c.reason = "; ".join(reasons) if reasons else "passes"
            if not reasons:
                best_gain = max(best_gain or 0.0, c.gain)
            say(f"    {c.id}: held-out gain {c.gain:.1%}, LRT {c.lrt:.3g} (p {c.p_value:.3g}) -> {c.reason}")
            if not reasons and (best_cand is None or c.heldout_error < best_cand.heldout_error):
                best_cand, best_fit = c, f
        for c in cands[top:]:
            c.reason = f"not refitted (score rank > {top})"
        all_cands += cands
        if best_cand is None:
            break
        best_cand.selected = True
        improvements[best_cand.id] = current_err - best_cand.heldout_error
        best_cand.reason = "selected: " + best_cand.reason
        selected.append(best_cand.id)
        current = best_fit
        ext_cov = best_cand.cov
        current_names = current_names + problem.ext_names(best_cand.id)
        current_train_err, current_err = best_cand.train_error, best_cand.heldout_error
        remaining = [e for e in remaining if e != best_cand.id]

    # ---- results
    discrepancy = bool(selected)
    values = problem.values(current.theta)
    parameters = {n: values[n] for e in selected for n in problem.ext_names(e)}
    std, stds = {}, {}
    if selected and ext_cov is not None:
        stds = _std_physical(problem, current.theta, current_names, ext_cov)
        std = {n: stds[n] for n in parameters}
    extended_moves = numerics_check("extended", current, stds) if numerics and selected else {}
    gain = 1.0 - current_err / max(base_err, 1e-300) if discrepancy else 0.0
    if discrepancy:
        them = "it" if len(selected) == 1 else "them"
        verdict = (f"The base model misses {_describe(selected)}: adding {them} removes {gain:.0%} of the held-out error "
                   f"({base_err:.3g} -> {current_err:.3g}).")
        caution = transfer_caution(conv, improvements)
        if caution:
            verdict += " " + caution
    else:
        why = verdict_notes[0] if verdict_notes else (
            "no extension removes a significant part of the held-out error" if all_cands else "no extension applies")
        verdict = f"No significant discrepancy: {why}."
        if convergence and conv.get("numerical_fraction", 0.0) > 0.5:
            verdict += (f" The prediction is not converged in dt: refining dt moves it by "
                        f"{conv['numerical_fraction']:.0%} of the error (held-out error {conv['heldout_error_dt']:.3g} "
                        f"at dt, {conv['heldout_error_dt2']:.3g} at dt/2), so a smaller physical effect cannot be told "
                        "from the discretisation.")
        if (conv.get("transfer_fraction") is not None and conv["transfer_fraction"] > 0.5
                and not conv["data_made_by_model"]):
            verdict += (f" The prediction depends on the transfers: {transfer_name(conv['flip_checked'])} in place of "
                        f"{transfer_name(conv['flip'])} moves it by {conv['transfer_fraction']:.0%} of the error, so a "
                        "smaller physical effect cannot be told from the grid's numerical dissipation.")
    if conv:
        conv["within_transfer_change"] = within_transfer_change(conv, improvements)
    # first-step candidates first (the ranked table of the contract), later steps after
    order = sorted(all_cands, key=lambda c: (c.step, -c.score))
    settings = dict(names=names, extensions=requested, holdout=holdout, holdout_sequences=list(holdout_sequences or []),
                    top=top, min_gain=min_gain, alpha=alpha, max_extensions=max_extensions, max_iter=max_iter, prune=prune,
                    convergence=convergence, numerics=numerics, noise_floor=noise_floor, train_groups=n_train,
                    heldout_groups=int(heldout.sum()), sequences=[s.name for s in sequences])
    for c in order:  # the workflow's working state is not part of the result
        c.lin_step, c.fit, c.cov = None, None, None
    seconds = _time.perf_counter() - start
    return Discovery(
        discrepancy=discrepancy,
        cause=selected[0] if selected else None,
        causes=selected,
        parameters=parameters,
        std=std,
        gain=float(gain),
        base_error=float(base_err),
        extended_error=float(current_err if discrepancy else base_err),
        base_train_error=float(base_train_err),
        extended_train_error=float(current_train_err),
        candidates=order,
        base_values=base_values,
        base_std=base_std,
        extended_values={n: values[n] for n in current_names},
        convergence=conv,
        numerics=base_moves,
        extended_numerics=extended_moves,
        numerics_check=checks,
        notes=notes,
        verdict=verdict,
        settings=settings,
        seconds=seconds,
        not_applicable=not_applicable,
        timing=phase.timing(seconds),
        problem=problem,
        base_theta=base.theta,
        extended_theta=current.theta,
        train_groups=train,
        heldout_groups=heldout,
        base_history=base.history,
    )


def _transfer_check(problem, r, r_other, rows, base_err: float, flip: float, substeps_factor: int) -> dict:
    """The transfer check's entries of ``Discovery.convergence``: how far the fitted base
    model's prediction moves (RMS over ``rows``, the held-out groups) when its transfers are
    swapped (residuals ``r`` -> ``r_other``, both at ``dt / substeps_factor``); ``None``
    where the swapped rollout is unhealthy."""
    change = problem.error(r_other - r, rows)
    ok = bool(np.isfinite(change))
    return {
        "flip": flip,
        "flip_checked": other_flip(flip),
        "transfer_dt_factor": 1.0 / substeps_factor,
        "heldout_error_transfer": problem.error(r_other, rows) if ok else None,
        "transfer_error": change if ok else None,
        "transfer_fraction": change / max(base_err, 1e-300) if ok else None,
    }


def within_transfer_change(convergence: dict, improvements: dict[str, float]) -> list[str]:
    """The extensions of ``improvements`` (``id ->`` held-out improvement) that
    :func:`transfer_caution` cautions against."""
    change = convergence.get("transfer_error")
    if change is None or convergence.get("data_made_by_model"):
        return []
    return [e for e, gain in improvements.items() if gain <= change]


def transfer_caution(convergence: dict, improvements: dict[str, float]) -> str | None:
    """The verdict's caution for selected extensions whose held-out improvement (``id ->``
    metres, or the data's unit) is no larger than the transfer check's change: they may stand
    in for the transfers' numerical dissipation rather than for physics the data show. None
    when there is no such extension, no transfer check, or the data may have been made by the
    model on its grid (``convergence["data_made_by_model"]``:
    :meth:`jaxmpm.observe.Observation.made_by`), which then has no such error."""
    within = within_transfer_change(convergence, improvements)
    if not within:
        return None
    change = convergence["transfer_error"]
    it, they = ("it", "it") if len(within) == 1 else ("them", "they")
    gains = ", ".join(f"{improvements[e]:.3g}" for e in within)
    fix = (f"rerun discover with the FLIP blend (scene key flip = {CHECK_FLIP:g}) or at a finer dx"
           if convergence["flip"] == 0.0 else "rerun discover at a finer dx")
    return (f"Caution: the held-out improvement of {', '.join(within)} ({gains}) is no larger than the change the "
            f"transfers make: with {transfer_name(convergence['flip_checked'])} in place of "
            f"{transfer_name(convergence['flip'])} the fitted base model's held-out prediction moves by {change:.3g}. "
            f"Unless the data were made by this model's transfers on this grid, {they} may stand in "
            f"for the grid's numerical dissipation: {fix} before trusting {it} "
            "(docs/discover.md, \"The transfer check\").")


def _describe(ids) -> str:
    return " + ".join(f"{X.EXTENSIONS[e].title} ({e})" for e in ids)
