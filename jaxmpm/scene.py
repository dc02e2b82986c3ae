"""Scene specs (TOML or JSON, DESIGN §5.1) -> :class:`~jaxmpm.model.Model` and params.

Every error names the offending key, file or value (:class:`~jaxmpm.errors.SceneError`).
"""

from __future__ import annotations

import copy
import json
import math
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from . import memory
from .colliders import COLLIDER_TYPES, CONTACTS, load_mesh, place, resolve_path, vector
from .constitutive import MATERIALS
from .errors import JaxmpmWarning, SceneError
from .model import COLLISION_MODES, Body, Collision, Model, Params, contact_notes
from .parameters import DENSITY, FRICTION, RESTITUTION, Parameter
from .state import Grid

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

_TOP_REQUIRED = ("dim", "dx", "domain", "frames", "frame_dt")
_TOP_OPTIONAL = ("gravity", "substeps", "dt", "collision", "flip", "bodies", "colliders")
_BODY_SHAPES = {
    "box": (("lo", "hi"), ()),
    "sphere": (("center", "radius"), ()),
    "mesh": (("path",), ("scale", "translate", "rotate")),
    "points": (("path",), ()),
}
_BODY_COMMON = ("shape", "material", "ppc", "velocity", "name")
_COLLIDER_COMMON = ("type", "name", "contact", "friction", "restitution", "velocity", "angular_velocity")


def _check_keys(spec: dict, required, optional, where: str) -> None:
    if not isinstance(spec, dict):
        raise SceneError(f"{where}: expected a table/object, got {type(spec).__name__}")
    for key in spec:
        if key not in required and key not in optional:
            raise SceneError(f"{where}: unknown key {key!r} (allowed: {', '.join(dict.fromkeys(list(required) + list(optional)))})")
    for key in required:
        if key not in spec:
            raise SceneError(f"{where}: missing required key {key!r}")


