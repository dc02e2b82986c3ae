"""PAC-NeRF / GIC dataset folders -> Observation, on tiny synthetic folders."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from jaxmpm.datasets import load_pacnerf
from jaxmpm.errors import ObservationError
from jaxmpm.render import Camera

H = W = 16
F = 20.0  # focal length, pixels
K = [[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]]
#: PAC-NeRF-style poses in OpenGL axes (camera looks along its -z): view 0 sits at +3 z
#: looking at the origin, view 1 at +3 x looking at the origin.
C2W_GL = [
    [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 3.0]],
    [[0.0, 0.0, 1.0, 3.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]],
]
TIMES = {-1: 0.0, 0: 0.0, 1: 1 / 24, 2: 2 / 24}


def _point(frame):
    """The object's centre at ``frame``: it moves up (+y) by 0.1 m per frame."""
    return np.array([0.0, 0.1 * frame, 0.0])


def _mask(view, frame):
    """A disk of radius 3 px around the object's centre as an OpenCV camera sees it."""
    c2w = np.vstack([np.asarray(C2W_GL[view]), [0, 0, 0, 1]]) @ np.diag([1.0, -1.0, -1.0, 1.0])
    pc = c2w[:3, :3].T @ (_point(frame) - c2w[:3, 3])
    u, v = F * pc[0] / pc[2] + W / 2, F * pc[1] / pc[2] + H / 2
    rows, cols = np.mgrid[0:H, 0:W] + 0.5
    return ((cols - u) ** 2 + (rows - v) ** 2 <= 9.0), (u, v)


def _folder(tmp_path, variant="alpha", frames=(0, 1, 2), size=None):
    folder = tmp_path / variant
    (folder / "data").mkdir(parents=True)
    entries = []
    rng = np.random.default_rng(0)
    background = {v: rng.integers(0, 60, (H, W, 3)).astype(np.uint8) for v in (0, 1)}
    for view in (0, 1):
        for frame in (-1, *frames):
            entries.append({"file_path": f"./data/r_{view}_{frame}.png", "time": TIMES[frame],
                            "c2w": C2W_GL[view], "intrinsic": K})
            bg = background[view]
            if frame < 0:
                iio.imwrite(folder / f"data/r_{view}_{frame}.png", bg)
                continue
            m, _ = _mask(view, frame)
            colour = np.array([200, 50 + 50 * frame, 30], np.uint8)
            rgb = np.where(m[..., None], colour, bg).astype(np.uint8)
            if size is not None and (view, frame) == (1, frames[-1]):
                rgb = np.zeros(size + (3,), np.uint8)
                m = np.zeros(size, bool)
            alpha = np.where(m, 255, 0).astype(np.uint8)
            white = np.where(m[..., None], rgb, 255).astype(np.uint8)
            if variant == "alpha":
                iio.imwrite(folder / f"data/r_{view}_{frame}.png", np.dstack([rgb, alpha]))
            else:
                iio.imwrite(folder / f"data/r_{view}_{frame}.png", rgb)
            if variant == "a":
                iio.imwrite(folder / f"data/a_{view}_{frame}.png", np.dstack([white, alpha]))
            if variant == "m":
                iio.imwrite(folder / f"data/m_{view}_{frame}.png", white)
    (folder / "all_data.json").write_text(json.dumps(entries))
    return folder


@pytest.mark.parametrize("variant", ["alpha", "a", "m", "background"])
def test_masks_images_and_cameras_are_read(tmp_path, variant):
    obs = load_pacnerf(_folder(tmp_path, variant))
    assert obs.masks.shape == (2, 3, H, W) and obs.images.shape == (2, 3, H, W, 3)
    np.testing.assert_allclose(obs.times, [0.0, 1 / 24, 2 / 24])
    np.testing.assert_allclose(obs.intrinsics, np.broadcast_to(K, (2, 3, 3)))
    for view in (0, 1):
        for frame in (0, 1, 2):
            want, _ = _mask(view, frame)
            np.testing.assert_array_equal(obs.masks[view, frame] > 0, want)
            # matted images: the object's colour inside, white outside
            inside = obs.images[view, frame][want]
            assert np.all(inside[:, 0] == 200)
            assert np.all(obs.images[view, frame][~want] == 255)


