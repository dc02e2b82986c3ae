"""Pinhole cameras: projection, rays, look-at, the PAC-NeRF rig and its ``all_data.json``.

Conventions (DESIGN §4, §5.2):

* ``K (3, 3)`` maps camera coordinates to pixel-homogeneous coordinates; pixel
  ``(row, col)`` covers ``[col, col+1) × [row, row+1)`` and its centre is
  ``(col + 0.5, row + 0.5)``, so ``cx = width/2`` is the image centre (as in PAC-NeRF's
  ``all_data.json`` and DVGO's ``mode="center"`` rays).
* ``cam_to_world (4, 4)`` maps camera coordinates to world coordinates with **OpenCV
  axes**: x right, y down, z forward (the viewing direction). It must be a rigid motion
  (orthonormal rotation with determinant +1).
* Depth means the camera-frame z coordinate ("z-depth"), not the distance along a ray.

A ``Camera`` may also hold a batch of V views (``K (V, 3, 3)``, ``cam_to_world
(V, 4, 4)``, one shared width/height) — see :func:`stack_cameras`; map a function over
such a batch with ``jax.vmap`` or ``jax.lax.map`` (width and height are static).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..errors import ObservationError

#: Flip between OpenCV camera axes (x right, y down, z forward) and OpenGL/Blender camera
#: axes (x right, y up, z backward): ``c2w_gl = c2w_cv @ _CV_GL`` and vice versa.
_CV_GL = np.diag([1.0, -1.0, -1.0, 1.0])

_DET_TOL = 1e-6
_ORTHO_TOL = 1e-3


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _validate(K: Any, c2w: Any, width: int, height: int) -> None:
    """Raise ObservationError for invalid intrinsics, poses or image sizes."""
    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)):
            raise ObservationError(f"camera {name} must be an int, got {size!r}")
        if size <= 0:
            raise ObservationError(f"camera {name} must be positive, got {size}")
    if K.shape[-2:] != (3, 3):
        raise ObservationError(f"intrinsics K must have shape (..., 3, 3), got {K.shape}")
    if c2w.shape[-2:] != (4, 4):
        raise ObservationError(f"cam_to_world must have shape (..., 4, 4), got {c2w.shape}")
    if K.shape[:-2] != c2w.shape[:-2]:
        raise ObservationError(
            f"K and cam_to_world have different batch shapes: {K.shape[:-2]} vs {c2w.shape[:-2]}"
        )
    if not (_is_concrete(K) and _is_concrete(c2w)):
        return  # values are checked when the camera is built from concrete arrays
    Kn = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
    Pn = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    for i, (k, p) in enumerate(zip(Kn, Pn)):
        where = f" (view {i})" if Kn.shape[0] > 1 else ""
        if not np.all(np.isfinite(k)):
            raise ObservationError(f"intrinsics K contain NaN or inf{where}: {k.tolist()}")
        if not (k[0, 0] > 0 and k[1, 1] > 0):
            raise ObservationError(
                f"focal lengths must be positive{where}: fx={k[0, 0]:g}, fy={k[1, 1]:g}"
            )
        if abs(k[1, 0]) > 1e-9 or np.max(np.abs(k[2] - np.array([0.0, 0.0, 1.0]))) > 1e-9:
            raise ObservationError(
                f"intrinsics K must be upper triangular with last row (0, 0, 1){where}: {k.tolist()}"
            )
        if not np.all(np.isfinite(p)):
            raise ObservationError(f"cam_to_world contains NaN or inf{where}")
        if np.max(np.abs(p[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > 1e-6:
            raise ObservationError(
                f"cam_to_world must have last row (0, 0, 0, 1){where}, got {p[3].tolist()}"
            )
        R = p[:3, :3]
        det = float(np.linalg.det(R))
        if abs(det) < _DET_TOL:
            raise ObservationError(
                f"cam_to_world is not invertible{where}: det of its rotation part is {det:.3g}"
            )
        err = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if err > _ORTHO_TOL or det < 0:
            raise ObservationError(
                f"cam_to_world is not a rigid motion{where}: its rotation part has "
                f"max|RᵀR − I| = {err:.3g} and det = {det:.3g} (need an orthonormal "
                "rotation with det +1)"
            )


class Camera(eqx.Module):
    """A pinhole camera (or a batch of V cameras sharing one image size).

    Attributes:
        K: intrinsics, ``(3, 3)`` or ``(V, 3, 3)``, pixels.
        cam_to_world: camera-to-world rigid transform, ``(4, 4)`` or ``(V, 4, 4)``,
            OpenCV camera axes (x right, y down, z forward).
        width: image width in pixels (static).
        height: image height in pixels (static).
    """

    K: Float[Array, "*V 3 3"]
    cam_to_world: Float[Array, "*V 4 4"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, K, cam_to_world, width: int, height: int, *, dtype=None):
        """Build and validate a camera.

        Arguments:
            K: intrinsics ``(3, 3)`` (or ``(V, 3, 3)``).
            cam_to_world: ``(4, 4)`` (or ``(V, 4, 4)``), OpenCV axes.
            width, height: image size in pixels (positive ints).
            dtype: floating dtype of the stored arrays (default: that of ``K`` if it is a
                floating array, as JAX stores it: a NumPy float64 ``K`` gives float32 unless
                x64 is enabled; else float32).

        Raises:
            ObservationError: non-positive focal lengths or sizes, a singular or
                non-rigid pose, NaNs, or malformed shapes.
        """
        if dtype is None:
            dt = getattr(K, "dtype", None)
            floating = dt is not None and jnp.issubdtype(dt, jnp.floating)
            dtype = jax.dtypes.canonicalize_dtype(dt) if floating else jnp.float32
        K = jnp.asarray(K, dtype=dtype) if _is_concrete(K) else K.astype(dtype)
        cam_to_world = (
            jnp.asarray(cam_to_world, dtype=dtype)
            if _is_concrete(cam_to_world)
            else cam_to_world.astype(dtype)
        )
        _validate(K, cam_to_world, width, height)
        self.K = K
        self.cam_to_world = cam_to_world
        self.width = int(width)
        self.height = int(height)

    # --- basic properties -------------------------------------------------------------

    @property
    def dtype(self):
        return self.K.dtype

    @property
    def num_views(self) -> int | None:
        """V for a batch of cameras, ``None`` for a single camera."""
        return None if self.K.ndim == 2 else int(self.K.shape[0])

    @property
    def num_pixels(self) -> int:
        return self.width * self.height

    @property
    def position(self) -> Float[Array, "*V 3"]:
        """Camera centre in world coordinates."""
        return self.cam_to_world[..., :3, 3]

    @property
    def rotation(self) -> Float[Array, "*V 3 3"]:
        """Camera-to-world rotation; its columns are the camera's x, y, z axes in world."""
        return self.cam_to_world[..., :3, :3]

    @property
    def world_to_cam(self) -> Float[Array, "*V 4 4"]:
        """The inverse rigid transform ``[Rᵀ, −Rᵀo; 0 0 0 1]``."""
        R = self.rotation
        Rt = jnp.swapaxes(R, -1, -2)
        t = -jnp.einsum("...ij,...j->...i", Rt, self.position)
        top = jnp.concatenate([Rt, t[..., None]], axis=-1)
        bottom = jnp.broadcast_to(
            jnp.asarray([0.0, 0.0, 0.0, 1.0], dtype=self.dtype), top.shape[:-2] + (1, 4)
        )
        return jnp.concatenate([top, bottom], axis=-2)

    def astype(self, dtype) -> Camera:
        """The same camera with arrays of another floating dtype."""
        return eqx.tree_at(
            lambda c: (c.K, c.cam_to_world), self, (self.K.astype(dtype), self.cam_to_world.astype(dtype))
        )

    def view(self, i: int) -> Camera:
        """Camera ``i`` of a batch."""
        if self.num_views is None:
            raise ValueError("view() needs a batch of cameras (see stack_cameras)")
        return jax.tree_util.tree_map(lambda a: a[i], self)

    def resized(self, width: int, height: int) -> Camera:
        """The same pose and field of view at another image size (K rescaled)."""
        sx = width / self.width
        sy = height / self.height
        S = jnp.asarray([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=self.dtype)
        return Camera(S @ self.K, self.cam_to_world, width, height)

    # --- geometry (single camera; vmap for batches) -----------------------------------

    def to_camera(self, points: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """World points to camera coordinates (OpenCV axes)."""
        R = self.rotation
        return jnp.einsum("ji,...j->...i", R, points - self.position)

    def project(
        self, points: Float[Array, "... 3"]
    ) -> tuple[Float[Array, "... 2"], Float[Array, "..."]]:
        """Project world points to continuous pixel coordinates.

        Returns:
            ``(uv, depth)``: pixel coordinates ``(..., 2)`` (x = column, y = row, pixel
            centres at ``+0.5``) and camera z-depth ``(...)``. Points with depth ≤ 0 are
            behind the camera; their ``uv`` is meaningless (finite, not NaN).
        """
        pc = self.to_camera(points)
        z = pc[..., 2]
        z_safe = jnp.where(jnp.abs(z) > 1e-12, z, 1e-12)
        hom = jnp.einsum("ij,...j->...i", self.K, pc)
        return hom[..., :2] / z_safe[..., None], z

    def unproject(
        self, uv: Float[Array, "... 2"], depth: Float[Array, "..."]
    ) -> Float[Array, "... 3"]:
        """Inverse of :meth:`project`: pixel coordinates and z-depth to world points."""
        dirs = self.camera_dirs(uv)
        pc = dirs * depth[..., None]
        return jnp.einsum("ij,...j->...i", self.rotation, pc) + self.position

    def camera_dirs(self, uv: Float[Array, "... 2"]) -> Float[Array, "... 3"]:
        """Camera-frame directions with z = 1 through pixel coordinates ``uv``."""
        K = self.K
        fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
        y = (uv[..., 1] - cy) / fy
        x = (uv[..., 0] - cx - s * y) / fx
        return jnp.stack([x, y, jnp.ones_like(x)], axis=-1)

    def pixel_coordinates(self, pixels: Int[Array, " P"] | None = None) -> Float[Array, "P 2"]:
        """Centres ``(col + 0.5, row + 0.5)`` of flat pixel indices (``row*width + col``).

        With ``pixels=None``, all pixels in raster order (``P = height*width``).
        """
        if pixels is None:
            pixels = jnp.arange(self.num_pixels, dtype=jnp.int32)
        row = pixels // self.width
        col = pixels - row * self.width
        return jnp.stack([col.astype(self.dtype) + 0.5, row.astype(self.dtype) + 0.5], axis=-1)

    def rays(
        self, pixels: Int[Array, " P"] | None = None
    ) -> tuple[Float[Array, "P 3"], Float[Array, "P 3"]]:
        """World-space rays through pixel centres.

        Arguments:
            pixels: flat pixel indices ``row*width + col``; ``None`` for all pixels.

        Returns:
            ``(origins, directions)``, each ``(P, 3)``; directions have unit length.
            The z-depth of ``o + t d`` is ``t * (d · camera_z)``.
        """
        d_cam = self.camera_dirs(self.pixel_coordinates(pixels))
        d = jnp.einsum("ij,pj->pi", self.rotation, d_cam)
        d = d / jnp.sqrt(jnp.sum(d * d, axis=-1, keepdims=True))
        o = jnp.broadcast_to(self.position, d.shape)
        return o, d


# --- building cameras ------------------------------------------------------------------


def stack_cameras(cameras: Sequence[Camera]) -> Camera:
    """Stack single cameras of one image size into a batch (``K (V,3,3)`` …).

    Raises:
        ObservationError: if the cameras differ in image size, or the list is empty.
    """
    cameras = list(cameras)
    if not cameras:
        raise ObservationError("stack_cameras needs at least one camera")
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ObservationError(f"cameras have different image sizes (width, height): {sorted(sizes)}")
    if any(c.num_views is not None for c in cameras):
        raise ObservationError("stack_cameras takes single cameras, not batches")
    dtype = jnp.result_type(*[c.dtype for c in cameras])
    return Camera(
        jnp.stack([c.K.astype(dtype) for c in cameras]),
        jnp.stack([c.cam_to_world.astype(dtype) for c in cameras]),
        cameras[0].width,
        cameras[0].height,
    )


def unstack_cameras(cameras: Camera) -> list[Camera]:
    """The single cameras of a batch (a single camera gives a one-element list)."""
    if cameras.num_views is None:
        return [cameras]
    return [cameras.view(i) for i in range(cameras.num_views)]


def as_camera_batch(cameras: Camera | Sequence[Camera]) -> Camera:
    """A batch of cameras from a batch, a single camera or a list of single cameras."""
    if isinstance(cameras, Camera):
        if cameras.num_views is None:
            return jax.tree_util.tree_map(lambda a: a[None], cameras)
        return cameras
    return stack_cameras(cameras)


def intrinsics_from_fov(fov_deg: float, width: int, height: int) -> np.ndarray:
    """Square-pixel intrinsics for a **vertical** field of view, principal point at the centre."""
    if not (0.0 < fov_deg < 180.0):
        raise ObservationError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    f = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(
    eye,
    target,
    up=(0.0, 1.0, 0.0),
    fov_deg: float = 45.0,
    width: int = 64,
    height: int | None = None,
    *,
    dtype=jnp.float32,
) -> Camera:
    """A camera at ``eye`` looking at ``target``.

    Arguments:
        eye: camera centre, world coordinates (3,).
        target: the point imaged at the principal point (3,).
        up: world direction that appears upwards in the image (its projection on the
            image plane points to decreasing rows).
        fov_deg: vertical field of view in degrees (square pixels).
        width, height: image size in pixels (``height`` defaults to ``width``).
        dtype: dtype of the camera's arrays.

    Raises:
        ObservationError: ``eye == target``, ``up`` parallel to the viewing direction,
            or a bad field of view / size.
    """
    height = width if height is None else height
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    fwd = target - eye
    n = np.linalg.norm(fwd)
    if n < 1e-12:
        raise ObservationError("look_at: eye and target coincide")
    fwd /= n
    right = np.cross(fwd, up)
    nr = np.linalg.norm(right)
    if nr < 1e-9 * max(np.linalg.norm(up), 1e-30):
        raise ObservationError("look_at: 'up' is parallel to the viewing direction")
    right /= nr
    down = np.cross(fwd, right)  # = −(true up); (right, down, fwd) is right-handed
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, eye
    return Camera(intrinsics_from_fov(fov_deg, width, height), c2w, width, height, dtype=dtype)


def _res(res) -> tuple[int, int]:
    if isinstance(res, (int, np.integer)):
        return int(res), int(res)
    w, h = res
    return int(w), int(h)


def pacnerf_rig(
    num_views: int = 11,
    radius: float = 3.0,
    target=(0.0, 0.0, 0.0),
    fov_deg: float = 45.0,
    res: int | tuple[int, int] = 400,
    *,
    up=(0.0, 1.0, 0.0),
    min_elevation_deg: float = 5.0,
    max_elevation_deg: float = 75.0,
    dtype=jnp.float32,
) -> Camera:
    """A PAC-NeRF-like rig: ``num_views`` cameras on a sphere looking at ``target``.

    PAC-NeRF renders 11 views with a 45° field of view from a sphere of radius 3 around
    the object, all above the ground (world up = +y). The exact per-scene poses live in
    each scene's ``all_data.json`` (:func:`load_cameras_json`); this helper spreads the
    cameras deterministically over the upper hemisphere instead: elevations evenly
    spaced in ``[min_elevation_deg, max_elevation_deg]`` and azimuths advancing by the
    golden angle.

    Arguments:
        num_views: number of cameras V.
        radius: distance from ``target``.
        target: the point all cameras look at.
        fov_deg: vertical field of view, degrees.
        res: image size, an int (square) or ``(width, height)``.
        up: world up direction.
        dtype: dtype of the arrays.

    Returns:
        A batch of V cameras.
    """
    if num_views < 1:
        raise ObservationError(f"num_views must be >= 1, got {num_views}")
    width, height = _res(res)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    # an orthonormal frame (a, b, up) for the azimuth
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    b = np.cross(a, up)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    for i in range(num_views):
        frac = 0.5 if num_views == 1 else i / (num_views - 1)
        elev = math.radians(min_elevation_deg + frac * (max_elevation_deg - min_elevation_deg))
        az = i * golden
        direction = math.cos(elev) * (math.cos(az) * a + math.sin(az) * b) + math.sin(elev) * up
        cams.append(
            look_at(target + radius * direction, target, up, fov_deg, width, height, dtype=dtype)
        )
    return stack_cameras(cams)


# --- PAC-NeRF / GIC all_data.json ------------------------------------------------------

_FILE_RE = re.compile(r"r_(-?\d+)_(-?\d+)\.[A-Za-z0-9]+$")


def load_cameras_json(
    path: str | os.PathLike,
    *,
    width: int | None = None,
    height: int | None = None,
    convention: str = "opengl",
    dtype=jnp.float32,
) -> tuple[Camera, list[dict]]:
    """Read the cameras of a PAC-NeRF / GIC ``all_data.json``.

    The file is a list of ``{"file_path": "./data/r_{view}_{frame}.png", "time": t,
    "c2w": 3×4 (or 4×4), "intrinsic": 3×3}``, one entry per image. PAC-NeRF's ``c2w`` uses
    **OpenGL/Blender camera axes** (x right, y up, camera looking along −z: in its files
    the camera sits at ``+3·z_axis`` from the object it looks at); it is converted to
    OpenCV axes here by ``c2w_cv = c2w_gl · diag(1, −1, −1, 1)``. Pass
    ``convention="opencv"`` for files that already use OpenCV axes.

    Arguments:
        path: the JSON file.
        width, height: image size; by default ``2·cx`` and ``2·cy`` (PAC-NeRF puts the
            principal point at the image centre); the files do not store it.
        convention: ``"opengl"`` (PAC-NeRF, GIC) or ``"opencv"``.
        dtype: dtype of the camera arrays.

    Returns:
        ``(cameras, entries)``: a batch of V cameras ordered by view index, and one dict
        per file entry ``{"view", "frame", "time", "file_path"}`` (``frame`` is ``None``
        when the file name does not follow ``r_{view}_{frame}``).

    Raises:
        ObservationError: unreadable/malformed file, inconsistent poses or intrinsics for
            the same view, or invalid cameras.
    """
    if convention not in ("opengl", "opencv"):
        raise ObservationError(f"convention must be 'opengl' or 'opencv', got {convention!r}")
    try:
        with open(path) as fh:
            data = json.load(fh)
    except (OSError, json.JSONDecodeError) as exc:
        raise ObservationError(f"cannot read camera file {os.fspath(path)!r}: {exc}") from exc
    if isinstance(data, dict) and "frames" in data:
        data = data["frames"]
    if not isinstance(data, list) or not data:
        raise ObservationError(f"{os.fspath(path)!r}: expected a non-empty list of frame entries")

    views: dict[Any, tuple[np.ndarray, np.ndarray]] = {}
    entries = []
    for n, item in enumerate(data):
        try:
            c2w = np.asarray(item["c2w"], dtype=np.float64)
            K = np.asarray(item["intrinsic"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise ObservationError(
                f"{os.fspath(path)!r}: entry {n} needs 'c2w' (3×4) and 'intrinsic' (3×3): {exc}"
            ) from exc
        if c2w.shape == (3, 4):
            c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
        if c2w.shape != (4, 4) or K.shape != (3, 3):
            raise ObservationError(
                f"{os.fspath(path)!r}: entry {n} has c2w of shape {c2w.shape} and intrinsic "
                f"of shape {K.shape}; expected (3, 4) and (3, 3)"
            )
        if convention == "opengl":
            c2w = c2w @ _CV_GL
        file_path = item.get("file_path", "")
        m = _FILE_RE.search(str(file_path))
        if m is not None:
            key, frame = int(m.group(1)), int(m.group(2))
        else:
            key, frame = None, None
            for k, (Kv, Pv) in views.items():
                if np.allclose(Kv, K, atol=1e-9) and np.allclose(Pv, c2w, atol=1e-9):
                    key = k
                    break
            if key is None:
                key = ("auto", len(views))
        if key in views:
            Kv, Pv = views[key]
            if not (np.allclose(Kv, K, atol=1e-6) and np.allclose(Pv, c2w, atol=1e-6)):
                raise ObservationError(
                    f"{os.fspath(path)!r}: view {key} has different cameras in different entries"
                )
        else:
            views[key] = (K, c2w)
        entries.append(
            {"view": key, "frame": frame, "time": float(item.get("time", 0.0)), "file_path": file_path}
        )

    keys = sorted((k for k in views if not isinstance(k, tuple)), key=int) + [
        k for k in views if isinstance(k, tuple)
    ]
    index = {k: i for i, k in enumerate(keys)}
    for e in entries:
        e["view"] = index[e["view"]]
    Ks = np.stack([views[k][0] for k in keys])
    Ps = np.stack([views[k][1] for k in keys])
    if width is None:
        width = int(round(2.0 * Ks[0, 0, 2]))
    if height is None:
        height = int(round(2.0 * Ks[0, 1, 2]))
    return Camera(Ks, Ps, width, height, dtype=dtype), entries


def save_cameras_json(
    path: str | os.PathLike,
    cameras: Camera | Sequence[Camera],
    times: Sequence[float] = (0.0,),
    *,
    frames: Sequence[int] | None = None,
    file_pattern: str = "./data/r_{view}_{frame}.png",
    convention: str = "opengl",
) -> None:
    """Write cameras in the PAC-NeRF ``all_data.json`` format (one entry per view × time).

    Arguments:
        path: output file.
        cameras: a batch of cameras (or a list of single cameras), OpenCV axes.
        times: times (s) of the frames; entry ``(v, f)`` gets ``times[f]``.
        frames: frame numbers used in the file names (default ``0 .. len(times)-1``).
        file_pattern: the image path of entry ``(view, frame)``.
        convention: camera axes written to ``c2w``: ``"opengl"`` (PAC-NeRF) or ``"opencv"``.
    """
    if convention not in ("opengl", "opencv"):
        raise ObservationError(f"convention must be 'opengl' or 'opencv', got {convention!r}")
    cams = as_camera_batch(cameras)
    Ks = np.asarray(cams.K, dtype=np.float64)
    Ps = np.asarray(cams.cam_to_world, dtype=np.float64)
    if convention == "opengl":
        Ps = Ps @ _CV_GL
    frames = list(range(len(times))) if frames is None else list(frames)
    if len(frames) != len(times):
        raise ObservationError(f"got {len(frames)} frame numbers for {len(times)} times")
    out = []
    for v in range(Ks.shape[0]):
        for f, t in zip(frames, times):
            out.append(
                {
                    "file_path": file_pattern.format(view=v, frame=f),
                    "time": float(t),
                    "c2w": Ps[v, :3, :].tolist(),
                    "intrinsic": Ks[v].tolist(),
                }
            )
    with open(path, "w") as fh:
        json.dump(out, fh, indent=2)


def check_image_size(cameras: Camera, images: Any, *, rgb: bool, what: str = "images") -> None:
    """Raise ObservationError unless ``images`` match the cameras' image size and count.

    Arguments:
        cameras: a single camera or a batch of V cameras.
        images: masks ``(V, [T,] H, W)`` (``rgb=False``) or RGB ``(V, [T,] H, W, 3)``
            (``rgb=True``); for a single camera the leading V axis is absent.
        rgb: whether ``images`` has a trailing channel axis.
        what: name used in the message.
    """
    shape = tuple(np.shape(images))
    need = 3 if rgb else 2
    if len(shape) < need or (rgb and shape[-1] != 3):
        raise ObservationError(
            f"{what} have shape {shape}; expected (..., H, W{', 3' if rgb else ''})"
        )
    hw = shape[-3:-1] if rgb else shape[-2:]
    if hw != (cameras.height, cameras.width):
        raise ObservationError(
            f"{what} have image size (H, W) = {hw} but the cameras are "
            f"(H, W) = ({cameras.height}, {cameras.width})"
        )
    nv = cameras.num_views
    if nv is not None and (len(shape) <= need or shape[0] != nv):
        raise ObservationError(
            f"{what} of shape {shape} do not have a leading axis of {nv} views (one per camera)"
        )


def project_points(points: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points with one pinhole camera (OpenCV axes, NumPy; no gradient).

    Arguments:
        points: ``(N, 3)`` world points, m.
        K: ``(3, 3)`` intrinsics.
        cam_to_world: ``(4, 4)`` pose, OpenCV axes.

    Returns:
        ``(uv (N, 2), depth (N,))``: pixel coordinates (column, row; pixel centres at +0.5)
        and camera z-depth (≤ 0 behind the camera).
    """
    points, K, cam_to_world = (np.asarray(a, float) for a in (points, K, cam_to_world))
    R, c = cam_to_world[:3, :3], cam_to_world[:3, 3]
    pc = (points - c) @ R
    z = pc[:, 2]
    hom = pc @ K.T
    return hom[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None], z


def pixel_of(points: np.ndarray, K: np.ndarray, cam_to_world: np.ndarray, height: int, width: int):
    """The pixel each point projects into: ``(row (N,), col (N,), seen (N,) bool)``; ``seen``
    is False behind the camera and outside the image (row and col are then meaningless)."""
    uv, z = project_points(points, K, cam_to_world)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    return row, col, (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)


def mean_colors(points: np.ndarray, images: np.ndarray, masks: np.ndarray | None, intrinsics: np.ndarray,
                cam_to_world: np.ndarray) -> np.ndarray:
    """Each point's mean colour over the views where it projects inside the mask (every view
    that sees it when ``masks`` is None); occlusion is ignored, so an interior point takes the
    colour of the surface in front of it. A point no view sees gets the mean of the others.

    Arguments:
        points: ``(N, 3)`` m.
        images: ``(V, H, W, 3)`` colours (any scale; the result has it).
        masks: ``(V, H, W)`` bool, or None.
        intrinsics, cam_to_world: ``(V, 3, 3)``, ``(V, 4, 4)`` (OpenCV axes).

    Returns:
        ``(N, 3)`` float64.
    """
    images = np.asarray(images, float)
    V, H, W = images.shape[:3]
    total, count = np.zeros((len(points), 3)), np.zeros(len(points))
    for v in range(V):
        row, col, ok = pixel_of(points, intrinsics[v], cam_to_world[v], H, W)
        if masks is not None:
            ok[ok] &= np.asarray(masks[v], bool)[row[ok], col[ok]]
        total[ok] += images[v, row[ok], col[ok]]
        count[ok] += 1
    mean = total.sum(0) / max(count.sum(), 1.0)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1.0)[:, None], mean)
