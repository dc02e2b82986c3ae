"""Loss terms for identification: tracks, silhouettes, masked RGB and probes.

Every term turns a simulated :class:`~jaxmpm.step.Trajectory` into a **residual vector**
``r`` scaled so that ``sum(r**2) = weight * (mean squared error of the term)``; the sum of
squares of all terms' residuals is the scalar loss. Levenberg–Marquardt works on the
residuals; Adam and BFGS on the scalar.

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

Probes are functions ``fn(state, model) -> scalar`` looked up by name
(:func:`probe_function`): ``front_x`` (the largest x of any particle, plus half a particle
spacing: the leading edge), ``back_x``, ``top_y``/``height`` (vertical), ``centroid_x``,
..., and parameterised names such as ``gauge@0.3`` (the height of the material column at
x = 0.3 m; ``gauge@0.3,0.1`` at x = 0.3, z = 0.1 in 3D). Register others with
:func:`register_probe` (e.g. ``register_probe("gauge_H2", gauge(0.582, 0.0))``) or pass
``probes={name: fn}`` to :func:`build_objective`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import JaxmpmError, ObservationError
from ..model import Model, Params
from ..observe import Observation
from ..state import State
from ..step import Trajectory, simulate

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
    "frame_interpolation",
    "frames_needed",
    "chamfer_residuals",
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
]


def probe_names() -> list[str]:
    """The registered and built-in probe names (patterns shown with placeholders)."""
    return sorted(_REGISTRY) + ["front_x|y|z", "back_x|y|z", "top_y", "height", "centroid_x|y|z", "gauge@X[,Z]"]


def probe_function(name: str, extra: dict[str, ProbeFn] | None = None) -> ProbeFn:
    """The probe function for ``name``: from ``extra``, the registry, or a built-in pattern.

    Raises:
        ObservationError: unknown probe names (the message lists what is known).
    """
    if extra and name in extra:
        return extra[name]
    if name in _REGISTRY:
        return _REGISTRY[name]
    for pattern, factory in _PATTERNS:
        m = pattern.fullmatch(name)
        if m:
            try:
                return factory(*[g for g in m.groups() if g is not None])
            except ValueError:
                break
    raise ObservationError(
        f"unknown probe {name!r}: register it with jaxmpm.identify.register_probe({name!r}, fn) or pass "
        f"probes={{{name!r}: fn}}; known probes: {', '.join(probe_names())}"
    )


# =========================================================================== time sampling


def frame_interpolation(frame_dt: float, times: np.ndarray, num_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame indices ``i0, i1`` and weights ``a`` so that ``x(t) = (1-a) x[i0] + a x[i1]``."""
    s = np.asarray(times, float) / frame_dt
    i0 = np.clip(np.floor(s + 1e-6).astype(int), 0, num_frames - 1)
    i1 = np.minimum(i0 + 1, num_frames - 1)
    a = np.where(i1 > i0, np.clip(s - i0, 0.0, 1.0), 0.0)
    a = np.where(a < 1e-6, 0.0, a)
    return i0, i1, a


def frames_needed(model: Model, times: np.ndarray) -> int:
    """Output frames (including t = 0) a simulation needs to cover ``times``."""
    return max(2, int(math.ceil(float(np.max(times)) / model.frame_dt - 1e-6)) + 1)


def _interp(arr, i0, i1, a):
    """``(1-a) arr[i0] + a arr[i1]`` along the leading axis (``a`` broadcast on the right)."""
    a = jnp.asarray(a, arr.dtype).reshape(a.shape + (1,) * (arr.ndim - 1))
    return (1.0 - a) * arr[i0] + a * arr[i1]


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


# =========================================================================== terms


@dataclass
class _Term:
    """One loss term (internal): ``residuals(traj, key) -> (R,)`` already weighted."""

    name: str
    weight: float
    count: int  # number of informative residual entries (for the Gauss–Newton covariance)
    fn: Callable[[Trajectory, Any], jnp.ndarray]
    info: dict = field(default_factory=dict)


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


