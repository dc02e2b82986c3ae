"""Multi-view observations (masks and images in the DESIGN §5.2 layout) and video files."""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ObservationError
from .camera import Camera, as_camera_batch, unstack_cameras
from .surfels import SurfelRenderer
from .volume import AbstractRenderer, VolumeRenderer

RENDERERS = ("volume", "surfels")


def make_renderer(
    kind: str, positions, *, spacing: float | None = None, **options
) -> AbstractRenderer:
    """A renderer of the named kind fitted to ``positions`` (``(..., N, 3)``).

    Arguments:
        kind: ``"volume"`` (:class:`VolumeRenderer`) or ``"surfels"`` (:class:`SurfelRenderer`).
        positions: concrete particle positions (all frames, so the volume grid covers them).
        spacing: particle spacing (estimated when omitted).
        options: attributes of the renderer (``background``, ``chunk_size``, …).
    """
    if kind == "volume":
        return VolumeRenderer.for_particles(positions, spacing=spacing, **options)
    if kind == "surfels":
        return SurfelRenderer.for_particles(positions, spacing=spacing, **options)
    raise ObservationError(f"unknown renderer {kind!r}; expected one of {RENDERERS}")


def render_views(
    positions,
    cameras: Camera | Sequence[Camera],
    renderer: str | AbstractRenderer = "volume",
    colors=None,
    *,
    spacing: float | None = None,
    per_frame: Mapping[str, np.ndarray] | None = None,
    threshold: float = 0.5,
    **options,
) -> dict[str, np.ndarray]:
    """Render a trajectory from V cameras into observation arrays (DESIGN §5.2).

    Arguments:
        positions: ``(T, N, 3)`` particle positions (or ``(N, 3)`` for one frame).
        cameras: a batch of V cameras or a list of single cameras (one image size).
        renderer: ``"volume"``, ``"surfels"`` or a renderer instance.
        colors: ``(N, 3)`` or ``(T, N, 3)`` RGB in [0, 1] (default: one colour).
        spacing: particle spacing used to build a named renderer (estimated if omitted).
        per_frame: extra per-particle renderer inputs with a leading T axis, e.g.
            ``{"F": F (T, N, 3, 3)}`` for surfels or ``{"volumes": (T, N)}`` for volume.
        threshold: alpha above which a pixel belongs to the mask.
        options: attributes of a named renderer (``background``, ``chunk_size``, …).

    Returns:
        ``{"masks": (V, T, H, W) uint8 0/255, "images": (V, T, H, W, 3) uint8,
        "intrinsics": (V, 3, 3) float32, "cam_to_world": (V, 4, 4) float32}``.
    """
    x = np.asarray(positions)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ObservationError(f"positions must have shape (T, N, 3), got {np.shape(positions)}")
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float32)
    T, N, _ = x.shape
    cams = as_camera_batch(cameras)
    if isinstance(renderer, str):
        renderer = make_renderer(renderer, x, spacing=spacing, **options)
    elif options:
        raise ObservationError(f"renderer options {sorted(options)} given with a renderer instance")
    dtype = x.dtype
    if colors is not None:
        colors = np.asarray(colors, dtype=dtype)
        if colors.shape == (N, 3):
            colors = np.broadcast_to(colors, (T, N, 3))
        if colors.shape != (T, N, 3):
            raise ObservationError(f"colors must have shape (N, 3) or (T, N, 3), got {colors.shape}")
    per_frame = dict(per_frame or {})
    for k, v in per_frame.items():
        if np.shape(v)[:1] != (T,):
            raise ObservationError(f"per_frame[{k!r}] must have a leading axis of T={T} frames")

    @jax.jit
    def one(xt, cam, ct, extra):
        out = renderer.render(xt, cam, ct, **extra)
        return out.alpha, out.rgb

    V = cams.num_views
    H, W = cams.height, cams.width
    masks = np.zeros((V, T, H, W), np.uint8)
    images = np.zeros((V, T, H, W, 3), np.uint8)
    for v, cam in enumerate(unstack_cameras(cams)):
        cam = cam.astype(dtype)
        for t in range(T):
            ct = None if colors is None else jnp.asarray(colors[t])
            extra = {k: jnp.asarray(np.asarray(val)[t]) for k, val in per_frame.items()}
            alpha, rgb = one(jnp.asarray(x[t]), cam, ct, extra)
            masks[v, t] = np.where(np.asarray(alpha) > threshold, 255, 0).astype(np.uint8)
            images[v, t] = to_uint8(np.asarray(rgb))
    return {
        "masks": masks,
        "images": images,
        "intrinsics": np.asarray(cams.K, dtype=np.float32),
        "cam_to_world": np.asarray(cams.cam_to_world, dtype=np.float32),
    }


