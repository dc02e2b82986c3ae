"""The one residual system of identification: tracks, silhouettes, masked RGB and probes.

Each kind of data is a :class:`Term` (an equinox module) built with its :class:`Layout` by
:func:`track_term`, :func:`image_terms` or :func:`probe_term`. A term reads a rollout's
:class:`Frames` (per-frame positions, velocities, masses and volumes) at the observed times,
shifted by a time offset ``t0`` (cubic Hermite interpolation between frames: exact at the
frames, differentiable in ``t0``), and returns a **residual vector**. How it is scaled is
the consumer's choice (:data:`NORMALISATIONS`): for :func:`jaxmpm.fit`
(:func:`build_objective`) ``sum(r**2) = weight * (mean squared error of the term)``, so the
sum of squares of all terms' residuals is the scalar loss (Levenberg–Marquardt works on the
residuals; Adam and BFGS on the scalar); for :func:`jaxmpm.discover` the sum over each
group of entries (one observed frame, one probe time bin) is that group's mean squared error.
A sweep of a loss uses :meth:`Objective.residuals_of` as its function of the trajectory.

=============  ==========================================  ==============================
term           compares                                    residual entries
=============  ==========================================  ==============================
``tracks``     observed points with the particles:         ``x_sim − x_obs`` per point and
               L2 when ``point_ids == "particles"``,       coordinate; or nearest-neighbour
               Chamfer (set to set) otherwise              distances both ways per frame
``silhouette`` rendered soft silhouettes with the masks    ``alpha − mask`` per sampled pixel
``rgb``        rendered colour with the images, where the  ``rgb − image`` per sampled pixel
               observed mask is set (PAC-NeRF's ray mask)  and channel
``probes``     named time series of the state (front       ``probe_sim − probe_obs`` per
               position, gauge height, ...)                sample
=============  ==========================================  ==============================

Image terms render only a batch of pixels per view and frame: a fixed batch for
least-squares methods (the residual function must be deterministic) or a fresh random batch
per call when a PRNG key is given (Adam). Pixels are drawn mostly from the dilated union of
the observed masks of each view and partly uniformly over the image, so that a simulated
body that strays far from the observed one is still seen.

Probes are functions ``fn(state, model) -> scalar`` of a state holding the frame's
positions, velocities, masses and reference volumes, looked up by name
(:func:`probe_function`): ``front_x`` (the largest x of any particle, plus half a particle
spacing: the leading edge), ``back_x``, ``top_y``/``height`` (vertical), ``centroid_x``,
..., and parameterised names such as ``gauge@0.3`` (the height of the material column at
x = 0.3 m: its highest particle; ``gauge@0.3,0.1`` at x = 0.3, z = 0.1 in 3D) and
``depth@0.3`` (the depth its material would fill: :func:`depth_gauge`, blind to spray). Register others with
:func:`register_probe` (e.g. ``register_probe("gauge_H2", gauge(0.582, 0.0))``) or pass
``probes={name: fn}`` to :func:`build_objective`.
"""

from __future__ import annotations

import abc
import math
import re
from dataclasses import dataclass
from typing import Any, Callable

import equinox as eqx

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..errors import JaxmpmError, ObservationError
from ..model import Model, Params
from ..observe import Observation
from ..state import State, make_state
from ..step import Trajectory, health_message, simulate, unhealthy

__all__ = [
    "TERMS",
    "ProbeFn",
    "register_probe",
    "probe_function",
    "probe_names",
    "front",
    "back",
    "top",
    "centroid",
    "gauge",
    "depth_gauge",
    "frames_needed",
    "hermite",
    "chamfer_residuals",
    "check_tracks",
    "Frames",
    "Term",
    "Layout",
    "NORMALISATIONS",
    "Tracks",
    "Probes",
    "Silhouette",
    "MaskedRGB",
    "track_term",
    "probe_term",
    "image_terms",
    "make_fit_renderer",
    "lifted_layers",
    "particle_colors",
    "Objective",
    "build_objective",
]

#: The loss terms by name.
TERMS = ("tracks", "silhouette", "rgb", "probes")

ProbeFn = Callable[[State, Model], Any]

_AXES = {"x": 0, "y": 1, "z": 2}
#: The vertical axis (gravity acts along -y in every shipped scene).
UP = 1


# =========================================================================== probes


def _spacing(state: State) -> jnp.ndarray:
    """Particle spacing ``h = V0^(1/D)`` (largest particle), the thickness a particle represents."""
    return jnp.max(state.vol0) ** (1.0 / state.dim)


def front(axis: int | str = 0) -> ProbeFn:
    """The leading edge along ``axis``: the largest coordinate of any particle + h/2."""
    a = _AXES[axis] if isinstance(axis, str) else int(axis)

    def fn(state: State, model: Model):
        return jnp.max(state.x[:, a]) + 0.5 * _spacing(state)

    return fn


def back(axis: int | str = 0) -> ProbeFn:
    """The trailing edge along ``axis``: the smallest coordinate of any particle − h/2."""
    a = _AXES[axis] if isinstance(axis, str) else int(axis)

    def fn(state: State, model: Model):
        return jnp.min(state.x[:, a]) - 0.5 * _spacing(state)

    return fn


def top(floor: float | None = None) -> ProbeFn:
    """Height of the highest material above ``floor`` (default: the domain's bottom)."""

    def fn(state: State, model: Model):
        base = model.grid.lo[UP] if floor is None else floor
        return jnp.max(state.x[:, UP]) + 0.5 * _spacing(state) - base

    return fn


def centroid(axis: int | str = 0) -> ProbeFn:
    """Mass-weighted mean coordinate along ``axis``."""
    a = _AXES[axis] if isinstance(axis, str) else int(axis)

    def fn(state: State, model: Model):
        return jnp.sum(state.mass * state.x[:, a]) / jnp.sum(state.mass)

    return fn


