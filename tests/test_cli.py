"""The ``jaxmpm`` command (DESIGN §5.3): a tiny simulate -> fit round trip, and every user error
ending with exit code 2, one line on stderr, no traceback and no clobbered output."""

from __future__ import annotations

import json

import imageio.v2 as imageio
import numpy as np
import pytest
from test_scene_io import BAD_OBSERVATIONS, BAD_SCENE_FILE_IDS, BAD_SCENES, bad_scene, bad_scene_files, write_bad_observation

from jaxmpm.cli import main
from jaxmpm.observe import load_observation

#: A 2D Newtonian block thrown onto a sticky floor: 48 particles, 3 frames x 10 substeps.
TINY_SCENE = """
dim = 2
dx = 0.05
domain = {{ lo = [0.0, 0.0], hi = [0.6, 0.6] }}
gravity = [0.0, -9.8]
frames = 3
frame_dt = 0.04
substeps = 10

[[bodies]]
shape = "box"
lo = [0.2, 0.15]
hi = [0.4, 0.3]
ppc = 4
velocity = [0.0, -1.5]
material = {{ model = "newtonian", mu = {mu}, kappa = 1e4, density = 1000.0 }}

[[colliders]]
type = "plane"
name = "floor"
point = [0.0, 0.1]
normal = [0.0, 1.0]
contact = "sticky"
"""

#: Stiff elastic block resting on a sticky floor with one substep per frame (dt = 0.04 s).
UNSTABLE_SCENE = """
dim = 2
dx = 0.05
domain = { lo = [0.0, 0.0], hi = [0.6, 0.6] }
frames = 4
frame_dt = 0.04
substeps = 1

[[bodies]]
shape = "box"
lo = [0.2, 0.1]
hi = [0.4, 0.3]
ppc = 4
material = { model = "elastic", E = 1e7, nu = 0.3 }

[[colliders]]
type = "plane"
point = [0.0, 0.1]
normal = [0.0, 1.0]
"""

SENTINEL = b"an existing file that a failed run must not touch"