def to_uint8(image) -> np.ndarray:
    """Float image in [0, 1] to uint8 (clipped, rounded)."""
    return np.clip(np.rint(np.asarray(image, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def tile_views(images, *, cols: int | None = None, pad: int = 0, fill: int = 255) -> np.ndarray:
    """Tile V views side by side: ``(V, T, H, W, C)`` → ``(T, rows·(H+pad), cols·(W+pad), C)``.

    Arguments:
        images: ``(V, T, H, W, 3)`` (or masks ``(V, T, H, W)``, given a channel axis of 1).
        cols: tiles per row (default ``ceil(sqrt(V))``).
        pad: pixels of ``fill`` between tiles.
        fill: value of padding and of empty tiles.
    """
    a = np.asarray(images)
    if a.ndim == 4:
        a = a[..., None]
    if a.ndim != 5:
        raise ObservationError(f"tile_views expects (V, T, H, W, C), got {np.shape(images)}")
    V, T, H, W, C = a.shape
    cols = int(math.ceil(math.sqrt(V))) if cols is None else int(cols)
    rows = int(math.ceil(V / cols))
    out = np.full((T, rows * (H + pad) - pad, cols * (W + pad) - pad, C), fill, dtype=a.dtype)
    for v in range(V):
        r, c = divmod(v, cols)
        y, x = r * (H + pad), c * (W + pad)
        out[:, y : y + H, x : x + W] = a[v]
    return out


def write_video(path: str | os.PathLike, frames, fps: float = 24.0) -> Path:
    """Write ``(T, H, W, 3)`` uint8 frames as a video, atomically; returns the path written.

    ``.mp4``/``.mov``/``.mkv``/``.webm`` go through imageio-ffmpeg (H.264 for mp4; odd
    sizes are edge-padded to even). If ffmpeg is unavailable or fails, a GIF is written
    next to it (same name, ``.gif``) with a warning. ``.gif`` writes a GIF directly. The file
    appears only when complete (:func:`jaxmpm.observe.atomic_write`).
    """
    import imageio.v2 as imageio
    import imageio.v3 as iio3

    from ..observe import atomic_write

    a = np.asarray(frames)
    if a.ndim == 3:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 4 or a.shape[-1] not in (3, 4):
        raise ObservationError(f"frames must have shape (T, H, W, 3), got {np.shape(frames)}")
    if a.dtype != np.uint8:
        a = to_uint8(a) if np.issubdtype(a.dtype, np.floating) else a.astype(np.uint8)
    path = Path(path)
    if path.suffix.lower() != ".gif":
        ph, pw = a.shape[1] % 2, a.shape[2] % 2
        if ph or pw:
            a = np.pad(a, ((0, 0), (0, ph), (0, pw), (0, 0)), mode="edge")

        def write_ffmpeg(tmp):
            with warnings.catch_warnings():
                # imageio-ffmpeg starts ffmpeg with fork+exec, which is safe here
                warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
                imageio.mimwrite(tmp, list(a), format="FFMPEG", fps=fps, macro_block_size=1, quality=8)

        try:
            return atomic_write(path, write_ffmpeg)
        except Exception as exc:  # ffmpeg missing or codec failure: fall back to GIF
            warnings.warn(f"could not write {path} with ffmpeg ({exc}); writing a GIF instead")
            path = path.with_suffix(".gif")
    return atomic_write(path, lambda tmp: iio3.imwrite(tmp, a, extension=".gif", duration=1000.0 / fps, loop=0))
