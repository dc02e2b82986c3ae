"""Is a camera miscalibrated? Per-view image offsets from the silhouettes' consistency.

A view's mask must lie inside the silhouette, in that view, of the visual hull the other views
carve: the hull contains the body. When one camera's pose or principal point is off by a few
pixels, its mask sits shifted against that silhouette, and the body it helps carve loses a
slice (docs/identify.md: 3 px in one of six views moved μ by 0.13 decades).

For each view, :func:`view_offsets` renders the other views' hull by casting a ray through
each pixel centre and asking whether some point of the ray (sampled inside the box of a
coarse hull of all views) projects into the masks of all but ``tolerance`` of the other views. The integer shift of the view's mask
that overlaps that silhouette best (IoU summed over the first few frames), refined to a
fraction of a pixel by a parabola through its neighbours, is the view's offset. Moving the
camera's principal point ``(cx, cy)`` by the offset puts the body where the mask shows it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import ObservationError
from .hull import inside_masks, visual_hull

#: A view is flagged when its offset is at least this long (px) ...
MIN_OFFSET_PX = 1.0
#: ... and shifting its mask by it raises its IoU with the other views' hull by at least this.
MIN_IOU_GAIN = 0.01


@dataclass(frozen=True)
class ViewOffsets:
    """What :func:`view_offsets` measured.

    Attributes:
        offsets: ``(V, 2)`` px, (column, row): where each view's masks sit relative to where
            its camera puts the body the other views agree on (add it to ``(cx, cy)``).
        iou: ``(V,)`` IoU of each view's masks with the other views' hull silhouette, as
            calibrated.
        iou_shifted: ``(V,)`` the same with the mask moved back by the nearest whole-pixel offset.
        frames: the frames compared.
    """

    offsets: np.ndarray
    iou: np.ndarray
    iou_shifted: np.ndarray
    frames: tuple[int, ...]

    def flagged(self, min_px: float = MIN_OFFSET_PX, min_gain: float = MIN_IOU_GAIN) -> np.ndarray:
        """``(V,)`` bool: views whose offset is at least ``min_px`` long and whose IoU the shift
        raises by at least ``min_gain``."""
        return (np.linalg.norm(self.offsets, axis=1) >= min_px) & (self.iou_shifted - self.iou >= min_gain)

    def corrected(self, intrinsics: np.ndarray, views: np.ndarray | None = None) -> np.ndarray:
        """``(V, 3, 3)`` intrinsics with the principal point of ``views`` (bool ``(V,)``,
        default :meth:`flagged`) moved by its offset."""
        views = self.flagged() if views is None else np.asarray(views, bool)
        K = np.array(intrinsics, dtype=float, copy=True)
        K[views, 0, 2] += self.offsets[views, 0]
        K[views, 1, 2] += self.offsets[views, 1]
        return K

    def describe(self) -> list[str]:
        """One line per flagged view."""
        out = []
        for v in np.flatnonzero(self.flagged()):
            du, dv = self.offsets[v]
            out.append(f"view {v}'s masks sit {du:+.1f} px across and {dv:+.1f} px down from where the other "
                       f"views put the body (IoU with their hull {self.iou[v]:.3f}, {self.iou_shifted[v]:.3f} shifted back)")
        return out


def pixel_rays(K: np.ndarray, cam_to_world: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """World rays through pixel centres: ``(origin (3,), directions (P, 3))`` (not unit
    length: a ray parameter of 1 is one unit of camera depth)."""
    uv1 = np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))], axis=-1)
    d_cam = uv1 @ np.linalg.inv(np.asarray(K, float)).T
    c2w = np.asarray(cam_to_world, float)
    return c2w[:3, 3], d_cam @ c2w[:3, :3].T


def hull_silhouette(
    masks: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    K: np.ndarray,
    c2w: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    lo,
    hi,
    *,
    tolerance: int = 0,
    samples: int = 96,
) -> np.ndarray:
    """Whether each pixel ``(rows, cols)`` of a camera ``(K, c2w)`` sees the visual hull of
    ``masks`` (``(V, H, W)`` bool, cameras ``intrinsics``, ``cam_to_world``) inside the box
    ``[lo, hi]``: some of ``samples`` points on its ray is inside at least ``V − tolerance``
    of the masks. Returns ``(P,)`` bool."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    origin, d = pixel_rays(K, c2w, rows, cols)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a, t_b = (lo - origin) / d, (hi - origin) / d
    t_near = np.nanmax(np.minimum(t_a, t_b), axis=1).clip(min=0.0)
    t_far = np.nanmin(np.maximum(t_a, t_b), axis=1)
    hit = t_far > t_near
    out = np.zeros(len(rows), bool)
    if not hit.any():
        return out
    s = (np.arange(samples) + 0.5) / samples
    t = t_near[hit, None] + (t_far - t_near)[hit, None] * s  # (P', S)
    points = origin + t[..., None] * d[hit, None, :]
    votes = inside_masks(points.reshape(-1, 3), masks, intrinsics, cam_to_world).sum(axis=0)
    out[hit] = (votes.reshape(t.shape) >= masks.shape[0] - tolerance).any(axis=1)
    return out