def _track_term(model: Model, obs: Observation, sel: np.ndarray, frames: int, weight: float) -> _Term:
    positions = np.asarray(obs.positions, float)[sel]
    T, N, D = positions.shape
    by_id = check_tracks(model, positions, obs.point_ids)
    valid = ~np.any(np.isnan(positions), axis=-1)
    if not valid.any():
        raise ObservationError("the observed tracks are all NaN in the fitted time window")
    i0, i1, a = frame_interpolation(model.frame_dt, np.asarray(obs.times, float)[sel], frames)
    dtype = model.bodies[0].x0.dtype
    obs_j = jnp.asarray(np.where(valid[..., None], positions, 0.0), dtype)
    valid_j = jnp.asarray(valid)
    sw = math.sqrt(weight)

    if by_id:
        scale = sw / math.sqrt(max(int(valid.sum()), 1))

        def fn(traj, key=None):
            x = _interp(traj.x, i0, i1, a)
            r = jnp.where(valid_j[..., None], x - obs_j, 0.0)
            return scale * r.reshape(-1)

        count = int(valid.sum()) * D
    else:

        def fn(traj, key=None):
            x = _interp(traj.x, i0, i1, a)
            r = jax.lax.map(lambda args: chamfer_residuals(*args), (x, obs_j, valid_j))
            return (sw / math.sqrt(r.size)) * r.reshape(-1)

        count = int(valid.sum()) + T * model.num_particles
    return _Term("tracks", weight, count, fn, {"points": N, "chamfer": not by_id})


def _probe_term(model: Model, obs: Observation, until: float | None, frames: int, weight: float, extra) -> tuple[_Term, dict]:
    names = list(obs.probe_names)
    fns = {n: probe_function(n, extra) for n in names}
    pt = np.asarray(obs.probe_times, float)
    pv = np.asarray(obs.probe_values, float)
    keep = np.isfinite(pv) & np.isfinite(pt) & (pt >= 0)
    if until is not None:
        keep &= pt <= until + 1e-4 * model.frame_dt
    if not keep.any():
        raise ObservationError("the observed probe values are all NaN (or outside the fitted time window)")
    dtype = model.bodies[0].x0.dtype
    rows = []
    for p, n in enumerate(names):
        t = np.where(keep[p], pt[p], 0.0)
        i0, i1, a = frame_interpolation(model.frame_dt, t, frames)
        rows.append((n, i0, i1, a, jnp.asarray(np.where(keep[p], pv[p], 0.0), dtype), jnp.asarray(keep[p])))
    scale = math.sqrt(weight) / math.sqrt(int(keep.sum()))

    def fn(traj, key=None):
        out = []
        for n, i0, i1, a, values, ok in rows:
            sim = _interp(traj.extra[n], i0, i1, a)
            out.append(jnp.where(ok, sim - values, 0.0))
        return scale * jnp.concatenate(out)

    return _Term("probes", weight, int(keep.sum()), fn, {"names": names}), fns


# --------------------------------------------------------------------------- images


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


def make_fit_renderer(kind, model: Model, **options):
    """A renderer covering the scene's whole domain at the particle spacing (3D scenes only).

    ``kind`` is ``"volume"``, ``"surfels"`` or a renderer instance (returned unchanged).
    """
    from ..render import AbstractRenderer, make_renderer

    if isinstance(kind, AbstractRenderer):
        return kind
    if model.dim != 3:
        raise JaxmpmError("image losses (silhouettes, RGB) need a 3D scene")
    h = float(np.max(np.concatenate([np.asarray(b.vol0) for b in model.bodies]))) ** (1.0 / 3.0)
    lo, hi = np.asarray(model.grid.lo, float), np.asarray(model.grid.hi, float)
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    return make_renderer(kind, corners, spacing=h, **options)


def _check_cameras(obs: Observation, dtype=jnp.float32):
    """Cameras from the observation, with clear errors for inconsistent image sizes."""
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