def gauge(x: float, z: float | None = None, *, width: float | None = None, floor: float | None = None) -> ProbeFn:
    """Gauge height at ``x`` (and ``z`` in 3D): the top of the material column there.

    The column is the particles within ``width/2`` of the gauge position horizontally
    (default: one grid cell, ``width = dx``); its height is the highest such particle + h/2
    above ``floor`` (default: the domain's bottom), or 0 where the column is dry.
    """

    def fn(state: State, model: Model):
        w = model.grid.dx if width is None else width
        base = model.grid.lo[UP] if floor is None else floor
        near = jnp.abs(state.x[:, 0] - x) <= 0.5 * w
        if state.dim == 3 and z is not None:  # without z: a line gauge across the whole width
            near = near & (jnp.abs(state.x[:, 2] - z) <= 0.5 * w)
        h = state.x[:, UP] + 0.5 * _spacing(state) - base
        return jnp.max(jnp.where(near, h, 0.0), initial=0.0)

    return fn


def _tent(d, half_width: float):
    """The tent kernel ``max(0, 1 - |d| / w) / w`` (unit integral, 1/m)."""
    return jnp.maximum(1.0 - jnp.abs(d) / half_width, 0.0) / half_width


def _tent_inside(centre: float, half_width: float, lo: float, hi: float) -> float:
    """The share of the tent centred at ``centre`` that lies in ``[lo, hi]``."""

    def below(s):  # the tent's integral up to s
        t = min(max((s - centre) / half_width, -1.0), 1.0)
        return 0.5 * (1.0 + t) ** 2 if t <= 0.0 else 1.0 - 0.5 * (1.0 - t) ** 2

    return below(hi) - below(lo)


def depth_gauge(x: float, z: float | None = None, *, width: float | None = None) -> ProbeFn:
    """Water depth at ``x`` (and ``z`` in 3D): the depth the material around the gauge would
    fill at its reference volume, m.

    Each particle's reference volume ``V0`` is spread horizontally over a tent of half-width
    ``width`` (default one grid cell, ``dx``) centred on the gauge: ``depth = sum_p V0_p
    k(x_p - x) k(z_p - z) / s``, ``k`` the unit tent and ``s`` the share of the tent inside the
    domain (a gauge on a wall or a symmetry plane reads the depth of its column, not half of
    it). In 2D ``V0`` is an area and there is no ``z``; in 3D without ``z`` it is a line gauge
    across the whole width (divided by the domain's extent in z). On a resting lattice of
    particles it reads the material's depth exactly; unlike :func:`gauge` (the highest
    particle), a few particles thrown above the column add only their own volume, and the
    reading varies continuously with the positions (a gradient for fits).
    """

    def fn(state: State, model: Model):
        grid = model.grid
        w = grid.dx if width is None else width
        weight = _tent(state.x[:, 0] - x, w) / _tent_inside(x, w, grid.lo[0], grid.hi[0])
        if state.dim == 3:
            if z is None:
                weight = weight / (grid.hi[2] - grid.lo[2])
            else:
                weight = weight * _tent(state.x[:, 2] - z, w) / _tent_inside(z, w, grid.lo[2], grid.hi[2])
        return jnp.sum(state.vol0 * weight)

    return fn


_REGISTRY: dict[str, ProbeFn] = {}


def register_probe(name: str, fn: ProbeFn | None = None):
    """Register a probe function ``fn(state, model) -> scalar`` under ``name``.

    Usable as a decorator (``@register_probe("my_probe")``). Observation files name their
    probes in ``probe_names``; a fit matches them by name.
    """
    if not isinstance(name, str) or not name:
        raise JaxmpmError(f"probe name must be a non-empty string, got {name!r}")

    def add(f):
        if not callable(f):
            raise JaxmpmError(f"probe {name!r}: expected a function (state, model) -> scalar, got {f!r}")
        _REGISTRY[name] = f
        return f

    return add if fn is None else add(fn)


_PATTERNS: list[tuple[re.Pattern, Callable[..., ProbeFn]]] = [
    (re.compile(r"front_([xyz])"), lambda a: front(a)),
    (re.compile(r"back_([xyz])"), lambda a: back(a)),
    (re.compile(r"(?:top_y|height)"), lambda: top()),
    (re.compile(r"centroid_([xyz])"), lambda a: centroid(a)),
    (re.compile(r"gauge@([-+0-9.eE]+)(?:,([-+0-9.eE]+))?"), lambda x, z=None: gauge(float(x), None if z is None else float(z))),
    (re.compile(r"depth@([-+0-9.eE]+)(?:,([-+0-9.eE]+))?"),
     lambda x, z=None: depth_gauge(float(x), None if z is None else float(z))),
]


_BUILT: dict[str, ProbeFn] = {}


def probe_names() -> list[str]:
    """The registered and built-in probe names (patterns shown with placeholders)."""
    return sorted(_REGISTRY) + ["front_x|y|z", "back_x|y|z", "top_y", "height", "centroid_x|y|z", "gauge@X[,Z]",
                                  "depth@X[,Z]"]


def probe_function(name: str, extra: dict[str, ProbeFn] | None = None) -> ProbeFn:
    """The probe function for ``name``: from ``extra``, the registry, or a built-in pattern.

    Raises:
        ObservationError: unknown probe names (the message lists what is known).
    """
    if extra and name in extra:
        return extra[name]
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _BUILT:
        return _BUILT[name]
    for pattern, factory in _PATTERNS:
        m = pattern.fullmatch(name)
        if m:
            try:
                fn = factory(*[g for g in m.groups() if g is not None])
            except ValueError:
                break
            # one function per name: a term built twice (a fit's windows) compares equal, and
            # compiled programs keyed on it are shared
            return _BUILT.setdefault(name, fn)
    raise ObservationError(
        f"unknown probe {name!r}: register it with jaxmpm.identify.register_probe({name!r}, fn) or pass "
        f"probes={{{name!r}: fn}}; known probes: {', '.join(probe_names())}"
    )


def probe_series(fn: ProbeFn, model: Model, traj) -> np.ndarray:
    """``fn(state, model)`` read at every recorded frame of ``traj`` (a
    :class:`~jaxmpm.step.Trajectory`): ``(frames,)``, each frame's positions put in the place of
    the final state's (a probe reads positions and the particles' fixed properties)."""
    return np.array([float(fn(eqx.tree_at(lambda s: s.x, traj.final, x), model)) for x in traj.x])


