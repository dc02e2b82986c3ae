"""Initial velocity and gravity from the free-fall frames of the silhouettes.

Per frame, the body's centre is triangulated from the views: the ray through each view's
silhouette centroid (the mean direction of the rays through the mask's pixels) and the point
nearest to all of them (least squares). A freely falling body moves rigidly (it carries no
stress), so its silhouettes keep their size: the free-fall frames are the leading frames whose
silhouette areas, corrected for the distance to each camera and the angle off its axis
(``area × d² cos³θ``, the image area of a small rigid body being ∝ ``1 / (d² cos³θ)``), stay
within :data:`SHAPE_TOLERANCE` of the first frame's (median over the views), and whose
centres one parabola ``c(t) = c0 + v0 t + g t² / 2`` fits within :data:`FREE_FALL_TOLERANCE`
cells (RMS). Contact is the first frame that breaks either. AS-DiffMPM estimates the initial
velocity and gravity from that phase; here ``g`` needs 3 free-fall frames, and ``v0`` from 2
frames is corrected by the scene's prior gravity (``v0 = Δc/Δt − g Δt / 2``; at 24 fps the
correction is 0.2 m/s).

The shape test matters: a parabola with a free ``g`` fits any smooth centre motion over a few
frames, including a droplet's spreading after it has landed (measured on ``jaxmpm demo
--video``'s droplet: without it 6 "free-fall" frames and g pointing up; its silhouettes grew
by 8 % (median) in the first frame after contact, against 1 % before).

The shape test needs masks whose areas are steadier than its tolerance. Where they are not
(:func:`area_noise` above :data:`AREA_NOISE_LIMIT`, as with masks whose borders move a pixel or
two either way at a low resolution: σ ≈ 0.45 measured on the 96 px drop datasets with
``jitter``) it would end every free fall at frame 1. With a prior gravity the centres then stand
in for it: a frame joins while its centre lies within the tolerance of where the parabola with
the prior's ``g`` through the frames before it (``c0`` and ``v0`` fitted) puts it, so a third
frame is already tested; ``g`` is not measured (the frames were chosen with it). A body that
lands is stopped by the collider, which that parabola does not bend to. A body supported from
the start (resting on a collider, or sliding on it) fails that parabola (at 24 fps at the third
frame). Where its centres follow a straight line (no acceleration: each next centre within the
tolerance of where the line through the frames before it puts it) past the frame the parabola
rejected, as a body that fell visibly before it landed does not, the body is reported as
supported (no free fall) and given that line's velocity, not the parabola's, which would be
``−g Δt / 2`` from 2 frames (0.2 m/s upwards at 24 fps) for a body at rest. Where the video is
too short for the parabola to fail, the two cannot be told apart. With clean masks the free
``g`` parabola finds a resting body at rest, with ``g ≈ 0``.

The centroid of a silhouette is the projection of the body's centre only for a convex body
seen from afar; the error is the same in every frame while the body keeps its shape (free
fall), so it moves ``c0``, not ``v0`` or ``g``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ObservationError

__all__ = ["FreeFall", "FREE_FALL_TOLERANCE", "SHAPE_TOLERANCE", "AREA_NOISE_LIMIT", "area_noise", "silhouette_rays",
           "triangulate", "free_fall"]

#: RMS residual (in cells of the scene's dx) below which frames count as free fall.
FREE_FALL_TOLERANCE = 0.1
#: Largest median relative change of the distance-corrected silhouette areas in free fall.
SHAPE_TOLERANCE = 0.05
#: Area noise (:func:`area_noise`) above which the shape test is left out where a prior gravity
#: can stand in for it: with σ = 0.1 the median over the views of a frame's relative change
#: from frame 0 is about 0.95 σ = 0.095 from the noise alone, so the test would end nearly every
#: free fall at frame 1. Measured on the 96 px drop datasets: 0.016–0.054 (clean, shifted,
#: missing-view, blurred and dark masks; contact's own deformation included), 0.45–0.47
#: (borders jittered 1–2 px); on the sysid benchmark's reduced silhouette cases (48 px):
#: 0.020–0.046.
AREA_NOISE_LIMIT = 2 * SHAPE_TOLERANCE


@dataclass(frozen=True)
class FreeFall:
    """What the free-fall frames say.

    Attributes:
        centres: ``(T, 3)`` triangulated body centre per frame, m (NaN where fewer than 2
            views see the body).
        spread: ``(T,)`` RMS distance of the centre rays from ``centres``, m.
        size_change: ``(T,)`` median over the views of the relative change of the
            distance-corrected silhouette area since frame 0.
        frames: number of leading frames of the free fall (contact at the next one).
        velocity: ``(3,)`` initial velocity, m/s (None with fewer than 2 free-fall frames and
            no supported frames).
        gravity: ``(3,)`` acceleration of the free fall, m/s² (None with fewer than 3).
        residual: RMS residual of the parabola over the free-fall frames, m.
        area_noise: robust σ of the silhouettes' relative area from frame to frame
            (:func:`area_noise`; NaN with fewer than 3 frames).
        shape_tested: whether the shape test decided the free fall; False where the masks'
            area noise exceeds :data:`AREA_NOISE_LIMIT` and the prior gravity's parabola
            decided it.
        supported: where the prior gravity's parabola decided (``shape_tested`` False) and
            rejected a frame, the number of leading frames whose centres follow a straight line
            within the tolerance, where that line reaches past the rejected frame: a body
            supported from the start, whose :attr:`velocity` is that line's (``frames`` is then
            1); 0 otherwise.
    """

    centres: np.ndarray
    spread: np.ndarray
    size_change: np.ndarray
    frames: int
    velocity: np.ndarray | None
    gravity: np.ndarray | None
    residual: float
    area_noise: float = float("nan")
    shape_tested: bool = True
    supported: int = 0

    def gravity_direction(self) -> np.ndarray | None:
        """Unit vector of :attr:`gravity` (None without it)."""
        return None if self.gravity is None else self.gravity / np.linalg.norm(self.gravity)


def silhouette_rays(masks: np.ndarray, cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per view and frame, the ray through the silhouette's centroid.

    Arguments:
        masks: ``(V, T, H, W)`` bool.
        cameras: a :class:`jaxmpm.render.Camera` batch of ``V`` views of ``H x W`` pixels.

    Returns:
        origins ``(V, 3)``, unit directions ``(V, T, 3)`` (NaN where the mask is empty), and
        whether the view sees the body ``(V, T)`` bool.
    """
    V, T = masks.shape[:2]
    origins = np.zeros((V, 3))
    dirs = np.full((V, T, 3), np.nan)
    seen = masks.reshape(V, T, -1).any(axis=-1)
    for v in range(V):
        cam = cameras.view(v)
        o, d = (np.asarray(a, float) for a in cam.rays())
        origins[v] = o[0]
        flat = masks[v].reshape(T, -1).astype(float)
        mean = flat @ d / np.maximum(flat.sum(axis=1, keepdims=True), 1.0)
        norm = np.linalg.norm(mean, axis=1, keepdims=True)
        dirs[v] = np.where(seen[v][:, None], mean / np.where(norm > 0, norm, 1.0), np.nan)
    return origins, dirs, seen