def _image_terms(
    model, obs, sel, frames, weights, renderer, num_pixels, uniform_fraction, margin, seed, colors
) -> list[_Term]:
    from ..render import render_pixels
    from ..render.losses import as_unit_float

    dtype = model.bodies[0].x0.dtype
    cams = _check_cameras(obs, dtype)
    V, H, W = cams.num_views, cams.height, cams.width
    times = np.asarray(obs.times, float)[sel]
    T = len(times)
    i0, i1, a = frame_interpolation(model.frame_dt, times, frames)
    masks = None if obs.masks is None else np.asarray(obs.masks)[:, sel]
    images = None if obs.images is None else np.asarray(obs.images)[:, sel]
    n = int(min(num_pixels, H * W))
    if margin is None:
        margin = max(2, int(round(0.05 * max(H, W))))
    cand = _candidates(masks, margin) if masks is not None else [np.arange(H * W)] * V
    cand = [c if len(c) else np.arange(H * W) for c in cand]
    rng = np.random.default_rng(seed)
    fixed = jnp.asarray(_fixed_pixels(rng, cand, T, H, W, n, uniform_fraction))
    n_uni = int(round(uniform_fraction * n))
    L = max(len(c) for c in cand)
    cand_table = jnp.asarray(np.stack([np.resize(c, L) for c in cand]).astype(np.int32))
    cand_count = jnp.asarray([len(c) for c in cand], jnp.int32)
    # (T, V, H*W[, 3]) targets, frames first so they can be gathered per frame
    tmask = None if masks is None else jnp.asarray(np.swapaxes(masks, 0, 1).reshape(T, V, H * W))
    timg = None if images is None else jnp.asarray(np.swapaxes(images, 0, 1).reshape(T, V, H * W, 3))
    renderer = make_fit_renderer(renderer, model)
    if isinstance(colors, str) and colors == "auto":
        colors = None if images is None else particle_colors(model, obs, cams)
    col = None if colors is None else jnp.asarray(colors, dtype)

    def pixels_for(key):
        if key is None:
            return fixed
        return _random_pixels(key, cand_table, cand_count, T, V, H * W, n, n_uni)

    def positions(traj):
        return _interp(traj.x, i0, i1, a)

    terms = []
    w_sil = weights.get("silhouette", 0.0)
    if masks is not None and w_sil > 0:
        scale = math.sqrt(w_sil / (T * V * n))

        def sil(traj, key=None):
            pix = pixels_for(key)
            x = positions(traj)

            def one(args):
                xt, pt, mt = args
                pred = render_pixels(renderer, xt, cams, pt, silhouette_only=True)
                target = as_unit_float(jax.vmap(lambda m, p: m[p])(mt, pt), dtype)
                return pred - target

            return scale * jax.lax.map(one, (x, pix, tmask)).reshape(-1)

        terms.append(_Term("silhouette", w_sil, T * V * n, sil, {"pixels": n, "views": V}))
    w_rgb = weights.get("rgb", 0.0)
    if images is not None and w_rgb > 0:
        # weights: the observed mask (PAC-NeRF's masked RGB); all sampled pixels without masks
        count = T * V * n * 3

        def rgb(traj, key=None):
            pix = pixels_for(key)
            x = positions(traj)

            def one(args):
                xt, pt, it, mt = args
                pred = render_pixels(renderer, xt, cams, pt, col).rgb
                target = as_unit_float(jax.vmap(lambda im, p: im[p])(it, pt), dtype)
                if mt is None:
                    m = jnp.ones(pt.shape, dtype)
                else:
                    m = as_unit_float(jax.vmap(lambda mm, p: mm[p])(mt, pt), dtype)
                return m[..., None] * (pred - target), jnp.sum(m)

            r, msum = jax.lax.map(one, (x, pix, timg, tmask))
            return math.sqrt(w_rgb / 3.0) * r.reshape(-1) / jnp.sqrt(jnp.maximum(jnp.sum(msum), 1.0))

        terms.append(_Term("rgb", w_rgb, count, rgb, {"pixels": n, "views": V}))
    return terms


def particle_colors(model: Model, obs: Observation, cams=None) -> np.ndarray:
    """Per-particle RGB from the first observed images: each particle's projection in every
    view where it falls inside the observed mask, averaged (occlusion is ignored, so interior
    particles take the colour of the surface in front of them)."""
    if obs.images is None:
        raise ObservationError("particle colours from images need 'images' in the observation")
    cams = _check_cameras(obs) if cams is None else cams
    x = np.concatenate([np.asarray(b.x0, float) for b in model.bodies])
    images = np.asarray(obs.images)[:, 0].astype(float) / 255.0
    masks = None if obs.masks is None else np.asarray(obs.masks)[:, 0] > 127
    V, H, W = images.shape[:3]
    total, count = np.zeros((len(x), 3)), np.zeros(len(x))
    K, P = np.asarray(cams.K, float), np.asarray(cams.cam_to_world, float)
    for v in range(V):
        R, o = P[v, :3, :3], P[v, :3, 3]
        pc = (x - o) @ R
        z = pc[:, 2]
        uv = (pc @ K[v].T)[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None]
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
        if masks is not None:
            ok[ok] &= masks[v, row[ok], col[ok]]
        total[ok] += images[v, row[ok], col[ok]]
        count[ok] += 1
    mean = total.sum(0) / max(count.sum(), 1)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], mean).astype(np.float32)


# =========================================================================== the objective


