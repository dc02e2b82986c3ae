"""Readers for public multi-view datasets: PAC-NeRF / GIC folders -> :class:`Observation`.

A PAC-NeRF scene folder (Li et al. 2023; GIC reads the same data) holds::

    all_data.json            [{"file_path": "./data/r_{view}_{frame}.png", "time": t,
                               "c2w": 3x4 (OpenGL axes), "intrinsic": 3x3}, ...]
    data/r_{view}_{frame}.png    the images (frame -1: background plate, -2: ray-mask alpha)
    data/a_{view}_{frame}.png    (after PAC-NeRF/GIC's matting) RGBA: matted RGB, alpha = mask
    data/m_{view}_{frame}.png    (after matting) RGB with the background set to white

:func:`load_pacnerf` returns the frames ``>= 0`` as an Observation with masks, images,
intrinsics and ``cam_to_world`` in OpenCV axes (converted by
:func:`jaxmpm.render.load_cameras_json`). Masks come from, in this order of preference
(``mask_source="auto"``): the ``a_`` images' alpha, the ``r_`` images' own alpha channel,
the ``m_`` images (pixels that are not white), or the difference from the frame ``-1``
background plate (exposure-compensated: :func:`background_mask`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import ObservationError
from .observe import Observation

__all__ = ["load_pacnerf", "save_pacnerf", "read_mask_image", "background_mask", "MASK_SOURCES"]

MASK_SOURCES = ("auto", "a", "alpha", "m", "background")

#: A pixel of an ``m_`` image counts as background when all channels are at least this.
WHITE_LEVEL = 250
#: Background-difference threshold (max over channels, 0–255).
BACKGROUND_THRESHOLD = 30


def read_image(path: Path) -> np.ndarray:
    """The image at ``path`` as ``(H, W, 3 or 4)`` uint8 (grey is repeated to RGB; an unreadable file is an
    ObservationError naming it)."""
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(path))
    except Exception as err:  # imageio raises many types
        raise ObservationError(f"cannot read image {path}: {err}") from None
    if img.dtype != np.uint8:
        if np.issubdtype(img.dtype, np.integer) and img.max() > 255:
            img = (img.astype(np.float64) / np.iinfo(img.dtype).max * 255.0 + 0.5).astype(np.uint8)
        else:
            img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] not in (3, 4):
        raise ObservationError(f"image {path} must be grey, RGB or RGBA, got shape {img.shape}")
    return img


def downscale_image(img: np.ndarray, factor: int) -> np.ndarray:
    """Block-average an ``(H, W[, C])`` image by an integer factor (cropping the remainder)."""
    if factor == 1:
        return img
    H, W = img.shape[:2]
    h, w = H // factor, W // factor
    if h == 0 or w == 0:
        raise ObservationError(f"downscale factor {factor} is too large for {W}x{H} images")
    crop = img[: h * factor, : w * factor].astype(np.float64)
    out = crop.reshape(h, factor, w, factor, *img.shape[2:]).mean(axis=(1, 3))
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def _entries(folder: Path) -> Path:
    path = folder / "all_data.json"
    if not path.is_file():
        raise ObservationError(f"{folder}: no all_data.json (a PAC-NeRF/GIC scene folder holds one)")
    return path


def load_pacnerf(
    folder: str | os.PathLike,
    *,
    frames: Sequence[int] | None = None,
    views: Sequence[int] | None = None,
    downscale: int = 1,
    mask_source: str = "auto",
    images: str = "matted",
    threshold: int = 128,
) -> Observation:
    """Read a PAC-NeRF / GIC scene folder into an :class:`Observation`.

    Arguments:
        folder: the scene folder (with ``all_data.json``).
        frames: frame numbers to keep (default: all frames >= 0 present for every view).
        views: view numbers to keep (default: all).
        downscale: integer factor to shrink the images by (block average; intrinsics
            rescaled) — e.g. 4 turns PAC-NeRF's 400x400 into 100x100.
        mask_source: ``"auto"``, ``"a"`` (the ``a_`` images' alpha), ``"alpha"`` (the
            ``r_`` images' alpha channel), ``"m"`` (non-white pixels of the ``m_`` images)
            or ``"background"`` (difference from the frame ``-1`` plate).
        images: ``"matted"`` (the object on white: ``a_``/``m_`` images, or ``r_``
            composited over white with the mask) or ``"raw"`` (the ``r_`` images).
        threshold: mask threshold on the alpha (0–255).

    Returns:
        An Observation with ``times`` from the file (seconds), ``masks (V, T, H, W)``,
        ``images (V, T, H, W, 3)``, ``intrinsics``, ``cam_to_world`` (OpenCV axes) and no
        scene (pair it with a scene spec for :func:`jaxmpm.fit_scene`).

    Raises:
        ObservationError: missing folder/files, inconsistent cameras or image sizes, no
            usable mask source, too few frames.
    """
    from .render import load_cameras_json

    folder = Path(folder)
    if not folder.is_dir():
        raise ObservationError(f"dataset folder not found: {folder}")
    if mask_source not in MASK_SOURCES:
        raise ObservationError(f"mask_source must be one of {MASK_SOURCES}, got {mask_source!r}")
    if images not in ("matted", "raw"):
        raise ObservationError(f"images must be 'matted' or 'raw', got {images!r}")
    if not isinstance(downscale, int) or downscale < 1:
        raise ObservationError(f"downscale must be a positive int, got {downscale!r}")
    path = _entries(folder)
    try:
        with open(path) as fh:
            raw = json.load(fh)
    except (OSError, json.JSONDecodeError) as err:
        raise ObservationError(f"cannot read {path}: {err}") from None
    if isinstance(raw, dict):
        raw = raw.get("frames", [])
    first = next((e for e in raw if isinstance(e, dict) and "file_path" in e), None) if isinstance(raw, list) else None
    if first is None:
        raise ObservationError(f"{path}: expected a list of entries with a 'file_path'")
    # the images' real size decides the camera size (PAC-NeRF stores no width/height)
    H0, W0 = read_image(_find_image(folder, first["file_path"], "r")).shape[:2]
    cams, entries = load_cameras_json(path, width=W0, height=H0)

    view_keys = sorted({e["view"] for e in entries})
    by = {}
    times = {}
    for e in entries:
        if e["frame"] is None:
            raise ObservationError(f"{path}: file name {e['file_path']!r} does not follow r_{{view}}_{{frame}}.png")
        by[(e["view"], e["frame"])] = e["file_path"]
        if e["frame"] >= 0:
            times.setdefault(e["frame"], e["time"])
    all_frames = sorted(f for f in times if all((v, f) in by for v in view_keys))
    if frames is not None:
        missing = [f for f in frames if f not in all_frames]
        if missing:
            raise ObservationError(f"{folder}: frames {missing} are not present for every view (have {all_frames})")
        all_frames = sorted(set(int(f) for f in frames))
    keep_views = view_keys if views is None else list(views)
    bad = [v for v in keep_views if v not in view_keys]
    if bad:
        raise ObservationError(f"{folder}: views {bad} do not exist (have {view_keys})")
    if len(all_frames) < 2:
        raise ObservationError(f"{folder}: too few frames (need at least 2 with frame number >= 0, found {len(all_frames)})")

    V, T = len(keep_views), len(all_frames)
    masks, imgs = None, None
    for vi, v in enumerate(keep_views):
        for ti, f in enumerate(all_frames):
            rel = by[(v, f)]
            rgb, alpha, _ = _frame(folder, rel, by.get((v, -1)), mask_source, images, threshold)
            rgb, alpha = downscale_image(rgb, downscale), downscale_image(alpha, downscale)
            if masks is None:
                H, W = alpha.shape
                masks = np.zeros((V, T, H, W), np.uint8)
                imgs = np.zeros((V, T, H, W, 3), np.uint8)
            if alpha.shape != masks.shape[2:]:
                raise ObservationError(
                    f"{folder / rel}: image size {alpha.shape[::-1]} differs from the first image's {masks.shape[2:][::-1]}"
                )
            masks[vi, ti] = np.where(alpha >= threshold, 255, 0).astype(np.uint8)
            imgs[vi, ti] = rgb
    K = np.asarray(cams.K, np.float64)[keep_views].copy()
    K[:, :2, :] /= downscale  # pixel i of the block average covers old pixels [i f, (i + 1) f)
    c2w = np.asarray(cams.cam_to_world, np.float64)[keep_views]
    t = np.asarray([times[f] for f in all_frames], float)
    if np.any(np.diff(t) <= 0):
        raise ObservationError(f"{path}: the frames' 'time' values must increase with the frame number, got {t.tolist()}")
    return Observation(times=t, masks=masks, images=imgs, intrinsics=K, cam_to_world=c2w)


def _find_image(folder: Path, rel: str, prefix: str) -> Path:
    p = (folder / rel).resolve()
    name = p.name
    if prefix != "r":
        name = prefix + name[1:] if name.startswith("r_") else name
    candidate = p.with_name(name)
    if prefix == "r" and not candidate.is_file():
        raise ObservationError(f"image not found: {candidate}")
    return candidate


def _frame(folder: Path, rel: str, background_rel: str | None, mask_source: str, images: str, threshold: int):
    """``(rgb (H, W, 3), alpha (H, W), source)`` of one entry."""
    r_path = _find_image(folder, rel, "r")
    a_path = _find_image(folder, rel, "a")
    m_path = _find_image(folder, rel, "m")
    raw = None
    alpha, src = None, None
    order = {"auto": ("a", "alpha", "m", "background")}.get(mask_source, (mask_source,))
    for s in order:
        if s == "a" and a_path.is_file():
            a = read_image(a_path)
            if a.shape[-1] == 4:
                alpha, src = a[..., 3], "a"
        elif s == "alpha":
            raw = read_image(r_path) if raw is None else raw
            if raw.shape[-1] == 4 and raw[..., 3].min() < 255:
                alpha, src = raw[..., 3], "alpha"
        elif s == "m" and m_path.is_file():
            m = read_image(m_path)[..., :3]
            alpha, src = np.where(np.all(m >= WHITE_LEVEL, axis=-1), 0, 255).astype(np.uint8), "m"
        elif s == "background" and background_rel is not None:
            bg_path = _find_image(folder, background_rel, "r")
            raw = read_image(r_path) if raw is None else raw
            bg = read_image(bg_path)[..., :3]
            if bg.shape != raw[..., :3].shape:
                raise ObservationError(f"background plate {bg_path} has a different size from {r_path}")
            alpha, src = background_mask(raw[..., :3], bg), "background"
        if alpha is not None:
            break
    if alpha is None:
        wanted = "any of a_ images, an alpha channel, m_ images or a background plate" if mask_source == "auto" else mask_source
        raise ObservationError(f"{r_path}: no mask source found ({wanted})")
    if images == "raw":
        raw = read_image(r_path) if raw is None else raw
        rgb = raw[..., :3]
    elif a_path.is_file():
        rgb = read_image(a_path)[..., :3]
    elif m_path.is_file():
        rgb = read_image(m_path)[..., :3]
    else:
        raw = read_image(r_path) if raw is None else raw
        w = (alpha >= threshold)[..., None]
        rgb = np.where(w, raw[..., :3], 255).astype(np.uint8)
    if rgb.shape[:2] != alpha.shape:
        raise ObservationError(f"{r_path}: the mask and the image differ in size ({alpha.shape} vs {rgb.shape[:2]})")
    return rgb, alpha, src


def background_mask(image: np.ndarray, plate: np.ndarray, threshold: int = BACKGROUND_THRESHOLD) -> np.ndarray:
    """The material's mask by difference from the background plate, exposure-compensated.

    A plate shot with another exposure or light level than the frames (the usual case: it is
    taken before or after the run) differs from them everywhere; so the plate is first scaled,
    per channel, by the median ratio frame / plate over the pixels where the plate is not
    dark (most pixels are background, so the median is the exposure ratio).

    Arguments:
        image, plate: ``(H, W, 3)`` uint8.
        threshold: the difference (max over channels, 0–255) above which a pixel is material.

    Returns:
        ``(H, W)`` uint8 mask, 255 on the material.
    """
    img, bg = image.astype(np.float64), plate.astype(np.float64)
    lit = bg > 16.0
    gain = np.array([np.median(img[..., c][lit[..., c]] / bg[..., c][lit[..., c]]) if lit[..., c].any() else 1.0
                     for c in range(3)])
    diff = np.max(np.abs(img - gain * bg), axis=-1)
    return np.where(diff > threshold, 255, 0).astype(np.uint8)


def read_mask_image(path: Path) -> np.ndarray:
    """A mask image: the alpha channel when it has one that is not all opaque, else grey > 127.

    Returns ``(H, W)`` bool.
    """
    img = read_image(path)
    if img.shape[-1] == 4 and img[..., 3].min() < 255:
        return img[..., 3] > 127
    return img[..., :3].mean(axis=-1) > 127


def save_pacnerf(
    folder: str | os.PathLike,
    observation: Observation,
    *,
    background: np.ndarray | None = None,
    collider_masks: np.ndarray | None = None,
    alpha: bool = True,
) -> Path:
    """Write an Observation with masks and images as a PAC-NeRF scene folder.

    Writes ``all_data.json`` (OpenGL axes, as PAC-NeRF), ``data/r_{view}_{frame}.png`` as
    RGBA (alpha = the mask), the frame ``-1`` background plate when ``background`` is given
    and ``data/c_{view}.png`` collider masks when ``collider_masks`` is given.

    Arguments:
        folder: output folder (created).
        observation: with ``masks (V, T, H, W)``, ``images``, ``intrinsics``, ``cam_to_world``.
        background: ``(V, H, W, 3)`` uint8 plates (frame −1).
        collider_masks: ``(V, H, W)`` bool masks of the colliders on the plates.
        alpha: write the masks as the images' alpha channel; ``False`` writes RGB only, and a
            reader takes the masks from the difference with the background plate.

    Returns:
        The folder.
    """
    import imageio.v3 as iio

    from .render import Camera, save_cameras_json

    obs = observation
    if obs.masks is None or obs.images is None:
        raise ObservationError("save_pacnerf needs an observation with masks and images")
    if not alpha and background is None:
        raise ObservationError("save_pacnerf(alpha=False) needs the background plates: the masks come from them")
    folder = Path(folder)
    (folder / "data").mkdir(parents=True, exist_ok=True)
    V, T, H, W = obs.masks.shape
    cams = Camera(np.asarray(obs.intrinsics, np.float32), np.asarray(obs.cam_to_world, np.float32), W, H)
    frames = list(range(T))
    times = [float(t) for t in obs.times]
    if background is not None:
        frames, times = [-1] + frames, [0.0] + times
    save_cameras_json(folder / "all_data.json", cams, times, frames=frames)
    for v in range(V):
        for t in range(T):
            image = np.concatenate([obs.images[v, t], obs.masks[v, t][..., None]], axis=-1) if alpha else obs.images[v, t]
            iio.imwrite(folder / "data" / f"r_{v}_{t}.png", np.asarray(image, np.uint8))
        if background is not None:
            iio.imwrite(folder / "data" / f"r_{v}_-1.png", np.asarray(background[v], np.uint8))
        if collider_masks is not None:
            iio.imwrite(folder / "data" / f"c_{v}.png", np.where(collider_masks[v], 255, 0).astype(np.uint8))
    return folder