# =========================================================================== time sampling


def frames_needed(model: Model, times: np.ndarray) -> int:
    """Output frames (including t = 0) a simulation needs to cover ``times``."""
    return max(2, int(math.ceil(float(np.max(times)) / model.frame_dt - 1e-6)) + 1)


def hermite(P, Pdot, times, t0, frame_dt: float):
    """Values at ``times - t0`` from per-frame values ``P (F, ...)`` and their time derivatives
    ``Pdot`` (cubic Hermite: exact at the frames, C1 in ``t0``; clamped to the simulated span)."""
    F = P.shape[0]
    dtype = P.dtype
    s = (jnp.asarray(times, dtype) - jnp.asarray(t0, dtype)) / frame_dt
    s = jnp.clip(s, 0.0, F - 1.0)
    i0 = jnp.clip(jnp.floor(jax.lax.stop_gradient(s) + 1e-6), 0, F - 2).astype(jnp.int32)
    u = s - i0.astype(dtype)
    u2, u3 = u * u, u * u * u
    h00, h10, h01, h11 = 2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2
    shape = (-1,) + (1,) * (P.ndim - 1)
    c = lambda h: h.reshape(shape)  # noqa: E731
    return c(h00) * P[i0] + c(h10) * frame_dt * Pdot[i0] + c(h01) * P[i0 + 1] + c(h11) * frame_dt * Pdot[i0 + 1]


# =========================================================================== chamfer


def _chunked_min(q, p, valid_p, chunk: int = 1024):
    """``min_j |q_i − p_j|²`` over valid ``p``, computed in chunks of ``q`` (bounded memory)."""
    n = q.shape[0]
    chunk = max(1, min(chunk, n))
    k = -(-n // chunk)
    pad = k * chunk - n
    qq = jnp.concatenate([q, jnp.broadcast_to(q[-1:], (pad, q.shape[1]))]) if pad else q

    def one(block):
        d2 = jnp.sum((block[:, None, :] - p[None, :, :]) ** 2, axis=-1)
        return jnp.min(jnp.where(valid_p[None, :], d2, jnp.inf), axis=1)

    out = jax.lax.map(one, qq.reshape(k, chunk, q.shape[1]))
    return out.reshape(-1)[:n]


def chamfer_residuals(sim, obs, valid):
    """Per-point nearest-neighbour distances in both directions (set-to-set, ``(M + N,)``).

    Arguments:
        sim: simulated particles ``(N, D)``.
        obs: observed points ``(M, D)`` (invalid ones anywhere finite).
        valid: ``(M,)`` which observed points count.
    """
    all_sim = jnp.ones(sim.shape[:1], bool)
    obs_to_sim = jnp.where(valid, _chunked_min(obs, sim, all_sim), 0.0)
    sim_to_obs = _chunked_min(sim, obs, valid)
    return jnp.sqrt(jnp.concatenate([obs_to_sim, sim_to_obs]) + 1e-12)


# =========================================================================== data checks and pixels


def check_tracks(model: Model, positions: np.ndarray, point_ids) -> bool:
    """Raise :class:`ObservationError` unless tracked ``positions`` ``(T, N, D)`` fit the
    scene; returns whether the points are the particles themselves (matched by id)."""
    _, n, d = positions.shape
    if d != model.dim:
        raise ObservationError(f"observed positions are {d}-D but the scene is {model.dim}-D")
    by_id = point_ids == "particles"
    if by_id and n != model.num_particles:
        raise ObservationError(
            f"observation has point_ids='particles' with {n} points but the scene has {model.num_particles} particles"
        )
    return by_id


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=radius)


def _candidates(masks: np.ndarray, margin: int) -> list[np.ndarray]:
    """Per view, the flat indices of the dilated union over frames of the masks."""
    out = []
    for v in range(masks.shape[0]):
        union = np.any(masks[v] > 127, axis=0)
        region = np.flatnonzero(_dilate(union, margin))
        out.append(region)
    return out


def _fixed_pixels(rng, candidates, T, H, W, n, uniform_fraction):
    """``(T, V, n)`` flat pixel indices: mostly from each view's candidate region."""
    V = len(candidates)
    out = np.zeros((T, V, n), np.int32)
    n_uni = int(round(uniform_fraction * n)) if len(candidates) else n
    for v, cand in enumerate(candidates):
        for t in range(T):
            k = n - n_uni if len(cand) else 0
            a = rng.choice(cand, size=k, replace=k > len(cand)) if k else np.zeros(0, int)
            b = rng.choice(H * W, size=n - k, replace=(n - k) > H * W)
            out[t, v] = np.concatenate([a, b])
    return out


def _random_pixels(key, cand_table, cand_count, T, V, HW, n, n_uni):
    """Traced version of :func:`_fixed_pixels` (with replacement) for a PRNG key."""
    k1, k2 = jax.random.split(key)
    u = jax.random.uniform(k1, (T, V, n - n_uni))
    count = cand_count[None, :, None]
    idx = jnp.minimum((u * count.astype(u.dtype)).astype(jnp.int32), count - 1)
    a = jnp.take_along_axis(jnp.broadcast_to(cand_table[None], (T,) + cand_table.shape), idx, axis=2)
    b = jax.random.randint(k2, (T, V, n_uni), 0, HW, dtype=jnp.int32)
    return jnp.concatenate([a, b], axis=-1)


def particle_spacing(model: Model) -> float:
    """The particle spacing ``h = V0^(1/D)`` of the largest particle (m)."""
    return float(np.max(np.concatenate([np.asarray(b.vol0) for b in model.bodies]))) ** (1.0 / model.dim)


def lifted_layers(model: Model) -> np.ndarray:
    """z offsets of the layers a 2D scene is lifted to for rendering (a slab of 3 particle spacings)."""
    h = particle_spacing(model)
    return np.array([-h, 0.0, h])


