"""Reading scene specs and files: collider specs, mesh/polyline/surfel files, placements, paths.

Shared by :mod:`jaxmpm.scene` (bodies) and the colliders. Every error is a
:class:`~jaxmpm.errors.SceneError` that names the key or the file (``where`` is the prefix of
the message, e.g. ``"collider 'floor'"`` or ``"bodies[0]"``).
"""

from __future__ import annotations

import importlib.resources
import os

import numpy as np

from ..errors import SceneError
from .base import rotation_matrix, vector
from .box import Box
from .disks import GaussianDisks, quaternion_to_matrix
from .mesh import MeshCollider
from .plane import Plane

#: Scene ``type`` -> (constructor from a spec dict, required keys, optional keys).
#: Every collider spec may also have ``contact``, ``friction``, ``restitution``, ``name``.
COLLIDER_TYPES: dict[str, tuple] = {}


def asset_path(name: str) -> str:
    """Path of a file shipped in ``jaxmpm/assets`` (``"bunny.obj"`` or ``"meshes/bunny.obj"``).

    Shipped meshes: ``bunny.obj``, ``armadillo.obj`` (Stanford 3D Scanning Repository,
    research use with acknowledgement) and ``bowl.obj`` (open hemisphere, normals into the
    bowl); see ``jaxmpm/assets/meshes/SOURCE.md``.

    Raises:
        FileNotFoundError: no such asset.
    """
    root = importlib.resources.files("jaxmpm") / "assets"
    for candidate in (root / name, root / "meshes" / name):
        if candidate.is_file():
            return str(candidate)
    raise FileNotFoundError(f"no asset named {name!r} in {root}")


def key_name(where: str, key: str) -> str:
    """How a spec key is named in messages: ``bodies[0].path`` for an entry of the scene file,
    ``collider 'floor': 'path'`` for a collider by name (``where`` = ``"collider 'floor'"``)."""
    return f"{where}.{key}" if where.endswith("]") else f"{where}: {key!r}"


def resolve_path(path, base_dir, where: str, assets: bool = True) -> str:
    """The file a spec's ``path`` names: relative paths against ``base_dir`` (the scene's
    folder), then the working directory, then (``assets``) the shipped assets.

    Raises:
        SceneError: ``path`` is not a non-empty string, names a directory, or no file exists.
    """
    if not isinstance(path, str) or not path:
        raise SceneError(f"{key_name(where, 'path')} must be a file name (string), got {path!r}")
    p = os.path.expanduser(path)
    candidates = [p] if os.path.isabs(p) else [os.path.join(str(base_dir or "."), p), p]
    for c in candidates:
        if os.path.isfile(c):
            return c
        if os.path.isdir(c):
            raise SceneError(f"{where}: {path!r} is a directory ({c}), not a file")
    if assets:
        try:
            return asset_path(p)
        except FileNotFoundError:
            pass
    looked = f"looked in {candidates[0]!r}" + (" and in the shipped assets" if assets else "")
    raise SceneError(f"{where}: file {path!r} not found ({looked})")


