"""Scene files and observation files (DESIGN §5.1, §5.2): round trips, every bad input, atomic writes."""

from __future__ import annotations

import copy
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.colliders import asset_path
from jaxmpm.errors import ObservationError, SceneError
from jaxmpm.observe import FORMAT, Observation, atomic_write, load_observation, save_observation
from jaxmpm.scene import load_scene

# --------------------------------------------------------------------------- scenes used below

SCENE_TOML = """
dim = 2
dx = 0.05
domain = { lo = [0.0, 0.0], hi = [1.0, 1.0] }
gravity = [0.0, -9.8]
frames = 3
frame_dt = 0.04
substeps = 10
collision = "grid"

[[bodies]]
name = "block"
shape = "box"
lo = [0.2, 0.3]
hi = [0.4, 0.5]
ppc = 4
velocity = [0.5, -1.0]
material = { model = "newtonian", mu = 200.0, kappa = 1e4, density = 900.0 }

[[bodies]]
shape = "sphere"
center = [0.7, 0.5]
radius = 0.1
ppc = 9
material = { model = "elastic", E = 1e5, nu = 0.3 }

[[bodies]]
shape = "points"
path = "points.npy"
material = { model = "sand", friction_angle = 35.0 }

[[colliders]]
type = "plane"
name = "floor"
point = [0.0, 0.1]
normal = [0.0, 1.0]
contact = "friction"
friction = 0.3

[[colliders]]
type = "box"
lo = [0.45, 0.1]
hi = [0.55, 0.2]
contact = "slip"
velocity = [0.0, 0.1]
"""

#: the same scene as SCENE_TOML, written by hand as JSON
SCENE_JSON = {
    "dim": 2,
    "dx": 0.05,
    "domain": {"lo": [0.0, 0.0], "hi": [1.0, 1.0]},
    "gravity": [0.0, -9.8],
    "frames": 3,
    "frame_dt": 0.04,
    "substeps": 10,
    "collision": "grid",
    "bodies": [
        {
            "name": "block",
            "shape": "box",
            "lo": [0.2, 0.3],
            "hi": [0.4, 0.5],
            "ppc": 4,
            "velocity": [0.5, -1.0],
            "material": {"model": "newtonian", "mu": 200.0, "kappa": 1e4, "density": 900.0},
        },
        {"shape": "sphere", "center": [0.7, 0.5], "radius": 0.1, "ppc": 9, "material": {"model": "elastic", "E": 1e5, "nu": 0.3}},
        {"shape": "points", "path": "points.npy", "material": {"model": "sand", "friction_angle": 35.0}},
    ],
    "colliders": [
        {"type": "plane", "name": "floor", "point": [0.0, 0.1], "normal": [0.0, 1.0], "contact": "friction", "friction": 0.3},
        {"type": "box", "lo": [0.45, 0.1], "hi": [0.55, 0.2], "contact": "slip", "velocity": [0.0, 0.1]},
    ],
}

POINTS = np.array([[0.1, 0.8], [0.12, 0.8], [0.1, 0.82], [0.12, 0.82], [0.11, 0.81]])