def make_fit_renderer(kind, model: Model, **options):
    """A renderer covering the scene's whole domain at the particle spacing.

    ``kind`` is ``"volume"``, ``"surfels"`` or a renderer instance (returned unchanged). A 2D
    scene is rendered as a slab ``±1.5 h`` thick around z = 0 (its particles lifted to the
    layers :func:`lifted_layers`).
    """
    from ..render import AbstractRenderer, make_renderer

    if isinstance(kind, AbstractRenderer):
        return kind
    h = particle_spacing(model)
    lo, hi = np.asarray(model.grid.lo, float), np.asarray(model.grid.hi, float)
    if model.dim == 2:
        lo, hi = np.append(lo, -1.5 * h), np.append(hi, 1.5 * h)
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    return make_renderer(kind, corners, spacing=h, **options)


def observation_cameras(obs: Observation, dtype=jnp.float32):
    """The observation's cameras (one batched :class:`jaxmpm.render.Camera`), with clear errors
    for inconsistent image sizes."""
    from ..render import Camera

    arr = obs.masks if obs.masks is not None else obs.images
    V, T, H, W = np.shape(arr)[:4]
    if obs.masks is not None and obs.images is not None and np.shape(obs.images)[:4] != np.shape(obs.masks):
        raise ObservationError(
            f"masks {np.shape(obs.masks)} and images {np.shape(obs.images)[:4]} disagree in views, frames or size"
        )
    K = np.asarray(obs.intrinsics, float)
    for v in range(V):
        cx, cy = K[v, 0, 2], K[v, 1, 2]
        if not (0.0 < cx < W and 0.0 < cy < H):
            raise ObservationError(
                f"view {v}: the principal point ({cx:g}, {cy:g}) lies outside the {W}x{H} images: the masks/images "
                f"do not have the size the intrinsics were made for (expected about {2 * cx:g}x{2 * cy:g})"
            )
    return Camera(K, np.asarray(obs.cam_to_world, float), W, H, dtype=dtype)


def particle_colors(model: Model, obs: Observation, cams=None) -> np.ndarray:
    """Per-particle RGB from the first observed images: each particle's projection in every
    view where it falls inside the observed mask, averaged (occlusion is ignored, so interior
    particles take the colour of the surface in front of them)."""
    if obs.images is None:
        raise ObservationError("particle colours from images need 'images' in the observation")
    from ..render import mean_colors

    cams = observation_cameras(obs) if cams is None else cams
    x = np.concatenate([np.asarray(b.x0, float) for b in model.bodies])
    images = np.asarray(obs.images)[:, 0].astype(float) / 255.0
    masks = None if obs.masks is None else np.asarray(obs.masks)[:, 0] > 127
    return mean_colors(x, images, masks, cams.K, cams.cam_to_world).astype(np.float32)


# =========================================================================== terms


class Frames(eqx.Module):
    """What the residual terms read from a rollout: per-frame positions and velocities and the
    particles' masses and reference volumes (frame 0 is the initial state).

    Attributes:
        x, v: ``(F, N, D)`` positions (m) and velocities (m/s) at the output frames.
        mass: ``(N,)`` kg (kg/m in 2D); vol0: ``(N,)`` m^3 (m^2 in 2D).
    """

    x: Float[Array, "F N D"]
    v: Float[Array, "F N D"]
    mass: Float[Array, " N"]
    vol0: Float[Array, " N"]

    @classmethod
    def of(cls, traj: Trajectory) -> "Frames":
        return cls(traj.x, traj.v, traj.final.mass, traj.final.vol0)


class Term(eqx.Module):
    """The residuals of one kind of data (abstract; the concrete terms are final).

    ``residuals(frames, t0, key=None) -> (M,)`` compares a rollout's :class:`Frames` with the
    data at the observed times shifted by ``t0`` (s; cubic Hermite interpolation between
    frames, :func:`hermite`). Entries are scaled as the term's :class:`Layout` says. ``key``
    (image terms only) draws a fresh random pixel batch; without it the batch is fixed.
    """

    frame_dt: float = eqx.field(static=True)

    @abc.abstractmethod
    def residuals(self, frames: Frames, t0, key=None) -> Float[Array, " M"]:
        """The scaled residual vector."""


@dataclass
class Layout:
    """Host-side description of a term's residual entries.

    Attributes:
        name: ``"tracks"``, ``"silhouette"``, ``"rgb"`` or ``"probes"``.
        weight: the term's weight.
        count: informative residual entries (the Gauss–Newton covariance's sample size).
        groups: ``(M,)`` per entry its group, entries of one group sharing one error (one
            observed frame; one frame-length time bin of a probe); ``-1`` for entries that carry
            no data (NaN or out-of-window samples: their residual is 0).
        group_times, group_kinds, group_labels: per group its time (s), kind and a label.
    """

    name: str
    weight: float
    count: int
    groups: np.ndarray
    group_times: np.ndarray
    group_kinds: list
    group_labels: list


#: How a term scales its residuals: ``"term"``: ``sum(r**2) = weight * (the term's mean
#: squared error)`` (:func:`jaxmpm.fit`); ``"group"``: the sum of squares over each group is
#: that group's mean squared error (:func:`jaxmpm.discover`'s per-frame statistics).
NORMALISATIONS = ("term", "group")


def _check_normalise(normalise: str) -> None:
    if normalise not in NORMALISATIONS:
        raise JaxmpmError(f"normalise must be one of {NORMALISATIONS}, got {normalise!r}")


def _frame_labels(times) -> list[str]:
    return [f"t={t:.4g}s" for t in times]


class Tracks(Term):
    """Tracked points: per point and coordinate ``x_sim − x_obs`` when the points are the
    particles (``point_ids == "particles"``), else the Chamfer distances both ways per frame."""

    times: Float[Array, " T"]
    target: Float[Array, "T M D"]
    valid: Bool[Array, "T M"]
    scale: Float[Array, " T"]
    by_id: bool = eqx.field(static=True)

    def residuals(self, frames: Frames, t0, key=None):
        x = hermite(frames.x, frames.v, self.times, t0, self.frame_dt)  # (T, N, D)
        if self.by_id:
            r = jnp.where(self.valid[..., None], x - self.target, 0.0)
            return (self.scale[:, None, None] * r).reshape(-1)
        r = jax.lax.map(lambda args: chamfer_residuals(*args), (x, self.target, self.valid))
        return (self.scale[:, None] * r).reshape(-1)


