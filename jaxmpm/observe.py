"""Observation files (DESIGN §5.2, ``format = "jaxmpm.observation/1"``) and atomic writes."""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import tempfile
import threading
import zipfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from .errors import ObservationError

FORMAT = "jaxmpm.observation/1"


@dataclass
class Observation:
    """Observed data of one sequence (NumPy arrays, SI units).

    Attributes:
        times: ``(T,)`` seconds since the scene's start.
        positions: ``(T, N, D)`` tracked points, NaN where missing; or None.
        point_ids: ``"particles"`` when point i is simulation particle i; else None.
        masks: ``(V, T, H, W)`` uint8 silhouettes (0/255); or None.
        images: ``(V, T, H, W, 3)`` uint8 RGB; or None.
        intrinsics: ``(V, 3, 3)`` pinhole intrinsics (with masks/images).
        cam_to_world: ``(V, 4, 4)`` camera poses, OpenCV axes (with masks/images).
        probe_names: names of probe time series, e.g. ``("front_x",)``.
        probe_times: ``(P, Tp)`` seconds.
        probe_values: ``(P, Tp)`` SI units.
        scene: the scene spec as JSON text (or None).
    """

    times: np.ndarray
    positions: np.ndarray | None = None
    point_ids: str | None = None
    masks: np.ndarray | None = None
    images: np.ndarray | None = None
    intrinsics: np.ndarray | None = None
    cam_to_world: np.ndarray | None = None
    probe_names: tuple[str, ...] | None = None
    probe_times: np.ndarray | None = None
    probe_values: np.ndarray | None = None
    scene: str | None = field(default=None, repr=False)

    def __post_init__(self):
        self.validate()

    @property
    def tracks_particles(self) -> bool:
        """Whether ``positions`` track every simulation particle by id (``point_ids ==
        "particles"``): such tracks pin the velocity and contact from any frames."""
        return self.positions is not None and self.point_ids == "particles"

    def validate(self, source: str = "observation") -> None:
        """Check shapes and the presence rules of §5.2; raise ObservationError naming the key."""
        for key in ("times", "positions", "intrinsics", "cam_to_world", "probe_times", "probe_values"):
            value = getattr(self, key)
            if value is not None and not _is_real(value):
                raise ObservationError(f"{source}: '{key}' must be a numeric array, got {np.asarray(value).dtype}")
        t = np.asarray(self.times)
        if t.ndim != 1 or len(t) == 0 or not np.all(np.isfinite(t)):
            raise ObservationError(f"{source}: 'times' must be a non-empty 1-D array of finite seconds")
        if np.any(np.diff(t) <= 0):
            raise ObservationError(f"{source}: 'times' must be strictly increasing")
        if all(a is None for a in (self.positions, self.masks, self.images, self.probe_names)):
            raise ObservationError(f"{source}: needs at least one of 'positions', 'masks', 'images', 'probe_names'")
        T = len(t)
        if self.positions is not None:
            p = np.asarray(self.positions)
            if p.ndim != 3 or p.shape[0] != T or p.shape[1] == 0 or p.shape[2] not in (2, 3):
                raise ObservationError(f"{source}: 'positions' must have shape (T={T}, N >= 1, D = 2 or 3), got {p.shape}")
            if np.any(np.isinf(p)):
                raise ObservationError(f"{source}: 'positions' contain infinite values (use NaN for missing points)")
            if np.all(np.isnan(p)):
                raise ObservationError(f"{source}: 'positions' are all NaN")
        if self.point_ids not in (None, "particles"):
            raise ObservationError(f"{source}: 'point_ids' must be 'particles' or absent, got {self.point_ids!r}")
        for key in ("masks", "images"):
            arr = getattr(self, key)
            if arr is None:
                continue
            arr = np.asarray(arr)
            want = 4 if key == "masks" else 5
            if arr.ndim != want or arr.shape[1] != T or (key == "images" and arr.shape[-1] != 3):
                shape = "(V, T, H, W)" if key == "masks" else "(V, T, H, W, 3)"
                raise ObservationError(f"{source}: '{key}' must have shape {shape} with T={T}, got {arr.shape}")
            if arr.dtype != np.uint8:
                raise ObservationError(f"{source}: '{key}' must be uint8, got {arr.dtype}")
            if self.intrinsics is None or self.cam_to_world is None:
                raise ObservationError(f"{source}: '{key}' need 'intrinsics' and 'cam_to_world'")
            V = arr.shape[0]
            if np.shape(self.intrinsics) != (V, 3, 3) or np.shape(self.cam_to_world) != (V, 4, 4):
                raise ObservationError(
                    f"{source}: 'intrinsics' must be (V={V}, 3, 3) and 'cam_to_world' (V={V}, 4, 4), got "
                    f"{np.shape(self.intrinsics)} and {np.shape(self.cam_to_world)}"
                )
        if self.probe_names is not None:
            if isinstance(self.probe_names, str) or not all(isinstance(n, str) for n in self.probe_names):
                raise ObservationError(f"{source}: 'probe_names' must be a list of strings, got {self.probe_names!r}")
            P = len(self.probe_names)
            pt, pv = np.asarray(self.probe_times), np.asarray(self.probe_values)
            if pt.ndim != 2 or pt.shape[0] != P or pv.shape != pt.shape:
                raise ObservationError(
                    f"{source}: 'probe_times' and 'probe_values' must both be (P={P}, Tp), got {pt.shape} and {pv.shape}"
                )

        if self.scene is not None:
            try:
                spec = json.loads(self.scene)
            except (TypeError, ValueError) as err:
                raise ObservationError(f"{source}: 'scene' must be the scene spec as JSON text ({err})") from None
            if not isinstance(spec, dict):
                raise ObservationError(f"{source}: 'scene' must be a JSON object, got {type(spec).__name__}")

    @property
    def scene_spec(self) -> dict | None:
        return None if self.scene is None else json.loads(self.scene)

    def made_by(self, model) -> bool:
        """Whether these data may have been made by ``model``'s transfers on its grid: the
        embedded scene (``scene``) has its ``dx`` and FLIP blend, or, with none embedded, they
        are tracks of its own particles (only a simulation with its particles makes those).
        Data it did not make carry its transfers' numerical error (docs/materials.md, "In
        fits")."""
        made = self.scene_spec
        if made is None:
            return self.tracks_particles
        return (float(made.get("flip", 0.0)) == model.flip
                and math.isclose(float(made["dx"]), model.grid.dx, rel_tol=1e-6))


