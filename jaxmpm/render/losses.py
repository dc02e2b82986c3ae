"""Image losses on random pixel batches, differentiable w.r.t. particle positions.

Typical fitting step::

    pixels = sample_pixels(key, V, H, W, 2048)             # (V, n) flat indices
    loss = silhouette_loss(renderer, x, cameras, masks, pixels)   # masks (V, H, W)

Only the sampled pixels are rendered, so a step's cost is bounded by ``V·n`` rays (or
``V·n·N`` pixel–surfel pairs) whatever the image size (PAC-NeRF trains on random ray
batches in the same way). Views are processed one after another (``lax.map``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..errors import ObservationError
from .camera import Camera, as_camera_batch, check_image_size
from .volume import AbstractRenderer, Rendered

_EPS = 1e-8


def sample_pixels(key: PRNGKeyArray, V: int, H: int, W: int, n: int) -> Int[Array, "V n"]:
    """``n`` distinct random pixels per view, as flat indices ``row*W + col`` (int32).

    Raises:
        ObservationError: if ``n`` exceeds ``H·W`` or a size is not positive.
    """
    if min(V, H, W, n) <= 0:
        raise ObservationError(f"sample_pixels needs positive V, H, W, n; got {(V, H, W, n)}")
    if n > H * W:
        raise ObservationError(f"cannot sample {n} distinct pixels from a {H}×{W} image")
    keys = jax.random.split(key, V)
    pick = jax.vmap(lambda k: jax.random.choice(k, H * W, (n,), replace=False))(keys)
    return pick.astype(jnp.int32)


def all_pixels(V: int, H: int, W: int) -> Int[Array, "V P"]:
    """Every pixel of every view, ``(V, H·W)`` flat indices."""
    return jnp.broadcast_to(jnp.arange(H * W, dtype=jnp.int32), (V, H * W))


def gather_pixels(images, pixels: Int[Array, "V n"]):
    """Values of ``images`` ``(V, H, W[, C])`` at flat pixel indices ``(V, n)`` → ``(V, n[, C])``."""
    images = jnp.asarray(images)
    V, H, W = images.shape[:3]
    flat = images.reshape((V, H * W) + images.shape[3:])
    return jax.vmap(lambda im, p: im[p])(flat, pixels)


def as_unit_float(a, dtype):
    """uint8 images/masks (0..255) → float in [0, 1]; floats are only cast."""
    a = jnp.asarray(a)
    if a.dtype == jnp.uint8:
        return a.astype(dtype) / 255.0
    if a.dtype == jnp.bool_:
        return a.astype(dtype)
    return a.astype(dtype)


# --- pointwise losses -------------------------------------------------------------------


def silhouette_l2(pred: Float[Array, "..."], target: Float[Array, "..."]) -> Float[Array, ""]:
    """Mean squared difference of soft silhouettes (both in [0, 1])."""
    d = pred - target.astype(pred.dtype)
    return jnp.mean(d * d)


def soft_iou_loss(pred: Float[Array, "..."], target: Float[Array, "..."]) -> Float[Array, ""]:
    """``1 − Σ p t / (Σ p + Σ t − Σ p t)`` (soft IoU; 0 when equal, 1 when disjoint)."""
    target = target.astype(pred.dtype)
    inter = jnp.sum(pred * target)
    union = jnp.sum(pred) + jnp.sum(target) - inter
    return 1.0 - inter / (union + _EPS)


def masked_rgb_l2(
    pred: Float[Array, "... 3"], target: Float[Array, "... 3"], mask: Float[Array, "..."] | None = None
) -> Float[Array, ""]:
    """Mean squared RGB error over the pixels where ``mask`` (weights in [0, 1]) is set.

    Without a mask, the mean over all pixels and channels.
    """
    d = pred - target.astype(pred.dtype)
    se = jnp.sum(d * d, axis=-1)
    if mask is None:
        return jnp.mean(se) / 3.0
    m = mask.astype(pred.dtype)
    return jnp.sum(m * se) / (3.0 * jnp.maximum(jnp.sum(m), 1.0))


# --- rendering the sampled pixels of all views --------------------------------------------


def render_pixels(
    renderer: AbstractRenderer,
    positions: Float[Array, "N 3"],
    cameras: Camera,
    pixels: Int[Array, "V n"],
    colors: Float[Array, "N 3"] | None = None,
    *,
    silhouette_only: bool = False,
    **particle_data,
) -> Rendered | Float[Array, "V n"]:
    """Render pixels ``(V, n)`` of V views (views in sequence with ``lax.map``).

    Returns a :class:`Rendered` with ``(V, n, ...)`` arrays, or only the alpha
    ``(V, n)`` when ``silhouette_only`` (cheaper for surfels: no sort, no colour).
    """
    cams = as_camera_batch(cameras)
    pixels = jnp.asarray(pixels)
    if pixels.ndim != 2 or pixels.shape[0] != cams.num_views:
        raise ObservationError(
            f"pixels must have shape (V, n) with V = {cams.num_views} views, got {pixels.shape}"
        )

    def one(args):
        cam, pix = args
        if silhouette_only:
            return renderer.silhouette(positions, cam, pixels=pix, **particle_data)
        return renderer.render(positions, cam, colors, pixels=pix, **particle_data)

    return jax.lax.map(one, (cams, pixels))


def _pixels_or_all(pixels, cams: Camera):
    if pixels is None:
        return all_pixels(cams.num_views, cams.height, cams.width)
    return jnp.asarray(pixels)


def silhouette_loss(
    renderer: AbstractRenderer,
    positions: Float[Array, "N 3"],
    cameras: Camera,
    target_masks,
    pixels: Int[Array, "V n"] | None = None,
    *,
    kind: str = "l2",
    **particle_data,
) -> Float[Array, ""]:
    """Silhouette loss of one frame seen by V cameras.

    Arguments:
        renderer: a renderer.
        positions: ``(N, 3)`` particle positions.
        cameras: a batch of V cameras (or a single camera with V = 1).
        target_masks: ``(V, H, W)`` masks, uint8 0/255 or floats in [0, 1].
        pixels: ``(V, n)`` flat pixel indices (e.g. :func:`sample_pixels`); all if None.
        kind: ``"l2"`` (:func:`silhouette_l2`) or ``"iou"`` (:func:`soft_iou_loss`).
        particle_data: renderer-specific per-particle inputs (``volumes``, ``F``, …).

    Raises:
        ObservationError: masks whose size or number of views does not match the cameras.
    """
    cams = as_camera_batch(cameras)
    check_image_size(cams, target_masks, rgb=False, what="target masks")
    if kind not in ("l2", "iou"):
        raise ObservationError(f"silhouette loss kind must be 'l2' or 'iou', got {kind!r}")
    pix = _pixels_or_all(pixels, cams)
    target = gather_pixels(as_unit_float(target_masks, positions.dtype), pix)
    pred = render_pixels(renderer, positions, cams, pix, silhouette_only=True, **particle_data)
    return silhouette_l2(pred, target) if kind == "l2" else soft_iou_loss(pred, target)


def rgb_loss(
    renderer: AbstractRenderer,
    positions: Float[Array, "N 3"],
    cameras: Camera,
    target_images,
    pixels: Int[Array, "V n"] | None = None,
    colors: Float[Array, "N 3"] | None = None,
    *,
    target_masks=None,
    **particle_data,
) -> Float[Array, ""]:
    """Masked RGB L2 loss of one frame seen by V cameras.

    Arguments:
        renderer: a renderer (its background should match the images' background).
        positions: ``(N, 3)``.
        cameras: a batch of V cameras.
        target_images: ``(V, H, W, 3)`` uint8 or floats in [0, 1].
        pixels: ``(V, n)`` flat pixel indices; all if None.
        colors: per-particle colours ``(N, 3)``.
        target_masks: optional ``(V, H, W)`` weights selecting the pixels that count
            (PAC-NeRF's ray mask); all pixels if None.
    """
    cams = as_camera_batch(cameras)
    check_image_size(cams, target_images, rgb=True, what="target images")
    pix = _pixels_or_all(pixels, cams)
    dtype = positions.dtype
    target = gather_pixels(as_unit_float(target_images, dtype), pix)
    mask = None
    if target_masks is not None:
        check_image_size(cams, target_masks, rgb=False, what="target masks")
        mask = gather_pixels(as_unit_float(target_masks, dtype), pix)
    pred = render_pixels(renderer, positions, cams, pix, colors, **particle_data)
    return masked_rgb_l2(pred.rgb, target, mask)


def check_observation_images(cameras: Camera, masks=None, images=None) -> None:
    """Check masks ``(V, T, H, W)`` / images ``(V, T, H, W, 3)`` against V cameras."""
    cams = as_camera_batch(cameras)
    if masks is not None:
        if np.ndim(masks) != 4:
            raise ObservationError(f"masks must have shape (V, T, H, W), got {np.shape(masks)}")
        check_image_size(cams, masks, rgb=False, what="masks")
    if images is not None:
        if np.ndim(images) != 5:
            raise ObservationError(f"images must have shape (V, T, H, W, 3), got {np.shape(images)}")
        check_image_size(cams, images, rgb=True, what="images")