def track_term(model: Model, obs: Observation, sel: np.ndarray, dtype, *, normalise: str = "term",
               weight: float = 1.0, window: np.ndarray | None = None) -> tuple[Tracks, Layout]:
    """The tracks term of the observed times ``sel`` (boolean ``(T_obs,)``), fitting those of
    them in ``window`` (boolean over the selected times; default all): the others keep their
    entries, at scale 0 (see :func:`build_objective`)."""
    _check_normalise(normalise)
    positions = np.asarray(obs.positions, float)[sel]
    times = np.asarray(obs.times, float)[sel]
    T, N, D = positions.shape
    on = np.ones(T, bool) if window is None else np.asarray(window, bool)
    by_id = check_tracks(model, positions, obs.point_ids)
    valid = ~np.any(np.isnan(positions), axis=-1)
    fitted = valid & on[:, None]
    if not fitted.any():
        raise ObservationError("the observed tracks are all NaN in the fitted time window")
    per_frame = N * D if by_id else N + model.num_particles
    if normalise == "term":  # the mean squared distance per point (m^2), times the weight
        n = int(fitted.sum()) if by_id else int(on.sum()) * per_frame
        scale = np.full(T, math.sqrt(weight / max(n, 1)))
    else:  # each frame's mean squared error per coordinate (per distance for Chamfer)
        scale = 1.0 / np.sqrt(np.maximum(valid.sum(axis=1) * D if by_id else valid.sum(axis=1) + model.num_particles, 1))
    term = Tracks(frame_dt=float(model.frame_dt), times=jnp.asarray(times, dtype),
                  target=jnp.asarray(np.where(valid[..., None], positions, 0.0), dtype), valid=jnp.asarray(valid),
                  scale=jnp.asarray(np.where(on, scale, 0.0), dtype), by_id=by_id)
    count = int(fitted.sum()) * D if by_id else int(fitted.sum()) + int(on.sum()) * model.num_particles
    layout = Layout("tracks", weight, count, np.repeat(np.where(on, np.arange(T), -1), per_frame), times,
                    ["tracks"] * T, _frame_labels(times))
    return term, layout


class Probes(Term):
    """Named time series of the state (:func:`probe_function`): ``probe_sim − probe_obs`` per
    sample. Probe functions see a state with the frame's positions, velocities, masses and
    reference volumes; their time derivatives for the interpolation come from a JVP along
    the velocities."""

    times: Float[Array, "P Tp"]
    target: Float[Array, "P Tp"]
    valid: Bool[Array, "P Tp"]
    scale: Float[Array, "P Tp"]
    model: Any
    fns: tuple = eqx.field(static=True)

    def frame_values(self, frames: Frames):
        """``(F, P)`` probe values at the frames and their time derivatives."""

        def one(x, v):
            st = make_state(x, v, frames.mass, frames.vol0)
            vals = [jax.jvp(lambda y, f=f: f(eqx.tree_at(lambda s: s.x, st, y), self.model), (x,), (v,))
                    for f in self.fns]
            return jnp.stack([a for a, _ in vals]), jnp.stack([b for _, b in vals])

        return jax.vmap(one)(frames.x, frames.v)

    def residuals(self, frames: Frames, t0, key=None):
        P, Pdot = self.frame_values(frames)
        out = []
        for p in range(len(self.fns)):
            sim = hermite(P[:, p], Pdot[:, p], self.times[p], t0, self.frame_dt)
            out.append(jnp.where(self.valid[p], sim - self.target[p], 0.0) * self.scale[p])
        return jnp.concatenate(out)


def probe_term(model: Model, obs: Observation, until: float | None, dtype, *, extra=None, normalise: str = "term",
               weight: float = 1.0) -> tuple[Probes, Layout]:
    """The probes term of the samples at times ``<= until`` (all when None)."""
    _check_normalise(normalise)
    names = list(obs.probe_names)
    fns = tuple(probe_function(n, extra) for n in names)
    pt = np.asarray(obs.probe_times, float)
    pv = np.asarray(obs.probe_values, float)
    keep = np.isfinite(pv) & np.isfinite(pt) & (pt >= 0)
    if until is not None:
        keep &= pt <= until + 1e-4 * model.frame_dt
    if not keep.any():
        raise ObservationError("the observed probe values are all NaN (or outside the fitted time window)")
    # groups: frame-length time bins of each probe (samples in a bin share one error)
    bins = np.where(keep, np.floor(np.where(keep, pt, 0.0) / model.frame_dt + 1e-6).astype(int), -1)
    gid = np.full(pt.shape, -1)
    gtime, gkind, glabel = [], [], []
    for p, n in enumerate(names):
        for b in np.unique(bins[p][bins[p] >= 0]):
            here = bins[p] == b
            gid[p, here] = len(gtime)
            gtime.append(float(np.mean(pt[p, here])))
            gkind.append(f"probe:{n}")
            glabel.append(n)
    if normalise == "term":
        scale = np.where(keep, math.sqrt(weight / int(keep.sum())), 0.0)
    else:
        counts = np.bincount(gid[gid >= 0], minlength=len(gtime))
        scale = np.where(gid >= 0, 1.0 / np.sqrt(np.maximum(counts[np.maximum(gid, 0)], 1)), 0.0)
    term = Probes(frame_dt=float(model.frame_dt), times=jnp.asarray(np.where(keep, pt, 0.0), dtype),
                  target=jnp.asarray(np.where(keep, pv, 0.0), dtype), valid=jnp.asarray(keep),
                  scale=jnp.asarray(scale, dtype), model=model, fns=fns)
    layout = Layout("probes", weight, int(keep.sum()), gid.reshape(-1), np.asarray(gtime), gkind, glabel)
    return term, layout


# --------------------------------------------------------------------------- images