def _shifted(mask: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """``mask`` moved by ``dr`` rows and ``dc`` columns, zero-filled."""
    out = np.zeros_like(mask)
    H, W = mask.shape
    out[max(dr, 0):H + min(dr, 0), max(dc, 0):W + min(dc, 0)] = mask[max(-dr, 0):H + min(-dr, 0),
                                                                     max(-dc, 0):W + min(-dc, 0)]
    return out


def _parabola_peak(f_minus: float, f_0: float, f_plus: float) -> float:
    """The vertex of the parabola through ``(-1, f_minus), (0, f_0), (1, f_plus)``, in [-½, ½]."""
    curvature = f_minus - 2.0 * f_0 + f_plus
    return float(np.clip(0.5 * (f_minus - f_plus) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def view_offsets(
    masks: np.ndarray,
    intrinsics: np.ndarray,
    cam_to_world: np.ndarray,
    lo,
    hi,
    *,
    frames: int = 3,
    search: int = 5,
    tolerance: int | None = None,
    samples: int = 96,
) -> ViewOffsets:
    """Each view's image offset against the visual hull of the other views (module docstring).

    A view off by a few pixels also carves the hull every other view is compared with, which
    biases their offsets by up to about a pixel. So when a view is flagged
    (:meth:`ViewOffsets.flagged`), every view is measured again with the flagged ones
    corrected: the other views take the second pass's figures, the flagged ones keep their
    first-pass IoUs and add the second pass's residual to their offsets.

    Arguments:
        masks: ``(V, T, H, W)`` bool or 0/255 silhouettes of the body.
        intrinsics, cam_to_world: ``(V, 3, 3)``, ``(V, 4, 4)`` (OpenCV axes).
        lo, hi: ``(3,)`` corners of the domain, m: the rays are sampled inside the part of
            it a coarse visual hull of all views occupies.
        frames: the first ``frames`` frames are compared (the body before it deforms much).
        search: largest shift tried, px, along each image axis.
        tolerance: a point is in the other views' hull when at most this many of them see
            it outside (default 1 with four or more other views; else 0).
        samples: points per ray.

    Returns:
        A :class:`ViewOffsets`.

    Raises:
        ObservationError: fewer than 3 views (two others cannot bound a hull), bad shapes, or a
            view whose masks are empty in every compared frame.
    """
    masks = np.asarray(masks) > 0
    if masks.ndim != 4:
        raise ObservationError(f"view_offsets: masks must be (V, T, H, W), got {masks.shape}")
    V, T = masks.shape[:2]
    if V < 3:
        raise ObservationError(f"view_offsets: needs at least 3 views, got {V}")
    if np.shape(intrinsics) != (V, 3, 3) or np.shape(cam_to_world) != (V, 4, 4):
        raise ObservationError(f"view_offsets: need {V} cameras, got intrinsics {np.shape(intrinsics)} and poses "
                               f"{np.shape(cam_to_world)}")
    if search < 1 or frames < 1:
        raise ObservationError(f"view_offsets: search and frames must be >= 1, got {search} and {frames}")
    for v in range(V):
        if not masks[v, :frames].any():
            raise ObservationError(f"view_offsets: view {v}'s masks are empty in frames {list(range(min(frames, T)))}")
    tol = (1 if V - 1 >= 4 else 0) if tolerance is None else int(tolerance)
    used = tuple(range(min(frames, T)))
    K, c2w = np.asarray(intrinsics, float), np.asarray(cam_to_world, float)
    lo, hi = _body_box(masks[:, list(used)], K, c2w, lo, hi, tol)

    def measure(K: np.ndarray) -> ViewOffsets:
        rows = [_view_offset(masks, K, c2w, v, used, lo, hi, search, tol, samples) for v in range(V)]
        offsets, iou, iou_shifted = (np.array(a) for a in zip(*rows))
        return ViewOffsets(offsets=offsets, iou=iou, iou_shifted=iou_shifted, frames=used)

    first = measure(K)
    bad = first.flagged()
    if not bad.any():
        return first
    second = measure(first.corrected(K))
    return ViewOffsets(offsets=second.offsets + np.where(bad[:, None], first.offsets, 0.0),
                       iou=np.where(bad, first.iou, second.iou),
                       iou_shifted=np.where(bad, first.iou_shifted, second.iou_shifted), frames=used)


#: Voxels along the domain's longest side of the coarse hull that bounds the rays (:func:`_body_box`).
BOX_VOXELS = 48


def _body_box(masks: np.ndarray, K: np.ndarray, c2w: np.ndarray, lo, hi, tolerance: int):
    """The part of the domain ``[lo, hi]`` the rays need: the bounding box, two voxels wider,
    of a coarse visual hull of all views (``tolerance`` of them may disagree) over the frames
    of ``masks`` ``(V, T, H, W)``; the domain itself when that hull is empty."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    voxel = float(np.max(hi - lo)) / BOX_VOXELS
    occupied = [visual_hull(masks[:, t], K, c2w, lo, hi, voxel, tolerance=tolerance) for t in range(masks.shape[1])]
    points = np.concatenate([h.centers() for h in occupied])
    if len(points) == 0:
        return lo, hi
    return np.maximum(points.min(axis=0) - 2.5 * voxel, lo), np.minimum(points.max(axis=0) + 2.5 * voxel, hi)


def _view_offset(masks, K, c2w, v, frames, lo, hi, search, tolerance, samples) -> tuple[np.ndarray, float, float]:
    """View ``v``'s ``(offset (2,) px, IoU, IoU at the best whole-pixel shift)`` against the
    hull of the other views, summed over ``frames``."""
    H, W = masks.shape[2:]
    others = np.array([w for w in range(masks.shape[0]) if w != v])
    shifts = np.arange(-search, search + 1)
    inter = np.zeros((len(shifts), len(shifts)))
    union = np.zeros_like(inter)
    for t in frames:
        mask = masks[v, t]
        if not mask.any():
            continue
        r, c = np.nonzero(mask)
        pad = search + 1 + max(np.ptp(r), np.ptp(c)) // 4
        r0, r1 = max(r.min() - pad, 0), min(r.max() + pad + 1, H)
        c0, c1 = max(c.min() - pad, 0), min(c.max() + pad + 1, W)
        rows, cols = np.mgrid[r0:r1, c0:c1]
        silhouette = np.zeros((H, W), bool)
        silhouette[r0:r1, c0:c1] = hull_silhouette(masks[others, t], K[others], c2w[others], K[v], c2w[v], rows.ravel(),
                                                   cols.ravel(), lo, hi, tolerance=tolerance,
                                                   samples=samples).reshape(rows.shape)
        for i, dr in enumerate(shifts):
            for j, dc in enumerate(shifts):
                moved = _shifted(mask, dr, dc)
                inter[i, j] += np.sum(moved & silhouette)
                union[i, j] += np.sum(moved | silhouette)
    iou = inter / np.maximum(union, 1)
    i, j = np.unravel_index(np.argmax(iou), iou.shape)
    di = _parabola_peak(iou[i - 1, j], iou[i, j], iou[i + 1, j]) if 0 < i < len(shifts) - 1 else 0.0
    dj = _parabola_peak(iou[i, j - 1], iou[i, j], iou[i, j + 1]) if 0 < j < len(shifts) - 1 else 0.0
    # the mask moved by (dr, dc) matches: its content sits (-dc, -dr) from the hull's silhouette
    return np.array([-(shifts[j] + dj), -(shifts[i] + di)]), float(iou[search, search]), float(iou[i, j])


def recalibrated(dataset, offsets: ViewOffsets):
    """``dataset`` (:class:`jaxmpm.reconstruct.Dataset`) with the flagged views' principal
    points moved by their offsets."""
    obs = dataset.observation
    K = offsets.corrected(np.asarray(obs.intrinsics)).astype(np.asarray(obs.intrinsics).dtype)
    return dataclasses.replace(dataset, observation=dataclasses.replace(obs, intrinsics=K))


def check_cameras(dataset, lo, hi, *, recalibrate: bool = False):
    """The cameras' consistency check of a dataset before its reconstruction.

    Returns:
        ``(dataset, offsets)``: :func:`view_offsets` of its masks inside the domain ``[lo,
        hi]`` (None with fewer than 3 views), and the dataset, :func:`recalibrated` when
        ``recalibrate`` and a view is flagged.
    """
    obs = dataset.observation
    if obs.masks.shape[0] < 3:
        return dataset, None
    offsets = view_offsets(obs.masks, obs.intrinsics, obs.cam_to_world, lo, hi)
    if recalibrate and offsets.flagged().any():
        dataset = recalibrated(dataset, offsets)
    return dataset, offsets
