"""Bad input found by trying the command as a new user (issue 14, item 3): each one is refused
with one clear line, before the work starts, and never leaves a temporary file behind."""

from __future__ import annotations

import copy
import importlib
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import numpy as np
import pytest

from jaxmpm.cli import main
from jaxmpm.errors import SceneError
from jaxmpm.scene import load_scene

#: A 2D Newtonian block on a sticky floor: 48 particles, 3 frames x 10 substeps.
SCENE = {
    "dim": 2,
    "dx": 0.05,
    "domain": {"lo": [0.0, 0.0], "hi": [0.6, 0.6]},
    "gravity": [0.0, -9.8],
    "frames": 3,
    "frame_dt": 0.04,
    "substeps": 10,
    "bodies": [{"shape": "box", "lo": [0.2, 0.15], "hi": [0.4, 0.3], "ppc": 4, "velocity": [0.0, -1.5],
                "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e4, "density": 1000.0}}],
    "colliders": [{"type": "plane", "name": "floor", "point": [0.0, 0.1], "normal": [0.0, 1.0]}],
}


def scene_with(**changes) -> dict:
    """SCENE with top-level keys replaced (``None`` removes a key) and ``body_*`` / ``material_*`` keys
    of its body replaced."""
    spec = copy.deepcopy(SCENE)
    for key, value in changes.items():
        if key.startswith("body_"):
            spec["bodies"][0][key[5:]] = value
        elif key.startswith("material_"):
            spec["bodies"][0]["material"][key[9:]] = value
        elif value is None:
            spec.pop(key)
        else:
            spec[key] = value
    return spec


def refused(spec, base_dir=None) -> str:
    with pytest.raises(SceneError) as info:
        load_scene(spec, base_dir=base_dir)
    message = str(info.value)
    assert "\n" not in message
    return message


def user_error(capsys, command: str, argv: list[str]) -> str:
    """Run ``jaxmpm argv``: exit code 2 and exactly one error line, no traceback."""
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 2, f"exit code {code}; stderr: {err}"
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"jaxmpm {command}: error: "), err
    return lines[0]


# --------------------------------------------------------------------------- memory


@pytest.mark.parametrize("frames", [10**12, 10**9])
def test_too_many_frames_refused_with_the_memory_it_needs(frames):
    message = refused(scene_with(frames=frames))
    # frames x 48 particles x 2D x (positions + velocities, stacked: 4 copies) x 4 bytes
    need = 4.0 * frames * 48 * 2 * 4 / 1e9
    assert f"needs about {need:.3g} GB" in message and "fewer frames" in message, message


def test_too_many_particles_refused_before_sampling(monkeypatch):
    monkeypatch.setenv("JAXMPM_MEMORY_LIMIT_GB", "4")
    # ppc = 250000 (500 per axis) over 10 x 10 cells: 25 million particles, about 8.4 GB
    message = refused(scene_with(body_ppc=250000, body_lo=[0.05, 0.05], body_hi=[0.55, 0.55]))
    assert "GB" in message and "more than JAXMPM_MEMORY_LIMIT_GB (4 GB)" in message, message
    assert "lower ppc" in message, message


def test_too_fine_a_grid_refused(monkeypatch):
    monkeypatch.setenv("JAXMPM_MEMORY_LIMIT_GB", "4")
    message = refused(scene_with(dx=3e-5))
    assert "GB" in message and "larger dx" in message, message


def test_memory_limit_lets_a_small_scene_run(monkeypatch):
    monkeypatch.setenv("JAXMPM_MEMORY_LIMIT_GB", "0.001")  # 1 MB: the 48-particle scene needs ~0.03 MB
    assert load_scene(scene_with()).model.num_particles == 48


# --------------------------------------------------------------------------- time stepping


@pytest.mark.parametrize("changes, words", [
    ({"substeps": 3_000_000_000}, ["'substeps' = 3e+09", "limit of 2147483647"]),
    ({"substeps": None, "dt": 1e-12}, ["'dt' = 1e-12", "substeps per frame", "limit of 2147483647"]),
    ({"dt": 0.001}, ["either 'substeps' or 'dt'"]),
    ({"frame_dt": 1e-300}, ["'frame_dt' = 1e-300", "too small for float32"]),
])
def test_time_step_input_refused_with_its_cause(changes, words):
    message = refused(scene_with(**changes))
    for word in words:
        assert word in message, message
    assert "strictly increasing" not in message


@pytest.mark.parametrize("material, key", [
    ({"model": "elastic", "E": 1e300, "nu": 0.3}, "E"),
    ({"model": "newtonian", "mu": 1.0, "kappa": 1e4, "density": 1e40}, "density"),
])
def test_values_float32_cannot_compute_with_refused(material, key):
    message = refused(scene_with(body_material=material))
    assert f"material.{key} = " in message and "float32" in message, message


def test_ppc_message_says_square():
    message = refused(scene_with(body_ppc=8))
    assert "perfect square in 2D" in message and "th power" not in message


# --------------------------------------------------------------------------- mesh files


def mesh_scene(path: str) -> dict:
    return {
        "dim": 3, "dx": 0.1, "domain": {"lo": [0.0, 0.0, 0.0], "hi": [1.0, 1.0, 1.0]}, "frames": 2, "frame_dt": 0.01,
        "substeps": 2,
        "bodies": [{"shape": "box", "lo": [0.4, 0.5, 0.4], "hi": [0.6, 0.7, 0.6],
                    "material": {"model": "newtonian", "mu": 1.0, "kappa": 1e4}}],
        "colliders": [{"type": "mesh", "name": "tet", "path": path, "scale": 0.3, "translate": [0.3, 0.1, 0.3]}],
    }


def test_mesh_with_a_nan_vertex_refused_naming_the_file(tmp_path):
    pytest.importorskip("trimesh")
    corners = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 {z}\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n"
    (tmp_path / "tet.obj").write_text(corners.format(z=1))
    assert load_scene(mesh_scene("tet.obj"), base_dir=tmp_path).model.colliders[0].num_faces == 4
    (tmp_path / "tet_nan.obj").write_text(corners.format(z="nan"))
    message = refused(mesh_scene("tet_nan.obj"), base_dir=tmp_path)
    assert "tet_nan.obj" in message and "NaN" in message and "vertex 3" in message, message


def test_garbage_mesh_file_is_not_a_readable_mesh(tmp_path):
    pytest.importorskip("trimesh")
    (tmp_path / "garbage.stl").write_bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8).tobytes())
    message = refused(mesh_scene("garbage.stl"), base_dir=tmp_path)
    assert "garbage.stl" in message and "not a readable mesh file" in message, message
    assert "No module named" not in message