class _PixelTerm(Term):
    """Image data compared at a batch of pixels per view and frame (abstract)."""

    times: Float[Array, " T"]
    cameras: Any
    renderer: Any
    lift: Float[Array, " L"]  # z offsets of the layers a 2D scene is lifted to (empty in 3D)
    masks: Any  # (T, V, H*W) uint8 or None
    fixed: Int[Array, "T V n"]
    cand_table: Int[Array, "V C"]
    cand_count: Int[Array, " V"]
    active: Bool[Array, " T"]  # the times fitted (the others are not rendered; their residuals are 0)
    n_uniform: int = eqx.field(static=True)

    def pixels(self, key):
        """The fixed batch, or a fresh random one drawn like it for a PRNG key."""
        if key is None:
            return self.fixed
        T, V, n = self.fixed.shape
        HW = self.masks.shape[-1] if self.masks is not None else self.cameras.height * self.cameras.width
        return _random_pixels(key, self.cand_table, self.cand_count, T, V, HW, n, self.n_uniform)

    def lifted(self, x):
        """Positions ``(..., N, D)`` as rendered: 3D as they are, 2D copied onto the layers ``lift``."""
        if x.shape[-1] == 3:
            return x
        layers = [jnp.concatenate([x, jnp.full(x.shape[:-1] + (1,), z, x.dtype)], axis=-1) for z in self.lift]
        return jnp.concatenate(layers, axis=-2)

    def positions(self, frames: Frames, t0):
        """``(T, N', 3)`` rendered positions at the observed times."""
        return self.lifted(hermite(frames.x, frames.v, self.times, t0, self.frame_dt))


class Silhouette(_PixelTerm):
    """Rendered soft silhouettes against the masks: ``alpha − mask`` per sampled pixel."""

    scale: Float[Array, " T"]

    def residuals(self, frames: Frames, t0, key=None):
        from ..render import render_pixels
        from ..render.losses import as_unit_float

        pix = self.pixels(key)
        x = self.positions(frames, t0)
        dtype = x.dtype

        def one(args):
            xt, pt, mt, on = args

            def compare(_):
                pred = render_pixels(self.renderer, xt, self.cameras, pt, silhouette_only=True)
                return pred - as_unit_float(jax.vmap(lambda m, p: m[p])(mt, pt), dtype)

            return jax.lax.cond(on, compare, lambda _: jnp.zeros(pt.shape, dtype), None)

        r = jax.lax.map(one, (x, pix, self.masks, self.active))
        return (self.scale[:, None, None] * r).reshape(-1)


class MaskedRGB(_PixelTerm):
    """Rendered colour against the images where the observed mask is set (PAC-NeRF's ray
    mask; every sampled pixel without masks): ``m (rgb − image)`` per pixel and channel,
    normalised by the sampled mask's sum so that ``sum(r**2) = weight × MSE``."""

    images: Any  # (T, V, H*W, 3) uint8
    colors: Any
    weight: float = eqx.field(static=True)

    def residuals(self, frames: Frames, t0, key=None):
        from ..render import render_pixels
        from ..render.losses import as_unit_float

        pix = self.pixels(key)
        x = self.positions(frames, t0)
        dtype = x.dtype

        def one(args):
            xt, pt, it, mt, on = args

            def compare(_):
                pred = render_pixels(self.renderer, xt, self.cameras, pt, self.colors).rgb
                target = as_unit_float(jax.vmap(lambda im, p: im[p])(it, pt), dtype)
                m = jnp.ones(pt.shape, dtype) if mt is None else as_unit_float(jax.vmap(lambda mm, p: mm[p])(mt, pt), dtype)
                return m[..., None] * (pred - target), jnp.sum(m)

            skip = lambda _: (jnp.zeros(pt.shape + (3,), dtype), jnp.zeros((), dtype))  # noqa: E731
            return jax.lax.cond(on, compare, skip, None)

        r, msum = jax.lax.map(one, (x, pix, self.images, self.masks, self.active))
        return math.sqrt(self.weight / 3.0) * r.reshape(-1) / jnp.sqrt(jnp.maximum(jnp.sum(msum), 1.0))


