"""Cameras: projection, rays, look-at, the PAC-NeRF rig, all_data.json, validation."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.errors import ObservationError
from jaxmpm.render import (
    Camera,
    check_image_size,
    load_cameras_json,
    look_at,
    pacnerf_rig,
    save_cameras_json,
    stack_cameras,
    unstack_cameras,
)

# One camera pose of PAC-NeRF's "bird" scene (view 9), as stored in its all_data.json
# (OpenGL/Blender axes; 800×800 images, fx = fy = 965.68, 45° field of view).
BIRD_C2W = [
    [0.8700352710140692, 0.10518821359481381, -0.4816368620778594, -1.4449105862335783],
    [0.0, 0.9769718864492504, 0.2133680695132077, 0.6401042085396231],
    [0.4929894797979721, -0.1856377461846724, 0.85, 2.55],
]
BIRD_K = [[965.6844046797067, 0.0, 400.0], [0.0, 965.6844046797067, 400.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("dtype", [jnp.float32, pytest.param(jnp.float64, marks=pytest.mark.x64)])
def test_look_at_projects_target_to_centre_and_keeps_dtype(dtype):
    cam = look_at((1.0, 2.0, -3.0), (0.1, 0.2, 0.3), (0, 1, 0), 50.0, 40, 30, dtype=dtype)
    assert cam.K.dtype == dtype and cam.cam_to_world.dtype == dtype
    uv, z = cam.project(jnp.asarray([0.1, 0.2, 0.3], dtype=dtype))
    np.testing.assert_allclose(np.asarray(uv), [20.0, 15.0], atol=1e-4)
    assert float(z) > 0
    R = np.asarray(cam.rotation, dtype=np.float64)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-6)
    assert np.linalg.det(R) > 0
    # world up (+y) appears upwards in the image: a point above the target has a smaller row
    uv_up, _ = cam.project(jnp.asarray([0.1, 0.5, 0.3], dtype=dtype))
    assert float(uv_up[1]) < 15.0
    # vertical field of view
    assert math.isclose(float(cam.K[1, 1]), 15.0 / math.tan(math.radians(25.0)), rel_tol=1e-5)


@pytest.mark.x64
def test_project_unproject_and_rays_round_trip():
    cam = look_at((0.3, 1.5, -2.5), (0.0, 0.2, 0.1), (0, 1, 0), 45.0, 33, 21, dtype=jnp.float64)
    pts = jax.random.uniform(jax.random.key(0), (50, 3), jnp.float64, -0.5, 0.5)
    pix = jnp.asarray([0, 5, 32, 33, 21 * 33 - 1], dtype=jnp.int32)

    @jax.jit
    def run(cam, pts, pix):
        uv, z = cam.project(pts)
        o, d = cam.rays(pix)
        uv2, z2 = cam.project(o + 2.0 * d)
        return cam.unproject(uv, z), d, uv2, z2, cam.pixel_coordinates(pix), d @ cam.rotation[:, 2]

    back, d, uv2, z2, centres, cosz = (np.asarray(a) for a in run(cam, pts, pix))
    np.testing.assert_allclose(back, np.asarray(pts), atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(uv2, centres, atol=1e-9)
    # pixel centres: index 33 is row 1, col 0
    np.testing.assert_allclose(centres[3], [0.5, 1.5])
    # the z-depth of o + t d is t (d · camera z)
    np.testing.assert_allclose(z2, 2.0 * cosz, atol=1e-10)


@pytest.mark.x64
def test_pacnerf_rig_geometry_and_batching():
    target = (0.1, 0.5, -0.2)
    rig = pacnerf_rig(11, radius=3.0, target=target, fov_deg=45.0, res=64, dtype=jnp.float64)
    assert rig.num_views == 11 and rig.width == rig.height == 64
    pos = np.asarray(rig.position)
    np.testing.assert_allclose(np.linalg.norm(pos - np.asarray(target), axis=1), 3.0, atol=1e-9)
    assert np.all(pos[:, 1] > target[1])  # all above the object
    np.testing.assert_allclose(np.asarray(rig.K[:, 0, 0]), 32.0 / math.tan(math.radians(22.5)))
    p = jnp.asarray([target, [0.3, 0.4, 0.0]], jnp.float64)
    project = jax.jit(lambda c: c.project(p)[0])
    batched = np.asarray(jax.jit(jax.vmap(lambda c: c.project(p)[0]))(rig))
    np.testing.assert_allclose(batched[:, 0], 32.0, atol=1e-9)
    # vmap over the batch equals a loop over single cameras
    looped = np.stack([np.asarray(project(c)) for c in unstack_cameras(rig)])
    np.testing.assert_allclose(batched, looped, atol=1e-12)
    again = stack_cameras(unstack_cameras(rig))
    np.testing.assert_array_equal(np.asarray(again.K), np.asarray(rig.K))


@pytest.mark.x64
def test_all_data_json_round_trip(tmp_path):
    rig = pacnerf_rig(4, res=(48, 32), dtype=jnp.float64)
    times = [0.0, 1 / 24, 2 / 24]
    path = tmp_path / "all_data.json"
    save_cameras_json(path, rig, times)
    raw = json.loads(path.read_text())
    assert len(raw) == 12
    assert set(raw[0]) == {"file_path", "time", "c2w", "intrinsic"}
    assert np.shape(raw[0]["c2w"]) == (3, 4) and raw[5]["file_path"] == "./data/r_1_2.png"
    cams, entries = load_cameras_json(path, dtype=jnp.float64)
    assert (cams.width, cams.height) == (48, 32)  # inferred from the principal point
    np.testing.assert_allclose(np.asarray(cams.K), np.asarray(rig.K), atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(cams.cam_to_world), np.asarray(rig.cam_to_world), atol=1e-12
    )
    assert [(e["view"], e["frame"]) for e in entries][:4] == [(0, 0), (0, 1), (0, 2), (1, 0)]
    assert entries[5]["time"] == pytest.approx(2 / 24)
    # the written c2w uses OpenGL axes: the camera looks along its -z axis
    c2w_gl = np.asarray(raw[0]["c2w"])
    to_target = -c2w_gl[:, 3] / np.linalg.norm(c2w_gl[:, 3])
    np.testing.assert_allclose(-c2w_gl[:, 2], to_target, atol=1e-9)


@pytest.mark.x64
def test_pacnerf_bird_pose_convention(tmp_path):
    """A real PAC-NeRF pose: the object at the origin must land at the image centre."""
    path = tmp_path / "all_data.json"
    entry = {"file_path": "./data/r_9_7.png", "time": 7 / 24, "c2w": BIRD_C2W, "intrinsic": BIRD_K}
    path.write_text(json.dumps([entry, dict(entry, file_path="./data/r_9_-1.png", time=-1 / 24)]))
    cams, entries = load_cameras_json(path, dtype=jnp.float64)
    assert (cams.width, cams.height, cams.num_views) == (800, 800, 1)
    assert [e["frame"] for e in entries] == [7, -1]
    cam = cams.view(0)
    uv, z = cam.project(jnp.zeros(3, jnp.float64))
    np.testing.assert_allclose(np.asarray(uv), [400.0, 400.0], atol=1e-6)
    assert float(z) == pytest.approx(3.0, abs=1e-6)
    uv_up, _ = cam.project(jnp.asarray([0.0, 0.3, 0.0], jnp.float64))
    assert float(uv_up[1]) < 400.0  # world +y is up in the image


@pytest.mark.parametrize(
    "K, c2w, size, match",
    [
        (np.eye(3), np.diag([1.0, 1.0, 0.0, 1.0]), (8, 8), "not invertible"),
        (np.eye(3), np.diag([1.0, 1.0, -1.0, 1.0]), (8, 8), "not a rigid motion"),
        (np.eye(3), np.diag([2.0, 2.0, 2.0, 1.0]), (8, 8), "not a rigid motion"),
        (np.diag([-5.0, 5.0, 1.0]), np.eye(4), (8, 8), "focal lengths must be positive"),
        (np.diag([5.0, 0.0, 1.0]), np.eye(4), (8, 8), "focal lengths must be positive"),
        (np.diag([5.0, 5.0, 1.0]), np.eye(4), (0, 8), "width must be positive"),
        (np.diag([5.0, 5.0, 1.0]), np.eye(4), (8, -2), "height must be positive"),
        (np.diag([5.0, 5.0, np.nan]), np.eye(4), (8, 8), "NaN"),
        (np.diag([5.0, 5.0, 1.0]), np.eye(3), (8, 8), r"\(\.\.\., 4, 4\)"),
    ],
)
def test_bad_cameras_raise(K, c2w, size, match):
    with pytest.raises(ObservationError, match=match):
        Camera(K, c2w, *size)


def test_bad_json_and_sizes_raise(tmp_path):
    singular = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 3.0]]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps([{"file_path": "r_0_0.png", "c2w": singular, "intrinsic": BIRD_K}]))
    with pytest.raises(ObservationError, match="not invertible"):
        load_cameras_json(path)
    path.write_text(json.dumps([{"file_path": "r_0_0.png", "c2w": BIRD_C2W}]))
    with pytest.raises(ObservationError, match="intrinsic"):
        load_cameras_json(path)
    with pytest.raises(ObservationError, match="cannot read"):
        load_cameras_json(tmp_path / "missing.json")
    a = look_at((0, 0, -3), (0, 0, 0), width=16)
    b = look_at((0, 0, -3), (0, 0, 0), width=16, height=12)
    with pytest.raises(ObservationError, match="different image sizes"):
        stack_cameras([a, b])
    rig = stack_cameras([a, a])
    check_image_size(rig, np.zeros((2, 5, 16, 16)), rgb=False)
    with pytest.raises(ObservationError, match=r"image size \(H, W\) = \(16, 15\)"):
        check_image_size(rig, np.zeros((2, 5, 16, 15)), rgb=False)
    with pytest.raises(ObservationError, match="views"):
        check_image_size(rig, np.zeros((3, 5, 16, 16, 3)), rgb=True)
    with pytest.raises(ObservationError, match="parallel"):
        look_at((0, 0, 0), (0, 1, 0), (0, 1, 0))