@pytest.mark.x64
def test_cameras_are_converted_to_opencv_axes(tmp_path):
    """The loaded pose projects the object's centre where it was drawn, and world +y (up)
    appears higher in the image (smaller row) — OpenCV axes: x right, y down, z forward."""
    obs = load_pacnerf(_folder(tmp_path, "alpha"))
    cams = Camera(obs.intrinsics, obs.cam_to_world, W, H, dtype=np.float64)
    for view in (0, 1):
        cam = cams.view(view)
        np.testing.assert_allclose(np.asarray(cam.cam_to_world)[:3, 2] @ -np.asarray(C2W_GL[view])[:3, 3],
                                   3.0, rtol=1e-6)  # z forward points at the origin
        rows = []
        for frame in (0, 1, 2):
            uv, depth = cam.project(np.asarray(_point(frame), np.float64))
            _, want = _mask(view, frame)
            np.testing.assert_allclose(np.asarray(uv), want, atol=1e-4)
            assert float(depth) > 0
            rows.append(float(uv[1]))
        assert rows[0] > rows[1] > rows[2]  # moving up in the world = moving up in the image
    assert rows[0] == pytest.approx(H / 2)


def test_downscale_views_and_frames(tmp_path):
    folder = _folder(tmp_path, "alpha")
    obs = load_pacnerf(folder, downscale=2, views=[1], frames=[1, 2])
    assert obs.masks.shape == (1, 2, H // 2, W // 2)
    np.testing.assert_allclose(obs.intrinsics[0], [[F / 2, 0, W / 4], [0, F / 2, H / 4], [0, 0, 1]])
    np.testing.assert_allclose(obs.times, [1 / 24, 2 / 24])


def test_bad_folders_are_clear_errors(tmp_path):
    with pytest.raises(ObservationError, match="not found"):
        load_pacnerf(tmp_path / "nothere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ObservationError, match="no all_data.json"):
        load_pacnerf(tmp_path / "empty")
    with pytest.raises(ObservationError, match="too few frames"):
        load_pacnerf(_folder(tmp_path / "one", "alpha", frames=(0,)))
    with pytest.raises(ObservationError, match="differs from the first image"):
        load_pacnerf(_folder(tmp_path / "size", "alpha", size=(8, 8)))
    folder = _folder(tmp_path / "gone", "alpha")
    (folder / "data" / "r_1_2.png").unlink()
    with pytest.raises(ObservationError, match="r_1_2.png"):
        load_pacnerf(folder)
    with pytest.raises(ObservationError, match="frames \\[7\\]"):
        load_pacnerf(_folder(tmp_path / "f", "alpha"), frames=[0, 7])
    plain = _folder(tmp_path / "plain", "rgb")  # no alpha, no a_/m_; but a background plate
    with pytest.raises(ObservationError, match="no mask source"):
        load_pacnerf(plain, mask_source="m")


@pytest.mark.parametrize("gain", [0.7, 1.0, 1.3])
def test_background_mask_compensates_the_plates_exposure(gain):
    """A plate shot darker or brighter than the frames still gives the material's mask: the
    plate is scaled by the median frame/plate ratio before the difference is taken."""
    from jaxmpm.datasets import BACKGROUND_THRESHOLD, background_mask

    rng = np.random.default_rng(1)
    plate = rng.integers(40, 190, (32, 40, 3)).astype(np.uint8)
    rows, cols = np.mgrid[0:32, 0:40]
    disk = (rows - 15) ** 2 + (cols - 22) ** 2 <= 36
    frame = np.clip(np.round(plate * gain), 0, 255)
    frame[disk] = [250, 20, 20]
    mask = background_mask(frame.astype(np.uint8), plate) > 0
    np.testing.assert_array_equal(mask, disk)
    # without the compensation, a 30 % exposure change marks background as material
    raw = np.max(np.abs(frame - plate.astype(float)), axis=-1) > BACKGROUND_THRESHOLD
    assert (raw & ~disk).mean() > 0.3 if gain != 1.0 else not (raw & ~disk).any()