def assert_user_error(code, capsys, command, words=()):
    """Exit code 2, exactly one line on stderr naming the command, no traceback."""
    out, err = capsys.readouterr()
    assert code == 2, f"exit code {code}; stderr: {err}"
    assert "Traceback" not in err and "Traceback" not in out
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith(f"jaxmpm {command}: error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], err
    for word in words:
        assert word in errors[0], f"{word!r} not in {errors[0]!r}"
    return errors[0]


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """``jaxmpm simulate`` of the tiny scene (mu = 200), run once for the module."""
    folder = tmp_path_factory.mktemp("cli")
    scene = folder / "scene.toml"
    scene.write_text(TINY_SCENE.format(mu=200.0))
    obs = folder / "out" / "obs.npz"
    code = main(["simulate", str(scene), "--out", str(obs)])
    return folder, scene, obs, code


def test_simulate_writes_a_valid_observation(simulated, capsys):
    folder, scene, path, code = simulated
    assert code == 0
    obs = load_observation(path)
    assert obs.positions.shape == (3, 48, 2)
    assert obs.point_ids == "particles"
    np.testing.assert_allclose(obs.times, [0.0, 0.04, 0.08], rtol=1e-6)
    assert np.all(np.isfinite(obs.positions))
    assert obs.positions[-1, :, 1].mean() < obs.positions[0, :, 1].mean()  # it fell
    spec = obs.scene_spec
    assert spec["dim"] == 2 and spec["bodies"][0]["material"]["mu"] == 200.0
    assert sorted(p.name for p in path.parent.iterdir()) == ["obs.npz"]  # no temp files left


def test_fit_recovers_mu_from_a_perturbed_start(simulated, capsys):
    folder, _, obs, code = simulated
    assert code == 0
    start = folder / "start.toml"
    start.write_text(TINY_SCENE.format(mu=140.0))
    out = folder / "fit.json"
    assert main(["fit", str(start), str(obs), "--params", "mu", "--out", str(out), "--numerics"]) == 0
    result = json.loads(out.read_text())
    assert {"params", "std", "loss", "seconds", "iterations"} <= set(result)
    # --numerics: the moves of a refit at dt/2 and with the FLIP blend, in fit.json and the table
    assert set(result["numerics"]) == {"mu"} and set(result["numerics"]["mu"]) == {"dt", "transfer"}
    assert all(np.isfinite(v) for v in result["numerics"]["mu"].values())
    assert result["stages"][-1]["numerics"]["transfer"]["flip_checked"] == 0.99
    assert not any("would move" in note for note in result["notes"])  # the data are this model's own
    assert set(result["params"]) == set(result["std"]) == {"mu"}
    assert result["params"]["mu"] == pytest.approx(200.0, rel=1e-2)
    assert np.isfinite(result["std"]["mu"]) and result["std"]["mu"] >= 0
    loss = result["loss"]
    assert len(loss) >= 2 and loss[-1] < 1e-3 * loss[0]
    assert all(b <= a * (1 + 1e-6) for a, b in zip(loss, loss[1:]))  # accepted steps never increase it
    assert isinstance(result["iterations"], int) and result["iterations"] >= 1
    assert result["seconds"] > 0
    captured = capsys.readouterr()
    assert "mu" in captured.out and "Traceback" not in captured.err
    assert "dt/2 move" in captured.out and "transfer move" in captured.out


@pytest.mark.parametrize("params, words", [
    ("bogus", ["'bogus'"]),
    ("mu,bogus", ["'bogus'"]),
    ("floor.bogus", ["floor.bogus"]),
    ("nobody.mu", ["nobody.mu", "'nobody'"]),
])  # fmt: skip
def test_fit_unknown_parameter_names(simulated, capsys, params, words):
    folder, scene, obs, _ = simulated
    out = folder / "unknown.json"
    code = main(["fit", str(scene), str(obs), "--params", params, "--out", str(out)])
    assert_user_error(code, capsys, "fit", words)
    assert not out.exists()


def test_fit_observation_of_another_dimension(simulated, tmp_path, capsys):
    _, scene, _, _ = simulated
    from jaxmpm.observe import Observation, save_observation

    obs = save_observation(tmp_path / "3d.npz", Observation(times=np.array([0.0, 0.04]), positions=np.zeros((2, 48, 3))))
    code = main(["fit", str(scene), str(obs), "--params", "mu", "--out", str(tmp_path / "f.json")])
    assert_user_error(code, capsys, "fit", ["3-D", "2-D"])


# --------------------------------------------------------------------------- bad input -> exit 2


@pytest.mark.parametrize("mutate, words", [case[1:] for case in BAD_SCENES], ids=[case[0] for case in BAD_SCENES])
def test_simulate_bad_scene_exits_2(tmp_path, capsys, mutate, words):
    scene = tmp_path / "bad.json"
    scene.write_text(json.dumps(bad_scene(mutate)))
    out = tmp_path / "obs.npz"
    out.write_bytes(SENTINEL)
    code = main(["simulate", str(scene), "--out", str(out)])
    assert_user_error(code, capsys, "simulate", words)
    assert out.read_bytes() == SENTINEL


@pytest.mark.parametrize("case", BAD_SCENE_FILE_IDS)
def test_simulate_bad_scene_file_exits_2(tmp_path, capsys, case):
    pytest.importorskip("trimesh")
    _, scene, words = {c[0]: c for c in bad_scene_files(tmp_path)}[case]
    out = tmp_path / "obs.npz"
    code = main(["simulate", scene, "--out", str(out)])
    assert_user_error(code, capsys, "simulate", words)
    assert not out.exists()


@pytest.mark.parametrize("case", BAD_OBSERVATIONS, ids=[c[0] for c in BAD_OBSERVATIONS])
def test_fit_bad_observation_exits_2(simulated, tmp_path, capsys, case):
    _, scene, _, _ = simulated
    path = write_bad_observation(tmp_path, case)
    out = tmp_path / "fit.json"
    out.write_bytes(SENTINEL)
    code = main(["fit", str(scene), path, "--params", "mu", "--out", str(out)])
    assert_user_error(code, capsys, "fit", [f"{case[0]}.npz", *case[2]])
    assert out.read_bytes() == SENTINEL


def test_fit_missing_observation_file(simulated, tmp_path, capsys):
    _, scene, _, _ = simulated
    code = main(["fit", str(scene), str(tmp_path / "nothere.npz"), "--out", str(tmp_path / "f.json")])
    assert_user_error(code, capsys, "fit", ["nothere.npz", "not found"])


@pytest.mark.parametrize("scan,words", [("1,x", ["--scan", "'1,x'"]), ("1,inf", ["--scan", "finite"])])
def test_fit_bad_scan_exits_2_before_loading(simulated, tmp_path, capsys, scan, words):
    _, scene, obs, _ = simulated
    out = tmp_path / "fit.json"
    code = main(["fit", str(scene), str(obs), "--scan", scan, "--out", str(out)])
    assert_user_error(code, capsys, "fit", words)
    assert not out.exists()


def test_fit_bad_scene_exits_2(simulated, tmp_path, capsys):
    _, _, obs, _ = simulated
    scene = tmp_path / "bad.json"
    scene.write_text(json.dumps(bad_scene(BAD_SCENES[0][1])))
    code = main(["fit", str(scene), str(obs), "--params", "mu", "--out", str(tmp_path / "f.json")])
    assert_user_error(code, capsys, "fit", ["'colour'"])


# --------------------------------------------------------------------------- unstable run


def test_unstable_simulation_exits_2_and_keeps_the_old_output(tmp_path, capsys):
    scene = tmp_path / "unstable.toml"
    scene.write_text(UNSTABLE_SCENE)
    out = tmp_path / "obs.npz"
    out.write_bytes(SENTINEL)
    code = main(["simulate", str(scene), "--out", str(out)])
    line = assert_user_error(code, capsys, "simulate", ["unstable", "frame ", "smaller dt"])
    # frame 0: the stiff block's stress-wave CFL number is checked before the first frame runs
    assert any(f"frame {i}" in line for i in range(0, 4))
    assert out.read_bytes() == SENTINEL
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obs.npz", "unstable.toml"]


# --------------------------------------------------------------------------- unwritable outputs


def test_unwritable_output_exits_2(simulated, tmp_path, capsys):
    _, scene, _, _ = simulated
    folder = tmp_path / "a_folder"
    folder.mkdir()
    code = main(["simulate", str(scene), "--out", str(folder)])
    assert_user_error(code, capsys, "simulate", ["a_folder"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_folder"]  # no temp file left behind


# --------------------------------------------------------------------------- views and video

#: A 3D elastic cube falling in free space: 64 particles, 3 frames x 5 substeps.
TINY_SCENE_3D = """
dim = 3
dx = 0.1
domain = { lo = [0.0, 0.0, 0.0], hi = [1.0, 1.0, 1.0] }
frames = 3
frame_dt = 0.04
substeps = 5

[[bodies]]
shape = "box"
lo = [0.4, 0.5, 0.4]
hi = [0.6, 0.7, 0.6]
material = { model = "elastic", E = 1e4, nu = 0.3 }
"""


def test_simulate_renders_views_into_the_observation_and_writes_a_video(tmp_path, capsys):
    import imageio.v3 as iio

    scene = tmp_path / "cube.toml"
    scene.write_text(TINY_SCENE_3D)
    obs_path, video = tmp_path / "obs.npz", tmp_path / "views.gif"
    code = main(["simulate", str(scene), "--out", str(obs_path), "--views", "2", "--res", "16", "--video", str(video)])
    assert code == 0, capsys.readouterr().err
    obs = load_observation(obs_path)
    assert obs.masks.shape == (2, 3, 16, 16) and obs.images.shape == (2, 3, 16, 16, 3)
    assert obs.intrinsics.shape == (2, 3, 3) and obs.cam_to_world.shape == (2, 4, 4)
    # the rig is centred on the body: every view sees it in every frame, and not everywhere
    covered = (obs.masks > 127).mean(axis=(2, 3))
    assert covered.min() > 0.02 and covered.max() < 0.9
    # the cube falls: in each view its silhouette's centroid moves down the image (OpenCV: +v)
    rows = np.arange(16)[None, None, :, None]
    centroid_v = (obs.masks * rows).sum(axis=(2, 3)) / obs.masks.sum(axis=(2, 3))
    assert np.all(centroid_v[:, -1] > centroid_v[:, 0])
    frames = iio.imread(video, index=None)
    assert frames.shape[0] == 3


def test_simulate_views_of_a_2d_scene_is_refused_before_simulating(simulated, tmp_path, capsys):
    _, scene, _, _ = simulated
    capsys.readouterr()
    code = main(["simulate", str(scene), "--out", str(tmp_path / "obs.npz"), "--views", "2"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines()[-1] == "jaxmpm simulate: error: --views needs a 3D scene", err
    assert "particles, grid" not in err  # refused before the scene ran
    assert not (tmp_path / "obs.npz").exists()


# --------------------------------------------------------------------------- demo


def test_demo_quick_identifies_the_droplet(tmp_path):
    """``jaxmpm demo --quick`` as a user runs it (a subprocess, float32): 33 s wall here."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-m", "jaxmpm.cli", "demo", "--quick", "--out", str(tmp_path)],
                         capture_output=True, text=True, env=env, timeout=3600)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads((tmp_path / "fit.json").read_text())
    for name, truth in result["truth"].items():
        assert result["params"][name] == pytest.approx(truth, rel=0.01), name
    assert {p.name for p in tmp_path.iterdir()} >= {"fit.json", "loss.png", "observation.npz"}
    assert any(p.suffix in (".mp4", ".gif") for p in tmp_path.iterdir())


@pytest.mark.slow  # 200 s here; its stages are tested in test_reconstruct.py and test_fit_images.py
def test_demo_video_goes_from_rendered_views_to_parameters(tmp_path, capsys):
    """``jaxmpm demo --video --quick`` with 2 LM steps per stage (the plumbing; the full run's
    accuracy is in docs/identify.md): a PAC-NeRF folder with collider masks is written and read
    back, the collider (the edge of a box) is reconstructed within a cell of the true one and
    written as surfels, the free fall gives the block's initial velocity, and identify writes
    its files."""
    from jaxmpm.demo import run_video_demo

    out = run_video_demo(tmp_path, quick=True, max_steps=2)
    dataset = tmp_path / "dataset"
    assert (dataset / "all_data.json").is_file() and (dataset / "scene_hint.toml").is_file()
    assert len(list((dataset / "data").glob("c_*.png"))) == 4
    assert set(out["files"]) >= {"fit", "report", "scene", "overlay", "overlay_frames", "iou", "collider_disks"}
    sheet = imageio.imread(out["files"]["overlay_frames"])  # a row per frame (6 of 6), a column per view (4 of 4)
    assert sheet.shape == (6 * 64 + 5 * 2, 4 * 64 + 3 * 2, 3) and sheet[..., 0].max() == 255
    assert out["chamfer_m"]["mesh"] < 0.05 and out["chamfer_m"]["surfels"] < 0.05  # dx = 0.05 m
    report = (tmp_path / "identify" / "report.md").read_text()
    assert "free fall: 2 frames" in report
    assert "(iou.png)" in report and "(overlay_frames.png)" in report
    scene = (tmp_path / "identify" / "scene.toml").read_text()
    assert 'path = "collider.obj"' in scene  # the hull mesh (the default; the surfels are written too)
    velocity = json.loads(scene.split("velocity = ")[1].split("\n")[0])
    np.testing.assert_allclose(velocity, [0.0, -1.0, 0.0], atol=0.05)  # from the free fall, corrected by g
    assert "truth" in capsys.readouterr().out


@pytest.mark.parametrize("flag, choice, value", [
    ("--refine-velocity", None, None), ("--refine-velocity", "auto", None), ("--refine-velocity", "yes", True),
    ("--refine-velocity", "no", False),
    ("--scan", None, None), ("--scan", "auto", None), ("--scan", "none", ()), ("--scan", "-1,2", (-1.0, 2.0)),
    ("--polish", None, None), ("--polish", "auto", None), ("--polish", "none", ()),
])
def test_fit_choice_reaches_the_fit(simulated, monkeypatch, flag, choice, value):
    """``jaxmpm fit --refine-velocity auto|yes|no`` is FitConfig.refine_velocity None|True|False;
    ``--scan auto|none|DECADES`` is FitConfig.scan None|()|the offsets; ``--polish auto|none`` is
    FitConfig.polish None|()."""
    import importlib

    folder, scene, obs, _ = simulated
    seen = {}

    class Stop(Exception):
        pass

    def fake_fit_scene(scene, obs, names, config, **kwargs):
        seen["config"] = config
        raise Stop

    monkeypatch.setattr(importlib.import_module("jaxmpm.fit"), "fit_scene", fake_fit_scene)
    argv = ["fit", str(scene), str(obs), "--params", "mu", "--out", str(folder / "choice.json")]
    with pytest.raises(Stop):
        main(argv + ([] if choice is None else [f"{flag}={choice}"]))
    field = flag.lstrip("-").replace("-", "_")
    assert getattr(seen["config"], field) == value and type(getattr(seen["config"], field)) is type(value)


@pytest.mark.parametrize("args, value", [([], None), (["--refine-velocity"], True), (["--refine-velocity", "yes"], True),
                                         (["--refine-velocity=no"], False), (["--refine-velocity", "auto"], None)])
def test_identify_refine_velocity_choice_reaches_identify(tmp_path, monkeypatch, args, value):
    """``jaxmpm identify --refine-velocity [auto|yes|no]``: absent or ``auto`` lets identify
    decide from the masks' noise (None), the bare flag still means yes (as before session 51);
    ``--numerics`` (with the bare flag) reaches it too."""
    import jaxmpm.reconstruct.pipeline as pipeline

    seen = {}

    class Stop(Exception):
        pass

    def fake_identify(*a, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(pipeline, "identify", fake_identify)
    with pytest.raises(Stop):
        main(["identify", str(tmp_path), "--material", "newtonian", "--out", str(tmp_path / "out")] + args
             + (["--numerics"] if value is True else []))
    assert seen["refine_velocity"] is value
    assert seen["numerics"] is (value is True)
