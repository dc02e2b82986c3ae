"""Reading an ``identify`` dataset: a PAC-NeRF folder, optional collider masks and a hint.

Everything is checked here, before any reconstruction or fitting starts, and every
problem is one :class:`~jaxmpm.errors.ObservationError` line naming the file or view.
The layout is documented in docs/file_formats.md ("identify datasets").
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ObservationError, SceneError
from ..observe import Observation

#: Scene keys a ``scene_hint.toml`` may give (DESIGN §5.1); anything else is an error.
HINT_KEYS = ("dim", "dx", "domain", "gravity", "frame_dt", "substeps", "dt", "collision", "flip", "colliders", "bodies")
#: Keys of the hint's ``[[bodies]]`` table (only the first body is used).
HINT_BODY_KEYS = ("material", "ppc", "name")
#: How far (in frames) the spacing of the ``time`` values may be from whole multiples of ``frame_dt``.
FRAME_TOLERANCE = 0.05


@dataclass
class Dataset:
    """An identify dataset, read and checked.

    Attributes:
        folder: the dataset folder.
        observation: frames ``>= 0``: ``masks (V, T, H, W)``, ``images``, cameras, ``times`` (s).
        collider_masks: ``(V, H, W)`` bool masks of the colliders on the background plates,
            or None (no ``data/c_{view}.png``).
        plates: ``(V, H, W, 3)`` uint8 background plates (frame −1: the colliders without
            the material), or None when not every view has one.
        hint: the scene hint (a dict of scene keys; empty when none was given).
        frame_dt: seconds between frames (from the hint, else from the ``time`` values).
    """

    folder: Path
    observation: Observation
    collider_masks: np.ndarray | None
    hint: dict = field(default_factory=dict)
    frame_dt: float = 0.0
    plates: np.ndarray | None = None

    @property
    def num_views(self) -> int:
        return int(self.observation.masks.shape[0])


def read_hint(source: str | os.PathLike | dict | None) -> dict:
    """A scene hint from a ``.toml``/``.json`` file or a dict, keys checked (empty when None)."""
    from ..scene import flip_share, read_spec

    if source is None:
        return {}
    where = "scene hint"
    if isinstance(source, dict):
        hint = dict(source)
    else:
        where = os.fspath(source)
        try:
            hint = read_spec(source)
        except SceneError as err:
            raise ObservationError(str(err)) from None
    unknown = sorted(set(hint) - set(HINT_KEYS))
    if unknown:
        raise ObservationError(f"{where}: unknown key {unknown[0]!r} (a hint may give {', '.join(HINT_KEYS)})")
    if hint.get("dim", 3) != 3:
        raise ObservationError(f"{where}: identify reconstructs 3D scenes; 'dim' must be 3, got {hint['dim']!r}")
    if "flip" in hint:
        try:
            flip_share(hint["flip"], where)
        except SceneError as err:
            raise ObservationError(str(err)) from None
    bodies = hint.get("bodies", [])
    if not isinstance(bodies, list) or len(bodies) > 1:
        raise ObservationError(f"{where}: 'bodies' must be a list with at most one [[bodies]] table")
    for key in (bodies[0] if bodies else {}):
        if key not in HINT_BODY_KEYS:
            raise ObservationError(f"{where}: unknown key 'bodies[0].{key}' (a hint's body may give {', '.join(HINT_BODY_KEYS)})")
    for k, c in enumerate(hint.get("colliders", [])):
        if not isinstance(c, dict) or c.get("type") != "plane":
            raise ObservationError(f"{where}: colliders[{k}] must be a plane (other colliders are reconstructed from data/c_*.png)")
    return hint


def _check_entries(folder: Path) -> tuple[list[dict], int, int]:
    """Check the files named by ``all_data.json``: every view has the same frames, every
    file exists, all images have one size. Returns ``(entries, H, W)``."""
    from ..datasets import read_image
    from ..render import load_cameras_json

    path = folder / "all_data.json"
    if not path.is_file():
        raise ObservationError(f"{folder}: no all_data.json (an identify dataset is a PAC-NeRF scene folder)")
    _, entries = load_cameras_json(path)
    frames_of: dict[int, set] = {}
    for e in entries:
        if e["frame"] is None:
            raise ObservationError(f"{path}: file name {e['file_path']!r} does not follow r_{{view}}_{{frame}}.png")
        frames_of.setdefault(e["view"], set()).add(e["frame"])
    counts = {f: sum(f in s for s in frames_of.values()) for s in frames_of.values() for f in s}
    V = len(frames_of)
    short = sorted(f for f, n in counts.items() if n != V)
    if short:
        f = short[0]
        missing = [v for v, s in frames_of.items() if f not in s]
        raise ObservationError(
            f"{path}: inconsistent camera counts: frame {f} has {counts[f]} views of {V} (view {missing[0]} has no entry for it)"
        )
    size = None
    for e in entries:
        p = (folder / e["file_path"]).resolve()
        if not p.is_file():
            raise ObservationError(f"view {e['view']}: image {p} listed in all_data.json does not exist")
        if e["frame"] < 0:
            continue
        hw = read_image(p).shape[:2]
        size = hw if size is None else size
        if hw != size:
            raise ObservationError(f"view {e['view']}: {p} is {hw[1]}x{hw[0]} px, the first image is {size[1]}x{size[0]}")
        for prefix in ("a", "m"):
            q = p.with_name(prefix + p.name[1:])
            qhw = read_image(q).shape[:2] if q.is_file() else size
            if qhw != size:
                raise ObservationError(f"view {e['view']}: mask {q} is {qhw[1]}x{qhw[0]} px, the images are {size[1]}x{size[0]}")
    return entries, size[0], size[1]


def _collider_masks(folder: Path, V: int, H: int, W: int, downscale: int) -> np.ndarray | None:
    from ..datasets import downscale_image, read_mask_image

    paths = [folder / "data" / f"c_{v}.png" for v in range(V)]
    have = [p.is_file() for p in paths]
    if not any(have):
        return None
    if not all(have):
        missing = [v for v, h in enumerate(have) if not h]
        raise ObservationError(f"view {missing[0]}: {paths[missing[0]]} is missing (collider masks must cover every view or none)")
    out = []
    for v, p in enumerate(paths):
        m = read_mask_image(p)
        if m.shape != (H, W):
            raise ObservationError(f"view {v}: collider mask {p} is {m.shape[1]}x{m.shape[0]} px, the images are {W}x{H}")
        out.append(downscale_image(np.where(m, 255, 0).astype(np.uint8), downscale) > 127)
    return np.stack(out)


def _plates(folder: Path, entries: list[dict], V: int, H: int, W: int, downscale: int) -> np.ndarray | None:
    """Frame −1 of every view, or None when some view has none (the plates are optional)."""
    from ..datasets import downscale_image, read_image

    paths = {e["view"]: (folder / e["file_path"]).resolve() for e in entries if e["frame"] == -1}
    if sorted(paths) != list(range(V)):
        return None
    out = []
    for v in range(V):
        rgb = read_image(paths[v])[..., :3]
        if rgb.shape[:2] != (H, W):
            raise ObservationError(f"view {v}: background plate {paths[v]} is {rgb.shape[1]}x{rgb.shape[0]} px, "
                                   f"the images are {W}x{H}")
        out.append(downscale_image(np.asarray(rgb, np.uint8), downscale))
    return np.stack(out)


def _frame_dt(times: np.ndarray, hint: dict, where: str) -> float:
    """Seconds between frames: the hint's ``frame_dt``, checked against the spacing of
    ``times`` (every spacing a whole number of frames, the smallest one frame), else the
    smallest spacing."""
    steps = np.diff(times)
    if "frame_dt" not in hint:
        return float(np.min(steps))
    dt = float(hint["frame_dt"])
    if not dt > 0:
        raise ObservationError(f"{where}: frame_dt must be positive, got {dt}")
    ratio = steps / dt
    off = np.abs(ratio - np.round(ratio))
    if np.max(off) > FRAME_TOLERANCE or abs(np.min(ratio) - 1.0) > FRAME_TOLERANCE:
        raise ObservationError(
            f"{where}: frame_dt = {dt:g} s does not match the 'time' values in all_data.json "
            f"(frames are {np.min(steps):g} s apart, i.e. {1 / np.min(steps):.4g} frames per second)"
        )
    return dt


def read_dataset(
    folder: str | os.PathLike,
    hint: str | os.PathLike | dict | None = None,
    *,
    downscale: int = 1,
    mask_source: str = "auto",
) -> Dataset:
    """Read and check an identify dataset (see docs/file_formats.md).

    Arguments:
        folder: the PAC-NeRF-layout folder (``all_data.json``, ``data/``).
        hint: a ``scene_hint.toml`` path or dict; default ``folder/scene_hint.toml`` when it
            exists.
        downscale: integer image shrink factor (as :func:`jaxmpm.load_pacnerf`).
        mask_source: the material masks' source (as :func:`jaxmpm.load_pacnerf`).

    Returns:
        A :class:`Dataset`.

    Raises:
        ObservationError: one line naming the file or view: inconsistent camera counts, a
            view without images, masks of the wrong size, a hint with unknown keys, a
            ``frame_dt`` that does not match ``time``.
    """
    from ..datasets import load_pacnerf

    folder = Path(folder)
    if not folder.is_dir():
        raise ObservationError(f"dataset folder not found: {folder}")
    if hint is None and (folder / "scene_hint.toml").is_file():
        hint = folder / "scene_hint.toml"
    hint_dict = read_hint(hint)
    entries, H, W = _check_entries(folder)
    obs = load_pacnerf(folder, downscale=downscale, mask_source=mask_source)
    V = obs.masks.shape[0]
    empty = [v for v in range(V) if not obs.masks[v, 0].any()]
    if empty:
        raise ObservationError(f"view {empty[0]}: the first frame's mask is empty (the body is not seen)")
    where = os.fspath(hint) if hint is not None and not isinstance(hint, dict) else "scene hint"
    dt = _frame_dt(np.asarray(obs.times, float), hint_dict, where)
    colliders = _collider_masks(folder, V, H, W, downscale)
    plates = _plates(folder, entries, V, H, W, downscale)
    return Dataset(folder=folder, observation=obs, collider_masks=colliders, hint=hint_dict, frame_dt=dt, plates=plates)