def image_terms(model: Model, obs: Observation, sel: np.ndarray, dtype, *, weights: dict, renderer, num_pixels: int,
                uniform_fraction: float = 0.25, margin: int | None = None, seed: int = 0, colors=None,
                normalise: str = "term", window: np.ndarray | None = None) -> list[tuple[_PixelTerm, Layout]]:
    """The silhouette and masked-RGB terms (those with a positive weight) of the observed
    times ``sel``, on one fixed pixel batch per view and frame: ``1 − uniform_fraction`` of
    it from the union over frames of each view's masks dilated by ``margin`` pixels (default
    5 % of the image size), the rest uniform over the image. A 2D scene is rendered lifted onto
    the layers :func:`lifted_layers`. Only the times in ``window`` (boolean over the selected
    times; default all) are rendered and fitted; the pixel batch is the same for every window."""
    _check_normalise(normalise)
    cams = observation_cameras(obs, dtype)
    V, H, W = cams.num_views, cams.height, cams.width
    times = np.asarray(obs.times, float)[sel]
    T = len(times)
    on = np.ones(T, bool) if window is None else np.asarray(window, bool)
    T_on = int(on.sum())
    groups = np.where(on, np.arange(T), -1)
    masks = None if obs.masks is None else np.asarray(obs.masks)[:, sel]
    images = None if obs.images is None else np.asarray(obs.images)[:, sel]
    n = int(min(num_pixels, H * W))
    if margin is None:
        margin = max(2, int(round(0.05 * max(H, W))))

    def candidates(frames):
        cand = _candidates(masks[:, frames], margin) if masks is not None else [np.arange(H * W)] * V
        return [c if len(c) else np.arange(H * W) for c in cand]

    # the pixels are drawn from the window's masks (as if only its times were observed); the
    # table is as long as the whole observation needs, so that its shape is the same in every window
    cand = candidates(on)
    L = max(len(c) for c in candidates(np.ones(T, bool)))
    fixed = np.zeros((T, V, n), np.int32)
    fixed[on] = _fixed_pixels(np.random.default_rng(seed), cand, T_on, H, W, n, uniform_fraction)
    shared = dict(
        frame_dt=float(model.frame_dt), times=jnp.asarray(times, dtype), cameras=cams, renderer=renderer,
        lift=jnp.asarray(lifted_layers(model) if model.dim == 2 else np.zeros(0), dtype),
        masks=None if masks is None else jnp.asarray(np.swapaxes(masks, 0, 1).reshape(T, V, H * W)),
        fixed=jnp.asarray(fixed),
        cand_table=jnp.asarray(np.stack([np.resize(c, L) for c in cand]).astype(np.int32)),
        cand_count=jnp.asarray([len(c) for c in cand], jnp.int32), active=jnp.asarray(on),
        n_uniform=int(round(uniform_fraction * n)),
    )
    out = []
    w_sil = weights.get("silhouette", 0.0)
    if masks is not None and w_sil > 0:
        per_frame = math.sqrt(w_sil / T_on) if normalise == "term" else 1.0
        term = Silhouette(scale=jnp.asarray(np.where(on, per_frame / math.sqrt(V * n), 0.0), dtype), **shared)
        out.append((term, Layout("silhouette", w_sil, T_on * V * n, np.repeat(groups, V * n), times,
                                 ["silhouette"] * T, _frame_labels(times))))
    w_rgb = weights.get("rgb", 0.0)
    if images is not None and w_rgb > 0:
        if normalise != "term":
            raise JaxmpmError("the masked-RGB term is normalised over the whole term only")
        if isinstance(colors, str) and colors == "auto":
            colors = particle_colors(model, obs, cams)
        term = MaskedRGB(images=jnp.asarray(np.swapaxes(images, 0, 1).reshape(T, V, H * W, 3)),
                         colors=None if colors is None else jnp.asarray(colors, dtype), weight=w_rgb, **shared)
        out.append((term, Layout("rgb", w_rgb, T_on * V * n * 3, np.repeat(groups, V * n * 3), times,
                                 ["rgb"] * T, _frame_labels(times))))
    return out


# =========================================================================== the objective


class Residuals(eqx.Module):
    """The residual vector of a parameter set (the pure part of an :class:`Objective`).

    A pytree: the rollout over ``length`` output frames, of which the first ``active`` are
    simulated (:func:`jaxmpm.simulate`'s ``active``), compared with the data by the terms.
    Objectives of one observation over different windows differ only in arrays (``active``,
    the terms' scales), so a function compiled for one (``equinox.filter_jit``) serves them
    all: ``fit``'s stages compile their residual program once per set of fitted names.

    ``__call__(params, key=None) -> (M,)``: NaN everywhere when the rollout is unhealthy.
    """

    model: Model
    terms: tuple
    active: Int[Array, ""]
    length: int = eqx.field(static=True)
    checkpoint: str | None = eqx.field(static=True)
    cfl_limit: float = eqx.field(static=True)

    def simulate(self, params: Params) -> Trajectory:
        return simulate(self.model, params, checkpoint=self.checkpoint, frames=self.length, active=self.active)

    def term_residuals(self, traj: Trajectory, key=None) -> list:
        """Per term its residual vector for a rollout (no health check)."""
        frames = Frames.of(traj)
        t0 = jnp.zeros((), traj.x.dtype)
        keys = [None] * len(self.terms) if key is None else list(jax.random.split(key, len(self.terms)))
        return [t.residuals(frames, t0, k) for t, k in zip(self.terms, keys)]

    def __call__(self, params: Params, key=None):
        traj = self.simulate(params)
        r = jnp.concatenate(self.term_residuals(traj, key))
        return jnp.where(jnp.any(unhealthy(traj, self.cfl_limit)), jnp.nan, r)


class Objective:
    """The loss of a parameter set against an observation (over a time window).

    Built by :func:`build_objective`. ``residuals(params, key=None)`` is the weighted
    residual vector (NaN everywhere when the simulation is unhealthy, :func:`jaxmpm.step.unhealthy`:
    NaN values, a CFL number above ``cfl_limit``, energy growth, a stress-wave CFL number above
    1); ``loss(params, key=None) = sum(residuals**2)``. The vector has an entry for every
    observed sample, those outside the window at 0 (the same length in every window).
    ``residuals_of(trajectory)`` evaluates a rollout made elsewhere (e.g. inside
    :func:`jaxmpm.sweep`) over :attr:`length` frames.

    Attributes:
        model: the model (its substeps are those of the fit's current dt).
        program: the :class:`Residuals` (a pytree; ``residuals`` calls it).
        frames: output frames simulated (covering the window).
        length: output frames of the rollout's arrays (covering every observed time).
        terms: the terms' names and weights.
        layouts: per term its :class:`Layout`.
        count: informative residual entries (for the Gauss–Newton covariance).
        until: last observed time included (seconds), or None for all.
        times: the observed times in the window (seconds).
    """

    def __init__(self, program: Residuals, layouts, frames: int, until, times):
        self.program = program
        self.model = program.model
        self.layouts = list(layouts)
        self.frames = frames
        self.length = program.length
        self.until = until
        self.times = times

    @property
    def terms(self) -> dict[str, float]:
        return {layout.name: layout.weight for layout in self.layouts}

    @property
    def count(self) -> int:
        return sum(layout.count for layout in self.layouts)

    def simulate(self, params: Params) -> Trajectory:
        return self.program.simulate(params)

    def residuals(self, params: Params, key=None):
        return self.program(params, key)

    def residuals_of(self, traj: Trajectory, key=None):
        """The residual vector of a rollout (no health check)."""
        return jnp.concatenate(self.program.term_residuals(traj, key))

    def loss(self, params: Params, key=None):
        r = self.residuals(params, key)
        return jnp.sum(r * r)

    def term_losses(self, params: Params) -> dict[str, float]:
        """Each term's share of the loss (a diagnostic; runs one simulation)."""
        traj = eqx.filter_jit(self.program.simulate)(params)
        return {layout.name: float(jnp.sum(r**2))
                for layout, r in zip(self.layouts, self.program.term_residuals(traj))}

    def health(self, params: Params) -> str | None:
        """None when the rollout at ``params`` is healthy over the window, else the one line
        of :func:`jaxmpm.step.health_message` naming the first unhealthy frame."""
        traj = simulate(self.model, params, checkpoint=None, frames=self.length)
        return health_message(self.model, traj.head(self.frames), self.cfl_limit)

    @property
    def cfl_limit(self) -> float:
        return self.program.cfl_limit