def load_mesh(path, where: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` and triangles ``(F, 3)`` of a 3D mesh file (any format trimesh reads;
    scenes are merged; duplicate vertices merged).

    Raises:
        SceneError: the file is a directory, cannot be read as a triangle mesh, has no faces,
            or has a NaN/infinite vertex (which trimesh would otherwise drop with its faces).
    """
    import trimesh

    p = str(path)
    if os.path.isdir(p):
        raise SceneError(f"{where}: {p!r} is a directory, not a mesh file")
    try:
        raw = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types
        # Unreadable bytes reach trimesh's text decoders, which may then ask for an optional
        # module: that ImportError says nothing about the file, so it is not repeated.
        detail = "" if isinstance(exc, ImportError) else f" ({type(exc).__name__}: {exc})"
        raise SceneError(f"{where}: {p!r} is not a readable mesh file{detail}") from None
    faces = getattr(raw, "faces", None)
    if faces is None or len(faces) == 0:
        # trimesh reads some unreadable bytes as an empty mesh (5.2: random bytes as an STL)
        raise SceneError(f"{where}: {p!r} has no faces: an empty mesh, or not a readable mesh file")
    v = np.asarray(raw.vertices, float)
    bad = ~np.all(np.isfinite(v), axis=1)
    if np.any(bad):
        raise SceneError(
            f"{where}: mesh {p!r} has {int(bad.sum())} vertex(es) with NaN or infinite coordinates "
            f"(first: vertex {int(np.flatnonzero(bad)[0])})"
        )
    mesh = trimesh.Trimesh(v, np.asarray(faces), process=True)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)


def placement(spec: dict, where: str, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``scale`` (a positive number or D of them), ``rotate`` (degrees) and ``translate``
    keys of a spec, applied to rest coordinates as ``x' = R (s * x) + t``.

    Returns:
        ``scale (D,)``, ``translate (D,)`` metres, ``R (D, D)``.
    """
    try:
        scale = np.asarray(spec.get("scale", 1.0), float).reshape(-1)
    except (TypeError, ValueError):
        scale = np.zeros(0)
    if scale.size not in (1, dim) or not np.all(np.isfinite(scale)) or np.any(scale <= 0):
        raise SceneError(
            f"{key_name(where, 'scale')} must be a positive number or {dim} positive numbers, got {spec.get('scale')!r}"
        )
    translate = vector(spec.get("translate", np.zeros(dim)), dim, key_name(where, "translate"))
    rot = vector(spec.get("rotate", np.zeros(3 if dim == 3 else 1)), 3 if dim == 3 else 1, key_name(where, "rotate"))
    return np.broadcast_to(scale, (dim,)).astype(float), translate, rotation_matrix(rot, dim)


def place(points: np.ndarray, spec: dict, where: str) -> np.ndarray:
    """``points (P, D)`` scaled, rotated and translated by the spec's placement keys."""
    scale, translate, rot = placement(spec, where, points.shape[1])
    return (points * scale) @ rot.T + translate


def _motion_args(spec: dict, name: str, dim: int) -> dict:
    """Parse ``velocity``, ``angular_velocity`` and ``pivot`` from a collider spec."""
    lengths = {"velocity": dim, "angular_velocity": 3 if dim == 3 else 1, "pivot": dim}
    return {key: vector(spec[key], n, key_name(f"collider {name!r}", key)) for key, n in lengths.items() if key in spec}


def plane_from_spec(spec: dict, name: str, dim: int, base_dir) -> Plane:
    """``type = "plane"``: ``point``, ``normal``; optional ``velocity``, ``angular_velocity``, ``pivot``."""
    point = vector(spec["point"], dim, key_name(f"collider {name!r}", "point"))
    return Plane(point, spec["normal"], contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


def box_from_spec(spec: dict, name: str, dim: int, base_dir) -> Box:
    """``type = "box"``: ``lo``, ``hi``; optional ``rotate`` (degrees about the centre) and motion."""
    lo = vector(spec["lo"], dim, key_name(f"collider {name!r}", "lo"))
    hi = vector(spec["hi"], dim, key_name(f"collider {name!r}", "hi"))
    rot = spec.get("rotate")
    return Box(lo, hi, rotate=rot, contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


def _polyline(points, segments, closed: bool, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(P, 2)`` and segments ``(S, 2)``: the given ones, or the chain 0-1-2-... (closed
    back to point 0 when ``closed``)."""
    try:
        pts = np.asarray(points, float)
    except (TypeError, ValueError):
        pts = np.zeros(0)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise SceneError(f"{where}: 'points' must be a list of at least two [x, y] points")
    if segments is None:
        n = len(pts)
        seg = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
        if closed:
            seg = np.concatenate([seg, [[n - 1, 0]]])
    else:
        seg = np.asarray(segments)
        if seg.ndim != 2 or seg.shape[1] != 2 or not np.issubdtype(seg.dtype, np.integer):
            raise SceneError(f"{where}: 'segments' must be pairs of point indices")
    return pts, seg


def load_polyline_npz(path, where: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """A 2D segment set from an ``.npz``: ``points (P, 2)``; optional ``segments (S, 2)`` int
    (default: the chain 0-1-2-...), optional ``closed`` (bool, default False: the chain is
    closed back to point 0 when True)."""
    try:
        with np.load(str(path)) as data:
            if "points" not in data:
                raise SceneError(f"{where}: {str(path)!r} has no 'points' array")
            pts = data["points"]
            seg = data["segments"] if "segments" in data else None
            closed = bool(data["closed"]) if "closed" in data else False
    except SceneError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise SceneError(f"{where}: cannot read {str(path)!r}: {exc}") from exc
    return _polyline(pts, seg, closed, where)


def mesh_from_spec(spec: dict, name: str, dim: int, base_dir) -> MeshCollider:
    """``type = "mesh"``: ``path`` (3D: any trimesh format, resolved against the scene folder,
    then the shipped assets; 2D: an ``.npz`` polyline) or, in 2D, inline ``points`` (+
    ``segments``, ``closed``); then ``scale`` (about the file's origin), ``rotate`` (degrees),
    ``translate``, in that order."""
    where = f"collider {name!r}"
    if ("path" in spec) == ("points" in spec):
        raise SceneError(f"{where}: give 'path'" + (" or 'points' (not both)" if dim == 2 else ""))
    if "points" in spec:
        if dim != 2:
            raise SceneError(f"{where}: inline 'points' are for 2D scenes; use 'path' in 3D")
        v, f = _polyline(spec["points"], spec.get("segments"), bool(spec.get("closed", False)), where)
    else:
        for key in ("segments", "closed"):
            if key in spec:
                raise SceneError(f"{where}: {key!r} goes with inline 'points', not with 'path'")
        path = resolve_path(spec["path"], base_dir, where)
        if dim == 2:
            if not path.endswith(".npz"):
                raise SceneError(f"{where}: a 2D mesh collider needs an .npz polyline, got {path!r}")
            v, f = load_polyline_npz(path, where)
        else:
            v, f = load_mesh(path, where)
    v = place(v, spec, where)
    return MeshCollider(v, f, contact=spec.get("contact", "sticky"), name=name, **_motion_args(spec, name, dim))


def read_ply_vertices(path) -> dict[str, np.ndarray]:
    """The ``vertex`` element of a PLY file (ascii or binary) as ``{property: (K,) array}``."""
    types = {
        "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
        "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
        "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
        "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
    }  # fmt: skip
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise ValueError("not a PLY file")
        fmt, elements = None, []
        while True:
            line = fh.readline()
            if not line:
                raise ValueError("PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property":
                if words[1] == "list":
                    elements[-1][2].append((words[-1], None))
                else:
                    elements[-1][2].append((words[-1], types[words[1]]))
            elif words[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise ValueError("the first PLY element must be 'vertex'")
        _, count, props = elements[0]
        if any(t is None for _, t in props):
            raise ValueError("list properties on vertices are not supported")
        if fmt == "ascii":
            rows = [fh.readline().split() for _ in range(count)]
            table = np.asarray(rows, float).reshape(count, len(props))
            return {p: table[:, i] for i, (p, _) in enumerate(props)}
        endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if endian is None:
            raise ValueError(f"unknown PLY format {fmt!r}")
        dt = np.dtype([(p, endian + t) for p, t in props])
        data = np.frombuffer(fh.read(dt.itemsize * count), dtype=dt, count=count)
        return {p: data[p].astype(float) for p, _ in props}


def load_disks(path, where: str = "disks") -> dict[str, np.ndarray]:
    """Surfels from an ``.npz`` or a 2DGS-style ``.ply``.

    ``.npz`` keys: ``centers (K, D)``; ``normals (K, D)`` or (3D) ``rotations (K, 4)``
    quaternions ``(w, x, y, z)`` whose third column is the normal and first two the tangent
    axes; ``scales`` — standard deviations along the tangent axes, ``(K, D-1)`` or ``(K,)``
    (isotropic), linear metres; optional ``tangents (K, 3)`` (the first tangent axis, 3D;
    default any perpendicular), optional ``opacity (K,)`` in [0, 1] (default 1).

    ``.ply`` (2DGS export): ``x, y, z``; ``rot_0..rot_3`` (quaternion w, x, y, z; the normal is
    the rotation's third column) or ``nx, ny, nz``; ``scale_0, scale_1`` log standard
    deviations; ``opacity`` as a logit. Returns a dict with the npz keys.
    """
    p = str(path)
    try:
        if p.endswith(".npz"):
            with np.load(p) as data:
                out = {k: np.asarray(data[k]) for k in data.files}
        else:
            props = read_ply_vertices(p)
            if not all(k in props for k in ("x", "y", "z")):
                raise ValueError("PLY vertices need x, y, z")
            out = {"centers": np.stack([props["x"], props["y"], props["z"]], axis=1)}
            if all(f"rot_{i}" in props for i in range(4)):
                out["rotations"] = np.stack([props[f"rot_{i}"] for i in range(4)], axis=1)
            elif all(k in props for k in ("nx", "ny", "nz")):
                out["normals"] = np.stack([props["nx"], props["ny"], props["nz"]], axis=1)
            if "scale_0" in props:
                s1 = props.get("scale_1", props["scale_0"])
                out["scales"] = np.exp(np.stack([props["scale_0"], s1], axis=1))
            if "opacity" in props:
                out["opacity"] = 1.0 / (1.0 + np.exp(-props["opacity"]))
    except Exception as exc:  # noqa: BLE001
        raise SceneError(f"{where}: cannot read disks from {p!r}: {exc}") from exc
    if "centers" not in out:
        raise SceneError(f"{where}: {p!r} has no 'centers'")
    if "scales" not in out:
        raise SceneError(f"{where}: {p!r} has no 'scales' (scale_0/scale_1 in a PLY)")
    return out


def disks_from_spec(spec: dict, name: str, dim: int, base_dir) -> GaussianDisks:
    """``type = "disks"``: ``path`` (.npz or 2DGS .ply, see :func:`load_disks`); optional
    ``scale`` (uniform), ``rotate``, ``translate`` (applied in that order), ``cutoff`` (3.0),
    ``min_opacity`` (0.05), ``orient`` ("knn"), ``flip`` (false)."""
    where = f"collider {name!r}"
    path = resolve_path(spec["path"], base_dir, where)
    data = load_disks(path, where)
    c = np.asarray(data["centers"], float)
    if c.ndim != 2 or c.shape[1] != dim:
        raise SceneError(f"collider {name!r}: disk centres must be (K, {dim}) in a {dim}D scene, got {c.shape}")
    scale, translate, rot = placement(spec, where, dim)
    if np.ptp(scale) > 0:
        raise SceneError(f"collider {name!r}: disks accept only a uniform 'scale'")
    k = float(scale[0])
    normals = data.get("normals")
    tangents = data.get("tangents")
    rotations = data.get("rotations")
    if rotations is not None:
        r = quaternion_to_matrix(np.asarray(rotations, float).reshape(-1, 4))
        r = np.einsum("ij,kjl->kil", rot, r)
        normals, tangents, rotations = r[:, :, 2], r[:, :, 0], None
    if normals is not None:
        normals = np.asarray(normals, float) @ rot.T
    if tangents is not None:
        tangents = np.asarray(tangents, float) @ rot.T
    return GaussianDisks(
        (c * k) @ rot.T + translate,
        normals=normals,
        scales=np.asarray(data["scales"], float) * k,
        tangents=tangents,
        opacity=data.get("opacity"),
        cutoff=float(spec.get("cutoff", 3.0)),
        min_opacity=float(spec.get("min_opacity", 0.05)),
        orient=str(spec.get("orient", "knn")),
        flip=bool(spec.get("flip", False)),
        contact=spec.get("contact", "sticky"),
        name=name,
        **_motion_args(spec, name, dim),
    )


_MOTION_KEYS = ("velocity", "angular_velocity", "pivot")
COLLIDER_TYPES.update(
    {
        "plane": (plane_from_spec, ("point", "normal"), _MOTION_KEYS),
        "box": (box_from_spec, ("lo", "hi"), ("rotate",) + _MOTION_KEYS),
        "mesh": (
            mesh_from_spec,
            (),
            ("path", "points", "segments", "closed", "scale", "translate", "rotate") + _MOTION_KEYS,
        ),
        "disks": (
            disks_from_spec,
            ("path",),
            ("scale", "translate", "rotate", "cutoff", "min_opacity", "orient", "flip") + _MOTION_KEYS,
        ),
    }
)