def _is_real(value) -> bool:
    """Whether ``value`` is an array of real numbers (not strings, objects or booleans)."""
    dtype = np.asarray(value).dtype
    return np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)


def atomic_write(path: str | Path, write) -> Path:
    """Call ``write(tmp_path)`` then rename onto ``path``: a failure never clobbers ``path``.

    The temporary file sits in ``path``'s folder (so the rename is atomic) and is removed on
    any exit, including Ctrl-C and SIGTERM. Errors name ``path``, not the temporary file.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    except OSError as err:
        raise OSError(f"cannot write {path}: {err.strerror or err}") from None
    os.close(fd)
    try:
        with _sigterm_as_exit():
            write(tmp)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
            os.replace(tmp, path)
    except OSError as err:
        raise OSError(f"cannot write {path}: {err.strerror or err}") from None
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


@contextlib.contextmanager
def _sigterm_as_exit():
    """Within the block, SIGTERM raises ``SystemExit(143)`` so that ``finally`` clauses run
    (the default action kills the process at once). Only in the main thread, where Python
    delivers signals; elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def save_observation(path: str | Path, obs: Observation) -> Path:
    """Write ``obs`` to an ``.npz`` file atomically."""
    obs.validate()
    arrays = {"format": np.array(FORMAT), "times": np.asarray(obs.times, float)}
    for f in fields(obs):
        value = getattr(obs, f.name)
        if f.name in ("times",) or value is None:
            continue
        if f.name in ("point_ids", "scene"):
            arrays[f.name] = np.array(value)
        elif f.name == "probe_names":
            arrays[f.name] = np.array(list(value), dtype=str)
        else:
            arrays[f.name] = np.asarray(value)

    def write(tmp):
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    return atomic_write(path, write)


def load_observation(path: str | Path) -> Observation:
    """Read an observation file (``np.load(..., allow_pickle=False)``) and validate it."""
    path = Path(path)
    if not path.is_file():
        raise ObservationError(f"observation file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ObservationError(f"{path}: not an .npz observation file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as data:
            contents = {k: data[k] for k in data.files}
    except Exception as err:  # zip errors, pickled objects, truncated files
        raise ObservationError(f"{path}: not a readable .npz observation file ({err})") from None
    fmt = contents.pop("format", None)
    if fmt is None or str(fmt) != FORMAT:
        raise ObservationError(f"{path}: 'format' must be {FORMAT!r}, got {None if fmt is None else str(fmt)!r}")
    if "times" not in contents:
        raise ObservationError(f"{path}: missing required key 'times'")
    known = {f.name for f in fields(Observation)}
    unknown = set(contents) - known
    if unknown:
        raise ObservationError(f"{path}: unknown keys {sorted(unknown)}")
    kwargs = dict(contents)
    for key in ("point_ids", "scene"):
        if key in kwargs:
            value = kwargs[key]
            if value.shape != () or value.dtype.kind != "U":
                raise ObservationError(f"{path}: '{key}' must be a string, got a {value.dtype} array of shape {value.shape}")
            kwargs[key] = str(kwargs[key])
    if "probe_names" in kwargs:
        names = kwargs["probe_names"]
        if names.ndim != 1 or names.dtype.kind != "U":
            raise ObservationError(f"{path}: 'probe_names' must be a 1-D array of strings, got {names.dtype} {names.shape}")
        kwargs["probe_names"] = tuple(str(s) for s in names)
    try:
        obs = Observation.__new__(Observation)
        for f in fields(Observation):
            setattr(obs, f.name, kwargs.get(f.name))
        obs.validate(str(path))
    except ObservationError:
        raise
    except Exception as err:
        raise ObservationError(f"{path}: malformed observation ({err})") from None
    return obs


# --------------------------------------------------------------------------- scene checks


def check_observation_matches(model, observation: Observation) -> None:
    """Raise ObservationError when the observation's embedded scene has another dimension or
    number of bodies than ``model``."""
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