def optical_axes(cameras, num_views: int) -> np.ndarray:
    """Unit viewing directions (the camera's +z, world axes) of ``num_views`` views, ``(V, 3)``."""
    return np.stack([np.asarray(cameras.view(v).rotation, float)[:, 2] for v in range(num_views)])


def triangulate(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """The point nearest (least squares) to the rays ``o_v + t d_v``, and the RMS distance of
    the rays from it (m). ``origins (V, 3)``, unit ``directions (V, 3)``; NaN rays are left
    out; fewer than 2 rays gives NaN."""
    ok = np.all(np.isfinite(directions), axis=1)
    if ok.sum() < 2:
        return np.full(3, np.nan), float("nan")
    o, d = origins[ok], directions[ok]
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors onto each ray's normal plane
    A, b = P.sum(axis=0), np.einsum("vij,vj->i", P, o)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    off = np.einsum("vij,vj->vi", P, x[None] - o)
    return x, float(np.sqrt(np.mean(np.sum(off * off, axis=1))))


def _parabola(times: np.ndarray, centres: np.ndarray, gravity: np.ndarray | None = None):
    """Least-squares ``c0 + v t + g t²/2`` through ``centres (k, 3)``: coefficients (rows
    ``c0, v`` and, with ``g`` free (``gravity`` None), ``g``) and the RMS residual (m)."""
    free = gravity is None
    known = np.zeros(3) if free else 0.5 * times[:, None] ** 2 * np.asarray(gravity, float)
    A = np.stack([np.ones_like(times), times] + ([0.5 * times**2] if free else []), axis=1)
    coef = np.linalg.lstsq(A, centres - known, rcond=None)[0]
    r = A @ coef + known - centres
    return coef, float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def _followed(times: np.ndarray, centres: np.ndarray, gravity: np.ndarray, limit: float) -> int:
    """How many leading frames (at least 2) follow the known-``gravity`` parabola: each next
    centre lies within ``limit`` (m) of where the parabola through the frames before it puts it
    (``gravity`` 0: a straight line)."""
    frames = 2
    while frames < len(times):
        c0, v0 = _parabola(times[:frames], centres[:frames], gravity)[0]
        t = times[frames]
        if np.linalg.norm(c0 + v0 * t + 0.5 * gravity * t**2 - centres[frames]) > limit:
            break
        frames = frames + 1
    return frames


def area_noise(corrected: np.ndarray) -> float:
    """Robust σ of the relative frame-to-frame noise of silhouette areas ``corrected (V, T)``
    (NaN where a view does not see the body): from the second differences of their logarithms
    over the frames, which white noise of σ makes σ√6 wide and a smooth change (a rigid fall, a
    body spreading after it lands) leaves small; their median absolute value over all views
    and frames, over 0.6745 √6. NaN with fewer than 3 frames."""
    with np.errstate(all="ignore"):
        d2 = np.diff(np.log(np.asarray(corrected, float)), n=2, axis=1)
    d2 = np.abs(d2[np.isfinite(d2)])
    return float(np.median(d2) / (0.6745 * np.sqrt(6.0))) if d2.size else float("nan")


def free_fall(masks: np.ndarray, cameras, times: np.ndarray, dx: float, gravity=None,
              tolerance: float = FREE_FALL_TOLERANCE, shape_tolerance: float = SHAPE_TOLERANCE) -> FreeFall:
    """The free-fall frames, initial velocity and gravity from the silhouettes.

    Arguments:
        masks: ``(V, T, H, W)`` bool silhouettes of the body.
        cameras: their :class:`jaxmpm.render.Camera` batch.
        times: ``(T,)`` frame times, s (frame 0 is the start).
        dx: the scene's cell size, m (the residual tolerance is ``tolerance * dx``).
        gravity: ``(3,)`` the scene's prior gravity, m/s², or None. Used for ``v0`` from 2
            frames, and in place of the shape test where the masks are too noisy for it.
        tolerance, shape_tolerance: see :data:`FREE_FALL_TOLERANCE`, :data:`SHAPE_TOLERANCE`.

    The free fall is grown frame by frame: a frame joins while its silhouettes keep their
    size and the parabola through all frames so far fits within the tolerance. A parabola
    passes through any 3 centres, so a fit of exactly 3 frames has no redundancy (its
    residual is 0) and its gravity is as noisy as the centres. Where the masks' area noise
    exceeds :data:`AREA_NOISE_LIMIT` and a prior gravity is given, the size is not tested
    and a frame joins while its centre lies within the tolerance of the prior's parabola
    through the frames before it (module docstring).
    """
    masks = np.asarray(masks, bool)
    times = np.asarray(times, float)
    if masks.ndim != 4 or masks.shape[1] != times.shape[0]:
        raise ObservationError(f"free_fall: masks (V, T, H, W) with T = {times.shape[0]} frames, got {masks.shape}")
    origins, dirs, seen = silhouette_rays(masks, cameras)
    T = times.shape[0]
    fits = [triangulate(origins, dirs[:, t]) for t in range(T)]
    centres = np.stack([c for c, _ in fits])
    spread = np.asarray([s for _, s in fits])
    valid = np.all(np.isfinite(centres), axis=1)
    size_change = np.full(T, np.nan)
    noise = float("nan")
    if valid[0]:
        area = masks.reshape(masks.shape[0], T, -1).sum(axis=-1).astype(float)
        to_centre = np.where(valid[None, :, None], centres[None], np.nan) - origins[:, None]  # (V, T, 3)
        dist = np.linalg.norm(to_centre, axis=-1)
        cos = np.einsum("vtk,vk->vt", to_centre, optical_axes(cameras, masks.shape[0])) / dist
        corrected = area * dist**2 * cos**3  # (V, T): a rigid body's image area ~ 1 / (d² cos³θ)
        noise = area_noise(np.where(seen, corrected, np.nan))
        both = seen & seen[:, :1]
        rel = np.where(both, np.abs(corrected / np.where(both[:, :1], corrected[:, :1], 1.0) - 1.0), np.nan)
        with np.errstate(all="ignore"):
            size_change = np.array([np.nanmedian(rel[:, t]) if both[:, t].any() else np.nan for t in range(T)])
    prior = None if gravity is None else np.asarray(gravity, float)
    shape_tested = prior is None or not noise > AREA_NOISE_LIMIT
    rigid = valid & (size_change <= shape_tolerance) if shape_tested else valid
    n_valid = int(np.argmin(rigid)) if not rigid.all() else T  # leading frames seen (and of constant size)
    limit = tolerance * dx
    t0 = times - times[0]
    frames, residual = min(n_valid, 2), 0.0
    if n_valid >= 3 and shape_tested:  # a parabola with a free g has no redundancy below 4 frames
        frames = 3
        while frames < n_valid:
            _, r = _parabola(t0[: frames + 1], centres[: frames + 1])
            if r > limit:
                break
            frames = frames + 1
    if not shape_tested and n_valid >= 2:
        frames = _followed(t0[:n_valid], centres[:n_valid], prior, limit)
    supported = 0
    if not shape_tested and 2 <= frames < n_valid:  # the prior's parabola rejected a frame: supported from the start?
        line = _followed(t0[:n_valid], centres[:n_valid], np.zeros(3), limit)
        supported = line if line > frames else 0  # the line explains the frame the parabola did not
    velocity = g = None
    if supported:  # no free fall: the velocity of the straight line through the supported frames
        coef, residual = _parabola(t0[:supported], centres[:supported], np.zeros(3))
        frames, velocity = 1, coef[1]
    elif frames >= 3 and shape_tested:  # g measured
        coef, residual = _parabola(t0[:frames], centres[:frames])
        velocity, g = coef[1], coef[2]
    elif frames >= 2:  # g known: the prior's (from 2 frames v0 = Δc/Δt − g Δt/2), or none given
        coef, residual = _parabola(t0[:frames], centres[:frames], np.zeros(3) if prior is None else prior)
        velocity = coef[1]
    return FreeFall(centres=centres, spread=spread, size_change=size_change, frames=frames, velocity=velocity,
                    gravity=g, residual=float(residual), area_noise=noise, shape_tested=shape_tested,
                    supported=supported)