@pytest.mark.parametrize("where", ["collider", "body"])
def test_directory_as_mesh_path_says_it_is_a_directory(tmp_path, where):
    (tmp_path / "adir.obj").mkdir()
    spec = mesh_scene("adir.obj")
    if where == "body":
        spec["colliders"] = []
        spec["bodies"][0] = {"shape": "mesh", "path": "adir.obj", "material": {"model": "newtonian", "mu": 1.0,
                                                                               "kappa": 1e4}}
    message = refused(spec, base_dir=tmp_path)
    assert "adir.obj" in message and "is a directory" in message and "not found" not in message, message


# --------------------------------------------------------------------------- the command


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(SCENE))
    return path


def read_only_folder(tmp_path) -> Path:
    """A folder this process cannot write into (root ignores permission bits: use /sys there)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError:
        return folder
    if os.path.isdir("/sys"):
        try:
            with tempfile.TemporaryFile(dir="/sys"):
                pass
        except OSError:
            return Path("/sys")
    pytest.skip("no read-only folder available to this user")


def test_discover_into_a_read_only_folder_refused_before_the_work(tmp_path, scene_file, capsys):
    ro = read_only_folder(tmp_path)
    target = ro / "report"
    # the observation file does not exist: the output is checked before anything is read
    line = user_error(capsys, "discover", ["discover", str(scene_file), str(tmp_path / "none.npz"), "--out", str(target)])
    assert f"--out {target}" in line and "cannot write into" in line and ".npz" not in line.split("--out")[0], line


def test_demo_into_a_read_only_folder_refused_before_the_work(tmp_path, capsys):
    target = read_only_folder(tmp_path) / "demo"
    line = user_error(capsys, "demo", ["demo", "--quick", "--out", str(target)])
    assert f"--out {target}" in line and "cannot write into" in line, line


def test_demo_collider_without_video_refused_before_the_work(tmp_path, capsys):
    line = user_error(capsys, "demo", ["demo", "--collider", "bunny", "--out", str(tmp_path / "demo")])
    assert "--collider" in line and "--video" in line, line
    assert not (tmp_path / "demo").exists()


def test_outputs_under_a_file_refused(tmp_path, scene_file, capsys):
    (tmp_path / "afile").write_text("")
    line = user_error(capsys, "simulate", ["simulate", str(scene_file), "--out", str(tmp_path / "afile" / "o.npz")])
    assert "afile is a file, not a folder" in line, line


@pytest.mark.parametrize("extra, words", [
    (["--video", "v.xyz"], ["--video v.xyz", "unsupported file type '.xyz'", ".mp4"]),
    (["--views", "2", "--res", "4"], ["--res must be >= 8, got 4"]),
    (["--views", "-1"], ["--views must be >= 1, got -1"]),
    (["--views", "2"], ["--views needs a 3D scene"]),
])
def test_simulate_options_checked_before_simulating(tmp_path, scene_file, capsys, monkeypatch, extra, words):
    step_module = importlib.import_module("jaxmpm.step")  # jaxmpm.step is also the name of a function

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated before checking the options")

    monkeypatch.setattr(step_module, "run_frames", no_simulation)
    out = tmp_path / "o.npz"
    line = user_error(capsys, "simulate", ["simulate", str(scene_file), "--out", str(out), *extra])
    for word in words:
        assert word in line, line
    assert not out.exists()


@pytest.mark.parametrize("extra, words", [
    (["--max-steps", "0"], ["--max-steps must be >= 1, got 0"]),
    (["--max-steps", "-5"], ["--max-steps must be >= 1, got -5"]),
    (["--params", "E,,E"], ["--params 'E,,E': empty parameter name"]),
    (["--params", "mu,kappa,mu"], ["--params 'mu,kappa,mu': mu given more than once"]),
])
def test_fit_options_refused(tmp_path, scene_file, capsys, extra, words):
    # the observation file does not exist: the options are checked before anything is read
    line = user_error(capsys, "fit", ["fit", str(scene_file), str(tmp_path / "none.npz"),
                                      "--out", str(tmp_path / "fit.json"), *extra])
    for word in words:
        assert word in line, line


# --------------------------------------------------------------------------- atomic writes


WRITER = textwrap.dedent("""
    import os, signal, sys
    from jaxmpm.observe import atomic_write

    def write(tmp):
        with open(tmp, "wb") as fh:
            fh.write(b"partial")
        if sys.argv[2] == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
        else:
            raise KeyboardInterrupt

    atomic_write(sys.argv[1], write)
""")


@pytest.mark.parametrize("how, code", [("sigterm", 143), ("interrupt", -2)])  # -2: killed by SIGINT
def test_interrupted_write_leaves_no_temporary_file(tmp_path, how, code):
    target = tmp_path / "obs.npz"
    target.write_bytes(b"old")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parent.parent),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", WRITER, str(target), how], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == code, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obs.npz"]
    assert target.read_bytes() == b"old"