class Objective:
    """The loss of a parameter set against an observation (over a time window).

    Built by :func:`build_objective`. ``residuals(params, key=None)`` is the weighted
    residual vector (NaN everywhere when the simulation is unhealthy: NaN values or a CFL
    number above ``cfl_limit``); ``loss(params, key=None) = sum(residuals**2)``.

    Attributes:
        model: the model (its substeps are those of the fit's current dt).
        frames: output frames simulated (covering the window).
        terms: the terms' names and weights.
        count: informative residual entries (for the Gauss–Newton covariance).
        until: last observed time included (seconds), or None for all.
    """

    def __init__(self, model, terms, frames, observe, checkpoint, cfl_limit, until, times):
        self.model = model
        self._terms = terms
        self.frames = frames
        self._observe = observe
        self.checkpoint = checkpoint
        self.cfl_limit = cfl_limit
        self.until = until
        self.times = times

    @property
    def terms(self) -> dict[str, float]:
        return {t.name: t.weight for t in self._terms}

    @property
    def count(self) -> int:
        return sum(t.count for t in self._terms)

    def simulate(self, params: Params) -> Trajectory:
        return simulate(self.model, params, checkpoint=self.checkpoint, observe=self._observe, frames=self.frames)

    @staticmethod
    def healthy(traj: Trajectory, cfl_limit: float):
        return ~jnp.any(traj.nan) & jnp.all(traj.cfl <= cfl_limit)

    def residuals(self, params: Params, key=None):
        traj = self.simulate(params)
        r = self._residuals_of(traj, key)
        return jnp.where(self.healthy(traj, self.cfl_limit), r, jnp.nan)

    def _residuals_of(self, traj, key=None):
        keys = [None] * len(self._terms) if key is None else list(jax.random.split(key, len(self._terms)))
        return jnp.concatenate([t.fn(traj, k) for t, k in zip(self._terms, keys)])

    def loss(self, params: Params, key=None):
        r = self.residuals(params, key)
        return jnp.sum(r * r)

    def term_losses(self, params: Params) -> dict[str, float]:
        """Each term's share of the loss (a diagnostic; runs one simulation)."""
        traj = jax.jit(self.simulate)(params)
        return {t.name: float(jnp.sum(t.fn(traj, None) ** 2)) for t in self._terms}

    def health(self, params: Params) -> tuple[bool, str]:
        """Whether the rollout at ``params`` is healthy, and a message naming the first bad frame."""
        traj = jax.jit(lambda p: self.simulate(p))(params)
        cfl, nan = np.asarray(traj.cfl), np.asarray(traj.nan)
        bad = nan | ~(cfl <= self.cfl_limit)
        if not bad.any():
            return True, ""
        i = int(np.argmax(bad))
        why = "NaN values appeared" if nan[i] else f"the CFL number reached {cfl[i]:.2f} (> {self.cfl_limit})"
        return False, f"unstable at frame {i} (t = {i * self.model.frame_dt:.4g} s): {why}"


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
        cfl_limit: rollouts whose CFL number exceeds this count as unhealthy (NaN loss).

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
    sel = np.ones(len(times), bool) if until is None else times <= until + 1e-4 * model.frame_dt
    if not sel.any():
        raise ObservationError(f"no observed time lies within the window t <= {until:g} s")
    t_probe = []
    if w["probes"] > 0:
        pt = np.asarray(observation.probe_times, float)
        ok = np.isfinite(pt) & (pt >= 0) & ((pt <= until + 1e-4 * model.frame_dt) if until is not None else True)
        t_probe = pt[ok].tolist()
    t_data = times[sel].tolist() if any(w[k] > 0 for k in ("tracks", "silhouette", "rgb")) else []
    t_all = np.asarray(t_data + t_probe, float)
    if len(np.unique(np.round(t_all / model.frame_dt, 6))) < 2 or np.max(t_all) <= 0:
        raise ObservationError(
            f"too few observed frames to fit: need samples at two or more distinct times after t = 0, got {len(t_all)}"
        )
    frames = frames_needed(model, t_all)
    terms: list[_Term] = []
    if w["tracks"] > 0:
        terms.append(_track_term(model, observation, sel, frames, w["tracks"]))
    if w["silhouette"] > 0 or w["rgb"] > 0:
        terms += _image_terms(model, observation, sel, frames, w, renderer, num_pixels, uniform_fraction,
                              pixel_margin, pixel_seed, colors)
    observe = None
    if w["probes"] > 0:
        term, fns = _probe_term(model, observation, until, frames, w["probes"], probes)
        terms.append(term)

        def observe(state, fns=fns):
            return {n: f(state, model) for n, f in fns.items()}

    return Objective(model, terms, frames, observe, checkpoint, cfl_limit, until, times[sel])