def _default_weights(obs: Observation) -> dict[str, float]:
    return {
        "tracks": 1.0 if obs.positions is not None else 0.0,
        "silhouette": 1.0 if obs.masks is not None else 0.0,
        # GIC's released configs put weight 0 on RGB when masks exist; PAC-NeRF uses RGB only
        "rgb": 1.0 if (obs.images is not None and obs.masks is None) else 0.0,
        "probes": 1.0 if obs.probe_names is not None else 0.0,
    }


def build_objective(
    model: Model,
    observation: Observation,
    *,
    weights: dict[str, float] | None = None,
    until: float | None = None,
    probes: dict[str, ProbeFn] | None = None,
    renderer: Any = "volume",
    num_pixels: int = 256,
    uniform_fraction: float = 0.25,
    pixel_margin: int | None = None,
    pixel_seed: int = 0,
    colors: Any = "auto",
    checkpoint: str | None = "nested",
    cfl_limit: float = 1.0,
) -> Objective:
    """The weighted loss of ``observation`` for ``model`` (see the module docstring).

    Arguments:
        model: the model whose parameters are fitted.
        observation: the data; every present kind of data with a positive weight is used.
        weights: per term (``"tracks"``, ``"silhouette"``, ``"rgb"``, ``"probes"``); missing
            terms take the defaults: 1 for tracks, silhouettes and probes when present; RGB 1
            only when images come without masks (with masks, 0 as in GIC's configs).
        until: use only observed samples at times ``<= until`` (a growing frame window).
        probes: extra probe functions by name (see :func:`probe_function`).
        renderer: ``"volume"``, ``"surfels"`` or a renderer instance (image terms).
        num_pixels: pixels rendered per view and frame.
        uniform_fraction: the share of them drawn uniformly over the image (the rest from
            the dilated union of each view's observed masks).
        pixel_margin: dilation of that union, in pixels (default 5 % of the image size).
        pixel_seed: seed of the fixed pixel batch used when no PRNG key is given.
        colors: particle colours for RGB: ``"auto"`` (from the first observed images),
            None (the renderer's default colour) or an ``(N, 3)`` array.
        checkpoint: checkpoint policy of the rollouts.
        cfl_limit: rollouts whose CFL number exceeds this count as unhealthy (NaN loss; the
            health check is :func:`jaxmpm.step.unhealthy`).

    Raises:
        ObservationError: nothing to fit, too few observed times, mismatched shapes.
    """
    if not isinstance(observation, Observation):
        raise ObservationError(f"expected an Observation, got {type(observation).__name__}")
    w = _default_weights(observation)
    for k, v in (weights or {}).items():
        if k not in TERMS:
            raise JaxmpmError(f"unknown loss term {k!r}; expected one of {TERMS}")
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise JaxmpmError(f"weight of {k!r} must be a finite number >= 0, got {v!r}")
        w[k] = float(v)
    present = {
        "tracks": observation.positions is not None,
        "silhouette": observation.masks is not None,
        "rgb": observation.images is not None,
        "probes": observation.probe_names is not None,
    }
    for k, v in w.items():
        if v > 0 and not present[k]:
            raise ObservationError(f"loss term {k!r} has weight {v:g} but the observation has no data for it")
    if not any(v > 0 for v in w.values()):
        raise ObservationError("no loss term has a positive weight for the data in this observation")
    times = np.asarray(observation.times, float)
    if np.any(times < 0):
        raise ObservationError("observed times must be >= 0 (seconds since the scene's start)")
    window = np.ones(len(times), bool) if until is None else times <= until + 1e-4 * model.frame_dt
    if not window.any():
        raise ObservationError(f"no observed time lies within the window t <= {until:g} s")
    t_probe, t_probe_all = [], []
    if w["probes"] > 0:
        pt = np.asarray(observation.probe_times, float)
        ok = np.isfinite(pt) & (pt >= 0)
        t_probe_all = pt[ok].tolist()
        t_probe = pt[ok & ((pt <= until + 1e-4 * model.frame_dt) if until is not None else True)].tolist()
    imaged = any(w[k] > 0 for k in ("tracks", "silhouette", "rgb"))
    t_data = times[window].tolist() if imaged else []
    t_all = np.asarray(t_data + t_probe, float)
    if len(np.unique(np.round(t_all / model.frame_dt, 6))) < 2 or np.max(t_all) <= 0:
        raise ObservationError(
            f"too few observed frames to fit: need samples at two or more distinct times after t = 0, got {len(t_all)}"
        )
    frames = frames_needed(model, t_all)
    length = frames_needed(model, np.asarray((times.tolist() if imaged else []) + t_probe_all + [0.0], float))
    dtype = model.bodies[0].x0.dtype
    every = np.ones(len(times), bool)
    terms: list[tuple[Term, Layout]] = []
    if w["tracks"] > 0:
        terms.append(track_term(model, observation, every, dtype, weight=w["tracks"], window=window))
    if w["silhouette"] > 0 or w["rgb"] > 0:
        terms += image_terms(model, observation, every, dtype, weights=w, renderer=make_fit_renderer(renderer, model),
                             num_pixels=num_pixels, uniform_fraction=uniform_fraction, margin=pixel_margin,
                             seed=pixel_seed, colors=colors, window=window)
    if w["probes"] > 0:
        terms.append(probe_term(model, observation, until, dtype, extra=probes, weight=w["probes"]))
    program = Residuals(model, tuple(t for t, _ in terms), jnp.asarray(frames, jnp.int32), length, checkpoint,
                        float(cfl_limit))
    return Objective(program, [layout for _, layout in terms], frames, until, times[window])