def _number(value, where: str, positive: bool = False, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"{where} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise SceneError(f"{where} must be finite, got {value!r}")
    if positive and value <= 0:
        raise SceneError(f"{where} must be > 0, got {value!r}")
    if integer and int(value) != value:
        raise SceneError(f"{where} must be an integer, got {value!r}")
    return value


def _declared(parameter: Parameter, value, where: str) -> float:
    """``value`` of a declared parameter, checked against its declared range (one line naming ``where``)."""
    value = _number(value, f"{where}.{parameter.name}")
    if value not in parameter.range:
        raise SceneError(f"{where}.{parameter.name} = {value} is out of range (must be {parameter.range.text})")
    return value


def _choice(value, choices, where: str):
    """``value`` if it is one of the strings ``choices`` (a list/dict value is a clear error, not a TypeError)."""
    if not isinstance(value, str) or value not in choices:
        raise SceneError(f"{where} must be one of {tuple(choices)}, got {value!r}")
    return value


#: Most lattice points one body may sample (beyond this the positions alone take gigabytes).
MAX_LATTICE_POINTS = 2**27

#: Counts of grid nodes and steps must fit the simulator's int32 indices and counters.
MAX_INT32 = 2**31 - 1


def _check_frame_times(frame_dt: float, frames: int, dtype) -> None:
    """Refuse a ``frame_dt`` (s) too small for the frame times ``i * frame_dt`` to be distinct
    numbers in ``dtype`` (else the observation's times collapse)."""
    name = np.dtype(dtype).name
    first = np.asarray(frame_dt, dtype)
    last = np.asarray((frames - 1) * frame_dt, dtype)
    # the times are distinct when one frame_dt is well above the spacing of dtype's numbers at the last time
    if not (first > 0 and np.isfinite(last) and frame_dt > 4 * float(np.spacing(last))):
        raise SceneError(
            f"scene: 'frame_dt' = {frame_dt:g} s is too small for {name}: the frame times are not distinct "
            f"numbers (the smallest usable is about {max(float(np.finfo(dtype).tiny), 4 * float(np.spacing(last))):.3g} s)"
        )


def _substeps(spec: dict, frame_dt: float) -> int:
    """Substeps per frame from ``substeps``, or from ``dt`` as ``ceil(frame_dt / dt)``; not both."""
    if "substeps" in spec and "dt" in spec:
        raise SceneError("scene: give either 'substeps' or 'dt', not both")
    if "substeps" in spec:
        substeps = _number(spec["substeps"], "scene: 'substeps'", positive=True, integer=True)
        where = f"'substeps' = {substeps:g}"
    elif "dt" in spec:
        dt = _number(spec["dt"], "scene: 'dt'", positive=True)
        substeps = max(1.0, math.ceil(min(frame_dt / dt, 2.0 * MAX_INT32) - 1e-9))
        where = f"'dt' = {dt:g} s gives {substeps:.3g} substeps per frame, which"
    else:
        raise SceneError("scene: missing required key 'substeps' (or 'dt')")
    if substeps > MAX_INT32:
        raise SceneError(f"scene: {where} is more than the simulator's limit of {MAX_INT32} substeps per frame")
    return int(substeps)


def read_spec(path: str | Path) -> dict:
    """Read a scene file (``.toml`` or ``.json``) into a dict."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise SceneError(f"{path}: cannot parse: not UTF-8 text ({err})") from None
    try:
        if path.suffix.lower() == ".toml":
            return tomllib.loads(text)
        if path.suffix.lower() == ".json":
            return json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
        raise SceneError(f"{path}: cannot parse: {err}") from None
    raise SceneError(f"{path}: scene files must end in .toml or .json")


# --------------------------------------------------------------------------- bodies


def _lattice_spacing(dx: float, ppc: int, dim: int, where: str) -> float:
    per_axis = round(ppc ** (1.0 / dim))
    if per_axis < 1 or per_axis**dim != ppc:
        power = {2: "square", 3: "cube"}[dim]
        raise SceneError(f"{where}.ppc = {ppc}: particles per cell must be a perfect {power} in {dim}D (e.g. {2**dim})")
    return dx / per_axis


def _lattice_axes(lo: np.ndarray, hi: np.ndarray, h: float, where: str = "body") -> list[np.ndarray]:
    counts = [max(int(math.floor((hi_d - lo_d) / h + 1e-9)), 0) for lo_d, hi_d in zip(lo, hi)]
    if math.prod(counts) > MAX_LATTICE_POINTS:
        raise SceneError(
            f"{where}: sampling it at particle spacing {h:.3g} m needs {math.prod(counts):.3g} lattice points "
            f"(more than {MAX_LATTICE_POINTS}); use a larger dx or a smaller ppc"
        )
    memory.check(memory.estimate(len(counts), math.prod(counts), 0, 0, 0, itemsize=4))
    return [lo_d + h * (np.arange(n) + 0.5) for lo_d, n in zip(lo, counts)]


def _lattice(lo: np.ndarray, hi: np.ndarray, h: float, where: str = "body") -> np.ndarray:
    axes = _lattice_axes(lo, hi, h, where)
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.reshape(-1) for m in mesh], axis=-1)


def _inside_mesh(vertices: np.ndarray, faces: np.ndarray, axes: list[np.ndarray]) -> np.ndarray:
    """Which points of the lattice ``axes`` (x, y, z) lie inside a closed triangle mesh, ``(nx*ny*nz,)`` bool.

    Parity of the crossings of a ray along +z from each lattice column (vectorised;
    ``trimesh``'s ``contains`` takes ~0.5 ms per point without embree). A column through a
    shared edge or vertex is counted once by the rasterisation "top-left" rule.
    """
    ax, ay, az = axes
    nx, ny, nz = len(ax), len(ay), len(az)
    inside = np.zeros((nx, ny, nz), bool)
    if not (nx and ny and nz):
        return inside.reshape(-1)
    hx, hy = (ax[1] - ax[0] if nx > 1 else 1.0), (ay[1] - ay[0] if ny > 1 else 1.0)
    tri = vertices[faces]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # twice the signed area in xy
    tri = tri[area != 0]  # faces parallel to the rays are never crossed
    tri = np.where((area[area != 0] < 0)[:, None, None], tri[:, ::-1], tri)  # counter-clockwise in xy
    # the lattice columns inside each triangle's xy bounding box
    i0 = np.clip(np.ceil((tri[:, :, 0].min(1) - ax[0]) / hx - 1e-9), 0, nx).astype(np.int64)
    i1 = np.clip(np.floor((tri[:, :, 0].max(1) - ax[0]) / hx + 1e-9) + 1, 0, nx).astype(np.int64)
    j0 = np.clip(np.ceil((tri[:, :, 1].min(1) - ay[0]) / hy - 1e-9), 0, ny).astype(np.int64)
    j1 = np.clip(np.floor((tri[:, :, 1].max(1) - ay[0]) / hy + 1e-9) + 1, 0, ny).astype(np.int64)
    ci, cj = np.maximum(i1 - i0, 0), np.maximum(j1 - j0, 0)
    counts = ci * cj
    k = np.repeat(np.arange(len(tri)), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    i = i0[k] + local // np.maximum(cj[k], 1)
    j = j0[k] + local % np.maximum(cj[k], 1)
    px, py = ax[i], ay[j]
    t = tri[k]
    w, covered = [], np.ones(len(k), bool)
    for e in range(3):
        a, b = t[:, e], t[:, (e + 1) % 3]
        ex, ey = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        # evaluate from the edge's lexicographically smaller end, so that the two faces
        # sharing an edge get bit-identical values (of opposite sign)
        swap = (a[:, 0] > b[:, 0]) | ((a[:, 0] == b[:, 0]) & (a[:, 1] > b[:, 1]))
        a0, a1 = np.where(swap, b[:, 0], a[:, 0]), np.where(swap, b[:, 1], a[:, 1])
        sx, sy = np.where(swap, -ex, ex), np.where(swap, -ey, ey)
        we = sx * (py - a1) - sy * (px - a0)
        we = np.where(swap, -we, we)  # > 0 left of the edge a -> b (inside)
        top_left = (ey < 0) | ((ey == 0) & (ex > 0))
        covered &= (we > 0) | ((we == 0) & top_left)
        w.append(we)
    w = np.stack(w)[:, covered]
    t, i, j = t[covered], i[covered], j[covered]
    # barycentric weight of vertex v is the edge function of the opposite edge
    z = (w[1] * t[:, 0, 2] + w[2] * t[:, 1, 2] + w[0] * t[:, 2, 2]) / w.sum(0)
    below = np.zeros((nx, ny, nz + 1), np.int64)
    np.add.at(below, (i, j, np.searchsorted(az, z)), 1)  # crossings below lattice point k sit at index <= k
    inside = np.cumsum(below, axis=-1)[..., :nz] % 2 == 1
    return inside.reshape(-1)


def _sample_body(spec: dict, dim: int, dx: float, base_dir: Path, where: str) -> tuple[np.ndarray, float]:
    shape = spec["shape"]
    ppc = int(_number(spec.get("ppc", 2**dim), f"{where}.ppc", positive=True, integer=True))
    h = _lattice_spacing(dx, ppc, dim, where)
    if shape == "box":
        lo, hi = vector(spec["lo"], dim, f"{where}.lo"), vector(spec["hi"], dim, f"{where}.hi")
        if np.any(hi <= lo):
            raise SceneError(f"{where}: box 'hi' must exceed 'lo' on every axis, got lo={lo.tolist()} hi={hi.tolist()}")
        x = _lattice(lo, hi, h, where)
    elif shape == "sphere":
        center = vector(spec["center"], dim, f"{where}.center")
        radius = _number(spec["radius"], f"{where}.radius", positive=True)
        x = _lattice(center - radius, center + radius, h, where)
        x = x[np.sum((x - center) ** 2, axis=-1) <= radius**2]
    elif shape == "mesh":
        if dim != 3:
            raise SceneError(f"{where}: shape 'mesh' needs dim = 3")
        import trimesh

        v, f = load_mesh(resolve_path(spec["path"], base_dir, where), where)
        mesh = trimesh.Trimesh(place(v, spec, where), f, process=False)
        if not mesh.is_watertight:
            raise SceneError(f"{where}: mesh {spec['path']} is not watertight, so its inside is undefined")
        axes = _lattice_axes(mesh.bounds[0], mesh.bounds[1], h, where)
        x = np.stack([m.reshape(-1) for m in np.meshgrid(*axes, indexing="ij")], axis=-1)
        x = x[_inside_mesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), axes)]
    elif shape == "points":
        path = resolve_path(spec["path"], base_dir, where, assets=False)
        try:
            x = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as err:
            raise SceneError(f"{where}: cannot read points file {path}: {err}") from None
        if not isinstance(x, np.ndarray):  # an .npz archive
            x.close()
            raise SceneError(f"{where}: points file {path} must be an .npy array, not an .npz archive")
        if x.ndim != 2 or x.shape[1] != dim or not np.issubdtype(x.dtype, np.number) or not np.all(np.isfinite(x)):
            raise SceneError(f"{where}: points file {path} must hold a finite (N, {dim}) numeric array, got {x.dtype} {x.shape}")
    else:  # checked by the caller
        raise AssertionError(shape)
    return np.asarray(x, float), h**dim


@dataclass
class Scene:
    """A loaded scene: the normalised spec, the model and the default parameters.

    Attributes:
        spec: the scene spec as a dict (what ``to_json`` writes).
        model: the static :class:`~jaxmpm.model.Model`.
        params: the parameter pytree built from the spec's values.
        base_dir: folder that relative paths resolve against.
    """

    spec: dict
    model: Model
    params: Params
    base_dir: Path

    def to_json(self) -> str:
        """The spec as JSON, with relative file paths made absolute so that it loads from anywhere."""
        spec = copy.deepcopy(self.spec)
        for item in spec.get("bodies", []) + spec.get("colliders", []):
            path = item.get("path")
            if isinstance(path, str) and not Path(path).expanduser().is_absolute():
                resolved = self.base_dir / Path(path).expanduser()
                if resolved.exists():
                    item["path"] = str(resolved.resolve())
        return json.dumps(spec, sort_keys=True)

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.model.bodies)

    @property
    def collider_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.model.colliders)


def load_scene(source: str | Path | dict, base_dir: str | Path | None = None, dtype=jnp.float32) -> Scene:
    """Load a scene from a file path or a spec dict.

    Arguments:
        source: path to a ``.toml``/``.json`` file, or the spec as a dict.
        base_dir: folder for relative paths (default: the file's folder, or the cwd).
        dtype: float dtype of the model and params (``jnp.float32`` or ``jnp.float64``;
            float64 requires ``jax.config.update("jax_enable_x64", True)``).

    Warns (:class:`jaxmpm.JaxmpmWarning`) for each collider friction or restitution that is set
    but does nothing, or less than its name says (:func:`jaxmpm.model.contact_notes`).
    """
    if isinstance(source, dict):
        spec = copy.deepcopy(source)
        base = Path(base_dir) if base_dir is not None else Path.cwd()
    else:
        spec = read_spec(source)
        base = Path(base_dir) if base_dir is not None else Path(source).resolve().parent
    scene = _build(spec, base, dtype)
    for note in contact_notes(scene.model, scene.params):
        warnings.warn(note, JaxmpmWarning, stacklevel=2)
    return scene


def flip_share(value, where: str) -> float:
    """The scene key ``flip`` (``Model.flip``, the FLIP share of the velocity update) checked:
    a number in [0, 1); raises SceneError naming ``where`` otherwise."""
    flip = float(_number(value, f"{where}: 'flip'"))
    if not 0.0 <= flip < 1.0:
        raise SceneError(f"{where}: 'flip' must be in [0, 1) (the FLIP share of the velocity update), got {flip}")
    return flip


def _build(spec: dict, base_dir: Path, dtype) -> Scene:
    _check_keys(spec, _TOP_REQUIRED, _TOP_OPTIONAL, "scene")
    dim = spec["dim"]
    if isinstance(dim, bool) or not isinstance(dim, (int, float)) or dim not in (2, 3):
        raise SceneError(f"scene: 'dim' must be 2 or 3, got {dim!r}")
    dim = int(dim)
    dx = _number(spec["dx"], "scene: 'dx'", positive=True)
    _check_keys(spec["domain"], ("lo", "hi"), (), "scene.domain")
    lo = vector(spec["domain"]["lo"], dim, "scene: 'domain.lo'")
    hi = vector(spec["domain"]["hi"], dim, "scene: 'domain.hi'")
    if np.any(hi - lo < 2 * dx):
        raise SceneError(f"scene: 'domain' must span at least 2 dx per axis, got lo={lo.tolist()} hi={hi.tolist()}")
    frames = int(_number(spec["frames"], "scene: 'frames'", positive=True, integer=True))
    if frames < 2:
        raise SceneError(f"scene: 'frames' must be >= 2 (frame 0 is the initial state), got {frames}")
    frame_dt = _number(spec["frame_dt"], "scene: 'frame_dt'", positive=True)
    substeps = _substeps(spec, frame_dt)
    gravity = vector(spec.get("gravity", [0.0, -9.8, 0.0][:dim]), dim, "scene: 'gravity'")
    collision = Collision(_choice(spec.get("collision", Collision.CPIC.value), COLLISION_MODES, "scene: 'collision'"))
    flip = flip_share(spec.get("flip", 0.0), "scene")
    grid = Grid(lo=tuple(lo.tolist()), hi=tuple(hi.tolist()), dx=float(dx))
    if grid.num_nodes >= MAX_INT32:  # flat node indices are int32
        raise SceneError(f"scene: 'dx' = {dx} is too small for the domain: the grid would have {grid.num_nodes:.3g} nodes")
    itemsize = np.dtype(dtype).itemsize
    memory.check(memory.estimate(dim, 0, grid.num_nodes, frames, 0, itemsize))

    bodies, body_params = [], []
    body_specs = spec.get("bodies", [])
    if not isinstance(body_specs, list) or not body_specs:
        raise SceneError("scene: 'bodies' must be a non-empty list of [[bodies]] tables")
    for k, bspec in enumerate(body_specs):
        body, bparams = _build_body(bspec, k, dim, dx, lo, hi, base_dir, dtype)
        bodies.append(body)
        body_params.append(bparams)

    colliders, collider_params = [], []
    collider_specs = spec.get("colliders", [])
    if not isinstance(collider_specs, list):
        raise SceneError("scene: 'colliders' must be a list of [[colliders]] tables")
    for k, cspec in enumerate(collider_specs):
        collider, cparams = _build_collider(cspec, k, dim, base_dir, dtype)
        colliders.append(collider)
        collider_params.append(cparams)
    num_particles = sum(len(b.x0) for b in bodies)
    num_fields = sum(1 for c in collider_specs if c.get("type") != "plane")
    memory.check(memory.estimate(dim, num_particles, grid.num_nodes, frames, num_fields, itemsize))
    _check_frame_times(frame_dt, frames, dtype)
    names = [b.name for b in bodies] + [c.name for c in colliders]
    if len(set(names)) != len(names):  # parameters are addressed as "<name>.<parameter>"
        raise SceneError(f"scene: body and collider names must be unique, got {names}")

    model = Model(
        grid=grid,
        bodies=tuple(bodies),
        colliders=tuple(colliders),
        frame_dt=float(frame_dt),
        substeps=substeps,
        frames=frames,
        collision=collision,
        flip=flip,
    )
    params = {
        "gravity": jnp.asarray(gravity, dtype),
        "bodies": tuple(body_params),
        "colliders": tuple(collider_params),
    }
    return Scene(spec=spec, model=model, params=params, base_dir=base_dir)


def _kind(spec, key: str, choices, where: str) -> str:
    """The value of the key that selects an entry's kind (a body's ``shape``, a collider's ``type``)."""
    if not isinstance(spec, dict):
        raise SceneError(f"{where}: expected a table/object")
    if key not in spec:
        raise SceneError(f"{where}: missing required key {key!r}")
    return _choice(spec[key], choices, f"{where}.{key}")


def _build_body(bspec, k, dim, dx, lo, hi, base_dir, dtype):
    where = f"bodies[{k}]"
    shape = _kind(bspec, "shape", _BODY_SHAPES, where)
    required, optional = _BODY_SHAPES[shape]
    _check_keys(bspec, ("shape", "material") + required, _BODY_COMMON + optional, where)
    mspec = bspec["material"]
    if not isinstance(mspec, dict):
        raise SceneError(f"{where}.material: expected a table/object, got {mspec!r}")
    if "model" not in mspec:
        raise SceneError(f"{where}.material: missing required key 'model'")
    cls = MATERIALS[_choice(mspec["model"], MATERIALS, f"{where}.material.model")]
    values = {key: val for key, val in mspec.items() if key not in ("model", "density")}
    for key, val in values.items():
        if isinstance(val, bool):
            raise SceneError(f"{where}.material: parameter {key!r} must be a number, got {val!r}")
    material_values = cls.validate(values, f"{where}.material")
    density = _declared(DENSITY, mspec.get("density", 1000.0), f"{where}.material")
    _check_representable({**material_values, "density": density}, dtype, f"{where}.material")
    velocity = vector(bspec.get("velocity", [0.0] * dim), dim, f"{where}.velocity")

    x, vol = _sample_body(bspec, dim, dx, base_dir, where)
    if len(x) == 0:
        raise SceneError(f"{where}: the body is empty (no particle falls inside its shape at dx = {dx})")
    outside = np.any((x < lo) | (x > hi), axis=-1)
    if outside.any():
        raise SceneError(
            f"{where}: {int(outside.sum())} of {len(x)} particles lie outside the domain "
            f"lo={lo.tolist()} hi={hi.tolist()}"
        )
    name = _name(bspec.get("name", f"body{k}"), where)
    body = Body(name=name, material=cls(), x0=jnp.asarray(x, dtype), vol0=jnp.full((len(x),), vol, dtype))
    bparams = {key: jnp.asarray(val, dtype) for key, val in material_values.items()}
    bparams["density"] = jnp.asarray(density, dtype)
    bparams["velocity"] = jnp.asarray(velocity, dtype)
    bparams["offset"] = jnp.zeros(dim, dtype)  # a parameter, not a scene key (DESIGN §5.1): fitted, e.g. by identify
    return body, bparams


def _check_representable(values: dict, dtype, where: str) -> None:
    """Refuse material values whose size the float dtype cannot compute with: the step forms
    products and squares of moduli, stresses and masses, so each magnitude must lie within
    ``[sqrt(tiny), sqrt(max)]`` of the dtype (float32: about 1e-19 to 1.8e19), or be 0."""
    info = np.finfo(dtype)
    top, bottom = float(np.sqrt(info.max)), float(np.sqrt(info.tiny))
    for key, value in values.items():
        size = float(np.max(np.abs(np.asarray(value, float))))
        if size >= top or 0 < size < bottom:
            raise SceneError(
                f"{where}.{key} = {value:g} is out of range for {info.dtype.name}, whose squares of it "
                f"would overflow or vanish (use magnitudes between {bottom:.1g} and {top:.1g}, or --float64)"
            )


def _name(value, where: str) -> str:
    if not isinstance(value, str) or not value or "." in value:
        raise SceneError(f"{where}.name must be a non-empty string without '.', got {value!r}")
    return value


def _build_collider(cspec, k, dim, base_dir, dtype):
    where = f"colliders[{k}]"
    kind = _kind(cspec, "type", COLLIDER_TYPES, where)
    ctor, required, optional = COLLIDER_TYPES[kind]
    _check_keys(cspec, ("type",) + tuple(required), _COLLIDER_COMMON + tuple(optional), where)
    _choice(cspec.get("contact", "sticky"), CONTACTS, f"{where}.contact")
    friction = _declared(FRICTION, cspec.get("friction", 0.0), where)
    restitution = _declared(RESTITUTION, cspec.get("restitution", 0.0), where)
    name = _name(cspec.get("name", f"{kind}{k}"), where)
    try:
        collider = ctor(cspec, name, dim, base_dir)
    except SceneError as err:  # the collider names itself; add where it sits in the file
        raise SceneError(f"{where}: {err}") from None
    except (TypeError, ValueError, IndexError, KeyError) as err:  # e.g. a number where a list belongs
        raise SceneError(f"{where} ({kind} {name!r}): invalid value: {err}") from None
    cparams = {"friction": jnp.asarray(friction, dtype), "restitution": jnp.asarray(restitution, dtype)}
    return collider, cparams