def small_spec(**top) -> dict:
    """A valid 2D scene (one box body, one plane) that loads in milliseconds."""
    spec = {
        "dim": 2,
        "dx": 0.1,
        "domain": {"lo": [0.0, 0.0], "hi": [1.0, 1.0]},
        "frames": 3,
        "frame_dt": 0.04,
        "substeps": 10,
        "bodies": [{"shape": "box", "lo": [0.3, 0.3], "hi": [0.5, 0.5], "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e4}}],
        "colliders": [{"type": "plane", "name": "floor", "point": [0.0, 0.1], "normal": [0.0, 1.0]}],
    }
    spec.update(top)
    return spec


def scene_folder(tmp_path):
    folder = tmp_path / "scene"
    folder.mkdir()
    np.save(folder / "points.npy", POINTS)
    (folder / "scene.toml").write_text(SCENE_TOML)
    (folder / "scene.json").write_text(json.dumps(SCENE_JSON))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    return folder, elsewhere


def assert_same_scene(a, b):
    """Identical models (structure, static fields, particle arrays) and identical params."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(a.model)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b.model)
    assert tree_a == tree_b  # grid, frame_dt, substeps, collision, bodies' materials, colliders' geometry
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    pa, pt_a = jax.tree_util.tree_flatten(a.params)
    pb, pt_b = jax.tree_util.tree_flatten(b.params)
    assert pt_a == pt_b
    for x, y in zip(pa, pb):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# --------------------------------------------------------------------------- scene round trips


def test_toml_and_json_versions_of_a_scene_are_identical(tmp_path, monkeypatch):
    folder, elsewhere = scene_folder(tmp_path)
    monkeypatch.chdir(elsewhere)  # relative paths resolve against the scene file's folder, not the cwd
    from_toml = load_scene(folder / "scene.toml")
    from_json = load_scene(str(folder / "scene.json"))
    assert_same_scene(from_toml, from_json)
    model = from_toml.model
    assert [b.name for b in model.bodies] == ["block", "body1", "body2"]
    assert [c.name for c in model.colliders] == ["floor", "box1"]
    assert (model.substeps, model.frames, model.collision) == (10, 3, "grid")
    assert model.frame_dt == 0.04 and model.grid.dx == 0.05
    p = from_toml.params
    np.testing.assert_allclose(p["gravity"], [0.0, -9.8], rtol=1e-6)
    assert float(p["bodies"][0]["mu"]) == 200.0 and float(p["bodies"][0]["density"]) == 900.0
    np.testing.assert_allclose(p["bodies"][0]["velocity"], [0.5, -1.0])
    assert float(p["bodies"][1]["E"]) == 1e5 and float(p["bodies"][1]["density"]) == 1000.0  # default density
    assert float(p["bodies"][2]["friction_angle"]) == 35.0
    np.testing.assert_allclose(p["colliders"][0]["friction"], 0.3, rtol=1e-6)


@pytest.mark.x64
def test_to_json_reloads_to_the_same_scene_from_anywhere(tmp_path, monkeypatch):
    folder, elsewhere = scene_folder(tmp_path)
    scene = load_scene(folder / "scene.toml", dtype=jnp.float64)
    text = scene.to_json()
    monkeypatch.chdir(elsewhere)
    # as a dict (what an observation's 'scene' holds): no base_dir needed, paths were made absolute
    again = load_scene(json.loads(text), dtype=jnp.float64)
    assert_same_scene(scene, again)
    # and as a .json file in another folder
    (elsewhere / "copy.json").write_text(text)
    assert_same_scene(scene, load_scene(elsewhere / "copy.json", dtype=jnp.float64))
    assert json.loads(again.to_json()) == json.loads(text)


@pytest.mark.x64
def test_box_and_sphere_bodies_are_filled_at_ppc(tmp_path):
    folder, _ = scene_folder(tmp_path)
    scene = load_scene(folder / "scene.toml", dtype=jnp.float64)
    box, sphere, points = scene.model.bodies
    # box: 0.2 x 0.2 at dx = 0.05 with 2x2 particles per cell, on a regular lattice inside [lo, hi]
    h = 0.05 / 2
    assert box.num_particles == 8 * 8
    x = np.asarray(box.x0)
    assert x.min(0) == pytest.approx([0.2 + h / 2, 0.3 + h / 2]) and x.max(0) == pytest.approx([0.4 - h / 2, 0.5 - h / 2])
    np.testing.assert_allclose(box.vol0, 0.05**2 / 4)
    # sphere (a disk in 2D): 3x3 per cell, count ~ area / h^2, all inside the radius
    h = 0.05 / 3
    assert sphere.num_particles == pytest.approx(math.pi * 0.1**2 / h**2, rel=0.05)
    assert np.all(np.linalg.norm(np.asarray(sphere.x0) - [0.7, 0.5], axis=1) <= 0.1)
    np.testing.assert_allclose(sphere.vol0, h**2)
    # points: exactly the file's positions, with the default ppc's volume
    np.testing.assert_array_equal(np.asarray(points.x0), POINTS)
    np.testing.assert_allclose(points.vol0, 0.05**2 / 4)


def _mesh_spec(path, dx=0.05, ppc=8, **body):
    return {
        "dim": 3,
        "dx": dx,
        "domain": {"lo": [-0.6, -0.6, -0.6], "hi": [0.6, 0.6, 0.6]},
        "frames": 2,
        "frame_dt": 0.04,
        "substeps": 2,
        "bodies": [{"shape": "mesh", "path": path, "ppc": ppc, "material": {"model": "elastic", "E": 1e5, "nu": 0.3}, **body}],
    }


@pytest.mark.x64
def test_mesh_body_is_filled_inside_the_mesh(tmp_path, monkeypatch):
    trimesh = pytest.importorskip("trimesh")
    folder = tmp_path / "meshes"
    folder.mkdir()
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.3)
    sphere.export(folder / "ico.obj")
    (folder / "scene.json").write_text(json.dumps(_mesh_spec("ico.obj")))
    monkeypatch.chdir(tmp_path)
    scene = load_scene(folder / "scene.json", dtype=jnp.float64)
    body = scene.model.bodies[0]
    x = np.asarray(body.x0)
    expected = sphere.volume / (0.05**3 / 8)
    assert body.num_particles == pytest.approx(expected, rel=0.1)
    np.testing.assert_allclose(body.vol0, 0.05**3 / 8)
    assert np.all(np.linalg.norm(x, axis=1) <= 0.3 + 1e-9)
    # agrees with trimesh's own inside test on lattice points near the surface
    r = np.linalg.norm(x, axis=1)
    assert np.all(sphere.contains(x[r > 0.27][::4]))
    # a cube mesh (lattice columns run exactly through its faces' diagonals) gives the box body's particles
    trimesh.creation.box(extents=[0.4, 0.4, 0.4]).export(folder / "cube.obj")
    cube = load_scene(_mesh_spec("cube.obj", dx=0.1), base_dir=folder, dtype=jnp.float64).model.bodies[0]
    box_spec = _mesh_spec("", dx=0.1)
    box_spec["bodies"][0] = {"shape": "box", "lo": [-0.2] * 3, "hi": [0.2] * 3, "ppc": 8, "material": ELASTIC}
    box = load_scene(box_spec, dtype=jnp.float64).model.bodies[0]
    assert cube.num_particles == box.num_particles == 8**3
    np.testing.assert_allclose(np.asarray(cube.x0), np.asarray(box.x0), atol=1e-12)


@pytest.mark.x64
def test_mesh_body_scale_rotate_translate_and_shipped_asset():
    trimesh = pytest.importorskip("trimesh")
    bunny = trimesh.load(asset_path("bunny.obj"), force="mesh")
    scale, translate = 0.8, [0.1, -0.05, 0.02]
    spec = _mesh_spec("bunny.obj", dx=0.05, ppc=8, scale=scale, rotate=[0.0, 90.0, 0.0], translate=translate)
    body = load_scene(spec, dtype=jnp.float64).model.bodies[0]  # "bunny.obj" falls back to the shipped asset
    expected = bunny.volume * scale**3 / (0.05**3 / 8)
    assert body.num_particles == pytest.approx(expected, rel=0.1)
    # the particles' centroid is the transformed mesh's centre of mass
    rot = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])[:3, :3]
    centre = rot @ (scale * bunny.center_mass) + translate
    np.testing.assert_allclose(np.asarray(body.x0).mean(0), centre, atol=0.01)
    # an absolute path gives the same particles
    again = load_scene({**spec, "bodies": [{**spec["bodies"][0], "path": asset_path("bunny.obj")}]}, dtype=jnp.float64)
    np.testing.assert_array_equal(np.asarray(again.model.bodies[0].x0), np.asarray(body.x0))


def test_relative_paths_resolve_against_the_scene_folder(tmp_path, monkeypatch):
    folder, elsewhere = scene_folder(tmp_path)
    np.save(elsewhere / "points.npy", POINTS + 0.1)  # a decoy in the cwd
    monkeypatch.chdir(elsewhere)
    scene = load_scene(folder / "scene.toml")
    np.testing.assert_allclose(np.asarray(scene.model.bodies[2].x0), POINTS, rtol=1e-6)
    assert scene.base_dir == folder.resolve()
    # a dict spec resolves against base_dir (default: the cwd)
    spec = copy.deepcopy(SCENE_JSON)
    np.testing.assert_allclose(np.asarray(load_scene(spec).model.bodies[2].x0), POINTS + 0.1, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(load_scene(spec, base_dir=folder).model.bodies[2].x0), POINTS, rtol=1e-6)


# --------------------------------------------------------------------------- bad scenes


def _set(path, value):
    """A mutation of small_spec(): set spec[path...] = value (``value is DELETE`` removes the key)."""

    def mutate(spec):
        node = spec
        for key in path[:-1]:
            node = node[key]
        if value is DELETE:
            del node[path[-1]]
        else:
            node[path[-1]] = value
        return spec

    return mutate


DELETE = object()
B, M, C = ("bodies", 0), ("bodies", 0, "material"), ("colliders", 0)

#: (id, mutation of small_spec(), words the one error message must contain)
BAD_SCENES = [
    # unknown keys, at every level
    ("top-unknown", _set(("colour",), "red"), ["unknown key", "'colour'"]),
    ("domain-unknown", _set(("domain", "mid"), [0.5, 0.5]), ["scene.domain", "unknown key", "'mid'"]),
    ("body-unknown", _set(B + ("colour",), "red"), ["bodies[0]", "unknown key", "'colour'"]),
    ("body-unknown-for-shape", _set(B + ("radius",), 0.1), ["bodies[0]", "unknown key", "'radius'"]),
    ("material-unknown", _set(M + ("viscosity",), 1.0), ["bodies[0].material", "unknown parameter", "'viscosity'"]),
    ("collider-unknown", _set(C + ("colour",), "red"), ["colliders[0]", "unknown key", "'colour'"]),
    # missing keys, at every level
    *[(f"top-missing-{k}", _set((k,), DELETE), ["missing required key", f"'{k}'"]) for k in ("dim", "dx", "domain", "frames", "frame_dt")],
    ("top-missing-substeps", _set(("substeps",), DELETE), ["missing required key", "'substeps'"]),
    ("top-missing-bodies", _set(("bodies",), DELETE), ["'bodies'"]),
    ("domain-missing-hi", _set(("domain", "hi"), DELETE), ["scene.domain", "missing required key", "'hi'"]),
    ("body-missing-lo", _set(B + ("lo",), DELETE), ["bodies[0]", "missing required key", "'lo'"]),
    ("body-missing-shape", _set(B + ("shape",), DELETE), ["bodies[0]", "'shape'"]),
    ("body-missing-material", _set(B + ("material",), DELETE), ["bodies[0]", "missing required key", "'material'"]),
    ("material-missing-model", _set(M + ("model",), DELETE), ["bodies[0].material", "missing required key", "'model'"]),
    ("material-missing-kappa", _set(M + ("kappa",), DELETE), ["bodies[0].material", "missing required parameter", "'kappa'"]),
    ("collider-missing-normal", _set(C + ("normal",), DELETE), ["colliders[0]", "missing required key", "'normal'"]),
    ("collider-missing-type", _set(C + ("type",), DELETE), ["colliders[0]", "'type'"]),
    # unknown names among choices
    ("body-shape", _set(B + ("shape",), "cone"), ["bodies[0].shape", "'cone'"]),
    ("material-model", _set(M + ("model",), "honey"), ["bodies[0].material.model", "'honey'"]),
    ("collider-type", _set(C + ("type",), "cylinder"), ["colliders[0].type", "'cylinder'"]),
    ("collider-contact", _set(C + ("contact",), "glue"), ["colliders[0].contact", "'glue'"]),
    ("collision", _set(("collision",), "mesh"), ["'collision'", "'mesh'"]),
    # values of the wrong type (a TypeError would be a traceback)
    ("dim-4", _set(("dim",), 4), ["'dim'", "4"]),
    ("shape-list", _set(B + ("shape",), ["box"]), ["bodies[0].shape", "['box']"]),
    ("model-list", _set(M + ("model",), ["newtonian"]), ["bodies[0].material.model"]),
    ("mu-string", _set(M + ("mu",), "stiff"), ["'mu'", "'stiff'"]),
    ("mu-bool", _set(M + ("mu",), True), ["'mu'", "True"]),
    ("velocity-length", _set(B + ("velocity",), [1.0, 2.0, 3.0]), ["bodies[0].velocity"]),
    ("plane-point-number", _set(C + ("point",), 0.5), ["colliders[0]", "floor"]),
    ("collider-name-dup", _set(C + ("name",), "body0"), ["names must be unique", "body0"]),
    ("body-name-dot", _set(B + ("name",), "a.b"), ["bodies[0].name", "'a.b'"]),
    ("colliders-table", _set(("colliders",), {"type": "plane"}), ["'colliders'", "list"]),
    ("ppc-not-power", _set(B + ("ppc",), 3), ["bodies[0].ppc", "3"]),
    ("substeps-fraction", _set(("substeps",), 2.5), ["'substeps'", "2.5"]),
    # out-of-range parameters
    ("dx-zero", _set(("dx",), 0.0), ["'dx'", "> 0"]),
    ("flip-one", _set(("flip",), 1.0), ["'flip'", "[0, 1)", "1.0"]),
    ("flip-string", _set(("flip",), "yes"), ["'flip'", "'yes'"]),
    ("dx-negative", _set(("dx",), -0.1), ["'dx'", "-0.1"]),
    ("dx-tiny", _set(("dx",), 1e-9), ["'dx'", "1e-09", "too small"]),
    ("frames-one", _set(("frames",), 1), ["'frames'", ">= 2"]),
    ("frame_dt-negative", _set(("frame_dt",), -0.04), ["'frame_dt'"]),
    ("density-negative", _set(M + ("density",), -1000.0), ["bodies[0].material.density", "-1000"]),
    ("mu-negative", _set(M + ("mu",), -1.0), ["mu = -1.0", "out of range"]),
    ("friction-negative", _set(C + ("friction",), -0.1), ["colliders[0].friction", "-0.1"]),
    ("gravity-nan", _set(("gravity",), [0.0, float("nan")]), ["'gravity'"]),
    # a body outside the domain, an empty body, a degenerate box
    ("body-outside", _set(B + ("hi",), [1.2, 0.5]), ["bodies[0]", "outside the domain"]),
    ("body-empty", _set(B, {"shape": "sphere", "center": [0.5, 0.5], "radius": 0.02, "material": {"model": "elastic", "E": 1e5, "nu": 0.3}}), ["bodies[0]", "empty"]),
    ("box-inverted", _set(B + ("hi",), [0.2, 0.5]), ["bodies[0]", "'hi' must exceed 'lo'"]),
]

ELASTIC, SAND = {"model": "elastic", "E": 1e5, "nu": 0.3}, {"model": "sand", "friction_angle": 30.0}
BAD_MATERIALS = [
    ("E-zero", {**ELASTIC, "E": 0.0}, ["E = 0.0", "> 0"]),
    ("E-negative", {**ELASTIC, "E": -1e5}, ["E = -100000.0", "> 0"]),
    ("nu-half", {**ELASTIC, "nu": 0.5}, ["nu = 0.5", "(-1, 0.5)"]),
    ("nu-minus-one", {**ELASTIC, "nu": -1.0}, ["nu = -1.0", "(-1, 0.5)"]),
    ("nu-large", {**ELASTIC, "nu": 0.7}, ["nu = 0.7"]),
    ("angle-zero", {**SAND, "friction_angle": 0.0}, ["friction_angle = 0.0", "(0, 90)"]),
    ("angle-90", {**SAND, "friction_angle": 90.0}, ["friction_angle = 90.0", "(0, 90)"]),
    ("angle-negative", {**SAND, "friction_angle": -10.0}, ["friction_angle = -10.0"]),
    ("density-negative-sand", {**SAND, "density": -5.0}, ["density", "-5"]),
    ("plasticine-missing-yield", {"model": "plasticine", "E": 1e5, "nu": 0.3}, ["missing required parameter", "'yield_stress'"]),
]
BAD_SCENES += [(f"material-{name}", _set(M, material), words) for name, material, words in BAD_MATERIALS]


def bad_scene(mutate) -> dict:
    return mutate(small_spec())


def test_small_spec_is_valid():
    scene = load_scene(small_spec())
    assert scene.model.num_particles == 16


@pytest.mark.parametrize("mutate, words", [case[1:] for case in BAD_SCENES], ids=[case[0] for case in BAD_SCENES])
def test_bad_scene_gives_one_clear_error(mutate, words):
    with pytest.raises(SceneError) as info:
        load_scene(bad_scene(mutate))
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert word in message, f"{word!r} not in {message!r}"


def bad_scene_files(tmp_path) -> list[tuple[str, str, list[str]]]:
    """(id, scene file, words) for errors in files: unreadable scene files, meshes, point files."""
    cases = []

    def write(name, content):
        path = tmp_path / name
        (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
        return str(path)

    cases.append(("toml-syntax", write("syntax.toml", "dim = 2\ndx = \n"), ["syntax.toml", "cannot parse"]))
    cases.append(("json-syntax", write("syntax.json", '{"dim": 2,'), ["syntax.json", "cannot parse"]))
    cases.append(("not-utf8", write("binary.toml", bytes(range(128, 256))), ["binary.toml", "cannot parse"]))
    cases.append(("wrong-suffix", write("scene.yaml", "dim: 2\n"), ["scene.yaml", ".toml or .json"]))
    cases.append(("missing-file", str(tmp_path / "nothere.toml"), ["not found", "nothere.toml"]))
    cases.append(("top-level-list", write("list.json", "[1, 2]"), ["scene", "table/object"]))
    # meshes: garbage bytes, a file that does not exist, an open mesh, a mesh body in 2D
    write("garbage.obj", bytes(range(256)) * 8)
    write("broken.obj", "v 0 0 0\nv 1 0 0\nf 1 2 3\nhello\n")
    for name, mesh, words in [
        ("mesh-garbage", "garbage.obj", ["bodies[0]", "garbage.obj"]),
        ("mesh-broken", "broken.obj", ["bodies[0]", "broken.obj"]),
        ("mesh-missing", "nothere.obj", ["bodies[0]", "not found", "nothere.obj"]),
        ("mesh-open", asset_path("bowl.obj"), ["bodies[0]", "bowl.obj", "watertight"]),
    ]:
        cases.append((name, write(f"{name}.json", json.dumps(_mesh_spec(mesh, dx=0.1))), words))
    spec = small_spec(bodies=[{"shape": "mesh", "path": "ico.obj", "material": ELASTIC}])
    cases.append(("mesh-2d", write("mesh2d.json", json.dumps(spec)), ["bodies[0]", "dim = 3"]))
    # mesh colliders
    spec = _mesh_spec(asset_path("bunny.obj"), dx=0.1, scale=0.3)
    spec["colliders"] = [{"type": "mesh", "path": "garbage.obj"}]
    cases.append(("collider-mesh-garbage", write("colgarbage.json", json.dumps(spec)), ["garbage.obj"]))
    spec["colliders"] = [{"type": "mesh", "path": "nothere.obj"}]
    cases.append(("collider-mesh-missing", write("colmissing.json", json.dumps(spec)), ["nothere.obj", "not found"]))
    # points files
    np.save(tmp_path / "flat.npy", np.zeros(6))
    np.savez(tmp_path / "points.npz", points=POINTS)
    np.save(tmp_path / "strings.npy", np.array([["a", "b"]]))
    np.save(tmp_path / "objects.npy", np.array([[0.5, None]], dtype=object), allow_pickle=True)
    (tmp_path / "garbage.npy").write_bytes(b"\x93NUMPY garbage")
    for name, file, words in [
        ("points-missing", "nothere.npy", ["bodies[0]", "not found", "nothere.npy"]),
        ("points-shape", "flat.npy", ["bodies[0]", "flat.npy", "(N, 2)"]),
        ("points-npz", "points.npz", ["bodies[0]", "points.npz", ".npy"]),
        ("points-strings", "strings.npy", ["bodies[0]", "strings.npy", "numeric"]),
        ("points-objects", "objects.npy", ["bodies[0]", "objects.npy"]),
        ("points-garbage", "garbage.npy", ["bodies[0]", "garbage.npy"]),
        ("points-path-number", 5, ["bodies[0].path", "5"]),
    ]:
        spec = small_spec(bodies=[{"shape": "points", "path": file, "material": ELASTIC}])
        cases.append((name, write(f"{name}.json", json.dumps(spec)), words))
    return cases


BAD_SCENE_FILE_IDS = [
    "toml-syntax", "json-syntax", "not-utf8", "wrong-suffix", "missing-file", "top-level-list",
    "mesh-garbage", "mesh-broken", "mesh-missing", "mesh-open", "mesh-2d", "collider-mesh-garbage",
    "collider-mesh-missing", "points-missing", "points-shape", "points-npz", "points-strings",
    "points-objects", "points-garbage", "points-path-number",
]  # fmt: skip


def test_bad_scene_file_ids_are_complete(tmp_path):
    assert [case[0] for case in bad_scene_files(tmp_path)] == BAD_SCENE_FILE_IDS


@pytest.mark.parametrize("case", BAD_SCENE_FILE_IDS)
def test_bad_scene_file_gives_one_clear_error(tmp_path, case):
    pytest.importorskip("trimesh")
    _, path, words = {c[0]: c for c in bad_scene_files(tmp_path)}[case]
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    for word in words:
        assert word in message, f"{word!r} not in {message!r}"


# --------------------------------------------------------------------------- observation files


def full_observation(rng=None) -> Observation:
    """An observation with every optional key, NaNs among the positions."""
    rng = rng or np.random.default_rng(0)
    T, N, V, H, W, P = 4, 5, 2, 6, 7, 3
    positions = rng.normal(size=(T, N, 3))
    positions[1, 2] = np.nan
    positions[3, :, 0] = np.nan
    return Observation(
        times=np.array([0.0, 0.05, 0.1, 0.3]),
        positions=positions,
        point_ids="particles",
        masks=(rng.random((V, T, H, W)) > 0.5).astype(np.uint8) * 255,
        images=rng.integers(0, 256, (V, T, H, W, 3), dtype=np.uint8),
        intrinsics=rng.normal(size=(V, 3, 3)),
        cam_to_world=rng.normal(size=(V, 4, 4)),
        probe_names=("front_x", "gauge_H2", "μ-probe"),
        probe_times=rng.random((P, 9)),
        probe_values=rng.normal(size=(P, 9)),
        scene=json.dumps(small_spec()),
    )


def test_observation_round_trip_is_exact(tmp_path):
    obs = full_observation()
    path = save_observation(tmp_path / "obs.npz", obs)
    again = load_observation(path)
    for key in ("times", "positions", "masks", "images", "intrinsics", "cam_to_world", "probe_times", "probe_values"):
        a, b = getattr(obs, key), getattr(again, key)
        np.testing.assert_array_equal(b, a)  # NaNs compare equal here
        assert b.shape == a.shape and b.dtype == np.asarray(a).dtype, key
    assert np.isnan(again.positions).sum() == np.isnan(obs.positions).sum() > 0
    assert again.point_ids == "particles" and isinstance(again.point_ids, str)
    assert again.probe_names == obs.probe_names and all(type(n) is str for n in again.probe_names)
    assert again.scene == obs.scene and again.scene_spec == small_spec()
    # the file holds the format string
    with np.load(path, allow_pickle=False) as data:
        assert str(data["format"]) == FORMAT


def test_observation_round_trip_with_only_some_keys(tmp_path):
    obs = Observation(times=np.array([0.0, 0.1]), positions=np.zeros((2, 3, 2)))
    again = load_observation(save_observation(tmp_path / "o.npz", obs))
    assert again.point_ids is None and again.scene is None and again.masks is None and again.probe_names is None
    np.testing.assert_array_equal(again.positions, obs.positions)
    probes = Observation(times=np.array([0.5]), probe_names=("h",), probe_times=np.ones((1, 2)), probe_values=np.zeros((1, 2)))
    again = load_observation(save_observation(tmp_path / "p.npz", probes))
    assert again.positions is None and again.probe_names == ("h",)


class _Trap:
    """Unpickling this creates a folder: loading must never unpickle."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def test_observation_is_loaded_without_pickle(tmp_path, monkeypatch):
    marker = tmp_path / "unpickled"
    trap = np.empty((), dtype=object)
    trap[()] = _Trap(str(marker))
    path = tmp_path / "evil.npz"
    np.savez(path, format=np.array(FORMAT), times=np.array([0.0, 0.1]), positions=np.zeros((2, 1, 2)), scene=trap)
    with pytest.raises(ObservationError, match="evil.npz"):
        load_observation(path)
    assert not marker.exists()
    # and np.load is asked for allow_pickle=False
    calls = []
    real_load = np.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("allow_pickle"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(np, "load", spy)
    load_observation(save_observation(tmp_path / "good.npz", full_observation()))
    assert calls and all(flag is False for flag in calls)


def _npz(**arrays):
    return {"format": np.array(FORMAT), "times": np.array([0.0, 0.1, 0.2]), "positions": np.zeros((3, 4, 2)), **arrays}


#: (id, file content: bytes or arrays for np.savez (None drops a key), words the error must contain)
BAD_OBSERVATIONS = [
    ("not-a-zip", b"this is not an npz file", ["not an .npz"]),
    ("empty-file", b"", ["not an .npz"]),
    ("npy-not-npz", "npy", ["not an .npz"]),
    ("truncated", "truncated", ["not"]),
    ("object-array", _npz(extra_objects=np.array([{"a": 1}], dtype=object)), ["not a readable"]),
    ("wrong-format", _npz(format=np.array("jaxmpm.observation/2")), ["'format'", "jaxmpm.observation/2"]),
    ("missing-format", _npz(format=None), ["'format'", "None"]),
    ("missing-times", _npz(times=None), ["missing required key 'times'"]),
    ("times-2d", _npz(times=np.zeros((3, 1))), ["'times'", "1-D"]),
    ("times-strings", _npz(times=np.array(["0", "1", "2"])), ["'times'", "numeric"]),
    ("times-decreasing", _npz(times=np.array([0.0, 0.2, 0.1])), ["'times'", "increasing"]),
    ("times-nan", _npz(times=np.array([0.0, np.nan, 0.2])), ["'times'", "finite"]),
    ("positions-wrong-T", _npz(positions=np.zeros((2, 4, 2))), ["'positions'", "(2, 4, 2)", "T=3"]),
    ("positions-2d", _npz(positions=np.zeros((3, 4))), ["'positions'", "(3, 4)"]),
    ("positions-D4", _npz(positions=np.zeros((3, 4, 4))), ["'positions'", "(3, 4, 4)"]),
    ("positions-empty", _npz(positions=np.zeros((3, 0, 2))), ["'positions'", "(3, 0, 2)"]),
    ("positions-all-nan", _npz(positions=np.full((3, 4, 2), np.nan)), ["'positions'", "all NaN"]),
    ("positions-inf", _npz(positions=np.full((3, 4, 2), np.inf)), ["'positions'", "infinite"]),
    ("positions-strings", _npz(positions=np.full((3, 4, 2), "x")), ["'positions'", "numeric"]),
    ("no-data", _npz(positions=None), ["at least one of"]),
    ("unknown-key", _npz(velocities=np.zeros(3)), ["unknown keys", "velocities"]),
    ("point-ids", _npz(point_ids=np.array("tracks")), ["'point_ids'", "tracks"]),
    ("scene-not-json", _npz(scene=np.array("{dim = 2")), ["'scene'", "JSON"]),
    ("scene-not-object", _npz(scene=np.array("[1, 2]")), ["'scene'", "JSON object"]),
    ("masks-without-cameras", _npz(masks=np.zeros((1, 3, 4, 4), np.uint8)), ["'masks'", "'intrinsics'"]),
    ("masks-wrong-T", _npz(masks=np.zeros((1, 2, 4, 4), np.uint8)), ["'masks'", "T=3"]),
    ("masks-float", _npz(masks=np.zeros((1, 3, 4, 4)), intrinsics=np.zeros((1, 3, 3)), cam_to_world=np.zeros((1, 4, 4))), ["'masks'", "uint8"]),
    ("images-no-rgb", _npz(images=np.zeros((1, 3, 4, 4, 4), np.uint8)), ["'images'"]),
    ("cameras-wrong-V", _npz(masks=np.zeros((2, 3, 4, 4), np.uint8), intrinsics=np.zeros((1, 3, 3)), cam_to_world=np.zeros((2, 4, 4))), ["'intrinsics'", "V=2"]),
    ("probes-shape", _npz(probe_names=np.array(["a", "b"]), probe_times=np.zeros((2, 5)), probe_values=np.zeros((2, 4))), ["'probe_times'", "'probe_values'"]),
    ("probes-missing-values", _npz(probe_names=np.array(["a"]), probe_times=np.zeros((1, 5))), ["'probe_values'"]),
    ("probe-names-scalar", _npz(probe_names=np.array("a"), probe_times=np.zeros((1, 5)), probe_values=np.zeros((1, 5))), ["'probe_names'"]),
    ("probe-values-strings", _npz(probe_names=np.array(["a"]), probe_times=np.zeros((1, 2)), probe_values=np.array([["a", "b"]])), ["'probe_values'", "numeric"]),
]


def write_bad_observation(tmp_path, case) -> str:
    name, content, _ = case
    path = tmp_path / f"{name}.npz"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "npy":
        with open(path, "wb") as fh:
            np.save(fh, np.zeros((3, 4, 2)))
    elif content == "truncated":
        save_observation(path, Observation(times=np.arange(3.0), positions=np.zeros((3, 50, 2))))
        path.write_bytes(path.read_bytes()[:-40])
    else:
        arrays = {k: v for k, v in content.items() if v is not None}
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)
    return str(path)


@pytest.mark.parametrize("case", BAD_OBSERVATIONS, ids=[c[0] for c in BAD_OBSERVATIONS])
def test_bad_observation_gives_one_clear_error(tmp_path, case):
    path = write_bad_observation(tmp_path, case)
    with pytest.raises(ObservationError) as info:
        load_observation(path)
    message = str(info.value)
    assert "\n" not in message
    assert f"{case[0]}.npz" in message  # names the file
    for word in case[2]:
        assert word in message, f"{word!r} not in {message!r}"


def test_missing_observation_file(tmp_path):
    with pytest.raises(ObservationError, match="not found.*nothere.npz"):
        load_observation(tmp_path / "nothere.npz")


def test_observation_constructor_validates():
    with pytest.raises(ObservationError, match="'positions'"):
        Observation(times=np.array([0.0, 0.1]), positions=np.zeros((3, 4, 2)))
    with pytest.raises(ObservationError, match="at least one of"):
        Observation(times=np.array([0.0, 0.1]))
    with pytest.raises(ObservationError, match="'scene'"):
        Observation(times=np.array([0.0, 0.1]), positions=np.zeros((2, 4, 2)), scene="not json")


# --------------------------------------------------------------------------- atomic writes


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_failing_write_leaves_old_file_and_no_temp_files(tmp_path):
    target = tmp_path / "out.npz"
    target.write_bytes(b"old contents")

    def failing(tmp):
        with open(tmp, "wb") as fh:
            fh.write(b"half written")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, failing)
    assert target.read_bytes() == b"old contents"
    assert _listing(tmp_path) == ["out.npz"]


def test_failing_save_observation_leaves_old_file(tmp_path, monkeypatch):
    target = tmp_path / "obs.npz"
    good = full_observation()
    save_observation(target, good)
    before = target.read_bytes()

    def boom(fh, **arrays):
        fh.write(b"PK partial")
        raise KeyboardInterrupt  # even an interrupt must not leave a partial file

    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(KeyboardInterrupt):
        save_observation(target, good)
    assert target.read_bytes() == before
    assert _listing(tmp_path) == ["obs.npz"]
    monkeypatch.undo()
    # an invalid observation is refused before anything is written
    bad = full_observation()
    bad.positions = np.zeros((1, 2, 3))
    with pytest.raises(ObservationError):
        save_observation(target, bad)
    assert target.read_bytes() == before
    assert _listing(tmp_path) == ["obs.npz"]


def test_atomic_write_replaces_and_creates_folders(tmp_path):
    target = tmp_path / "a" / "b" / "fit.json"
    atomic_write(target, lambda tmp: open(tmp, "w").write("1"))
    atomic_write(target, lambda tmp: open(tmp, "w").write("2"))
    assert target.read_text() == "2"
    assert _listing(target.parent) == ["fit.json"]
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0o600
