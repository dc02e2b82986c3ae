"""The cameras' consistency check (jaxmpm.reconstruct.calibration): a view whose camera is off
by a few pixels is found, by how much, and corrected; consistent views are left alone."""

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmpm.errors import ObservationError
from jaxmpm.reconstruct import ViewOffsets, check_cameras, view_offsets
from jaxmpm.reconstruct.calibration import hull_silhouette
from jaxmpm.reconstruct.pipeline import identify_warnings
from jaxmpm.render import pacnerf_rig

LO, HI = np.zeros(3), np.full(3, 0.6)
#: a ball falling through three frames (m)
CENTRES = np.array([[0.30, 0.40, 0.30], [0.30, 0.36, 0.30], [0.30, 0.30, 0.30]])
RADIUS = 0.08


def rig(views=6, res=96):
    return pacnerf_rig(views, radius=1.0, target=(0.3, 0.3, 0.3), res=res, min_elevation_deg=0.0, max_elevation_deg=60.0)


def ball_masks(cams) -> np.ndarray:
    """Exact silhouettes ``(V, T, H, W)`` of the ball at :data:`CENTRES` (rays that meet it)."""
    out = np.zeros((cams.num_views, len(CENTRES), cams.height, cams.width), bool)
    for v in range(cams.num_views):
        o, d = (np.asarray(a, float) for a in cams.view(v).rays())
        for t, c in enumerate(CENTRES):
            oc = o - c
            b = np.sum(oc * d, axis=-1)
            out[v, t] = (b * b - np.sum(oc * oc, axis=-1) + RADIUS**2 > 0).reshape(cams.height, cams.width)
    return out


def moved_principal_point(cams, view: int, du: float, dv: float):
    K = np.array(cams.K, float)
    K[view, 0, 2] += du
    K[view, 1, 2] += dv
    return with_intrinsics(cams, K)


def with_intrinsics(cams, K):
    return eqx.tree_at(lambda c: c.K, cams, jnp.asarray(K, cams.K.dtype))


def offsets_of(masks, cams) -> ViewOffsets:
    return view_offsets(masks, np.asarray(cams.K, float), np.asarray(cams.cam_to_world, float), LO, HI)


def test_consistent_views_have_no_offset():
    cams = rig()
    res = offsets_of(ball_masks(cams), cams)
    assert np.abs(res.offsets).max() < 0.5, res.offsets
    assert not res.flagged().any() and res.describe() == []
    assert res.frames == (0, 1, 2)


@pytest.mark.parametrize("view, du, dv", [(0, 3.0, 0.0), (2, 0.0, -2.0), (4, 1.5, 1.5)])
def test_a_miscalibrated_view_is_found_with_its_offset_and_corrected(view, du, dv):
    """The masks are those of a camera whose principal point is off by (du, dv) px; the check
    is given the nominal cameras. It flags that view alone, measures the offset to a third of
    a pixel (the half-pixel one too), and the corrected camera re-renders the masks it saw."""
    cams = rig()
    masks = ball_masks(cams)
    masks[view] = ball_masks(moved_principal_point(cams, view, du, dv))[view]
    res = offsets_of(masks, cams)
    np.testing.assert_allclose(res.offsets[view], [du, dv], atol=0.34)
    assert res.flagged().tolist() == [v == view for v in range(6)]
    others = np.arange(6) != view
    assert np.abs(res.offsets[others]).max() < 0.75
    assert res.describe()[0].startswith(f"view {view}'s masks sit {res.offsets[view, 0]:+.1f} px across")
    # the corrected principal point renders what the view saw (to the sub-pixel error)
    fixed = with_intrinsics(cams, res.corrected(np.asarray(cams.K, float)))
    before = np.mean(masks[view] != ball_masks(cams)[view])
    after = np.mean(masks[view] != ball_masks(fixed)[view])
    assert after < 0.25 * before


def test_the_other_views_hull_silhouette_contains_the_views_own_mask():
    """The ray test: every pixel of a consistent view's mask sees the other views' hull, and
    the hull's silhouette is larger than the ball's (a visual hull contains the body)."""
    cams = rig()
    masks = ball_masks(cams)[:, 0]
    K, c2w = np.asarray(cams.K, float), np.asarray(cams.cam_to_world, float)
    rows, cols = np.mgrid[0:96, 0:96]
    seen = hull_silhouette(masks[1:], K[1:], c2w[1:], K[0], c2w[0], rows.ravel(), cols.ravel(), LO, HI)
    seen = seen.reshape(96, 96)
    assert np.mean(seen[masks[0]]) > 0.99
    assert seen.sum() > masks[0].sum()


def test_check_cameras_recalibrates_only_when_asked(tmp_path):
    cams = rig()
    masks = ball_masks(cams)
    masks[0] = ball_masks(moved_principal_point(cams, 0, 3.0, 0.0))[0]

    @dataclasses.dataclass
    class Obs:
        masks: np.ndarray
        intrinsics: np.ndarray
        cam_to_world: np.ndarray

    @dataclasses.dataclass
    class Data:
        observation: Obs

    data = Data(Obs(masks, np.asarray(cams.K, np.float32), np.asarray(cams.cam_to_world, np.float32)))
    same, res = check_cameras(data, LO, HI)
    assert same is data and res.flagged()[0]
    fixed, res2 = check_cameras(data, LO, HI, recalibrate=True)
    K0, K1 = data.observation.intrinsics, fixed.observation.intrinsics
    assert K1.dtype == K0.dtype and K1[0, 0, 2] - K0[0, 0, 2] == pytest.approx(res2.offsets[0, 0], abs=1e-4)
    np.testing.assert_array_equal(K1[1:], K0[1:])
    # two views cannot bound a hull: no check
    two = Data(Obs(masks[:2], data.observation.intrinsics[:2], data.observation.cam_to_world[:2]))
    assert check_cameras(two, LO, HI) == (two, None)


def test_a_flagged_view_is_a_warning_unless_it_was_corrected():
    res = ViewOffsets(offsets=np.array([[2.9, -0.1], [0.2, 0.1], [0.0, 0.3]]), iou=np.array([0.59, 0.68, 0.70]),
                      iou_shifted=np.array([0.67, 0.68, 0.70]), frames=(0, 1, 2))
    recon = type("Recon", (), {"collider_roof": None, "free_fall": None, "collider": None})()
    result = type("Fit", (), {"notes": []})()
    warned = identify_warnings(result, recon, 0.05, res)
    assert len(warned) == 1 and warned[0].startswith("view 0's masks sit +2.9 px across") and "--recalibrate-views" in warned[0]
    assert identify_warnings(result, recon, 0.05, res, recalibrated_views=True) == []
    assert identify_warnings(result, recon, 0.05, None) == []


def test_bad_input_is_refused():
    cams = rig(views=3, res=32)
    masks = ball_masks(cams)
    K, c2w = np.asarray(cams.K, float), np.asarray(cams.cam_to_world, float)
    with pytest.raises(ObservationError, match="at least 3 views"):
        view_offsets(masks[:2], K[:2], c2w[:2], LO, HI)
    with pytest.raises(ObservationError, match=r"\(V, T, H, W\)"):
        view_offsets(masks[:, 0], K, c2w, LO, HI)
    with pytest.raises(ObservationError, match="need 3 cameras"):
        view_offsets(masks, K[:2], c2w, LO, HI)
    empty = masks.copy()
    empty[1] = False
    with pytest.raises(ObservationError, match="view 1's masks are empty"):
        view_offsets(empty, K, c2w, LO, HI)
